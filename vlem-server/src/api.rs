//! The request and response bodies of the query server, shared by the server and its client.

use serde::{Deserialize, Serialize};
use vlem_core::live::RunStatus;

/// `POST /query`: texts and how to select points.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QueryRequest {
    /// Query texts (at least one).
    pub texts: Vec<String>,
    /// Segmenter name: `threshold` (default), `argmax`, `cluster`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segmenter: Option<String>,
    /// Minimum normalised similarity (default 0.75 for `threshold`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f32>,
    /// The generic text `argmax` and `cluster` compare against (default "object").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline: Option<String>,
    /// Compute a grasp on each query's best point set.
    #[serde(default)]
    pub grasp: bool,
    /// Include each point set's point indices in the answer.
    #[serde(default)]
    pub indices: bool,
}

/// `POST /snapshot`'s answer: where the server saved the map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SnapshotSaved {
    /// The saved file's path on the server's machine.
    pub path: String,
    /// Its name in the run's output folder (`snapshot-NNNN.vlem`).
    pub file: String,
    /// Map elements saved.
    pub points: usize,
    /// Frames integrated into the saved map.
    pub frames_integrated: usize,
    /// Bytes of the file.
    pub bytes: u64,
}

/// The map part of [`Status`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapStatus {
    /// Registered map name.
    pub kind: String,
    /// Map elements.
    pub points: usize,
    /// Embedding dimension.
    pub dim: usize,
    /// Host bytes of map storage.
    pub bytes: usize,
    /// Device bytes of map storage (`[map] device = "cuda"`), 0 for a map on the host.
    #[serde(default)]
    pub device_bytes: usize,
    /// Frames integrated.
    pub frames_integrated: usize,
}

/// `GET /status`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Status {
    /// The run's counters and latest pose.
    pub run: RunStatus,
    /// The map, when the pipeline has one.
    pub map: Option<MapStatus>,
    /// The encoder that embeds query texts, when there is one.
    pub encoder: Option<String>,
}

/// The body of every error answer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorReply {
    /// What went wrong, as the command line would say it.
    pub error: String,
}
