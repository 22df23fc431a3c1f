//! vlem-trackers: camera pose sources.
//!
//! - `ground-truth` ([`ground_truth`]): poses read from the dataset;
//! - `odometry` ([`odometry`]): frame-to-frame dense RGB-D odometry (hybrid photometric +
//!   geometric, coarse to fine), the paper's "Localisation" without a model;
//! - `frame-to-model` ([`frame_to_model`]): the same registration against depth and colour
//!   ray-cast from a TSDF voxel-block map ([`tsdf`]) of everything tracked so far, which also
//!   yields the dense colour model (a marching-cubes mesh).

mod error;
pub mod frame_to_model;
pub mod ground_truth;
pub mod odometry;
pub mod tsdf;

pub use error::TrackerError;
pub use frame_to_model::FrameToModelTracker;
pub use ground_truth::GroundTruthTracker;
pub use odometry::OdometryTracker;
