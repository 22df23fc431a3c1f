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
}
