//! The paper's 2D protocol: an encoder's pixel embeddings against a label image, with the class
//! names as text queries and the same threshold-sweep IoU as in 3D, accumulated over the
//! evaluated frames (every 30th in the paper).
//!
//! A pixel's similarity to class `c` is `(text_c · e + 1) / 2` with `e` its unit-norm embedding
//! ([`PixelEmbeddings::embedding_at`]); pixels without an embedding are predicted negative for
//! every class; pixels whose label is not an evaluated class are ignored. Embeddings covering an
//! image of another size are looked up at the corresponding pixel.

use vlem_core::{EmbeddingLayout, NO_REGION, PixelEmbeddings};

use super::classes::ClassIndex;
use super::sweep::ThresholdSweep;
use crate::error::{EvalError, Result};

/// Adds one labelled image (`labels`: row-major ids, `width x height`) to `sweep`, whose class `c`
/// has the text embedding `texts[c]` and the id that `index` maps to `c`. Returns the number of
/// evaluated pixels (those of an evaluated class).
///
/// # Errors
/// [`EvalError::InvalidParameter`] when the label image size is wrong, or the texts do not match
/// the sweep's classes or the embeddings' dimension.
pub fn add_image(
    sweep: &mut ThresholdSweep,
    labels: &[u16],
    width: u32,
    height: u32,
    embeddings: &PixelEmbeddings,
    texts: &[Vec<f32>],
    index: &ClassIndex,
) -> Result<u64> {
    let dim = embeddings.dim();
    if labels.len() != width as usize * height as usize
        || texts.len() != sweep.classes()
        || texts.iter().any(|t| t.len() != dim)
    {
        return Err(EvalError::InvalidParameter {
            name: "label image / text embeddings".into(),
            value: format!(
                "{} labels for {width}x{height}, {} texts of dimensions {:?}",
                labels.len(),
                texts.len(),
                texts.iter().map(Vec::len).collect::<Vec<_>>()
            ),
            reason: format!(
                "need one label per pixel and {} texts of the embeddings' dimension {dim}",
                sweep.classes()
            ),
        });
    }
    let score = |e: &[f32], t: &[f32]| (vlem_core::query::dot(e, t) + 1.0) * 0.5;
    // In the region layout every pixel of a region scores the same: score each region once.
    let segment_bins: Option<Vec<usize>> = match embeddings.layout() {
        EmbeddingLayout::Regions { table, .. } => Some(
            table
                .chunks_exact(dim)
                .flat_map(|row| {
                    texts
                        .iter()
                        .map(|t| sweep.bin(Some(score(row, t))))
                        .collect::<Vec<_>>()
                })
                .collect(),
        ),
        EmbeddingLayout::PatchGrid { .. } => None,
    };
    let (ew, eh) = (embeddings.width(), embeddings.height());
    let lookup = |u: u32, v: u32| -> (u32, u32) {
        if (ew, eh) == (width, height) {
            (u, v)
        } else {
            (
                ((u64::from(u) * u64::from(ew)) / u64::from(width)) as u32,
                ((u64::from(v) * u64::from(eh)) / u64::from(height)) as u32,
            )
        }
    };
    let classes = texts.len();
    let mut e = vec![0.0f32; dim];
    let mut bins = vec![0usize; classes];
    let mut evaluated = 0u64;
    for v in 0..height {
        for u in 0..width {
            let Some(truth) = index.index(labels[v as usize * width as usize + u as usize]) else {
                continue;
            };
            let (eu, ev) = lookup(u, v);
            match (&segment_bins, embeddings.layout()) {
                (Some(table), EmbeddingLayout::Regions { index: seg, .. }) => {
                    let s = seg
                        .get(ev as usize * ew as usize + eu as usize)
                        .copied()
                        .unwrap_or(NO_REGION);
                    if s == NO_REGION {
                        bins.fill(0);
                    } else {
                        let row = s as usize * classes;
                        bins.copy_from_slice(table.get(row..row + classes).unwrap_or(&[]));
                    }
                }
                _ => {
                    if embeddings.embedding_at(eu, ev, &mut e) {
                        for (b, t) in bins.iter_mut().zip(texts) {
                            *b = sweep.bin(Some(score(&e, t)));
                        }
                    } else {
                        bins.fill(0);
                    }
                }
            }
            for (c, &b) in bins.iter().enumerate() {
                sweep.add_bin(c, c == truth, b, 1);
            }
            evaluated += 1;
        }
    }
    Ok(evaluated)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::semseg::classes::Class;
    use crate::semseg::scores::SemsegScores;

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

    /// A 2x2 image, thresholds 0, 0.5, 1; worked by hand.
    #[test]
    fn region_embeddings_against_a_label_image() {
        // Pixels: (0,0) wall in segment 0 ([1, 0]); (1,0) wall in segment 1 ([0, 1]); (0,1) floor
        // in segment 0; (1,1) unlabelled.
        let e = PixelEmbeddings::from_regions(
            2,
            2,
            2,
            vec![0, 1, 0, NO_REGION],
            vec![1.0, 0.0, 0.0, 1.0],
        )
        .unwrap();
        let texts = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
        let classes = classes();
        let mut sweep = ThresholdSweep::new(2, 2).unwrap();
        let n = add_image(
            &mut sweep,
            &[1, 1, 2, 0],
            2,
            2,
            &e,
            &texts,
            &ClassIndex::new(&classes),
        )
        .unwrap();
        assert_eq!(n, 3);
        let s = SemsegScores::from_sweep(&sweep, &classes);
        // wall: positives 1, 0.5; negative 1. t = 0, 0.5: TP 2, FP 1 -> 2/3; t = 1: TP 1, FP 1,
        // FN 1 -> 1/3. floor: positive 0.5; negatives 0.5, 1. t = 0, 0.5: TP 1, FP 2 -> 1/3;
        // t = 1: TP 0, FP 1, FN 1 -> 0.
        let wall = (2.0 / 3.0 + 2.0 / 3.0 + 1.0 / 3.0) / 3.0;
        let floor = (1.0 / 3.0 + 1.0 / 3.0) / 3.0;
        assert!((s.classes[0].iou.unwrap() - wall).abs() < 1e-12, "{s:?}");
        assert!((s.classes[1].iou.unwrap() - floor).abs() < 1e-12, "{s:?}");
    }

    #[test]
    fn unsegmented_pixels_and_patch_grids() {
        let texts = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
        let classes = classes();
        let index = ClassIndex::new(&classes);
        // A wall pixel without a segment: a false negative at every threshold.
        let e = PixelEmbeddings::from_regions(1, 1, 2, vec![NO_REGION], vec![1.0, 0.0]).unwrap();
        let mut sweep = ThresholdSweep::new(2, 2).unwrap();
        add_image(&mut sweep, &[1], 1, 1, &e, &texts, &index).unwrap();
        assert_eq!(sweep.class_iou(0), Some(0.0));
        // A 1x1 patch grid of [1, 0] over a 2x1 label image at twice the embedding size.
        let e = PixelEmbeddings::from_patch_grid(1, 1, 2, 1, 1, vec![1.0, 0.0]).unwrap();
        let mut sweep = ThresholdSweep::new(2, 2).unwrap();
        assert_eq!(
            add_image(&mut sweep, &[1, 1], 2, 1, &e, &texts, &index).unwrap(),
            2
        );
        // Both wall pixels score 1 for wall: IoU 1 at every threshold.
        assert_eq!(sweep.class_iou(0), Some(1.0));
        assert!(add_image(&mut sweep, &[1], 2, 1, &e, &texts, &index).is_err());
    }
}
