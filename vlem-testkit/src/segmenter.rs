//! The conformance suite for [`Segmenter`] implementations:
//! [`segmenter_conformance!`](crate::segmenter_conformance).
//!
//! The suite's map ([`clustered_map`]) holds [`QUERIES`] compact clusters of points, one per query;
//! a cluster's points score about 0.9 for its own query and 0.1 for the others, and 0.5 for the
//! baseline query where the segmenter asks for one ([`Segmenter::baseline_query`]). What every
//! segmenter must do:
//! - [`Segmenter::name`] is a name registered for the segmenter stage in the registry;
//! - every point set is valid: its query index is in range, its indices are in range and unique,
//!   and its `mean_score` is the mean of the query's scores over its indices (0 when empty);
//! - each query gets points, and only points of its own cluster;
//! - an empty map (and a list of no queries) gives no point set or only empty ones;
//! - score lists (or baseline scores) of another length than the positions are an error, not a
//!   panic;
//! - segmenting twice gives the same point sets.
//!
//! The checks report failures by panicking, like `assert!`, with the segmenter and point set in
//! the message.
#![allow(
    clippy::panic,
    reason = "a test kit reports failed checks by panicking, exactly as assert! does"
)]

use std::collections::BTreeSet;

use vlem_core::{PointSet, QueryScores, Registry, Segmenter, StageKind};

/// How the suite gets a segmenter: a function (or non-capturing closure) building a fresh one.
pub type BuildSegmenter = fn() -> Box<dyn Segmenter>;

/// Number of queries (and clusters) of [`clustered_map`].
pub const QUERIES: usize = 3;

/// Score of a cluster's points for its own query (give or take 0.02).
pub const OWN_SCORE: f32 = 0.9;

/// Score of a cluster's points for the other queries.
pub const OTHER_SCORE: f32 = 0.1;

/// Score of every point for the baseline query.
pub const BASELINE_SCORE: f32 = 0.5;

/// How far a point set's `mean_score` may be from the mean of its scores.
pub const MEAN_TOLERANCE: f32 = 1e-5;

/// Runs the segmenter conformance suite as `#[test]` functions in a module
/// `segmenter_conformance`.
///
/// `$build` is an expression of type [`BuildSegmenter`] (`fn() -> Box<dyn Segmenter>`): a
/// function path or a closure that captures nothing. Each test builds its own segmenter. The
/// crate that registers the segmenter must be linked into the test binary (building the segmenter
/// through it is enough).
///
/// Invoke it once per module (it declares `mod segmenter_conformance`). `$build` is expanded
/// inside that module, which imports the invoking module's items with `use super::*`: plain names
/// and `crate::` paths work, `super::` paths do not.
///
/// ```
/// use vlem_core::{CoreError, PointSet, QueryScores, Result, Segmenter};
///
/// /// Every point scoring at least 0.5, per query.
/// struct Half;
///
/// impl Segmenter for Half {
///     fn name(&self) -> &'static str {
///         "half"
///     }
///     fn segment(&self, positions: &[[f32; 3]], scores: &QueryScores) -> Result<Vec<PointSet>> {
///         let mut sets = Vec::new();
///         for (query, s) in scores.scores.iter().enumerate() {
///             if s.len() != positions.len() {
///                 return Err(CoreError::MissingStage { message: "score count".into() });
///             }
///             let indices: Vec<usize> = (0..s.len()).filter(|&i| s[i] >= 0.5).collect();
///             let sum: f32 = indices.iter().map(|&i| s[i]).sum();
///             let mean_score = if indices.is_empty() { 0.0 } else { sum / indices.len() as f32 };
///             sets.push(PointSet { query, indices, mean_score });
///         }
///         Ok(sets)
///     }
/// }
///
/// // A real segmenter also registers itself (`vlem_core::register_segmenter!("half", ...)`),
/// // which the suite's `name_is_registered` checks.
/// vlem_testkit::segmenter_conformance!(|| Box::new(Half));
/// # fn main() {}
/// ```
#[macro_export]
macro_rules! segmenter_conformance {
    ($build:expr $(,)?) => {
        /// The vlem-testkit segmenter conformance suite.
        mod segmenter_conformance {
            #[allow(
                unused_imports,
                reason = "`$build` may name items of the invoking module"
            )]
            use super::*;

            #[test]
            fn name_is_registered() {
                $crate::segmenter::check_registered($build);
            }

            #[test]
            fn point_sets_are_valid() {
                $crate::segmenter::check_point_sets_valid($build);
            }

            #[test]
            fn each_query_gets_points_of_its_own_cluster() {
                $crate::segmenter::check_clusters_found($build);
            }

            #[test]
            fn an_empty_map_gives_no_points() {
                $crate::segmenter::check_empty($build);
            }

            #[test]
            fn mismatched_score_lengths_are_an_error() {
                $crate::segmenter::check_mismatched_lengths($build);
            }

            #[test]
            fn segmentation_is_deterministic() {
                $crate::segmenter::check_determinism($build);
            }
        }
    };
}

/// Checks that the segmenter's name is registered for the segmenter stage.
#[track_caller]
pub fn check_registered(build: BuildSegmenter) {
    let segmenter = build();
    let name = segmenter.name();
    let registry = match Registry::global() {
        Ok(r) => r,
        Err(e) => panic!("the registry cannot be built: {e}"),
    };
    if let Err(e) = registry.get(StageKind::Segmenter, name) {
        panic!("segmenter `{name}` is not registered: {e}");
    }
}

/// The suite's map: [`QUERIES`] clusters of 5x5x5 points 1 cm apart (dense enough for
/// any subset of a cluster to stay one cluster for a density-based clustering), 1 m from each other, and the
/// scores of every point (see the module docs); the baseline scores only when `with_baseline`.
pub fn clustered_map(with_baseline: bool) -> (Vec<[f32; 3]>, QueryScores) {
    let mut positions = Vec::new();
    let mut scores = vec![Vec::new(); QUERIES];
    for cluster in 0..QUERIES {
        for k in 0..125usize {
            let (x, y, z) = (k % 5, k / 5 % 5, k / 25);
            positions.push([
                cluster as f32 + 0.01 * x as f32,
                0.01 * y as f32,
                0.01 * z as f32,
            ]);
            for (query, s) in scores.iter_mut().enumerate() {
                s.push(if query == cluster {
                    // A spread of scores, as real similarities have, deterministic.
                    OWN_SCORE + 0.02 * ((k * 7 % 11) as f32 / 10.0 - 0.5)
                } else {
                    OTHER_SCORE
                });
            }
        }
    }
    let baseline = with_baseline.then(|| vec![BASELINE_SCORE; positions.len()]);
    let scores = QueryScores {
        queries: (0..QUERIES).map(|q| format!("query {q}")).collect(),
        scores,
        baseline,
    };
    (positions, scores)
}

/// Checks every point set of the segmenter on [`clustered_map`] with [`check_point_set`].
#[track_caller]
pub fn check_point_sets_valid(build: BuildSegmenter) {
    let segmenter = build();
    let (positions, scores) = clustered_map(segmenter.baseline_query().is_some());
    for set in segment(segmenter.as_ref(), &positions, &scores, "the clustered map") {
        check_point_set(&set, &positions, &scores, segmenter.name());
    }
}

/// Checks that each query of [`clustered_map`] gets at least one point, and only points of its
/// own cluster.
#[track_caller]
pub fn check_clusters_found(build: BuildSegmenter) {
    let segmenter = build();
    let (positions, scores) = clustered_map(segmenter.baseline_query().is_some());
    let sets = segment(segmenter.as_ref(), &positions, &scores, "the clustered map");
    let per_cluster = positions.len() / QUERIES;
    for query in 0..QUERIES {
        let own = query * per_cluster..(query + 1) * per_cluster;
        let selected: Vec<usize> = sets
            .iter()
            .filter(|s| s.query == query)
            .flat_map(|s| s.indices.iter().copied())
            .collect();
        assert!(
            !selected.is_empty(),
            "segmenter `{}`: query {query} got no point, though its cluster (points {own:?}) \
             scores {OWN_SCORE} and everything else {OTHER_SCORE}",
            segmenter.name()
        );
        if let Some(stray) = selected.iter().find(|i| !own.contains(i)) {
            panic!(
                "segmenter `{}`: query {query} got point {stray}, outside its cluster (points \
                 {own:?}), which scores {OTHER_SCORE} for it",
                segmenter.name()
            );
        }
    }
}

/// Checks that an empty map, with and without queries, gives no point set or only empty ones.
#[track_caller]
pub fn check_empty(build: BuildSegmenter) {
    let segmenter = build();
    let baseline = segmenter.baseline_query().is_some().then(Vec::new);
    for queries in [QUERIES, 0] {
        let scores = QueryScores {
            queries: (0..queries).map(|q| format!("query {q}")).collect(),
            scores: vec![Vec::new(); queries],
            baseline: baseline.clone(),
        };
        let what = format!("an empty map with {queries} queries");
        for set in segment(segmenter.as_ref(), &[], &scores, &what) {
            assert!(
                set.indices.is_empty(),
                "segmenter `{}`, {what}: a point set with indices {:?}",
                segmenter.name(),
                set.indices
            );
            check_point_set(&set, &[], &scores, segmenter.name());
        }
    }
}

/// Checks that a score list one short (and, where the segmenter asks for a baseline, baseline
/// scores one short) is refused with an error, not a panic.
#[track_caller]
pub fn check_mismatched_lengths(build: BuildSegmenter) {
    let segmenter = build();
    let with_baseline = segmenter.baseline_query().is_some();
    let (positions, good) = clustered_map(with_baseline);
    let mut short_query = good.clone();
    short_query.scores[1].pop();
    let mut cases = vec![("query 1 has one score too few", short_query)];
    if with_baseline {
        let mut short_baseline = good;
        if let Some(b) = short_baseline.baseline.as_mut() {
            b.pop();
        }
        cases.push(("the baseline has one score too few", short_baseline));
    }
    for (what, scores) in cases {
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            segmenter.segment(&positions, &scores).is_err()
        }));
        match outcome {
            Ok(true) => {}
            Ok(false) => panic!(
                "segmenter `{}`: {what}, yet segmenting succeeded",
                segmenter.name()
            ),
            Err(_) => panic!(
                "segmenter `{}`: {what}, and segmenting panicked instead of returning an error",
                segmenter.name()
            ),
        }
    }
}

/// Checks that segmenting [`clustered_map`] twice gives the same point sets.
#[track_caller]
pub fn check_determinism(build: BuildSegmenter) {
    let segmenter = build();
    let (positions, scores) = clustered_map(segmenter.baseline_query().is_some());
    let first = segment(segmenter.as_ref(), &positions, &scores, "the clustered map");
    let second = segment(segmenter.as_ref(), &positions, &scores, "the clustered map");
    assert!(
        first == second,
        "segmenter `{}`: two segmentations of one map differ",
        segmenter.name()
    );
}

/// Asserts that `set` is valid for `positions` and `scores`: query in range, indices in range and
/// unique, `mean_score` the mean of its scores within [`MEAN_TOLERANCE`] (0 when empty).
#[track_caller]
pub fn check_point_set(set: &PointSet, positions: &[[f32; 3]], scores: &QueryScores, name: &str) {
    let what = format!("segmenter `{name}`, point set of query {}", set.query);
    assert!(
        set.query < scores.scores.len(),
        "{what}: query index out of range ({} queries)",
        scores.scores.len()
    );
    let mut seen = BTreeSet::new();
    for &i in &set.indices {
        assert!(
            i < positions.len(),
            "{what}: index {i} out of range ({} points)",
            positions.len()
        );
        assert!(seen.insert(i), "{what}: index {i} appears twice");
    }
    let s = &scores.scores[set.query];
    let mean = if set.indices.is_empty() {
        0.0
    } else {
        set.indices.iter().map(|&i| s[i]).sum::<f32>() / set.indices.len() as f32
    };
    assert!(
        (set.mean_score - mean).abs() <= MEAN_TOLERANCE,
        "{what}: mean_score {} but its {} points score {mean} on average",
        set.mean_score,
        set.indices.len()
    );
}

/// Segments, panicking with context on an error.
#[track_caller]
fn segment(
    segmenter: &dyn Segmenter,
    positions: &[[f32; 3]],
    scores: &QueryScores,
    what: &str,
) -> Vec<PointSet> {
    segmenter
        .segment(positions, scores)
        .unwrap_or_else(|e| panic!("segmenter `{}`, {what}: {e}", segmenter.name()))
}
