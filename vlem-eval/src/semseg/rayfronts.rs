//! The RayFronts protocol (Alama et al., "RayFronts", 2025), as its `semseg_eval` evaluates
//! open-vocabulary 3D semantic segmentation:
//!
//! 1. every map point gets a class distribution `softmax_c(temperature · cos(e, text_c))` over the
//!    evaluated classes (temperature 100, CLIP's logit scale);
//! 2. prompt denoising (from MaskCLIP+): a class whose probability stays below 0.5 at every map
//!    point is dropped;
//! 3. each point is labelled with the most probable remaining class, or 0 (no prediction) when
//!    that probability is below 0.1 or no class remains;
//! 4. predictions and ground truth are voxelised (5 cm; majority label per voxel, the smallest
//!    label on a tie, 0 included, so a voxel of mostly unlabelled points predicts nothing);
//! 5. every ground-truth voxel takes the most frequent label among its k = 5 nearest predicted
//!    voxels (no distance limit; the smallest label on a tie);
//! 6. over ground-truth voxels of an evaluated class: per class `IoU = TP / (TP + FP + FN)`,
//!    classes absent from the ground truth excluded (a NaN-mean), the frequency-weighted mean
//!    (f-mIoU, weights `(TP + FN) / Σ(TP + FN)`) and the accuracy (fraction labelled correctly).
//!
//! Labels in this module are class positions plus one (`c + 1` for `classes[c]`), 0 meaning no
//! prediction (or, in the ground truth, not an evaluated class: ignored).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use serde::Serialize;

use super::classes::Class;
use super::ground_truth::{Voxel, majority, voxel_key};
use super::scores::{ClassScore, SemsegScores, mean_present};
use crate::error::{EvalError, Result};

/// The protocol's parameters (RayFronts' defaults for ScanNet).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RayFrontsParams {
    /// Softmax temperature applied to cosine similarities.
    pub temperature: f32,
    /// Prompt denoising: classes whose maximum probability over the map is below this are dropped.
    pub denoise_threshold: f32,
    /// Points whose best probability is below this get no prediction.
    pub prediction_threshold: f32,
    /// Voxel size for predictions and ground truth (metres).
    pub voxel_size: f64,
    /// Predicted voxels voting per ground-truth voxel.
    pub k: usize,
}

impl Default for RayFrontsParams {
    fn default() -> Self {
        Self {
            temperature: 100.0,
            denoise_threshold: 0.5,
            prediction_threshold: 0.1,
            voxel_size: 0.05,
            k: 5,
        }
    }
}

/// The class probabilities of one embedding: `softmax(temperature · text_c · e)`.
fn probabilities(e: &[f32], texts: &[Vec<f32>], temperature: f32, out: &mut Vec<f32>) {
    out.clear();
    out.extend(
        texts
            .iter()
            .map(|t| temperature * vlem_core::query::dot(e, t)),
    );
    let max = out.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0;
    for x in out.iter_mut() {
        *x = (*x - max).exp();
        sum += *x;
    }
    if sum > 0.0 && sum.is_finite() {
        out.iter_mut().for_each(|x| *x /= sum);
    }
}

/// Steps 1–3: the label (`c + 1`, or 0) of every row of the row-major `embeddings` (`dim` wide),
/// and which classes prompt denoising kept.
///
/// # Errors
/// [`EvalError::InvalidParameter`] when a text is not `dim` long or the table is not whole rows.
pub fn predict(
    embeddings: &[f32],
    dim: usize,
    texts: &[Vec<f32>],
    params: &RayFrontsParams,
) -> Result<(Vec<u16>, Vec<bool>)> {
    if dim == 0 || !embeddings.len().is_multiple_of(dim) || texts.iter().any(|t| t.len() != dim) {
        return Err(EvalError::InvalidParameter {
            name: "embeddings".into(),
            value: format!("{} values of dimension {dim}", embeddings.len()),
            reason: format!(
                "need whole rows and text embeddings of the same dimension (got {:?})",
                texts.iter().map(Vec::len).collect::<Vec<_>>()
            ),
        });
    }
    let classes = texts.len();
    // Pass 1: the maximum probability of each class over the map.
    let max_prob = embeddings
        .par_chunks_exact(dim)
        .with_min_len(1024)
        .fold(
            || (vec![0.0f32; classes], Vec::new()),
            |(mut best, mut p), e| {
                probabilities(e, texts, params.temperature, &mut p);
                for (b, x) in best.iter_mut().zip(&p) {
                    *b = b.max(*x);
                }
                (best, p)
            },
        )
        .map(|(best, _)| best)
        .reduce(
            || vec![0.0f32; classes],
            |a, b| a.iter().zip(&b).map(|(x, y)| x.max(*y)).collect(),
        );
    let kept: Vec<bool> = max_prob
        .iter()
        .map(|&m| m >= params.denoise_threshold)
        .collect();
    // Pass 2: the best kept class, if probable enough (probabilities are not renormalised).
    let labels = embeddings
        .par_chunks_exact(dim)
        .with_min_len(1024)
        .map_init(Vec::new, |p, e| {
            probabilities(e, texts, params.temperature, p);
            let mut best: Option<(usize, f32)> = None;
            for (c, &x) in p.iter().enumerate() {
                if kept[c] && best.is_none_or(|(_, b)| x > b) {
                    best = Some((c, x));
                }
            }
            match best {
                Some((c, x)) if x >= params.prediction_threshold => (c + 1) as u16,
                _ => 0,
            }
        })
        .collect();
    Ok((labels, kept))
}

/// Step 4: merges labelled points per voxel of `voxel_size` metres: the mean position and the
/// majority label (the smallest on a tie, 0 included), ordered by voxel index.
pub fn voxelise(
    positions: &[[f32; 3]],
    labels: &[u16],
    voxel_size: f64,
) -> (Vec<[f32; 3]>, Vec<u16>) {
    let inv = 1.0 / voxel_size;
    let mut voxels: FxHashMap<[i32; 3], Voxel> = FxHashMap::default();
    for (p, &label) in positions.iter().zip(labels) {
        voxels.entry(voxel_key(*p, inv)).or_default().add(*p, label);
    }
    let mut voxels: Vec<_> = voxels.into_iter().collect();
    voxels.sort_unstable_by_key(|(key, _)| *key);
    voxels.iter().filter_map(|(_, v)| v.result()).unzip()
}

/// Step 5: for each ground-truth position, the most frequent label among its `k` nearest
/// predicted positions (all of them when there are fewer; the smallest label on a tie; 0 when
/// there are none).
pub fn knn_vote(
    gt_positions: &[[f32; 3]],
    pred_positions: &[[f32; 3]],
    pred_labels: &[u16],
    k: usize,
) -> Vec<u16> {
    let tree: ImmutableKdTree<f32, 3> = match ImmutableKdTree::new_from_slice(pred_positions) {
        Ok(tree) => tree,
        Err(_) => return vec![0; gt_positions.len()],
    };
    let k = NonZeroUsize::new(k.min(pred_positions.len())).unwrap_or(NonZeroUsize::MIN);
    gt_positions
        .par_iter()
        .with_min_len(1024)
        .map(|q| {
            let mut counts: Vec<(u16, u32)> = Vec::with_capacity(k.get());
            for n in tree
                .query(q)
                .nearest_n::<SquaredEuclidean<f32>>(k)
                .execute()
            {
                let label = pred_labels.get(n.item as usize).copied().unwrap_or(0);
                match counts.iter_mut().find(|(l, _)| *l == label) {
                    Some((_, c)) => *c += 1,
                    None => counts.push((label, 1)),
                }
            }
            majority(&counts).unwrap_or(0)
        })
        .collect()
}

/// Step 6: per-class IoU, mIoU, f-mIoU and accuracy of aligned ground-truth and predicted labels
/// (`c + 1` for `classes[c]`; ground truth 0 is ignored, prediction 0 is a miss).
///
/// # Errors
/// [`EvalError::InvalidParameter`] when the lists differ in length.
pub fn metrics(gt: &[u16], pred: &[u16], classes: &[Class]) -> Result<SemsegScores> {
    if gt.len() != pred.len() {
        return Err(EvalError::InvalidParameter {
            name: "aligned labels".into(),
            value: format!("{} ground-truth and {} predicted", gt.len(), pred.len()),
            reason: "need one prediction per ground-truth element".into(),
        });
    }
    let n = classes.len();
    let (mut tp, mut fp, mut fn_) = (vec![0u64; n + 1], vec![0u64; n + 1], vec![0u64; n + 1]);
    let mut valid = 0u64;
    for (&g, &p) in gt.iter().zip(pred) {
        let (g, p) = (usize::from(g), usize::from(p));
        if g == 0 || g > n {
            continue;
        }
        valid += 1;
        if p == g {
            tp[g] += 1;
        } else {
            fn_[g] += 1;
            if p != 0 && p <= n {
                fp[p] += 1;
            }
        }
    }
    let scores: Vec<ClassScore> = classes
        .iter()
        .enumerate()
        .map(|(c, class)| {
            let i = c + 1;
            let support = tp[i] + fn_[i];
            ClassScore {
                id: class.id,
                name: class.name.clone(),
                iou: (support > 0).then(|| tp[i] as f64 / (tp[i] + fp[i] + fn_[i]) as f64),
                support,
            }
        })
        .collect();
    let fmiou = (valid > 0).then(|| {
        scores
            .iter()
            .filter_map(|c| c.iou.map(|iou| iou * c.support as f64 / valid as f64))
            .sum()
    });
    let accuracy = (valid > 0).then(|| tp.iter().sum::<u64>() as f64 / valid as f64);
    Ok(SemsegScores {
        miou: mean_present(&scores),
        classes: scores,
        fmiou,
        accuracy,
    })
}

/// The protocol end to end on a map (row-major unit-norm `embeddings`, `dim` wide, at
/// `map_positions`) against ground-truth voxels (`gt_labels` are NYU40 ids; build them at
/// `params.voxel_size`), with `texts[c]` the text embedding of `classes[c]`. Also returns the
/// classes prompt denoising kept.
///
/// # Errors
/// Those of [`predict`] and [`metrics`], and [`EvalError::InvalidParameter`] for `k` 0 or a
/// voxel size that is not positive.
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
    params: &RayFrontsParams,
) -> Result<(SemsegScores, Vec<bool>)> {
    if params.k == 0 || !(params.voxel_size.is_finite() && params.voxel_size > 0.0) {
        return Err(EvalError::InvalidParameter {
            name: "RayFronts parameters".into(),
            value: format!("k = {}, voxel size = {}", params.k, params.voxel_size),
            reason: "k must be at least 1 and the voxel size positive".into(),
        });
    }
    let (labels, kept) = predict(embeddings, dim, texts, params)?;
    let (pred_positions, pred_labels) = voxelise(map_positions, &labels, params.voxel_size);
    let index = super::classes::ClassIndex::new(classes);
    let gt: Vec<u16> = gt_labels
        .iter()
        .map(|&id| index.index(id).map_or(0, |c| (c + 1) as u16))
        .collect();
    let aligned = knn_vote(gt_positions, &pred_positions, &pred_labels, params.k);
    Ok((metrics(&gt, &aligned, classes)?, kept))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn classes(n: u16) -> Vec<Class> {
        (1..=n)
            .map(|id| Class {
                id,
                name: format!("class {id}"),
            })
            .collect()
    }

    #[test]
    fn predictions_follow_softmax_denoising_and_threshold() {
        let texts = vec![vec![1.0, 0.0], vec![0.0, 1.0], vec![-1.0, 0.0]];
        // [1, 0] -> class 1; [0, 1] -> class 2; [0.6, 0.8]: logits 60, 80, -60 -> class 2.
        let e = [1.0, 0.0, 0.0, 1.0, 0.6, 0.8];
        let (labels, kept) = predict(&e, 2, &texts, &RayFrontsParams::default()).unwrap();
        assert_eq!(labels, vec![1, 2, 2]);
        // Class 3 ([-1, 0]) is never probable: denoised away.
        assert_eq!(kept, vec![true, true, false]);

        // Temperature 1 and 11 identical prompts: every probability is 1/11 < 0.1 -> no label,
        // and with denoising on, every class is dropped.
        let same = vec![vec![1.0, 0.0]; 11];
        let mut params = RayFrontsParams {
            temperature: 1.0,
            ..RayFrontsParams::default()
        };
        let (labels, kept) = predict(&e[..2], 2, &same, &params).unwrap();
        assert_eq!(labels, vec![0]);
        assert!(kept.iter().all(|k| !k));
        params.denoise_threshold = 0.0;
        let (labels, _) = predict(&e[..2], 2, &same, &params).unwrap();
        assert_eq!(labels, vec![0]);
        // With ten prompts, 1/10 >= 0.1: the first class wins the tie.
        let (labels, _) = predict(&e[..2], 2, &same[..10], &params).unwrap();
        assert_eq!(labels, vec![1]);
        // Temperature 1, two prompts: softmax(1, 0) = (0.731, 0.269) at [1, 0].
        params.denoise_threshold = 0.5;
        let (labels, kept) = predict(&e[..2], 2, &texts[..2], &params).unwrap();
        assert_eq!(labels, vec![1]);
        assert_eq!(kept, vec![true, false]);
        assert!(predict(&e, 3, &texts, &params).is_err());
    }

    #[test]
    fn voxels_take_mean_position_and_majority_label() {
        let positions = [
            [0.01, 0.0, 0.0],
            [0.02, 0.0, 0.0],
            [0.03, 0.0, 0.0],
            [0.07, 0.0, 0.0],
        ];
        let (p, l) = voxelise(&positions, &[2, 2, 1, 0], 0.05);
        assert_eq!(l, vec![2, 0]);
        assert!(
            (p[0][0] - 0.02).abs() < 1e-6 && (p[1][0] - 0.07).abs() < 1e-6,
            "{p:?}"
        );
        let (_, l) = voxelise(&positions[..2], &[3, 1], 0.05);
        assert_eq!(l, vec![1]);
    }

    #[test]
    fn knn_votes_take_the_mode_and_smallest_on_ties() {
        let at = |x: f32| [x, 0.0, 0.0];
        let pred = [at(0.0), at(1.0), at(2.0), at(3.0), at(10.0)];
        let labels = [1, 1, 2, 0, 2];
        // 0.4: neighbours 0, 1, 2 -> 1, 1, 2 -> 1. 2.6: 3, 2, 1 -> 0, 2, 1 -> tie -> 0.
        // 9: 10, 3, 2 -> 2, 0, 2 -> 2.
        let votes = knn_vote(&[at(0.4), at(2.6), at(9.0)], &pred, &labels, 3);
        assert_eq!(votes, vec![1, 0, 2]);
        // More neighbours asked than there are: all five vote, 1 and 2 tie at two -> 1.
        assert_eq!(knn_vote(&[at(0.0)], &pred, &labels, 10), vec![1]);
        assert_eq!(knn_vote(&[at(0.0)], &[], &[], 5), vec![0]);
    }

    #[test]
    fn metrics_on_hand_made_labels() {
        // gt 1 -> 1 (TP 1); gt 1 -> 2 (FN 1, FP 2); gt 2 -> 2 (TP 2); gt 2 -> 0 (FN 2);
        // gt 3 -> 1 (FN 3, FP 1); gt 0 -> 3 ignored. Class 4 absent.
        let gt = [1, 1, 2, 2, 3, 0];
        let pred = [1, 2, 2, 0, 1, 3];
        let s = metrics(&gt, &pred, &classes(4)).unwrap();
        let iou: Vec<Option<f64>> = s.classes.iter().map(|c| c.iou).collect();
        assert_eq!(iou, vec![Some(1.0 / 3.0), Some(1.0 / 3.0), Some(0.0), None]);
        assert!((s.miou.unwrap() - 2.0 / 9.0).abs() < 1e-12);
        // Frequencies 2, 2, 1 of 5.
        assert!((s.fmiou.unwrap() - 4.0 / 15.0).abs() < 1e-12);
        assert!((s.accuracy.unwrap() - 0.4).abs() < 1e-12);
        assert_eq!(s.evaluated_classes(), 3);
        assert!(metrics(&gt, &pred[..2], &classes(4)).is_err());
    }

    #[test]
    fn end_to_end_on_a_tiny_map() {
        // Two walls of map points: x = 0 is class id 7 ([1, 0]), x = 1 is id 9 ([0, 1]).
        let map: Vec<[f32; 3]> = (0..4)
            .flat_map(|i| [[0.0, i as f32 * 0.1, 0.0], [1.0, i as f32 * 0.1, 0.0]])
            .collect();
        let embeddings: Vec<f32> = (0..4).flat_map(|_| [1.0, 0.0, 0.0, 1.0]).collect();
        let classes = vec![
            Class {
                id: 7,
                name: "table".into(),
            },
            Class {
                id: 9,
                name: "window".into(),
            },
        ];
        let texts = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
        // Ground truth: two voxels of id 7 near x = 0, one of id 9 near x = 0 (wrong), one id 40
        // (not evaluated, ignored) and one id 9 near x = 1.
        let gt = [
            [0.0, 0.0, 0.0],
            [0.0, 0.1, 0.0],
            [0.0, 0.2, 0.0],
            [0.0, 0.3, 0.0],
            [1.0, 0.0, 0.0],
        ];
        let labels = [7, 7, 9, 40, 9];
        let params = RayFrontsParams {
            k: 1,
            ..RayFrontsParams::default()
        };
        let (s, kept) = evaluate(
            &gt,
            &labels,
            &map,
            &embeddings,
            2,
            &classes,
            &texts,
            &params,
        )
        .unwrap();
        assert_eq!(kept, vec![true, true]);
        // table: TP 2, FP 1 -> 2/3; window: TP 1, FN 1 -> 1/2.
        let iou: Vec<Option<f64>> = s.classes.iter().map(|c| c.iou).collect();
        assert_eq!(iou, vec![Some(2.0 / 3.0), Some(0.5)]);
        assert!((s.accuracy.unwrap() - 0.75).abs() < 1e-12);
        assert!((s.fmiou.unwrap() - (0.5 * 2.0 / 3.0 + 0.5 * 0.5)).abs() < 1e-12);
    }
}
