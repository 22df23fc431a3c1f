//! vlem-core: the types, stage traits, configuration, plugin registry, pipeline and map file of
//! vlem, a framework for real-time 3D vision-language embedding mapping (Rauch et al., "VLEM").
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
