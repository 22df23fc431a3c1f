//! vlem-maps: embedding maps and query segmenters.
//!
//! Each map is behind a cargo feature named after it (`point-cloud`, `voxel`, `segment`); segmenters are always built.
//! Everything registers itself with the vlem registry; binaries reference this crate so that the
//! registrations are linked.

mod common;
pub mod error;
pub mod grasp;
#[cfg(feature = "point-cloud")]
pub mod point_cloud;
#[cfg(feature = "segment")]
pub mod segment;
pub mod segmenters;
pub mod storage;
#[cfg(feature = "voxel")]
pub mod voxel;

pub use error::MapError;
