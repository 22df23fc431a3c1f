//! The checks every map makes: a parameter out of range (and the ranges maps share), the embedding dimension against the
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

/// `value` must lie in `min..=max` (`vlem_core::ranges::count`; `unit` may be empty).
///
/// # Errors
/// [`invalid_parameter`] naming the range and the value otherwise.
pub fn count_in(
    map: &str,
    name: &'static str,
    value: usize,
    (min, max): (usize, usize),
    unit: &str,
) -> Result<(), CoreError> {
    vlem_core::ranges::count(value, min, max, unit)
        .map(|_| ())
        .map_err(|range| invalid_parameter(map, name, &range))
}

/// `value` must be a number in `min..=max` (`vlem_core::ranges::number`).
///
/// # Errors
/// [`invalid_parameter`] naming the range and the value otherwise.
pub fn number_in(
    map: &str,
    name: &'static str,
    value: f32,
    (min, max): (f32, f32),
    unit: &str,
) -> Result<(), CoreError> {
    vlem_core::ranges::number(value, min, max, unit)
        .map(|_| ())
        .map_err(|range| invalid_parameter(map, name, &range))
}

/// `value` must be at least 1 (a budget, a count, a stride).
///
/// # Errors
/// [`invalid_parameter`] otherwise.
pub fn at_least_one(map: &str, name: &'static str, value: usize) -> Result<(), CoreError> {
    if value == 0 {
        return Err(invalid_parameter(map, name, "must be at least 1"));
    }
    Ok(())
}

/// `value` must be a positive, finite number of metres (a distance, a cell size, a depth).
///
/// # Errors
/// [`invalid_parameter`] otherwise.
pub fn positive_metres(map: &str, name: &'static str, value: f32) -> Result<(), CoreError> {
    if !(value.is_finite() && value > 0.0) {
        return Err(invalid_parameter(
            map,
            name,
            "must be a positive number of metres",
        ));
    }
    Ok(())
}

/// `value` must lie in [0, 1] (a fusion weight).
///
/// # Errors
/// [`invalid_parameter`] otherwise.
pub fn unit_weight(map: &str, name: &'static str, value: f32) -> Result<(), CoreError> {
    if !(0.0..=1.0).contains(&value) {
        return Err(invalid_parameter(map, name, "must lie in [0, 1]"));
    }
    Ok(())
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
