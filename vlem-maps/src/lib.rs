//! vlem-maps: embedding maps (storage and integration; the query path is `vlem-query`).
//!
//! Each map is behind a cargo feature named after it (`point-cloud`, `voxel`, `segment`) and is a
//! folder module built from [`kit`] (the shared config block, the frame's pixels in world
//! coordinates, input checks).
//!
//! - `point-cloud` ([`point_cloud`]): the paper's map; correspondences by projective association
//!   in a pixel window or by a k-d tree, downsampling to the budget by voxel groups from a radix
//!   sort, its buffers kept between frames;
//! - `voxel` ([`voxel`]): RayFronts-style voxels; `segment` ([`segment`]): Open-Fusion-style 3D
//!   segments, with their association and Hungarian solver;
//! - [`kit`]: the config block every map shares (`dim`, `max_depth`, `pixel_stride`, `precision`,
//!   `device`) and its checks, `FramePixels` over a frame's valid, in-range, embedded pixels in
//!   world coordinates, memory accounting;
//! - [`storage`]: the `f32`/`f16` embedding table and its row fusion; with feature `candle`
//!   (`cuda` for GPUs) the device table, one preallocated tensor that a frame's compact
//!   embeddings are fused into and queried on, chosen by `[map] device` (`storage/table.rs`);
//!   the point-cloud and voxel maps use it, their geometry staying on the host;
//! - AVX2 builds of the projective search and of the row fusion, chosen at run time
//!   (`point_cloud/association/wide.rs`, `storage/wide.rs`: the crate's only `unsafe`).
//!
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
