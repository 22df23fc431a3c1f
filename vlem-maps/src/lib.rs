//! vlem-maps: embedding maps (storage and integration; the query path is `vlem-query`).
//!
//! Each map is behind a cargo feature named after it (`point-cloud`, `voxel`, `segment`) and is a
//! folder module built from [`kit`] (the shared config block, the frame's pixels in world
//! coordinates, input checks).
//! Everything registers itself with the vlem registry; binaries reference this crate so that the
//! registrations are linked. The crate declares the cargo feature of each map with
//! [`vlem_core::feature_hint!`] whether or not it is compiled in, so that asking a binary built
//! without it for that map says which feature to enable.

mod error;
pub mod kit;
#[cfg(feature = "point-cloud")]
pub mod point_cloud;
#[cfg(feature = "segment")]
pub mod segment;
pub mod storage;
#[cfg(test)]
#[allow(
    clippy::unwrap_used,
    dead_code,
    reason = "test fixtures; a build with one map uses a part of them"
)]
mod test_fixtures;
#[cfg(feature = "voxel")]
pub mod voxel;

pub use error::MapError;

/// What [`map_config!`] expands to, reachable from crates that use it without naming
/// `vlem-backends` themselves; not API.
#[doc(hidden)]
pub mod __private {
    pub use vlem_backends::ComputeDevice;
}

vlem_core::feature_hint!(Map, "point-cloud", "point-cloud");
vlem_core::feature_hint!(Map, "voxel", "voxel");
vlem_core::feature_hint!(Map, "segment", "segment");
