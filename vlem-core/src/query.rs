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
    check_texts(embeddings.len(), dim, &[text])?;
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

/// [`normalised_similarity`] of several texts in one pass over `embeddings`: each row is read
/// once and scored against every text (the texts stay in cache), so `T` texts cost one pass over
/// the table's memory instead of `T`. `out[t]` receives `texts[t]`'s scores, bit for bit what
/// [`normalised_similarity`] gives.
///
/// # Errors
/// As [`normalised_similarity`], for the first text of the wrong length.
pub fn normalised_similarity_many(
    embeddings: &[f32],
    dim: usize,
    texts: &[&[f32]],
    out: &mut Vec<Vec<f32>>,
) -> Result<()> {
    check_texts(embeddings.len(), dim, texts)?;
    let n = embeddings.len() / dim;
    for_each_row_scored(n, texts.len(), out, |row, scores| {
        let e = &embeddings[row * dim..(row + 1) * dim];
        for (s, text) in scores.iter_mut().zip(texts) {
            *s = (dot(e, text) + 1.0) * 0.5;
        }
    });
    Ok(())
}

/// The checks of [`normalised_similarity`] for every text: each `dim` long, the table a whole
/// number of rows.
///
/// # Errors
/// [`CoreError::DimensionMismatch`] naming the first mismatch.
pub fn check_texts(values: usize, dim: usize, texts: &[&[f32]]) -> Result<()> {
    if let Some(text) = texts.iter().find(|t| t.len() != dim) {
        return Err(CoreError::DimensionMismatch {
            what: "query embedding".into(),
            expected: dim,
            actual: text.len(),
        });
    }
    if dim == 0 {
        return Err(CoreError::DimensionMismatch {
            what: "query embedding".into(),
            expected: 0,
            actual: 0,
        });
    }
    if !values.is_multiple_of(dim) {
        return Err(CoreError::DimensionMismatch {
            what: "map embedding table (length modulo dim)".into(),
            expected: 0,
            actual: values % dim,
        });
    }
    Ok(())
}

/// Rows scored against `texts` texts: `score(row, scores)` fills one row's score per text, and
/// the scores land in `out[t][row]`. Blocks of rows run in parallel on large tables, each writing
/// its own slice of every text's output, so no output is shared between threads and nothing is
/// gathered and copied afterwards.
pub fn for_each_row_scored(
    rows: usize,
    texts: usize,
    out: &mut Vec<Vec<f32>>,
    score: impl Fn(usize, &mut [f32]) + Sync,
) {
    /// Rows per block: a block writes one contiguous 4 KiB run of each text's scores.
    const BLOCK: usize = 1024;
    out.resize_with(texts, Vec::new);
    for scores in out.iter_mut() {
        scores.clear();
        scores.resize(rows, 0.0);
    }
    if texts == 0 || rows == 0 {
        return;
    }
    // Block b's slice of every text's output.
    let mut blocks: Vec<Vec<&mut [f32]>> = (0..rows.div_ceil(BLOCK))
        .map(|_| Vec::with_capacity(texts))
        .collect();
    for scores in out.iter_mut() {
        for (block, slice) in blocks.iter_mut().zip(scores.chunks_mut(BLOCK)) {
            block.push(slice);
        }
    }
    let run = |(b, mut slices): (usize, Vec<&mut [f32]>)| {
        let mut row_scores = vec![0.0f32; texts];
        let len = slices.first().map_or(0, |s| s.len());
        for i in 0..len {
            score(b * BLOCK + i, &mut row_scores);
            for (slice, &s) in slices.iter_mut().zip(&row_scores) {
                slice[i] = s;
            }
        }
    };
    if rows >= PARALLEL_MIN_POINTS {
        blocks.into_par_iter().enumerate().for_each(run);
    } else {
        blocks.into_iter().enumerate().for_each(run);
    }
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
    fn many_texts_in_one_pass_score_as_one_text_at_a_time() {
        for n in [0, 5, 1023, 1025, PARALLEL_MIN_POINTS + 7] {
            let dim = 19;
            let embeddings: Vec<f32> = (0..n * dim)
                .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
                .collect();
            let texts: Vec<Vec<f32>> = (0..4)
                .map(|t| {
                    (0..dim)
                        .map(|k| ((t * 31 + k * 17) % 13) as f32 / 13.0)
                        .collect()
                })
                .collect();
            let refs: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
            let mut many = Vec::new();
            normalised_similarity_many(&embeddings, dim, &refs, &mut many).unwrap();
            assert_eq!(many.len(), 4);
            for (text, scores) in texts.iter().zip(&many) {
                let mut one = Vec::new();
                normalised_similarity(&embeddings, dim, text, &mut one).unwrap();
                assert_eq!(&one, scores, "n = {n}");
            }
        }
        let mut out = Vec::new();
        let err = normalised_similarity_many(&[0.0; 4], 2, &[&[1.0, 0.0], &[1.0]], &mut out);
        assert!(err.is_err());
        normalised_similarity_many(&[0.0; 4], 2, &[], &mut out).unwrap();
        assert!(out.is_empty());
    }

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
