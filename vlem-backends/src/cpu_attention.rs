//! Attention on the CPU in blocks of queries whose scores stay in the caches.
//!
//! Why it exists: the attention layer's plain product materialises every head's scores, then
//! passes over them again for the added terms, the softmax (three passes) and the product with
//! the values. At NARADIO B/16's 1200 tokens that is 12 × 1200 × 1200 floats (69 MB) a layer,
//! far beyond the caches; at one thread on an AVX2 CPU the step took 167 ms a layer, of which
//! the two products are ~75 ms of arithmetic. Here each task takes one (batch, head) row and a
//! block of its queries: the block's scores (at most [`BLOCK_SCORES`] floats, 1 MiB) are
//! written, completed, normalised and multiplied by the values while they are in the core's
//! caches (its L2 and the L3 beside it), never written to memory and read back. The products
//! stay the same matrix products. With the faster `exp` that came with it, the step took ~97 ms
//! a layer (BENCHMARKS.md, "Attention in cache-sized blocks on the CPU").
//!
//! Per score it runs the plain layer's operations in the plain layer's order: the query scaled,
//! its dot product with the key, plus the added term (a bias, a prior, SAM's relative positions
//! as `rel_h + rel_w`), the softmax of [`crate::kernels::softmax_runs`], and the weighted sum of
//! the values. Only the matrix products' blocking differs, so the results agree with the plain
//! layer's to f32 rounding (the tests compare both with a plain triple loop and with each other).

use rayon::prelude::*;

use crate::kernels::{matmul, matmul_by_transpose, softmax_runs};

/// Scores per block at most (floats): 1 MiB, 218 queries of 1200 keys. Smaller blocks fit a
/// core's L2 cache better but repack the keys for the product more often and leave the product
/// with short sides: on NARADIO B/16 at one thread (AVX2, 512 KiB of L2 a core) blocks of 24,
/// 48, 96 and 192 queries took the two products 105, 93, 85 and 77 ms a layer, 436 and whole
/// rows 82 and 87 ms (BENCHMARKS.md, "Attention in cache-sized blocks").
pub(crate) const BLOCK_SCORES: usize = 1 << 18;

/// The sizes of one attention: `rows` = batch × heads independent attentions of `queries`
/// queries over `keys` keys, each vector `head_dim` wide.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Sizes {
    /// Batch entries.
    pub batch: usize,
    /// Heads per entry.
    pub heads: usize,
    /// Queries per row.
    pub queries: usize,
    /// Keys (and values) per row.
    pub keys: usize,
    /// Width of a query, key and value.
    pub head_dim: usize,
}

/// What is added to the scaled products before the softmax.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Terms<'a> {
    /// Nothing.
    None,
    /// A `(queries × keys)` matrix per row, found at `batch_stride · b + head_stride · h` for
    /// batch entry `b` and head `h` (a stride of 0 broadcasts: a causal mask, NACLIP's prior,
    /// TinyViT's per-head table).
    Bias {
        /// The matrices.
        data: &'a [f32],
        /// Offset between batch entries (0: shared).
        batch_stride: usize,
        /// Offset between heads (0: shared).
        head_stride: usize,
    },
    /// SAM's decomposed relative positions on an `h × w` grid (`queries = keys = h · w`): the
    /// score of query `i` and key `(ky, kx)` gains `rel_h[i, ky] + rel_w[i, kx]`.
    Relative {
        /// Grid rows and columns.
        grid: (usize, usize),
        /// `(rows, queries, h)`.
        rel_h: &'a [f32],
        /// `(rows, queries, w)`.
        rel_w: &'a [f32],
    },
}

/// `out = softmax(q · kᵀ · scale + terms) · v` for every row: `q` and `out` `(rows, queries,
/// head_dim)`, `k` and `v` `(rows, keys, head_dim)`, row-major, rows = batch × heads in that
/// order. Runs on rayon's pool, one task per row and block of queries.
///
/// # Panics
/// When a slice is shorter than its sizes say: the caller's bug (the tensor glue checks the
/// shapes before), never a user input.
pub(crate) fn attend(
    inputs: (&[f32], &[f32], &[f32]),
    sizes: Sizes,
    scale: f32,
    terms: Terms<'_>,
    out: &mut [f32],
) {
    attend_in_blocks(inputs, sizes, (scale, terms), out, BLOCK_SCORES);
}

/// [`attend`] with at most `block_scores` scores a block (the tests cross block edges with
/// small inputs).
fn attend_in_blocks(
    (q, k, v): (&[f32], &[f32], &[f32]),
    sizes: Sizes,
    (scale, terms): (f32, Terms<'_>),
    out: &mut [f32],
    block_scores: usize,
) {
    let Sizes {
        batch,
        heads,
        queries,
        keys,
        head_dim: d,
    } = sizes;
    let rows = batch * heads;
    assert!(
        q.len() >= rows * queries * d
            && k.len() >= rows * keys * d
            && v.len() >= rows * keys * d
            && out.len() >= rows * queries * d,
        "attend: slices too short for {sizes:?}"
    );
    if rows == 0 || queries == 0 || d == 0 {
        return;
    }
    if keys == 0 {
        // An empty softmax: no weights, nothing mixed (the plain layer's product gives zeros).
        out[..rows * queries * d].fill(0.0);
        return;
    }
    let block = (block_scores / keys).clamp(1, queries);
    out[..rows * queries * d]
        .par_chunks_mut(queries * d)
        .enumerate()
        .for_each(|(row, out_row)| {
            let q_row = &q[row * queries * d..(row + 1) * queries * d];
            let k_row = &k[row * keys * d..(row + 1) * keys * d];
            let v_row = &v[row * keys * d..(row + 1) * keys * d];
            out_row.par_chunks_mut(block * d).enumerate().for_each_init(
                || (vec![0f32; block * d], vec![0f32; block * keys]),
                |(scaled, scores), (index, out_block)| {
                    let first = index * block;
                    let count = out_block.len() / d;
                    let scaled = &mut scaled[..count * d];
                    let scores = &mut scores[..count * keys];
                    for (s, x) in scaled.iter_mut().zip(&q_row[first * d..]) {
                        *s = x * scale;
                    }
                    matmul_by_transpose(scaled, k_row, scores, (count, d, keys));
                    add_terms(terms, sizes, row, first, scores);
                    softmax_runs(scores, keys);
                    matmul(scores, v_row, out_block, (count, keys, d));
                },
            );
        });
}

/// Adds `terms` to the scores of queries `first..` of `row` (`scores`: `(count, keys)`).
fn add_terms(terms: Terms<'_>, sizes: Sizes, row: usize, first: usize, scores: &mut [f32]) {
    let Sizes {
        heads,
        queries,
        keys,
        ..
    } = sizes;
    match terms {
        Terms::None => {}
        Terms::Bias {
            data,
            batch_stride,
            head_stride,
        } => {
            let start = (row / heads) * batch_stride + (row % heads) * head_stride + first * keys;
            let len = scores.len();
            for (s, b) in scores.iter_mut().zip(&data[start..start + len]) {
                *s += b;
            }
        }
        Terms::Relative {
            grid: (h, w),
            rel_h,
            rel_w,
        } => {
            for (i, query_scores) in scores.chunks_exact_mut(keys).enumerate() {
                let query = row * queries + first + i;
                let along_h = &rel_h[query * h..(query + 1) * h];
                let along_w = &rel_w[query * w..(query + 1) * w];
                for (key_row, &rh) in query_scores.chunks_exact_mut(w).zip(along_h) {
                    for (s, &rw) in key_row.iter_mut().zip(along_w) {
                        *s += rh + rw;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut state = seed;
        (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                ((state >> 33) as f32 / (1u64 << 31) as f32) - 0.5
            })
            .collect()
    }

    /// The attention of one row by its definition, in f64.
    fn by_definition(
        (q, k, v): (&[f32], &[f32], &[f32]),
        sizes: Sizes,
        scale: f32,
        term: impl Fn(usize, usize, usize) -> f32,
    ) -> Vec<f32> {
        let Sizes {
            batch,
            heads,
            queries,
            keys,
            head_dim: d,
        } = sizes;
        let mut out = vec![0f32; batch * heads * queries * d];
        for row in 0..batch * heads {
            for i in 0..queries {
                let qi = &q[(row * queries + i) * d..][..d];
                let scores: Vec<f64> = (0..keys)
                    .map(|j| {
                        let kj = &k[(row * keys + j) * d..][..d];
                        let dot: f64 = qi
                            .iter()
                            .zip(kj)
                            .map(|(a, b)| f64::from(*a) * f64::from(scale) * f64::from(*b))
                            .sum();
                        dot + f64::from(term(row, i, j))
                    })
                    .collect();
                let max = scores.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let weights: Vec<f64> = scores.iter().map(|s| (s - max).exp()).collect();
                let total: f64 = weights.iter().sum();
                for c in 0..d {
                    let mixed: f64 = weights
                        .iter()
                        .enumerate()
                        .map(|(j, w)| w / total * f64::from(v[(row * keys + j) * d + c]))
                        .sum();
                    out[(row * queries + i) * d + c] = mixed as f32;
                }
            }
        }
        out
    }

    fn worst(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    #[test]
    fn blocks_give_the_definition_with_every_kind_of_term() {
        // 100 scores a block: 23 queries of 40 keys make two full blocks and a short one, 1000
        // keys a block of one query.
        for (queries, keys) in [(23, 40), (3, 1000), (5, 7), (1, 1), (40, 40)] {
            let sizes = Sizes {
                batch: 2,
                heads: 3,
                queries,
                keys,
                head_dim: 8,
            };
            let rows = 6;
            let q = random(rows * queries * 8, 1);
            let k = random(rows * keys * 8, 2);
            let v = random(rows * keys * 8, 3);
            let scale = 8f32.powf(-0.5);
            let mut out = vec![f32::NAN; rows * queries * 8];

            attend_in_blocks((&q, &k, &v), sizes, (scale, Terms::None), &mut out, 100);
            let want = by_definition((&q, &k, &v), sizes, scale, |_, _, _| 0.0);
            assert!(worst(&out, &want) < 1e-5, "plain {queries}x{keys}");
            let mut whole = vec![f32::NAN; out.len()];
            attend((&q, &k, &v), sizes, scale, Terms::None, &mut whole);
            assert!(
                worst(&whole, &want) < 1e-5,
                "plain {queries}x{keys}, whole rows"
            );

            // One bias per head, shared over the batch.
            let bias = random(3 * queries * keys, 4);
            let terms = Terms::Bias {
                data: &bias,
                batch_stride: 0,
                head_stride: queries * keys,
            };
            attend_in_blocks((&q, &k, &v), sizes, (scale, terms), &mut out, 100);
            let want = by_definition((&q, &k, &v), sizes, scale, |row, i, j| {
                bias[((row % 3) * queries + i) * keys + j]
            });
            assert!(worst(&out, &want) < 1e-5, "bias {queries}x{keys}");
        }
    }

    #[test]
    fn relative_positions_add_along_the_key_grid() {
        // A 30 × 40 grid: 1200 keys, 27 queries a block, the last of 12.
        let (h, w) = (30, 40);
        let block_scores = 27 * 1200;
        let n = h * w;
        let sizes = Sizes {
            batch: 1,
            heads: 1,
            queries: n,
            keys: n,
            head_dim: 4,
        };
        let q = random(n * 4, 5);
        let k = random(n * 4, 6);
        let v = random(n * 4, 7);
        let rel_h = random(n * h, 8);
        let rel_w = random(n * w, 9);
        let mut out = vec![f32::NAN; n * 4];
        let terms = Terms::Relative {
            grid: (h, w),
            rel_h: &rel_h,
            rel_w: &rel_w,
        };
        attend_in_blocks((&q, &k, &v), sizes, (0.5, terms), &mut out, block_scores);
        let want = by_definition((&q, &k, &v), sizes, 0.5, |_, i, j| {
            rel_h[i * h + j / w] + rel_w[i * w + j % w]
        });
        assert!(worst(&out, &want) < 1e-5);
    }

    #[test]
    fn no_keys_mixes_nothing() {
        let sizes = Sizes {
            batch: 1,
            heads: 2,
            queries: 3,
            keys: 0,
            head_dim: 4,
        };
        let q = random(24, 10);
        let mut out = vec![f32::NAN; 24];
        attend((&q, &[], &[]), sizes, 1.0, Terms::None, &mut out);
        assert!(out.iter().all(|&x| x == 0.0));
    }
}
