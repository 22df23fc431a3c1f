//! Embedding tables in `f32` or `f16`, shared by every map.
//!
//! `f16` halves the bytes per stored value; embeddings are unit vectors whose entries are far
//! from f16's limits, so the ranking of points for a query is kept (tested below). Arithmetic always
//! happens in `f32`: rows are widened into a scratch buffer, updated and narrowed back.

#[cfg(feature = "candle")]
mod device;
// The table that chooses host or device storage: the point-cloud and voxel maps' (the segment map
// keeps its rows on the host).
#[cfg(any(feature = "point-cloud", feature = "voxel"))]
mod table;
mod wide;

#[cfg(any(feature = "point-cloud", feature = "voxel"))]
pub(crate) use table::Table;

#[cfg(feature = "candle")]
pub use device::{CHUNK_ROWS, DeviceTable, FrameTable, Lookups, RowSums, swap_removal_moves};

use half::f16;
// Slice conversions use the CPU's F16C instructions where present (detected at run time);
// element-wise `to_f32` would be a software conversion several times slower.
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use serde::Deserialize;
use vlem_core::Result;
use vlem_core::query::dot;

/// Storage type of the embeddings of a map (`precision = "f32"` or `"f16"` in `[map]`).
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// 4 bytes per value (default).
    #[default]
    F32,
    /// 2 bytes per value.
    F16,
}

#[derive(Clone, Debug, PartialEq)]
enum Values {
    F32(Vec<f32>),
    F16(Vec<f16>),
}

/// A row-major `rows x dim` table of embeddings.
#[derive(Clone, Debug, PartialEq)]
pub struct EmbeddingStore {
    dim: usize,
    values: Values,
}

/// Below this many rows, work stays on one thread.
const PARALLEL_MIN_ROWS: usize = 4096;

impl EmbeddingStore {
    /// An empty table.
    pub fn new(dim: usize, precision: Precision) -> Self {
        let values = match precision {
            Precision::F32 => Values::F32(Vec::new()),
            Precision::F16 => Values::F16(Vec::new()),
        };
        Self { dim, values }
    }

    /// A table holding `values` (`rows x dim`, row-major), narrowed to `precision`.
    pub fn from_f32(dim: usize, precision: Precision, values: Vec<f32>) -> Self {
        let values = match precision {
            Precision::F32 => Values::F32(values),
            Precision::F16 => {
                let mut narrow = vec![f16::ZERO; values.len()];
                narrow.convert_from_f32_slice(&values);
                Values::F16(narrow)
            }
        };
        Self { dim, values }
    }

    /// Embedding dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Storage type.
    pub fn precision(&self) -> Precision {
        match self.values {
            Values::F32(_) => Precision::F32,
            Values::F16(_) => Precision::F16,
        }
    }

    fn value_count(&self) -> usize {
        match &self.values {
            Values::F32(v) => v.len(),
            Values::F16(v) => v.len(),
        }
    }

    /// Number of rows (0 for a dimension-0 table).
    pub fn rows(&self) -> usize {
        self.value_count().checked_div(self.dim).unwrap_or(0)
    }

    /// Bytes allocated for the values.
    pub fn memory_bytes(&self) -> usize {
        match &self.values {
            Values::F32(v) => v.capacity() * 4,
            Values::F16(v) => v.capacity() * 2,
        }
    }

    /// Appends a row (length `dim`).
    pub fn push(&mut self, row: &[f32]) {
        match &mut self.values {
            Values::F32(v) => v.extend_from_slice(row),
            Values::F16(v) => v.extend(row.iter().map(|&x| f16::from_f32(x))),
        }
    }

    /// Reserves room for at least `rows` more rows, like [`Vec::reserve`].
    pub fn reserve(&mut self, rows: usize) {
        let n = rows * self.dim;
        match &mut self.values {
            Values::F32(v) => v.reserve(n),
            Values::F16(v) => v.reserve(n),
        }
    }

    /// Appends `rows` zero rows (to be filled with [`EmbeddingStore::par_update_rows_from`]).
    ///
    /// The zeros are written in parallel: a frame's new rows are hundreds of megabytes at
    /// 512 dimensions early in a run, and their first write is where their pages are faulted in.
    pub fn grow(&mut self, rows: usize) {
        let n = rows * self.dim;
        match &mut self.values {
            Values::F32(v) => v.par_extend(rayon::iter::repeat_n(0.0, n)),
            Values::F16(v) => v.par_extend(rayon::iter::repeat_n(f16::ZERO, n)),
        }
    }

    /// Copies row `i` into `out` as `f32`.
    pub fn row_into(&self, i: usize, out: &mut [f32]) {
        let d = self.dim;
        match &self.values {
            Values::F32(v) => out.copy_from_slice(&v[i * d..(i + 1) * d]),
            Values::F16(v) => v[i * d..(i + 1) * d].convert_to_f32_slice(out),
        }
    }

    /// Overwrites row `i`.
    pub fn set_row(&mut self, i: usize, row: &[f32]) {
        let d = self.dim;
        match &mut self.values {
            Values::F32(v) => v[i * d..(i + 1) * d].copy_from_slice(row),
            Values::F16(v) => v[i * d..(i + 1) * d].convert_from_f32_slice(row),
        }
    }

    /// Calls `update(row_index, row)` for every row from `first` on, in parallel, with the row
    /// widened to `f32`; writes the row back when `update` returns true.
    pub fn par_update_rows_from<F>(&mut self, first: usize, update: F)
    where
        F: Fn(usize, &mut [f32]) -> bool + Sync,
    {
        self.par_update_rows_with(first, || (), |_, i, row| update(i, row));
    }

    /// Like [`EmbeddingStore::par_update_rows_from`], with per-thread state made by `init` (e.g. a
    /// scratch buffer) passed to every call.
    pub fn par_update_rows_with<S, I, F>(&mut self, first: usize, init: I, update: F)
    where
        I: Fn() -> S + Sync + Send,
        F: Fn(&mut S, usize, &mut [f32]) -> bool + Sync,
    {
        // A vector of `()` allocates nothing.
        let mut nothing = vec![(); self.rows().saturating_sub(first)];
        self.par_update_rows_zip(first, &mut nothing, init, |state, i, row, ()| {
            update(state, i, row)
        });
    }

    /// Like [`EmbeddingStore::par_update_rows_with`], with each row's item of `beside` (one per row
    /// from `first` on) passed along: a table kept beside the embeddings, such as a map's colours,
    /// updated in the same pass.
    pub fn par_update_rows_zip<T, S, I, F>(
        &mut self,
        first: usize,
        beside: &mut [T],
        init: I,
        update: F,
    ) where
        T: Send,
        I: Fn() -> S + Sync + Send,
        F: Fn(&mut S, usize, &mut [f32], &mut T) -> bool + Sync,
    {
        let d = self.dim;
        if d == 0 {
            return;
        }
        debug_assert_eq!(beside.len(), self.rows().saturating_sub(first));
        match &mut self.values {
            Values::F32(v) => v[first * d..]
                .par_chunks_exact_mut(d)
                .zip(beside.par_iter_mut())
                .enumerate()
                .with_min_len(256)
                .for_each_init(init, |state, (i, (row, item))| {
                    update(state, first + i, row, item);
                }),
            Values::F16(v) => v[first * d..]
                .par_chunks_exact_mut(d)
                .zip(beside.par_iter_mut())
                .enumerate()
                .with_min_len(256)
                .for_each_init(
                    || (init(), vec![0.0f32; d]),
                    |(state, scratch), (i, (row, item))| {
                        row.convert_to_f32_slice(scratch);
                        if update(state, first + i, scratch, item) {
                            row.convert_from_f32_slice(scratch);
                        }
                    },
                ),
        }
    }

    /// Moves the last row into row `i` and drops the last row (order is not kept).
    pub fn swap_remove(&mut self, i: usize) {
        let d = self.dim;
        let last = self.rows() - 1;
        match &mut self.values {
            Values::F32(v) => {
                v.copy_within(last * d..(last + 1) * d, i * d);
                v.truncate(last * d);
            }
            Values::F16(v) => {
                v.copy_within(last * d..(last + 1) * d, i * d);
                v.truncate(last * d);
            }
        }
    }

    /// Keeps the first `rows` rows.
    pub fn truncate(&mut self, rows: usize) {
        let n = rows * self.dim;
        match &mut self.values {
            Values::F32(v) => v.truncate(n),
            Values::F16(v) => v.truncate(n),
        }
    }

    /// All values widened to `f32` (for snapshots).
    pub fn to_f32(&self) -> Vec<f32> {
        match &self.values {
            Values::F32(v) => v.clone(),
            Values::F16(v) => v.to_f32_vec(),
        }
    }

    /// The paper's normalised similarity `(text . e + 1) / 2` of every row, into `out`.
    ///
    /// # Errors
    /// [`vlem_core::CoreError::DimensionMismatch`] when `text` is not `dim` long.
    pub fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> Result<()> {
        match &self.values {
            Values::F32(v) => vlem_core::query::normalised_similarity(v, self.dim, text, out),
            Values::F16(v) => {
                vlem_core::query::check_texts(v.len(), self.dim, &[text])?;
                let d = self.dim;
                out.clear();
                out.resize(v.len() / d, 0.0);
                let score = |(s, row): (&mut f32, &[f16])| {
                    f16_row_scores(row, &[text], std::slice::from_mut(s));
                };
                if out.len() >= PARALLEL_MIN_ROWS {
                    out.par_iter_mut()
                        .zip(v.par_chunks_exact(d))
                        .with_min_len(1024)
                        .for_each(score);
                } else {
                    out.iter_mut().zip(v.chunks_exact(d)).for_each(score);
                }
                Ok(())
            }
        }
    }
}

impl EmbeddingStore {
    /// [`EmbeddingStore::similarity`] of several texts in one pass over the table (each row read
    /// and, in f16, widened once), `out[t]` bit for bit what `similarity(texts[t])` gives.
    ///
    /// # Errors
    /// [`vlem_core::CoreError::DimensionMismatch`] when a text is not `dim` long.
    pub fn similarity_many(&self, texts: &[&[f32]], out: &mut Vec<Vec<f32>>) -> Result<()> {
        match &self.values {
            Values::F32(v) => vlem_core::query::normalised_similarity_many(v, self.dim, texts, out),
            Values::F16(v) => {
                vlem_core::query::check_texts(v.len(), self.dim, texts)?;
                let d = self.dim;
                vlem_core::query::for_each_row_scored(
                    v.len() / d,
                    texts.len(),
                    out,
                    |r, scores| f16_row_scores(&v[r * d..(r + 1) * d], texts, scores),
                );
                Ok(())
            }
        }
    }
}

/// `(text . row + 1) / 2` of one f16 row for each of `texts` (all `row.len()` long), into
/// `scores`: the row is widened 64 values at a time, once for all texts, and each text's dot
/// product summed over those chunks in order, so one text and several score alike, bit for bit.
fn f16_row_scores(row: &[f16], texts: &[&[f32]], scores: &mut [f32]) {
    let mut wide = [0.0f32; 64];
    scores.fill(0.0);
    for (c, chunk) in row.chunks(64).enumerate() {
        let wide = &mut wide[..chunk.len()];
        chunk.convert_to_f32_slice(wide);
        for (s, text) in scores.iter_mut().zip(texts) {
            *s += dot(wide, &text[c * 64..c * 64 + chunk.len()]);
        }
    }
    for s in scores.iter_mut() {
        *s = (*s + 1.0) * 0.5;
    }
}

/// `e_M := (1 - w) e_P + w e_M`, renormalised; falls back to `e_P` when the two cancel out.
#[inline]
pub fn fuse_into(map: &mut [f32], observed: &[f32], map_weight: f32) {
    wide::fuse_into(map, observed, map_weight);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_rows(n: usize, dim: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut v: Vec<f32> = (0..n * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
        v.chunks_exact_mut(dim).for_each(|r| {
            vlem_core::embeddings::normalise(r);
        });
        v
    }

    #[test]
    fn f16_keeps_the_ranking_of_f32_and_halves_the_bytes() {
        let (n, dim) = (5000, 512);
        let rows = random_rows(n, dim, 1);
        let text = random_rows(1, dim, 2);
        let full = EmbeddingStore::from_f32(dim, Precision::F32, rows.clone());
        let half = EmbeddingStore::from_f32(dim, Precision::F16, rows);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        full.similarity(&text, &mut a).unwrap();
        half.similarity(&text, &mut b).unwrap();
        // Rounding a unit vector to f16 moves each entry by at most 2^-11 of itself, so a unit
        // query's dot product moves by at most 2^-11 and a score by 2^-12. Any two points whose
        // f32 scores differ by more than twice that keep their order; closer ones are ties.
        let tie = 2.0 * 2f32.powi(-12);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&i, &j| a[j].total_cmp(&a[i]));
        for (k, &i) in order.iter().enumerate() {
            for &j in &order[k + 1..] {
                if a[i] - a[j] > tie {
                    assert!(b[i] > b[j], "points {i} and {j} swap places at f16");
                }
            }
        }
        assert!(
            a.iter()
                .zip(&b)
                .all(|(x, y)| (x - y).abs() <= 2f32.powi(-12) + 1e-6)
        );
        assert_eq!(half.memory_bytes() * 2, full.memory_bytes());
    }

    #[test]
    fn updates_swap_remove_and_fusion_work_in_both_precisions() {
        for precision in [Precision::F32, Precision::F16] {
            let mut s = EmbeddingStore::new(2, precision);
            s.push(&[1.0, 0.0]);
            s.push(&[0.0, 1.0]);
            s.grow(1);
            s.par_update_rows_from(2, |i, row| {
                assert_eq!(i, 2);
                row.copy_from_slice(&[0.6, 0.8]);
                true
            });
            s.par_update_rows_from(0, |i, row| {
                if i == 0 {
                    fuse_into(row, &[0.0, 1.0], 0.5);
                }
                i == 0
            });
            let mut row = [0.0; 2];
            s.row_into(0, &mut row);
            let half = std::f32::consts::FRAC_1_SQRT_2;
            assert!((row[0] - half).abs() < 1e-3 && (row[1] - half).abs() < 1e-3);
            s.swap_remove(0);
            assert_eq!(s.rows(), 2);
            s.row_into(0, &mut row);
            assert!((row[0] - 0.6).abs() < 1e-3, "{precision:?}: {row:?}");
            assert!(s.similarity(&[1.0], &mut Vec::new()).is_err());
        }
    }
}
