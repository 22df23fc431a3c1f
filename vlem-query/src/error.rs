//! The error type of `vlem-query`: what can go wrong between a text and a grasp.

use vlem_core::{CoreError, StageKind};

/// Failures of queries, segmenters and grasps.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum QueryError {
    /// A parameter out of its range.
    #[error("parameter `{name}` {reason}")]
    InvalidParameter {
        /// Parameter name as in the config.
        name: &'static str,
        /// What the valid range is.
        reason: String,
    },
    /// Score lists that do not match the points.
    #[error("query {query} has {actual} scores for {expected} points")]
    ScoreCount {
        /// Query index.
        query: usize,
        /// Points.
        expected: usize,
        /// Scores given.
        actual: usize,
    },
    /// A segmenter that compares against a baseline query got no baseline scores.
    #[error(
        "no similarities for the baseline query \"{baseline}\": the caller must score it (see `Segmenter::baseline_query`)"
    )]
    MissingBaseline {
        /// The baseline text.
        baseline: String,
    },
    /// Baseline scores that do not match the points.
    #[error("the baseline query has {actual} scores for {expected} points")]
    BaselineCount {
        /// Points.
        expected: usize,
        /// Scores given.
        actual: usize,
    },
    /// Too few (distinct) points to place a grasp.
    #[error("too few points for a grasp: {found} at the grasp depth, at least {needed} needed")]
    GraspPoints {
        /// Usable points found.
        found: usize,
        /// The minimum.
        needed: usize,
    },
    /// The object is wider than the gripper opens at the grasp depth.
    #[error(
        "the object is {width:.3} m wide at the grasp depth, the gripper opens to {max_width:.3} m"
    )]
    GraspWidth {
        /// Narrowest width of the object in the grasp slab (m).
        width: f64,
        /// The gripper's maximum opening (m).
        max_width: f64,
    },
    /// The map was built without an encoder, so it holds no embeddings to compare texts with.
    #[error("{map} was mapped without an encoder (geometry only): it cannot answer text queries")]
    GeometryOnly {
        /// The map (a file name, or "the live map").
        map: String,
    },
    /// The encoder that embeds the query texts makes embeddings of another size than the map's.
    #[error(
        "the map holds {map_dim}-d embeddings but the encoder `{encoder}` makes {encoder_dim}-d ones"
    )]
    EncoderDimension {
        /// The map's embedding dimension.
        map_dim: usize,
        /// The encoder's registered name.
        encoder: String,
        /// The encoder's dimension.
        encoder_dim: usize,
    },
    /// A query text the encoder could not embed.
    #[error("cannot embed the query \"{text}\": {source}")]
    Embed {
        /// The text.
        text: String,
        /// Why.
        source: CoreError,
    },
    /// The baseline text of a segmenter the encoder could not embed.
    #[error(
        "cannot embed the query \"{text}\", the baseline of segmenter `{segmenter}` (set its `baseline` parameter, e.g. to \"{generic}\", which the encoder can embed; `vlem query --baseline TEXT`): {source}"
    )]
    Baseline {
        /// The baseline text.
        text: String,
        /// The segmenter's name.
        segmenter: &'static str,
        /// The encoder's generic text, which it can embed.
        generic: String,
        /// Why it could not be embedded.
        source: Box<CoreError>,
    },
    /// No texts were given.
    #[error("no query texts given")]
    NoTexts,
    /// An error of the core (registry, map file, similarity kernel).
    #[error(transparent)]
    Core(#[from] CoreError),
}

impl QueryError {
    /// Wraps this error for the pipeline, naming the implementation.
    pub fn into_core(self, kind: StageKind, name: &str) -> CoreError {
        CoreError::stage(kind, name, self)
    }
}

/// Results of this crate.
pub type Result<T, E = QueryError> = std::result::Result<T, E>;
