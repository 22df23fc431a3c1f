//! vlem-core: the types, stage traits, configuration, plugin registry, pipeline and map file of
//! vlem, a framework for real-time 3D vision-language embedding mapping (Rauch et al., "VLEM").
//!
//! What is where:
//! - [`types`]: images, intrinsics, poses, frames, regions; [`embeddings`]: an encoder's output,
//!   [`PixelEmbeddings`] (a region table or a patch grid; `PatchSampler` reads patch-grid pixels as
//!   weights of grid rows);
//! - `traits/`, one file per stage trait ([`FrameSource`], [`Tracker`], [`RegionProposer`],
//!   [`Encoder`], [`EmbeddingMap`], [`Segmenter`]), and [`StageKind`], a leaf module;
//! - the `inventory` registry ([`Registry`]; `register_*!` macros, datasets included, with a probe
//!   for `kind = "auto"`; `feature_hint!`);
//! - [`config`]: the TOML config and its loading (the keys every dataset reader shares; readers'
//!   and the ROS 2 node's own keys stay tables for their crates to parse);
//! - [`pipeline`]: the threaded pipeline, its `RunReport` and its `StopHandle` (ends a run early
//!   from another thread, e.g. on Ctrl-C); [`stream`]: frames pushed in by a caller;
//! - [`live`]: the map while it is built, shared with readers; [`mapfile`]: the map file format;
//! - [`files`]: crash-safe result files and the process's memory; [`query`]: the similarity
//!   kernel; [`ranges`]: the checked ranges of config values.
//!
//! See `ARCHITECTURE.md` at the repository root for the data flow and which crate owns what.

pub mod config;
pub mod embeddings;
mod error;
pub mod files;
pub mod live;
pub mod mapfile;
pub mod pipeline;
pub mod query;
pub mod ranges;
mod registry;
mod stage;
pub mod stream;
mod traits;
pub mod types;

pub use config::{Config, StageConfig};
pub use embeddings::{EmbeddingLayout, NO_REGION, PixelEmbeddings};
pub use error::{CoreError, Result, message_chain};
pub use mapfile::{MapMetadata, MapSnapshot, read_map_file, write_map_file};
pub use registry::{
    BuildContext, BuildFn, Builder, DatasetProbe, DatasetReader, FeatureHint, OpenDatasetFn,
    Registration, Registry, load_config, parse_params,
};
pub use stage::StageKind;
pub use traits::embedding_map::{EmbeddingMap, IntegrationStats, MapBudget, Observation};
pub use traits::encoder::{Encoder, GENERIC_TEXT};
pub use traits::frame_source::FrameSource;
pub use traits::observer::{NoObserver, RunObserver};
pub use traits::region_proposer::RegionProposer;
pub use traits::segmenter::{PointSet, QueryScores, Segmenter};
pub use traits::tracker::{TrackedPose, Tracker, TrackingState};
pub use types::{
    ColouredMesh, DepthImage, Frame, Intrinsics, LabelImage, LabelNames, PinholeF32, PixelRect,
    Pose, Region, RgbImage, RigidF32,
};

#[doc(hidden)]
pub mod __private {
    pub use inventory;
}
