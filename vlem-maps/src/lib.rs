//! vlem-maps: embedding maps (storage and integration; the query path is `vlem-query`).
//!
//! Each map is behind a cargo feature named after it (`point-cloud`, `voxel`, `segment`).
//! Everything registers itself with the vlem registry; binaries reference this crate so that the
//! registrations are linked.

mod common;
pub mod error;
#[cfg(feature = "point-cloud")]
pub mod point_cloud;
#[cfg(feature = "segment")]
pub mod segment;
pub mod storage;
#[cfg(feature = "voxel")]
pub mod voxel;

pub use error::MapError;
