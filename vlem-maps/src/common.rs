//! Pieces every map shares: validating an observation, resolving the embedding dimension,
//! and parameter errors.

use vlem_core::{CoreError, MapSnapshot, Observation, StageKind};

use crate::error::MapError;

/// The error for a map parameter out of its range, named for the pipeline.
pub(crate) fn invalid_parameter(map: &str, name: &'static str, reason: &str) -> CoreError {
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
pub(crate) fn resolve_dim(
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
pub(crate) fn check_observation(dim: usize, obs: &Observation<'_>) -> Result<(), MapError> {
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
pub(crate) fn check_snapshot(dim: usize, snapshot: &MapSnapshot) -> Result<(), CoreError> {
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

/// Buckets of a `std` hash table whose full capacity (no tombstones) is `capacity`: the table
/// keeps 1/8 of its buckets free (one bucket below 8 buckets), and bucket counts are powers of two.
/// Each bucket holds one entry and one control byte.
#[cfg_attr(
    not(any(feature = "voxel", feature = "segment")),
    allow(dead_code, reason = "only the voxel and segment maps have hash tables")
)]
pub(crate) fn hash_buckets(capacity: usize) -> usize {
    match capacity {
        0 => 0,
        c if c < 8 => (c + 1).next_power_of_two(),
        c => (c / 7 * 8).next_power_of_two(),
    }
}

/// A lower bound on the bytes of a `std` B-tree map of `len` entries of `entry` (key plus value)
/// bytes: nodes of up to 11 entries after a 12-byte header (parent pointer, index, length), so
/// at least `len / 11` of them; when there are several, one is internal, with 12 edge pointers
/// besides. Nodes are often only half full, so the real figure is up to about twice this.
#[cfg_attr(
    not(feature = "segment"),
    allow(dead_code, reason = "only the segment map has B-trees")
)]
pub(crate) fn btree_bytes(len: usize, entry: usize) -> usize {
    const CAPACITY: usize = 11;
    let nodes = len.div_ceil(CAPACITY);
    let leaf = (12 + CAPACITY * entry).next_multiple_of(8);
    let edges = if nodes > 1 { (CAPACITY + 1) * 8 } else { 0 };
    nodes * leaf + edges
}
