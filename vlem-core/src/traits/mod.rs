//! The stage traits of the pipeline, one per file.
//!
//! All are dyn-compatible and `Send + Sync` (sources only `Send`): the pipeline holds `Box<dyn _>`
//! built by the [registry](crate::Registry) from the TOML config, and moves them between threads.

pub mod embedding_map;
pub mod encoder;
pub mod frame_source;
pub mod observer;
pub mod region_proposer;
pub mod segmenter;
pub mod tracker;
