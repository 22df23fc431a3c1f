//! The result row of one `vlem study` cell: what `study` writes to `result.json` and `study.csv`,
//! and what `study_plot` draws. Its own module so that both read it without importing each other.

use serde::{Deserialize, Serialize};

/// One cell's outcome: a CSV row.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
pub(crate) struct CellResult {
    pub cell: usize,
    pub sequence: String,
    pub tracker: String,
    pub encoder: String,
    pub map: String,
    /// `ok`, or `failed`.
    pub status: String,
    pub protocol: String,
    pub classes: String,
    pub miou: Option<f64>,
    pub map_points: Option<u64>,
    pub map_bytes: Option<u64>,
    /// Peak resident memory of the mapping run (`vlem run`).
    pub peak_resident_bytes: Option<u64>,
    pub frames: Option<u64>,
    pub wall_seconds: Option<f64>,
    pub load_ms: Option<f64>,
    pub track_ms: Option<f64>,
    pub propose_ms: Option<f64>,
    pub encode_ms: Option<f64>,
    pub integrate_ms: Option<f64>,
    pub eval_seconds: Option<f64>,
    /// Why a failed cell failed (the last line its process printed).
    pub error: String,
}
