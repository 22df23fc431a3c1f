//! The error type of `vlem-trackers`.

/// Failures of the trackers in this crate.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TrackerError {
    /// The ground-truth tracker met a frame without a pose.
    #[error(
        "frame {frame} has no pose: the dataset has no trajectory (add one, e.g. trajectory.log / groundtruth.txt, or use a tracker that estimates poses)"
    )]
    MissingPose {
        /// Frame index.
        frame: usize,
    },
    /// A tracker or TSDF parameter is out of range.
    #[error("parameter `{name}` {reason}")]
    InvalidParameter {
        /// The parameter's config key.
        name: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// An image, camera or pose handed to the TSDF volume is unusable.
    #[error("TSDF volume: {what} {reason}")]
    TsdfInput {
        /// The input: "depth image", "colour image", "intrinsics", "pose", ...
        what: &'static str,
        /// What is wrong with it.
        reason: String,
    },
}
