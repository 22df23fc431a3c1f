//! vlem as one library: every crate of the workspace under one name, a [`prelude`], and every
//! implementation the enabled features compile in linked, so that a program that depends on
//! `vlem` alone builds any stage by the name a config gives it.
//!
//! ```toml
//! [dependencies]
//! vlem = { path = "../vlem", default-features = false, features = ["point-cloud", "colour-names"] }
//! ```
//!
//! Without `default-features`, the `cli` feature is off too: the command's own dependencies
//! (argument parsing, progress bars, plots, signal handling) are not compiled.
//! `tests/library-user/` is such a program, outside the workspace; CI builds and runs it.
//!
//! A program that runs the candle models (CLIP, SAM, dinov3, NARADIO, MiniLM) on the CPU calls
//! [`backends::use_all_cpus_once`] and [`backends::keep_freed_memory`] first thing in `main`, as
//! the `vlem` command does: the first gives candle its thread count once (without
//! `RAYON_NUM_THREADS` it recounts the cores from /proc/cpuinfo for every op), the second keeps
//! freed model buffers for reuse.
//!
//! ```no_run
//! use vlem::prelude::*;
//!
//! let config = load_config("configs/demo.toml".as_ref())?;
//! # Ok::<(), vlem::core::CoreError>(())
//! ```
//!
//! Why it exists: implementations register themselves with `inventory`, and a crate that a
//! program depends on but never names is not linked, so its registrations vanish without a word.
//! Before this crate, a library user listed five or six crates and wrote `use … as _;` for each
//! plugin; here that list is written once ([`plugins`]), with the cargo features that turn each
//! implementation on (feature name = implementation name, as for the `vlem` command, which is
//! built on this library).
//!
//! The modules are the workspace's crates, each with its own docs: [`core`] (types, the stage
//! traits, the registry, config, pipeline, live map and map file), [`datasets`], [`trackers`],
//! [`maps`], [`backends`] (the models), [`query`] (answers, segmenters, grasps, heatmaps),
//! [`eval`] (trajectory and semantic-segmentation evaluation, studies), [`server`] (the HTTP
//! query server) and, with the feature `ros2`, [`ros2`] (the live node).

pub use vlem_backends as backends;
pub use vlem_core as core;
pub use vlem_datasets as datasets;
pub use vlem_eval as eval;
pub use vlem_maps as maps;
pub use vlem_query as query;
#[cfg(feature = "ros2")]
pub use vlem_ros2 as ros2;
pub use vlem_server as server;
pub use vlem_trackers as trackers;

pub mod plugins;

/// What most programs built on vlem use: the config and the pipeline, the registry that builds
/// stages by name, the types a frame source produces, the stage traits, the map file and the
/// query answers.
pub mod prelude {
    pub use vlem_core::config::{Config, DatasetConfig, Mode, PipelineConfig};
    pub use vlem_core::live::LiveMap;
    pub use vlem_core::pipeline::{Pipeline, Progress, RunReport};
    pub use vlem_core::{
        BuildContext, CoreError, EmbeddingMap, Encoder, Frame, FrameSource, Intrinsics,
        MapSnapshot, Pose, RegionProposer, Registry, Segmenter, StageConfig, Tracker, load_config,
        read_map_file, write_map_file,
    };
    pub use vlem_query::answer::{AnswerOptions, Selection, answer_live, answer_snapshot};
}
