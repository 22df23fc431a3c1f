//! vlem-query: the query path of vlem, from a text to a grasp, for every front-end.
//!
//! text → [`answer::embed_texts`] (the encoder that made the map, [`answer::encoder_for_map`]) →
//! per-point similarities ([`answer::score_snapshot`] on a saved map, [`answer::score_live`] on a
//! map being built) → a [`vlem_core::Segmenter`] ([`segmenters`]) → point sets → a grasp
//! ([`grasp`]) → a summary ([`answer::Answer`]) and a heatmap ([`heatmap`]).
//!
//! Maps (`vlem-maps`) own only storage and integration; everything that turns scores into
//! decisions lives here, so the `vlem` command, its query server and future front-ends share it.
//! The segmenters register themselves with the vlem registry: binaries reference this crate so
//! that the registrations are linked.

pub mod answer;
pub mod error;
pub mod grasp;
pub mod heatmap;
pub mod segmenters;

pub use error::QueryError;
