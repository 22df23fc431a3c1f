//! The pipeline stages that have pluggable implementations.
//!
//! A leaf of the crate: it imports nothing from it, so that the error type, the registry and the
//! stage traits can all name a stage without importing one another.

use std::fmt;

/// The pipeline stages that have pluggable implementations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum StageKind {
    /// [`FrameSource`](crate::FrameSource) readers, config section `[dataset]`.
    Dataset,
    /// [`Tracker`](crate::Tracker), config section `[tracker]`.
    Tracker,
    /// [`RegionProposer`](crate::RegionProposer), config section `[proposer]`.
    Proposer,
    /// [`Encoder`](crate::Encoder), config section `[encoder]`.
    Encoder,
    /// [`EmbeddingMap`](crate::EmbeddingMap), config section `[map]`.
    Map,
    /// [`Segmenter`](crate::Segmenter), config section `[query.segmenter]`.
    Segmenter,
}

impl StageKind {
    /// Every stage, in pipeline order.
    pub const ALL: [StageKind; 6] = [
        StageKind::Dataset,
        StageKind::Tracker,
        StageKind::Proposer,
        StageKind::Encoder,
        StageKind::Map,
        StageKind::Segmenter,
    ];

    /// The config section that configures this stage.
    pub fn section(self) -> &'static str {
        match self {
            StageKind::Dataset => "dataset",
            StageKind::Tracker => "tracker",
            StageKind::Proposer => "proposer",
            StageKind::Encoder => "encoder",
            StageKind::Map => "map",
            StageKind::Segmenter => "query.segmenter",
        }
    }
}

impl fmt::Display for StageKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            StageKind::Dataset => "dataset",
            StageKind::Tracker => "tracker",
            StageKind::Proposer => "region proposer",
            StageKind::Encoder => "encoder",
            StageKind::Map => "map",
            StageKind::Segmenter => "segmenter",
        })
    }
}
