//! Segmenters: per-point similarities → point sets (paper, "3D Query Segmentation").

use serde::Deserialize;
use vlem_core::{BuildContext, PointSet, QueryScores, Segmenter, StageKind, parse_params};

use crate::error::MapError;

/// `[query.segmenter] kind = "threshold"`: every point whose normalised similarity reaches the
/// threshold, independently per query (the paper's binary thresholding).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ThresholdSegmenter {
    /// Minimum normalised similarity in `[0, 1]`; default 0.75.
    #[serde(default = "default_threshold")]
    pub threshold: f32,
}

fn default_threshold() -> f32 {
    0.75
}

impl Default for ThresholdSegmenter {
    fn default() -> Self {
        Self {
            threshold: default_threshold(),
        }
    }
}

const THRESHOLD: &str = "threshold";

fn build_threshold(
    params: &toml::Table,
    _ctx: &BuildContext,
) -> vlem_core::Result<Box<dyn Segmenter>> {
    let segmenter: ThresholdSegmenter = parse_params(StageKind::Segmenter, THRESHOLD, params)?;
    if !(0.0..=1.0).contains(&segmenter.threshold) {
        return Err(MapError::InvalidParameter {
            name: "threshold",
            reason: format!("must lie in [0, 1], got {}", segmenter.threshold),
        }
        .into_core(StageKind::Segmenter, THRESHOLD));
    }
    Ok(Box::new(segmenter))
}

vlem_core::register_segmenter!(
    THRESHOLD,
    "points whose similarity reaches a threshold, per query",
    build_threshold
);

impl Segmenter for ThresholdSegmenter {
    fn name(&self) -> &'static str {
        THRESHOLD
    }

    fn segment(
        &self,
        positions: &[[f32; 3]],
        scores: &QueryScores,
    ) -> vlem_core::Result<Vec<PointSet>> {
        scores
            .scores
            .iter()
            .enumerate()
            .map(|(query, s)| {
                if s.len() != positions.len() {
                    return Err(MapError::ScoreCount {
                        query,
                        expected: positions.len(),
                        actual: s.len(),
                    }
                    .into_core(StageKind::Segmenter, THRESHOLD));
                }
                let indices: Vec<usize> =
                    (0..s.len()).filter(|&i| s[i] >= self.threshold).collect();
                let mean_score = if indices.is_empty() {
                    0.0
                } else {
                    indices.iter().map(|&i| s[i]).sum::<f32>() / indices.len() as f32
                };
                Ok(PointSet {
                    query,
                    indices,
                    mean_score,
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_keeps_points_at_or_above_it() {
        let seg = ThresholdSegmenter { threshold: 0.5 };
        let scores = QueryScores {
            queries: vec!["a".into(), "b".into()],
            scores: vec![vec![0.2, 0.5, 0.9], vec![0.0, 0.0, 0.1]],
            baseline: None,
        };
        let sets = seg.segment(&[[0.0; 3]; 3], &scores).unwrap();
        assert_eq!(sets[0].indices, vec![1, 2]);
        assert!((sets[0].mean_score - 0.7).abs() < 1e-6);
        assert!(sets[1].indices.is_empty());
        assert_eq!(sets[1].mean_score, 0.0);
        let err = seg.segment(&[[0.0; 3]; 2], &scores).unwrap_err();
        assert_eq!(
            err.to_string(),
            "segmenter `threshold`: query 0 has 3 scores for 2 points"
        );
    }
}
