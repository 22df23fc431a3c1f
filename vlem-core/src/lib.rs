//! vlem-core: the types, stage traits, configuration, plugin registry, pipeline and map file of
//! vlem, a framework for real-time 3D vision-language embedding mapping (Rauch et al., "VLEM").
//!
//! See `ARCHITECTURE.md` at the repository root for the data flow and which crate owns what.

pub mod config;
pub mod embeddings;
pub mod error;
pub mod mapfile;
pub mod pipeline;
pub mod query;
pub mod registry;
pub mod traits;
pub mod types;

pub use config::{Config, StageConfig};
pub use embeddings::{EmbeddingLayout, NO_SEGMENT, PixelEmbeddings};
pub use error::{CoreError, Result};
pub use mapfile::{MapMetadata, MapSnapshot, read_map_file, write_map_file};
pub use registry::{BuildContext, Registry, StageKind, parse_params};
pub use traits::embedding_map::{EmbeddingMap, IntegrationStats, MapBudget, Observation};
pub use traits::encoder::Encoder;
pub use traits::frame_source::FrameSource;
pub use traits::observer::{NoObserver, RunObserver};
pub use traits::region_proposer::RegionProposer;
pub use traits::segmenter::{PointSet, QueryScores, Segmenter};
pub use traits::tracker::{TrackedPose, Tracker, TrackingState};
pub use types::{
    ColouredMesh, DepthImage, Frame, Intrinsics, LabelImage, LabelNames, PixelRect, Pose, Region,
    RgbImage, RigidF32,
};
