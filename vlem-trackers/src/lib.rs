//! vlem-trackers: camera pose sources.
//!
//! `ground-truth` reads poses from the dataset. Dense RGB-D odometry and frame-to-model tracking
//! on a TSDF voxel-block map (the paper's "Localisation") are planned here as `odometry` and
//! `frame-to-model`; they are not implemented yet.

pub mod error;
pub mod ground_truth;

pub use error::TrackerError;
pub use ground_truth::GroundTruthTracker;
