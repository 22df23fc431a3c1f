//! Text-query scoring shared by every map: the paper's normalised cosine similarity
//! `s = (e_text . e_map + 1) / 2`, one pass over the embeddings at memory speed.

use rayon::prelude::*;

use crate::error::{CoreError, Result};

/// Below this many points a query runs on one thread (spawning costs more than it saves).
const PARALLEL_MIN_POINTS: usize = 16 * 1024;

/// Writes `(text . e_i + 1) / 2` for every row `e_i` of the row-major `embeddings` into `out`.
///
/// Rows and `text` are expected unit-norm, so scores lie in `[0, 1]`.
///
/// # Errors
/// [`CoreError::DimensionMismatch`] when `text` is not `dim` long or `embeddings` is not a whole
/// number of rows.
pub fn normalised_similarity(
    embeddings: &[f32],
    dim: usize,
    text: &[f32],
    out: &mut Vec<f32>,
) -> Result<()> {
    if text.len() != dim || dim == 0 {
        return Err(CoreError::DimensionMismatch {
            what: "query embedding".into(),
            expected: dim,
            actual: text.len(),
        });
    }
    if !embeddings.len().is_multiple_of(dim) {
        return Err(CoreError::DimensionMismatch {
            what: "map embedding table (length modulo dim)".into(),
            expected: 0,
            actual: embeddings.len() % dim,
        });
    }
    let n = embeddings.len() / dim;
    out.clear();
    out.resize(n, 0.0);
    let score = |(s, row): (&mut f32, &[f32])| *s = (dot(row, text) + 1.0) * 0.5;
    if n >= PARALLEL_MIN_POINTS {
        out.par_iter_mut()
            .zip(embeddings.par_chunks_exact(dim))
            .with_min_len(1024)
            .for_each(score);
    } else {
        out.iter_mut()
            .zip(embeddings.chunks_exact(dim))
            .for_each(score);
    }
    Ok(())
}

/// Dot product written so the compiler vectorises it (eight independent accumulators).
#[inline]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ac, ar) = a.split_at(a.len() - a.len() % 8);
    let (bc, br) = b.split_at(ac.len().min(b.len()));
    for (x, y) in ac.chunks_exact(8).zip(bc.chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let tail: f32 = ar.iter().zip(br).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn similarity_maps_cosine_to_unit_interval() {
        let e = [1.0, 0.0, 0.0, 1.0, -1.0, 0.0];
        let mut out = Vec::new();
        normalised_similarity(&e, 2, &[1.0, 0.0], &mut out).unwrap();
        assert_eq!(out, vec![1.0, 0.5, 0.0]);
        let err = normalised_similarity(&e, 2, &[1.0], &mut out).unwrap_err();
        assert_eq!(
            err.to_string(),
            "query embedding has dimension 1, expected 2"
        );
    }

    #[test]
    fn dot_matches_naive_sum_for_odd_lengths() {
        let a: Vec<f32> = (0..37).map(|i| i as f32 * 0.5).collect();
        let b: Vec<f32> = (0..37).map(|i| 1.0 - i as f32 * 0.01).collect();
        let naive: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot(&a, &b) - naive).abs() < 1e-3);
    }

    #[test]
    fn large_maps_take_the_parallel_path_with_the_same_result() {
        let n = PARALLEL_MIN_POINTS + 3;
        let e: Vec<f32> = (0..n * 2)
            .map(|i| if i % 2 == 0 { 0.6 } else { 0.8 })
            .collect();
        let mut out = Vec::new();
        normalised_similarity(&e, 2, &[0.8, 0.6], &mut out).unwrap();
        assert_eq!(out.len(), n);
        assert!(out.iter().all(|s| (s - (0.96 + 1.0) / 2.0).abs() < 1e-6));
    }
}
