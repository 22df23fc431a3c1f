//! The paper's 3D protocol: ground-truth points take the similarity of their nearest map point
//! within 5 cm, and each class's IoU is averaged over the full range of similarity thresholds.
//!
//! Similarities are vlem's normalised cosine `s = (e_text · e + 1) / 2`, computed by
//! [`vlem_core::query::normalised_similarity`], the function `vlem query` uses, so a threshold here
//! means what it means there. A ground-truth point with no map point within the radius is
//! predicted negative for every class: it can only add false negatives (of its own class).

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::classes::{Class, ClassIndex};
use super::scores::SemsegScores;
use super::sweep::ThresholdSweep;
use crate::error::{EvalError, Result};

/// The association radius of the paper (metres).
pub const DEFAULT_ASSOCIATION_RADIUS: f32 = 0.05;

/// For every ground-truth point, the index of its nearest map point if that lies within `radius`
/// metres.
///
/// # Errors
/// [`EvalError::InvalidParameter`] for a radius that is not positive and finite.
pub fn associate(gt: &[[f32; 3]], map: &[[f32; 3]], radius: f32) -> Result<Vec<Option<u32>>> {
    if !(radius.is_finite() && radius > 0.0) {
        return Err(EvalError::InvalidParameter {
            name: "association radius".into(),
            value: radius.to_string(),
            reason: "must be a positive number of metres".into(),
        });
    }
    let tree: ImmutableKdTree<f32, 3> = match ImmutableKdTree::new_from_slice(map) {
        Ok(tree) => tree,
        // Only an empty map fails: nothing is associated.
        Err(_) => return Ok(vec![None; gt.len()]),
    };
    // kiddo's distances are in the metric's units: squared metres.
    let r2 = radius * radius;
    Ok(gt
        .par_iter()
        .with_min_len(4096)
        .map(|q| {
            let nearest = tree
                .query(q)
                .nearest_one::<SquaredEuclidean<f32>>()
                .execute();
            (nearest.distance <= r2).then_some(nearest.item as u32)
        })
        .collect())
}

/// The threshold sweep of the VLEM protocol from precomputed similarities: `scores[c][m]` is the
/// similarity of map point `m` to class `classes[c]`; ground-truth point `i` (label `labels[i]`,
/// ignored unless an evaluated class) takes the similarities of map point `association[i]`.
///
/// # Errors
/// [`EvalError::InvalidParameter`] when the lengths disagree or `steps` is 0.
pub fn sweep_3d(
    labels: &[u16],
    association: &[Option<u32>],
    scores: &[Vec<f32>],
    classes: &[Class],
    steps: usize,
) -> Result<ThresholdSweep> {
    if labels.len() != association.len() || scores.len() != classes.len() {
        return Err(EvalError::InvalidParameter {
            name: "inputs".into(),
            value: format!(
                "{} labels, {} associations, {} score rows",
                labels.len(),
                association.len(),
                scores.len()
            ),
            reason: format!(
                "need one association per label and one score row per class ({})",
                classes.len()
            ),
        });
    }
    let index = ClassIndex::new(classes);
    let mut sweep = ThresholdSweep::new(classes.len(), steps)?;
    for (&label, &map_point) in labels.iter().zip(association) {
        let Some(truth) = index.index(label) else {
            continue;
        };
        for (c, row) in scores.iter().enumerate() {
            let score = map_point.and_then(|m| row.get(m as usize).copied());
            sweep.add(c, c == truth, score);
        }
    }
    Ok(sweep)
}

/// The VLEM protocol end to end: associates `gt_positions` to the map within `radius`, scores the
/// map's row-major unit-norm `embeddings` (`dim` wide) against each class's text embedding
/// (`texts[c]` for `classes[c]`) and sweeps `steps + 1` thresholds.
///
/// Also returns how many ground-truth points had a map point within the radius.
///
/// # Errors
/// The errors of [`associate`] and [`sweep_3d`], and a dimension mismatch between the texts and
/// the map.
#[allow(
    clippy::too_many_arguments,
    reason = "the protocol's inputs, each a plain slice or number"
)]
pub fn evaluate(
    gt_positions: &[[f32; 3]],
    gt_labels: &[u16],
    map_positions: &[[f32; 3]],
    embeddings: &[f32],
    dim: usize,
    classes: &[Class],
    texts: &[Vec<f32>],
    radius: f32,
    steps: usize,
) -> Result<(SemsegScores, usize)> {
    let association = associate(gt_positions, map_positions, radius)?;
    let associated = association.iter().filter(|a| a.is_some()).count();
    let scores = texts
        .iter()
        .map(|t| {
            let mut s = Vec::new();
            vlem_core::query::normalised_similarity(embeddings, dim, t, &mut s)?;
            Ok(s)
        })
        .collect::<Result<Vec<_>>>()?;
    let sweep = sweep_3d(gt_labels, &association, &scores, classes, steps)?;
    Ok((SemsegScores::from_sweep(&sweep, classes), associated))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn classes() -> Vec<Class> {
        vec![
            Class {
                id: 1,
                name: "wall".into(),
            },
            Class {
                id: 2,
                name: "floor".into(),
            },
        ]
    }

    #[test]
    fn association_uses_the_radius_in_metres() {
        let map = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let gt = [[0.04, 0.0, 0.0], [0.94, 0.0, 0.0], [0.5, 0.0, 0.0]];
        let a = associate(&gt, &map, 0.05).unwrap();
        assert_eq!(a, vec![Some(0), None, None]);
        assert_eq!(associate(&gt, &[], 0.05).unwrap(), vec![None; 3]);
        assert!(associate(&gt, &map, 0.0).is_err());
    }

    /// Two map points, four ground-truth points, thresholds 0, 0.5, 1; worked by hand.
    #[test]
    fn protocol_on_a_hand_made_scene() {
        // Map point 0 is "wall"-like ([1, 0]), map point 1 "floor"-like ([0, 1]).
        let map = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let embeddings = [1.0, 0.0, 0.0, 1.0];
        let texts = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
        // GT: a wall point at map point 0, a floor point at map point 0 (mislabelled map), a floor
        // point at map point 1, a wall point far from the map, and an unlabelled point.
        let gt = [
            [0.01, 0.0, 0.0],
            [0.0, 0.02, 0.0],
            [1.0, 0.03, 0.0],
            [5.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
        ];
        let labels = [1, 2, 2, 1, 0];
        let (scores, associated) = evaluate(
            &gt,
            &labels,
            &map,
            &embeddings,
            2,
            &classes(),
            &texts,
            0.05,
            2,
        )
        .unwrap();
        assert_eq!(associated, 4);
        // Similarities: map point 0 scores wall 1, floor 0.5; map point 1 wall 0.5, floor 1.
        // wall: positives {1 (gt 0), none (gt 3)}, negatives {1 (gt 1), 0.5 (gt 2)}.
        //   t = 0: TP 1, FP 2, FN 1 -> 1/4; t = 0.5: same -> 1/4; t = 1: TP 1, FP 1, FN 1 -> 1/3.
        let wall = (0.25 + 0.25 + 1.0 / 3.0) / 3.0;
        // floor: positives {0.5 (gt 1), 1 (gt 2)}, negatives {0.5 (gt 0), none (gt 3)}.
        //   t = 0: TP 2, FP 1 -> 2/3; t = 0.5: 2/3; t = 1: TP 1, FP 0, FN 1 -> 1/2.
        let floor = (2.0 / 3.0 + 2.0 / 3.0 + 0.5) / 3.0;
        let got: Vec<f64> = scores.classes.iter().map(|c| c.iou.unwrap()).collect();
        assert!((got[0] - wall).abs() < 1e-12, "{got:?}");
        assert!((got[1] - floor).abs() < 1e-12, "{got:?}");
        assert!((scores.miou.unwrap() - (wall + floor) / 2.0).abs() < 1e-12);
        assert_eq!(scores.classes[0].support, 2);
        assert_eq!(scores.classes[1].support, 2);
        assert_eq!(scores.evaluated_classes(), 2);
    }

    #[test]
    fn classes_absent_from_the_ground_truth_have_no_iou() {
        let labels = [1, 1];
        let association = [Some(0), None];
        let scores = vec![vec![0.9], vec![0.9]];
        let sweep = sweep_3d(&labels, &association, &scores, &classes(), 100).unwrap();
        let s = SemsegScores::from_sweep(&sweep, &classes());
        assert_eq!(s.classes[1].iou, None);
        // wall: t <= 0.9: TP 1, FN 1 -> 1/2 (91 thresholds 0.00..=0.90); above: 0.
        let expected = 91.0 * 0.5 / 101.0;
        assert!((s.miou.unwrap() - expected).abs() < 1e-12, "{s:?}");
        assert!(sweep_3d(&labels, &[None], &scores, &classes(), 100).is_err());
    }
}
