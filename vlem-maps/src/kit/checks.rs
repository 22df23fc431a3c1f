//! The checks every map makes: a parameter out of range, the embedding dimension against the
//! encoder's, an observation's and a snapshot's embeddings against the map's dimension.

use vlem_core::{CoreError, MapSnapshot, Observation, StageKind};

use crate::error::MapError;

/// The error for a map parameter out of its range, named for the pipeline.
pub fn invalid_parameter(map: &str, name: &'static str, reason: &str) -> CoreError {
    CoreError::stage(
        StageKind::Map,
        map,
        MapError::InvalidParameter {
            name,
            reason: reason.to_owned(),
        },
    )
}

/// The map's embedding dimension: the configured `dim` if any (it must equal the encoder's), else
/// the encoder's, else 0 (geometry only).
pub fn resolve_dim(
    map: &str,
    configured: Option<usize>,
    encoder: Option<usize>,
) -> Result<usize, CoreError> {
    match (configured, encoder) {
        (Some(map_dim), Some(encoder_dim)) if map_dim != encoder_dim => Err(invalid_parameter(
            map,
            "dim",
            &format!(
                "is {map_dim} but the encoder produces {encoder_dim}-d embeddings: \
                 remove `dim` or set it to {encoder_dim}"
            ),
        )),
        (Some(d), _) => Ok(d),
        (None, d) => Ok(d.unwrap_or(0)),
    }
}

/// Checks that an observation's embeddings fit a map of dimension `dim`.
pub fn check_observation(dim: usize, obs: &Observation<'_>) -> Result<(), MapError> {
    let frame = obs.frame;
    match (dim, obs.embeddings) {
        (0, None) => Ok(()),
        (0, Some(e)) => Err(MapError::UnexpectedEmbeddings { dim: e.dim() }),
        (d, None) => Err(MapError::MissingEmbeddings { dim: d }),
        (d, Some(e)) if e.dim() != d => Err(MapError::Dimension {
            expected: d,
            actual: e.dim(),
        }),
        (_, Some(e)) if (e.width(), e.height()) != (frame.depth.width(), frame.depth.height()) => {
            Err(MapError::EmbeddingSize {
                frame: frame.index,
                embeddings: (e.width(), e.height()),
                depth: (frame.depth.width(), frame.depth.height()),
            })
        }
        _ => Ok(()),
    }
}

/// Checks that a snapshot is consistent and has the map's embedding dimension (before `restore`).
pub fn check_snapshot(dim: usize, snapshot: &MapSnapshot) -> Result<(), CoreError> {
    snapshot.validate()?;
    if snapshot.dim != dim {
        return Err(CoreError::DimensionMismatch {
            what: format!("snapshot of map `{}`", snapshot.map_kind),
            expected: dim,
            actual: snapshot.dim,
        });
    }
    Ok(())
}
