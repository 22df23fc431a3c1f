//! The error type of `vlem-maps`.

use vlem_core::{CoreError, StageKind};

/// Failures of the maps in this crate.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MapError {
    /// A parameter out of its range.
    #[error("parameter `{name}` {reason}")]
    InvalidParameter {
        /// Parameter name as in the config.
        name: &'static str,
        /// What the valid range is.
        reason: String,
    },
    /// The map stores embeddings but the observation has none.
    #[error(
        "the map stores {dim}-d embeddings but the frame has none: configure an [encoder], or set [map] dim = 0 for geometry only"
    )]
    MissingEmbeddings {
        /// Map dimension.
        dim: usize,
    },
    /// A geometry-only map was given embeddings.
    #[error("the map is geometry-only (dim 0) but the frame carries {dim}-d embeddings")]
    UnexpectedEmbeddings {
        /// Their dimension.
        dim: usize,
    },
    /// Embeddings of another dimension than the map's.
    #[error("embeddings have dimension {actual}, the map stores {expected}")]
    Dimension {
        /// Map dimension.
        expected: usize,
        /// Given dimension.
        actual: usize,
    },
    /// Embeddings that cover another image size than the depth image.
    #[error("frame {frame}: embeddings cover {}x{} pixels but the depth image is {}x{}", embeddings.0, embeddings.1, depth.0, depth.1)]
    EmbeddingSize {
        /// Frame index.
        frame: usize,
        /// Embedding width and height.
        embeddings: (u32, u32),
        /// Depth width and height.
        depth: (u32, u32),
    },
    /// The device in `[map] device` could not be opened, or a tensor operation on it failed.
    #[error(transparent)]
    Device(#[from] vlem_backends::BackendError),
    /// A tensor operation of the device table failed (device memory, a driver error).
    #[error("the map's device table: {0}")]
    DeviceTable(String),
}

impl MapError {
    /// Wraps this error for the pipeline, naming the implementation.
    pub fn into_core(self, kind: StageKind, name: &str) -> CoreError {
        CoreError::stage(kind, name, self)
    }
}
