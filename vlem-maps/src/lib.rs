//! vlem-maps: embedding maps and query segmenters.
//!
//! Each map is behind a cargo feature named after it (`point-cloud`, `voxel`, `segment`) and is a
//! folder module; segmenters are always built, and so is [`kit`], what every map is built from
//! (shared config block, the frame's pixels in world coordinates, input checks).
//! Everything registers itself with the vlem registry; binaries reference this crate so that the
//! registrations are linked.

pub mod error;
pub mod grasp;
pub mod kit;
#[cfg(feature = "point-cloud")]
pub mod point_cloud;
#[cfg(feature = "segment")]
pub mod segment;
pub mod segmenters;
pub mod storage;
#[cfg(feature = "voxel")]
pub mod voxel;

pub use error::MapError;
