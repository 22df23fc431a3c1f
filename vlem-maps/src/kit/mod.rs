//! The map-authoring kit: what every map is built from, so that a new map is its fusion rule and
//! little else.
//!
//! Why it exists: the point-cloud, voxel and segment maps (and the ground truth of `vlem-eval`)
//! each had their own copy of the same config fields with their checks, and of the loop that
//! back-projects a frame's valid pixels. Here they are written once:
//! - [`map_config!`](crate::map_config) declares a map's `[map]` config with the shared
//!   parameters of [`MapCommon`] (`dim`, `max_depth`, `pixel_stride`, `precision`, `device`), whose
//!   [`MapCommon::validate`] checks them and resolves the embedding dimension;
//! - [`FramePixels`] iterates the valid, in-range, embedded pixels of a frame in world
//!   coordinates ([`Pixel`]), and [`embedding`] looks a pixel's embedding up;
//! - [`check_observation`] and [`check_snapshot`] check inputs against the map's dimension, and
//!   [`invalid_parameter`] names a parameter out of its range;
//! - [`EmbeddingStore`](crate::storage::EmbeddingStore) (in `storage`) holds the embeddings.
//!
//! `examples/custom_map.rs` in the repository builds a small map on it.

mod checks;
mod config;
pub(crate) mod memory;
mod pixels;

pub use checks::{
    at_least_one, check_observation, check_snapshot, count_in, invalid_parameter, number_in,
    positive_metres, resolve_dim, unit_weight,
};
pub use config::{DEFAULT_MAX_DEPTH, DEFAULT_PIXEL_STRIDE, MapCommon};
pub use pixels::{FramePixels, Pixel, embedding};
