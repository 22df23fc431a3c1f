//! Segmenters: per-point similarities → point sets (paper, "3D Query Segmentation").
//!
//! - `threshold`: binary thresholding, independently per query;
//! - `argmax`: the partition of the map by the highest similarity among the queries and a generic
//!   baseline ("object"), whose points are dropped;
//! - `cluster`: the partition, then per query a 3-component Gaussian mixture on the similarities
//!   (keeping the highest-mean component) and DBSCAN on the coordinates; one point set per cluster,
//!   best first — the closed point sets a robot can grasp.

pub mod dbscan;
pub mod gmm;

use serde::Deserialize;
use vlem_core::ranges;
use vlem_core::{BuildContext, PointSet, QueryScores, Segmenter, StageKind, parse_params};

use crate::error::QueryError;

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
        return Err(QueryError::InvalidParameter {
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
                    return Err(QueryError::ScoreCount {
                        query,
                        expected: positions.len(),
                        actual: s.len(),
                    }
                    .into_core(StageKind::Segmenter, THRESHOLD));
                }
                let indices: Vec<usize> =
                    (0..s.len()).filter(|&i| s[i] >= self.threshold).collect();
                Ok(PointSet {
                    query,
                    mean_score: mean_score(s, &indices),
                    indices,
                })
            })
            .collect()
    }
}

/// Mean of `s` over `indices`; 0 when empty.
fn mean_score(s: &[f32], indices: &[usize]) -> f32 {
    if indices.is_empty() {
        0.0
    } else {
        indices.iter().map(|&i| s[i]).sum::<f32>() / indices.len() as f32
    }
}

fn default_baseline() -> String {
    vlem_core::GENERIC_TEXT.into()
}

/// `[query.segmenter] kind = "argmax"`: the paper's partition. Every point goes to the query with
/// the highest similarity among `[s_1, …, s_N, s_baseline]`; points the baseline wins (or ties)
/// are dropped. One point set per query.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ArgmaxSegmenter {
    /// The generic baseline text a point must beat; default "object".
    #[serde(default = "default_baseline")]
    pub baseline: String,
    /// Minimum similarity of a point to the query it wins, in `[0, 1]`; default 0 (none).
    #[serde(default)]
    pub threshold: f32,
}

impl Default for ArgmaxSegmenter {
    fn default() -> Self {
        Self {
            baseline: default_baseline(),
            threshold: 0.0,
        }
    }
}

impl ArgmaxSegmenter {
    /// The indices of the points each query wins, one list per query.
    ///
    /// # Errors
    /// Score lists (or the baseline's) of another length than `positions`, or no baseline scores.
    pub fn partition(
        &self,
        positions: &[[f32; 3]],
        scores: &QueryScores,
    ) -> Result<Vec<Vec<usize>>, QueryError> {
        let n = positions.len();
        for (query, s) in scores.scores.iter().enumerate() {
            if s.len() != n {
                return Err(QueryError::ScoreCount {
                    query,
                    expected: n,
                    actual: s.len(),
                });
            }
        }
        let baseline = scores
            .baseline
            .as_deref()
            .ok_or_else(|| QueryError::MissingBaseline {
                baseline: self.baseline.clone(),
            })?;
        if baseline.len() != n {
            return Err(QueryError::BaselineCount {
                expected: n,
                actual: baseline.len(),
            });
        }
        let mut sets = vec![Vec::new(); scores.scores.len()];
        for (i, &base) in baseline.iter().enumerate() {
            // The first query wins ties between queries; NaN never wins.
            let mut best: Option<(usize, f32)> = None;
            for (q, s) in scores.scores.iter().enumerate() {
                if s[i] > best.map_or(f32::NEG_INFINITY, |b| b.1) {
                    best = Some((q, s[i]));
                }
            }
            if let Some((q, s)) = best
                && s > base
                && s >= self.threshold
            {
                sets[q].push(i);
            }
        }
        Ok(sets)
    }
}

const ARGMAX: &str = "argmax";

fn check_unit(name: &'static str, value: f32) -> Result<(), QueryError> {
    if (0.0..=1.0).contains(&value) {
        Ok(())
    } else {
        Err(QueryError::InvalidParameter {
            name,
            reason: format!("must lie in [0, 1], got {value}"),
        })
    }
}

fn check_baseline(baseline: &str) -> Result<(), QueryError> {
    if baseline.trim().is_empty() {
        Err(QueryError::InvalidParameter {
            name: "baseline",
            reason: "must be a non-empty text such as \"object\"".into(),
        })
    } else {
        Ok(())
    }
}

fn build_argmax(
    params: &toml::Table,
    _ctx: &BuildContext,
) -> vlem_core::Result<Box<dyn Segmenter>> {
    let segmenter: ArgmaxSegmenter = parse_params(StageKind::Segmenter, ARGMAX, params)?;
    check_unit("threshold", segmenter.threshold)
        .and_then(|()| check_baseline(&segmenter.baseline))
        .map_err(|e| e.into_core(StageKind::Segmenter, ARGMAX))?;
    Ok(Box::new(segmenter))
}

vlem_core::register_segmenter!(
    ARGMAX,
    "partition by the best of the queries and a baseline (\"object\")",
    build_argmax
);

impl Segmenter for ArgmaxSegmenter {
    fn name(&self) -> &'static str {
        ARGMAX
    }

    fn baseline_query(&self) -> Option<&str> {
        Some(&self.baseline)
    }

    fn segment(
        &self,
        positions: &[[f32; 3]],
        scores: &QueryScores,
    ) -> vlem_core::Result<Vec<PointSet>> {
        let sets = self
            .partition(positions, scores)
            .map_err(|e| e.into_core(StageKind::Segmenter, ARGMAX))?;
        Ok(sets
            .into_iter()
            .enumerate()
            .map(|(query, indices)| PointSet {
                query,
                mean_score: mean_score(&scores.scores[query], &indices),
                indices,
            })
            .collect())
    }
}

fn default_components() -> usize {
    3
}

fn default_eps() -> f32 {
    0.05
}

fn default_min_points() -> usize {
    10
}

/// `[query.segmenter] kind = "cluster"`: the paper's full procedure for closed point sets. The
/// argmax partition; per query a Gaussian mixture on the similarities of its points (means
/// initialised evenly from the minimum to the maximum similarity), keeping the points of the
/// highest-mean component; DBSCAN on their coordinates, dropping noise. One point set per cluster,
/// ranked by mean similarity (best first) within each query.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ClusterSegmenter {
    /// The generic baseline text a point must beat; default "object".
    #[serde(default = "default_baseline")]
    pub baseline: String,
    /// Minimum similarity of a point to the query it wins, in `[0, 1]`; default 0 (none).
    #[serde(default)]
    pub threshold: f32,
    /// Gaussian mixture components; default 3 (the paper).
    #[serde(default = "default_components")]
    pub components: usize,
    /// DBSCAN neighbourhood radius in metres; default 0.05.
    #[serde(default = "default_eps")]
    pub eps: f32,
    /// DBSCAN: points (itself included) within `eps` that make a point a core point; default 10.
    #[serde(default = "default_min_points")]
    pub min_points: usize,
}

impl Default for ClusterSegmenter {
    fn default() -> Self {
        Self {
            baseline: default_baseline(),
            threshold: 0.0,
            components: default_components(),
            eps: default_eps(),
            min_points: default_min_points(),
        }
    }
}

const CLUSTER: &str = "cluster";

/// The most mixture components the cluster segmenter fits (3 separates background, clutter and
/// the queried object; dozens are already one per point set).
const MAX_COMPONENTS: usize = 64;

fn build_cluster(
    params: &toml::Table,
    _ctx: &BuildContext,
) -> vlem_core::Result<Box<dyn Segmenter>> {
    let s: ClusterSegmenter = parse_params(StageKind::Segmenter, CLUSTER, params)?;
    let range = |name: &'static str, checked: Result<(), String>| {
        checked.map_err(|reason| QueryError::InvalidParameter { name, reason })
    };
    let checked = check_unit("threshold", s.threshold)
        .and_then(|()| check_baseline(&s.baseline))
        .and_then(|()| {
            // The mixture fit holds points × components responsibilities, on every query.
            range(
                "components",
                ranges::count(s.components, 1, MAX_COMPONENTS, "").map(drop),
            )
        })
        .and_then(|()| range("eps", ranges::number(s.eps, 1e-4, 10.0, "m").map(drop)))
        .and_then(|()| {
            range(
                "min_points",
                ranges::count(s.min_points, 1, 1_000_000, "points").map(drop),
            )
        });
    checked.map_err(|e| e.into_core(StageKind::Segmenter, CLUSTER))?;
    Ok(Box::new(s))
}

vlem_core::register_segmenter!(
    CLUSTER,
    "argmax partition, then GMM on similarity and DBSCAN on coordinates; one set per cluster",
    build_cluster
);

impl Segmenter for ClusterSegmenter {
    fn name(&self) -> &'static str {
        CLUSTER
    }

    fn baseline_query(&self) -> Option<&str> {
        Some(&self.baseline)
    }

    fn segment(
        &self,
        positions: &[[f32; 3]],
        scores: &QueryScores,
    ) -> vlem_core::Result<Vec<PointSet>> {
        let argmax = ArgmaxSegmenter {
            baseline: self.baseline.clone(),
            threshold: self.threshold,
        };
        let partition = argmax
            .partition(positions, scores)
            .map_err(|e| e.into_core(StageKind::Segmenter, CLUSTER))?;
        let mut out = Vec::new();
        for (query, members) in partition.into_iter().enumerate() {
            let s = &scores.scores[query];
            let member_scores: Vec<f32> = members.iter().map(|&i| s[i]).collect();
            let kept: Vec<usize> = gmm::top_component(&member_scores, self.components)
                .into_iter()
                .map(|k| members[k])
                .collect();
            let kept_positions: Vec<[f32; 3]> = kept.iter().map(|&i| positions[i]).collect();
            let mut sets: Vec<PointSet> =
                dbscan::dbscan(&kept_positions, self.eps, self.min_points)
                    .into_iter()
                    .map(|cluster| {
                        let indices: Vec<usize> = cluster.into_iter().map(|k| kept[k]).collect();
                        PointSet {
                            query,
                            mean_score: mean_score(s, &indices),
                            indices,
                        }
                    })
                    .collect();
            sets.sort_by(|a, b| b.mean_score.total_cmp(&a.mean_score));
            out.extend(sets);
        }
        Ok(out)
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

    #[test]
    fn argmax_partitions_and_drops_the_baseline() {
        let seg = ArgmaxSegmenter::default();
        assert_eq!(seg.baseline_query(), Some("object"));
        let scores = QueryScores {
            queries: vec!["a".into(), "b".into()],
            scores: vec![vec![0.9, 0.2, 0.6, 0.5], vec![0.1, 0.8, 0.7, 0.5]],
            baseline: Some(vec![0.5, 0.5, 0.5, 0.5]),
        };
        let sets = seg.segment(&[[0.0; 3]; 4], &scores).unwrap();
        assert_eq!(sets.len(), 2);
        assert_eq!(sets[0].indices, vec![0]);
        assert_eq!(sets[1].indices, vec![1, 2]);
        assert!((sets[1].mean_score - 0.75).abs() < 1e-6);
        // Point 3 ties the baseline: dropped.
        let strict = ArgmaxSegmenter {
            threshold: 0.85,
            ..ArgmaxSegmenter::default()
        };
        let sets = strict.segment(&[[0.0; 3]; 4], &scores).unwrap();
        assert_eq!(sets[0].indices, vec![0]);
        assert!(sets[1].indices.is_empty());

        let missing = QueryScores {
            baseline: None,
            ..scores.clone()
        };
        let err = seg.segment(&[[0.0; 3]; 4], &missing).unwrap_err();
        assert!(err.to_string().contains("\"object\""), "{err}");
        let short = QueryScores {
            baseline: Some(vec![0.5; 3]),
            ..scores
        };
        assert!(seg.segment(&[[0.0; 3]; 4], &short).is_err());
    }

    #[test]
    fn cluster_keeps_high_similarity_blobs_ranked_best_first() {
        // Two 6×6×3 blobs 1 m apart with high similarity, a low-similarity carpet between them,
        // a few isolated high-similarity points, and points the baseline wins.
        let mut positions = Vec::new();
        let mut query = Vec::new();
        let mut base = Vec::new();
        let grid = |c: [f32; 3], out: &mut Vec<[f32; 3]>| {
            for x in 0..6 {
                for y in 0..6 {
                    for z in 0..3 {
                        out.push([
                            c[0] + 0.01 * x as f32,
                            c[1] + 0.01 * y as f32,
                            c[2] + 0.01 * z as f32,
                        ]);
                    }
                }
            }
        };
        grid([0.0, 0.0, 0.0], &mut positions);
        query.resize(positions.len(), 0.85);
        grid([1.0, 0.0, 0.0], &mut positions);
        query.resize(positions.len(), 0.9);
        let carpet_start = positions.len();
        for i in 0..200 {
            positions.push([0.3 + 0.002 * i as f32, 0.5, 0.0]);
            query.push(0.55 + 0.0001 * (i % 7) as f32);
        }
        for i in 0..150 {
            positions.push([0.3 + 0.002 * i as f32, 0.8, 0.0]);
            query.push(0.7 + 0.0001 * (i % 5) as f32);
        }
        positions.extend([[5.0, 5.0, 5.0], [-5.0, 0.0, 2.0]]);
        query.extend([0.88, 0.88]);
        base.resize(positions.len(), 0.5);
        positions.push([0.0, 0.0, 0.0]);
        query.push(0.95);
        base.push(0.99);
        let scores = QueryScores {
            queries: vec!["mug".into()],
            scores: vec![query],
            baseline: Some(base),
        };
        let seg = ClusterSegmenter::default();
        let sets = seg.segment(&positions, &scores).unwrap();
        assert_eq!(sets.len(), 2, "{sets:?}");
        assert!((sets[0].mean_score - 0.9).abs() < 1e-6);
        assert_eq!(sets[0].indices, (108..216).collect::<Vec<_>>());
        assert!((sets[1].mean_score - 0.85).abs() < 1e-6);
        assert_eq!(sets[1].indices, (0..108).collect::<Vec<_>>());
        for set in &sets {
            assert!(set.indices.iter().all(|&i| i < carpet_start));
        }

        // Nothing won by the query: no sets, no error.
        let none = QueryScores {
            queries: vec!["mug".into()],
            scores: vec![vec![0.1; 4]],
            baseline: Some(vec![0.5; 4]),
        };
        assert!(seg.segment(&[[0.0; 3]; 4], &none).unwrap().is_empty());
        assert!(
            seg.segment(
                &[],
                &QueryScores {
                    queries: vec!["mug".into()],
                    scores: vec![vec![]],
                    baseline: Some(vec![]),
                }
            )
            .unwrap()
            .is_empty()
        );
    }

    #[test]
    fn builders_validate_parameters() {
        let ctx = BuildContext {
            config_dir: std::path::PathBuf::new(),
            embedding_dim: None,
        };
        let table = |text: &str| -> toml::Table { toml::from_str(text).unwrap() };
        assert!(build_argmax(&table(""), &ctx).is_ok());
        assert!(build_argmax(&table("threshold = 2.0"), &ctx).is_err());
        assert!(build_argmax(&table("baseline = \"\""), &ctx).is_err());
        let seg = build_cluster(&table("baseline = \"thing\"\neps = 0.1"), &ctx).unwrap();
        assert_eq!(seg.baseline_query(), Some("thing"));
        for bad in [
            "eps = 0.0",
            "min_points = 0",
            "components = 0",
            "epss = 1.0",
        ] {
            assert!(build_cluster(&table(bad), &ctx).is_err(), "{bad}");
        }
    }
}
