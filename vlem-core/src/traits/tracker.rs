//! `Tracker`: the camera pose of every frame.
//!
//! Why it exists: VLEM's point is that it needs no ground-truth poses (paper, "Localisation"), yet
//! comparison studies want them. A tracker owns whatever state pose estimation needs (previous
//! frame, a TSDF model, ...) and answers one pose per frame, in order. It never sees embeddings.

use crate::error::{CoreError, Result};
use crate::types::{ColouredMesh, Frame, Pose};

/// How tracking went for one frame.
#[derive(Clone, Debug, PartialEq)]
pub enum TrackingState {
    /// The pose is an estimate the map may use.
    Tracking,
    /// Tracking failed; the returned pose is a fallback and the frame must not be integrated.
    Lost {
        /// Why (e.g. "too little valid depth").
        reason: String,
    },
}

/// A tracker's answer for one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackedPose {
    /// Camera-to-world pose (a fallback when `state` is `Lost`). Always finite.
    pub pose: Pose,
    /// Whether the pose can be trusted.
    pub state: TrackingState,
}

/// Estimates camera poses from a stream of frames, one call per frame in chronological order.
pub trait Tracker: Send + Sync {
    /// The registered name.
    fn name(&self) -> &'static str;

    /// Whether this tracker reads poses from the frames (then the dataset must have them).
    fn needs_dataset_poses(&self) -> bool {
        false
    }

    /// Tracks one frame.
    ///
    /// # Errors
    /// An error stops the run; a frame that merely cannot be tracked is reported as
    /// [`TrackingState::Lost`] instead.
    fn track(&mut self, frame: &Frame) -> Result<TrackedPose>;

    /// The dense colour model the tracker built (e.g. a mesh of its TSDF), for export beside
    /// the embedding map.
    ///
    /// # Errors
    /// [`CoreError::Unsupported`] for trackers that keep no model (the default).
    fn colour_model(&self) -> Result<ColouredMesh> {
        Err(CoreError::Unsupported {
            implementation: self.name().to_owned(),
            capability: "colour model export",
        })
    }
}
