//! `Segmenter`: from per-point query similarities to point sets.
//!
//! Why it exists: the paper turns heatmaps into sets of points in several ways (binary threshold,
//! argmax against a generic "object" query, GMM + DBSCAN clustering) and robots need closed point
//! sets (to grasp an object). A segmenter owns only that decision; it never touches embeddings.

use crate::error::Result;

/// Similarities of every map point for a list of queries.
#[derive(Clone, Debug, PartialEq)]
pub struct QueryScores {
    /// Query texts, in order.
    pub queries: Vec<String>,
    /// `scores[q][i]`: normalised similarity of point `i` to query `q`, in `[0, 1]`.
    pub scores: Vec<Vec<f32>>,
    /// Similarity of every point to the generic baseline query ([`Segmenter::baseline_query`],
    /// e.g. "object"), when the segmenter asked for one.
    pub baseline: Option<Vec<f32>>,
}

/// Points selected for one query.
#[derive(Clone, Debug, PartialEq)]
pub struct PointSet {
    /// Index into [`QueryScores::queries`].
    pub query: usize,
    /// Indices of the selected points.
    pub indices: Vec<usize>,
    /// Mean similarity of the selected points (0 when empty).
    pub mean_score: f32,
}

/// Selects point sets from query similarities.
pub trait Segmenter: Send + Sync {
    /// The registered name.
    fn name(&self) -> &'static str;

    /// A generic text (e.g. "object") whose similarity the caller must also compute and pass as
    /// [`QueryScores::baseline`]: the paper's baseline that a point must beat to belong to a query.
    /// `None` (the default) for segmenters that need none.
    fn baseline_query(&self) -> Option<&str> {
        None
    }

    /// Point sets for the queries, in any order and any number per query.
    ///
    /// # Errors
    /// Inconsistent inputs (score lists of different lengths than `positions`).
    fn segment(&self, positions: &[[f32; 3]], scores: &QueryScores) -> Result<Vec<PointSet>>;
}
