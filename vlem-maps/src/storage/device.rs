//! The embedding table on a candle device: `[map] device = "cuda"` for the point-cloud and voxel
//! maps, and candle's CPU device in the tests.
//!
//! Why it exists: with a 512-d encoder on a GPU, the host table ([`EmbeddingStore`]) has every
//! frame's embeddings copied back to the host and a million rows fused there while the GPU
//! waits. Here the table is one `capacity × dim` tensor on the device, allocated for the budget
//! when the map is built. A frame's embeddings cross to the device once, in their compact form
//! (the region table, or the patch grid), and the rows to fuse or insert cross as index lists
//! with the (at most four) table rows and weights each pixel's embedding is made of. Fusion
//! (blend, renormalise), insertion, the budget's merges and row moves, and a query's scores (all
//! texts in one matrix product) are tensor operations on the device; rows come back to the host
//! only when asked (snapshots, saves).
//!
//! Each operation works on at most [`CHUNK_ROWS`] rows at a time, so its temporaries stay small
//! (64 MiB at 512-d) however large a frame or a merge is. The same code runs on candle's CPU
//! device, which is how the test suite checks it against the host table; on a CPU the host table
//! is faster and stays the default.
//!
//! [`EmbeddingStore`]: super::EmbeddingStore

use candle_core::{DType, Device, Tensor};
use vlem_core::embeddings::PatchSampler;
use vlem_core::{EmbeddingLayout, NO_REGION, PixelEmbeddings};

use super::Precision;
use crate::error::MapError;

/// Rows per tensor operation: bounds each temporary to `CHUNK_ROWS × dim × 4` bytes (64 MiB at
/// 512-d), and is large enough that a frame of 300k rows is ten launches of each kernel.
pub const CHUNK_ROWS: usize = 32_768;

type CandleResult<T> = candle_core::Result<T>;

fn table_error(e: candle_core::Error) -> MapError {
    MapError::DeviceTable(e.to_string())
}

/// A `rows × dim` embedding table in one preallocated tensor on a candle device.
///
/// Not `Clone`: a candle tensor's clone shares its storage, and the table writes in place, so a
/// clone would change with the original.
#[derive(Debug)]
pub struct DeviceTable {
    dim: usize,
    precision: Precision,
    /// `capacity × dim`; rows from `rows` on are unused.
    values: Tensor,
    rows: usize,
}

/// How the map rows' new embeddings are made from a frame's table: per row, `taps` pairs of a
/// frame-table row and its weight (one pair of weight 1 for segments, four for a patch grid).
#[derive(Clone, Debug, Default)]
pub struct Lookups {
    taps: usize,
    cells: Vec<u32>,
    weights: Vec<f32>,
}

impl Lookups {
    /// Number of rows looked up.
    pub fn len(&self) -> usize {
        self.cells.len().checked_div(self.taps).unwrap_or(0)
    }

    /// Whether no row was looked up.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn clear(&mut self, taps: usize) {
        self.taps = taps;
        self.cells.clear();
        self.weights.clear();
    }
}

/// One frame's embeddings on the device, in their compact form, and the host-side lookup of each
/// pixel's recipe in it.
#[derive(Debug)]
pub struct FrameTable<'a> {
    embeddings: &'a PixelEmbeddings,
    sampler: Option<PatchSampler<'a>>,
    /// `table rows × dim`, `f32`.
    table: Tensor,
}

impl<'a> FrameTable<'a> {
    /// Copies the frame's region table or patch grid to `table`'s device.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy fails.
    pub fn upload(embeddings: &'a PixelEmbeddings, table: &DeviceTable) -> Result<Self, MapError> {
        let d = embeddings.dim();
        let data = match embeddings.layout() {
            EmbeddingLayout::Regions { table, .. } => table,
            EmbeddingLayout::PatchGrid { data, .. } => data,
        };
        let rows = data.len().checked_div(d).unwrap_or(0);
        let tensor =
            Tensor::from_slice(data, (rows, d), table.values.device()).map_err(table_error)?;
        Ok(Self {
            embeddings,
            sampler: embeddings.patch_sampler(),
            table: tensor,
        })
    }

    /// Pairs per looked-up row: 1 for segments, 4 for a patch grid.
    pub fn taps(&self) -> usize {
        if self.sampler.is_some() { 4 } else { 1 }
    }

    /// Starts a new list of lookups from this frame.
    pub fn lookups(&self, lookups: &mut Lookups) {
        lookups.clear(self.taps());
    }

    /// Appends the recipe of pixel `pixel` (linear index `v * width + u`) to `lookups`; false
    /// (nothing appended) where the pixel has no embedding: no segment, or a patch interpolation
    /// that cancels out, as [`embedding`](crate::kit::embedding) has none there.
    pub fn push(&self, pixel: u32, lookups: &mut Lookups) -> bool {
        debug_assert_eq!(lookups.taps, self.taps());
        let Some(pairs) = self.recipe(pixel) else {
            return false;
        };
        for (cell, weight) in &pairs[..lookups.taps] {
            lookups.cells.push(*cell);
            lookups.weights.push(*weight);
        }
        true
    }

    /// Pixel `pixel`'s unit embedding as `(frame-table row, weight)` pairs: the first
    /// [`FrameTable::taps`] are used (one of weight 1 for a segment); `None` where the pixel has
    /// no embedding.
    pub fn recipe(&self, pixel: u32) -> Option<[(u32, f32); 4]> {
        match (&self.sampler, self.embeddings.layout()) {
            (Some(sampler), _) => {
                let width = self.embeddings.width();
                sampler.weights(pixel % width, pixel / width)
            }
            (None, EmbeddingLayout::Regions { index, .. }) => match index.get(pixel as usize) {
                Some(&s) if s != NO_REGION => Some([(s, 1.0), (0, 0.0), (0, 0.0), (0, 0.0)]),
                _ => None,
            },
            (None, EmbeddingLayout::PatchGrid { .. }) => None,
        }
    }

    /// Per group `g` of `count`, the sum of `weights[i] · row cells[i]` over the pairs `i` with
    /// `groups[i] == g` (a voxel's pixels, as the rows they are made of).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn sums(
        &self,
        groups: &[u32],
        cells: &[u32],
        weights: &[f32],
        count: usize,
    ) -> Result<RowSums, MapError> {
        let sums = || -> CandleResult<Tensor> {
            let device = self.table.device();
            let d = self.embeddings.dim();
            let n = cells.len();
            let zeros = Tensor::zeros((count, d), DType::F32, device)?;
            if n == 0 {
                return Ok(zeros);
            }
            let rows = self
                .table
                .index_select(&Tensor::from_slice(cells, n, device)?, 0)?
                .broadcast_mul(&Tensor::from_slice(weights, (n, 1), device)?)?;
            zeros.index_add(&Tensor::from_slice(groups, n, device)?, &rows, 0)
        };
        sums().map(RowSums).map_err(table_error)
    }

    /// The `f32` embeddings of lookups `range` (`rows × dim`).
    fn observed(&self, lookups: &Lookups, range: std::ops::Range<usize>) -> CandleResult<Tensor> {
        let (t, d) = (lookups.taps, self.embeddings.dim());
        let k = range.len();
        let device = self.table.device();
        let cells = Tensor::from_slice(
            &lookups.cells[range.start * t..range.end * t],
            k * t,
            device,
        )?;
        let rows = self.table.index_select(&cells, 0)?;
        if t == 1 {
            return Ok(rows);
        }
        let weights = Tensor::from_slice(
            &lookups.weights[range.start * t..range.end * t],
            (k, t, 1),
            device,
        )?;
        rows.reshape((k, t, d))?.broadcast_mul(&weights)?.sum(1)
    }
}

/// Sums of a frame's embedding rows per group (see [`FrameTable::sums`]), on the device.
#[derive(Clone, Debug)]
pub struct RowSums(Tensor);

impl RowSums {
    /// Per group, whether its sum has a positive, finite norm (can be normalised), copied to the
    /// host.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn usable(&self) -> Result<Vec<bool>, MapError> {
        let usable = || -> CandleResult<Vec<u8>> {
            let norm = self.0.sqr()?.sum(1)?.sqrt()?;
            norm.gt(0.0)?
                .mul(&norm.le(f64::from(f32::MAX))?)?
                .to_vec1::<u8>()
        };
        usable()
            .map(|v| v.into_iter().map(|b| b != 0).collect())
            .map_err(table_error)
    }
}

fn dtype(precision: Precision) -> DType {
    match precision {
        Precision::F32 => DType::F32,
        Precision::F16 => DType::F16,
    }
}

/// `rows`' chunks of at most [`CHUNK_ROWS`].
fn chunks(rows: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    (0..rows)
        .step_by(CHUNK_ROWS)
        .map(move |start| start..(start + CHUNK_ROWS).min(rows))
}

/// Each row of `blend` (`k × dim`) divided by its norm; the row of `fallback` where that norm is
/// zero or not finite (the host table's rule for rows that cancel out).
fn normalise_or(blend: &Tensor, fallback: &Tensor) -> CandleResult<Tensor> {
    let norm = blend.sqr()?.sum_keepdim(1)?.sqrt()?;
    // 1 where the norm is positive and finite (NaN compares false), else 0.
    let ok = norm.gt(0.0)?.mul(&norm.le(f64::from(f32::MAX))?)?;
    // Divide by 1 where the norm is bad: those rows take the fallback below.
    let safe = ok.where_cond(&norm, &norm.ones_like()?)?;
    let normalised = blend.broadcast_div(&safe)?;
    ok.broadcast_as(blend.shape())?
        .contiguous()?
        .where_cond(&normalised, fallback)
}

/// `indexes` (`k` rows) as the `k × dim` index tensor `scatter_set` takes.
fn row_indexes(indexes: &Tensor, dim: usize) -> CandleResult<Tensor> {
    let k = indexes.dim(0)?;
    indexes.unsqueeze(1)?.broadcast_as((k, dim))?.contiguous()
}

impl DeviceTable {
    /// An empty table with room for `capacity` rows, allocated now on `device`.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the device cannot hold it.
    pub fn new(
        device: &Device,
        dim: usize,
        precision: Precision,
        capacity: usize,
    ) -> Result<Self, MapError> {
        let values =
            Tensor::zeros((capacity, dim), dtype(precision), device).map_err(table_error)?;
        Ok(Self {
            dim,
            precision,
            values,
            rows: 0,
        })
    }

    /// The device the table is on.
    pub fn device(&self) -> &Device {
        self.values.device()
    }

    /// Embedding dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Storage type.
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Rows allocated.
    pub fn capacity(&self) -> usize {
        self.values.dim(0).unwrap_or(0)
    }

    /// Device bytes allocated for the values.
    pub fn device_bytes(&self) -> usize {
        self.capacity() * self.dim * self.values.dtype().size_in_bytes()
    }

    /// Makes room for `rows` rows: a new tensor of at least a quarter more rows, the rows copied
    /// over. With a capacity of the budget this happens once, when the first frame takes the
    /// map over its budget before the merge brings it back.
    fn ensure_capacity(&mut self, rows: usize) -> CandleResult<()> {
        if rows <= self.capacity() {
            return Ok(());
        }
        let capacity = rows.max(self.capacity() + self.capacity() / 4);
        let values = Tensor::zeros((capacity, self.dim), self.values.dtype(), self.device())?;
        if self.rows > 0 {
            values.slice_set(&self.values.narrow(0, 0, self.rows)?.contiguous()?, 0, 0)?;
        }
        self.values = values;
        Ok(())
    }

    /// Fuses the looked-up embeddings into map rows `rows` (one per lookup, no row twice):
    /// `e_M := (1 - w) e_P + w e_M`, renormalised, `e_P` where the two cancel out.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn fuse(
        &mut self,
        frame: &FrameTable<'_>,
        rows: &[u32],
        lookups: &Lookups,
        map_weight: f32,
    ) -> Result<(), MapError> {
        debug_assert_eq!(rows.len(), lookups.len());
        self.fuse_chunks(frame, rows, lookups, map_weight)
            .map_err(table_error)
    }

    fn fuse_chunks(
        &mut self,
        frame: &FrameTable<'_>,
        rows: &[u32],
        lookups: &Lookups,
        map_weight: f32,
    ) -> CandleResult<()> {
        let w = f64::from(map_weight);
        for range in chunks(rows.len()) {
            let indexes = Tensor::from_slice(&rows[range.clone()], range.len(), self.device())?;
            let map = self
                .values
                .index_select(&indexes, 0)?
                .to_dtype(DType::F32)?;
            let observed = frame.observed(lookups, range)?;
            let blend = observed.affine(1.0 - w, 0.0)?.add(&map.affine(w, 0.0)?)?;
            let fused = normalise_or(&blend, &observed)?.to_dtype(self.values.dtype())?;
            self.values
                .scatter_set(&row_indexes(&indexes, self.dim)?, &fused, 0)?;
        }
        Ok(())
    }

    /// Appends one row per lookup, its embedding as looked up.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails (device memory included).
    pub fn append(&mut self, frame: &FrameTable<'_>, lookups: &Lookups) -> Result<(), MapError> {
        self.append_chunks(frame, lookups).map_err(table_error)
    }

    fn append_chunks(&mut self, frame: &FrameTable<'_>, lookups: &Lookups) -> CandleResult<()> {
        self.ensure_capacity(self.rows + lookups.len())?;
        for range in chunks(lookups.len()) {
            let k = range.len();
            let rows = frame
                .observed(lookups, range)?
                .to_dtype(self.values.dtype())?;
            self.values.slice_set(&rows, 0, self.rows)?;
            self.rows += k;
        }
        Ok(())
    }

    /// Replaces each group's target row by the renormalised sum of its members' rows (the first
    /// member's row where they cancel out). Group `g`'s members are `members[ends[g - 1]..ends[g]]`
    /// (from 0 for the first); groups do not share rows.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn merge_groups(
        &mut self,
        members: &[u32],
        ends: &[u32],
        targets: &[u32],
    ) -> Result<(), MapError> {
        debug_assert_eq!(ends.len(), targets.len());
        self.merge_chunks(members, ends, targets)
            .map_err(table_error)
    }

    fn merge_chunks(&mut self, members: &[u32], ends: &[u32], targets: &[u32]) -> CandleResult<()> {
        let ends: Vec<usize> = ends.iter().map(|&e| e as usize).collect();
        let mut group = 0;
        let mut group_of = Vec::new();
        let mut firsts = Vec::new();
        while group < ends.len() {
            // Whole groups, up to CHUNK_ROWS members (a larger group alone).
            let start = if group == 0 { 0 } else { ends[group - 1] };
            let mut last = group;
            while last + 1 < ends.len() && ends[last + 1] - start <= CHUNK_ROWS {
                last += 1;
            }
            let groups = group..last + 1;
            let end = ends[last];
            group_of.clear();
            firsts.clear();
            let mut from = start;
            for (g, &to) in ends[groups.clone()].iter().enumerate() {
                group_of.extend(std::iter::repeat_n(g as u32, to - from));
                firsts.push(members[from]);
                from = to;
            }
            let device = self.device().clone();
            let count = groups.len();
            let rows = Tensor::from_slice(&members[start..end], end - start, &device)?;
            let rows = self.values.index_select(&rows, 0)?.to_dtype(DType::F32)?;
            let group_of = Tensor::from_slice(&group_of, end - start, &device)?;
            let sums = Tensor::zeros((count, self.dim), DType::F32, &device)?
                .index_add(&group_of, &rows, 0)?;
            let firsts = Tensor::from_slice(&firsts, count, &device)?;
            let first_rows = self.values.index_select(&firsts, 0)?.to_dtype(DType::F32)?;
            let merged = normalise_or(&sums, &first_rows)?.to_dtype(self.values.dtype())?;
            let targets = Tensor::from_slice(&targets[groups], count, &device)?;
            self.values
                .scatter_set(&row_indexes(&targets, self.dim)?, &merged, 0)?;
            group = last + 1;
        }
        Ok(())
    }

    /// Copies row `from[i]` into row `to[i]` for every `i`. No row may be both a source and a
    /// destination (what the budget's swap-removals reduce to).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn move_rows(&mut self, from: &[u32], to: &[u32]) -> Result<(), MapError> {
        debug_assert_eq!(from.len(), to.len());
        self.move_chunks(from, to).map_err(table_error)
    }

    fn move_chunks(&mut self, from: &[u32], to: &[u32]) -> CandleResult<()> {
        for range in chunks(from.len()) {
            let k = range.len();
            let sources = Tensor::from_slice(&from[range.clone()], k, self.device())?;
            let rows = self.values.index_select(&sources, 0)?;
            let targets = Tensor::from_slice(&to[range], k, self.device())?;
            self.values
                .scatter_set(&row_indexes(&targets, self.dim)?, &rows, 0)?;
        }
        Ok(())
    }

    /// Updates map row `slots[i]` with group `groups[i]` of `sums` for every `i`:
    /// `old_weights[i] · row + sum_weights[i] · sum`, renormalised; where that cancels out, the
    /// sum renormalised; where that cancels too, the row stays as it was (the voxel map's running
    /// mean). No slot twice.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails.
    pub fn blend_sums(
        &mut self,
        slots: &[u32],
        sums: &RowSums,
        groups: &[u32],
        old_weights: &[f32],
        sum_weights: &[f32],
    ) -> Result<(), MapError> {
        let k = slots.len();
        if k == 0 {
            return Ok(());
        }
        let blend = |table: &mut Self| -> CandleResult<()> {
            let device = table.device().clone();
            let slots = Tensor::from_slice(slots, k, &device)?;
            let old = table.values.index_select(&slots, 0)?.to_dtype(DType::F32)?;
            let new = sums
                .0
                .index_select(&Tensor::from_slice(groups, k, &device)?, 0)?;
            let mixed = old
                .broadcast_mul(&Tensor::from_slice(old_weights, (k, 1), &device)?)?
                .add(&new.broadcast_mul(&Tensor::from_slice(sum_weights, (k, 1), &device)?)?)?;
            let rows =
                normalise_or(&mixed, &normalise_or(&new, &old)?)?.to_dtype(table.values.dtype())?;
            table
                .values
                .scatter_set(&row_indexes(&slots, table.dim)?, &rows, 0)
        };
        blend(self).map_err(table_error)
    }

    /// Appends group `groups[i]` of `sums`, renormalised, for every `i` (each must be
    /// [`RowSums::usable`]).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when a tensor operation fails (device memory included).
    pub fn append_sums(&mut self, sums: &RowSums, groups: &[u32]) -> Result<(), MapError> {
        let k = groups.len();
        if k == 0 {
            return Ok(());
        }
        let append = |table: &mut Self| -> CandleResult<()> {
            table.ensure_capacity(table.rows + k)?;
            let device = table.device().clone();
            let new = sums
                .0
                .index_select(&Tensor::from_slice(groups, k, &device)?, 0)?;
            let rows = normalise_or(&new, &new)?.to_dtype(table.values.dtype())?;
            table.values.slice_set(&rows, 0, table.rows)?;
            table.rows += k;
            Ok(())
        };
        append(self).map_err(table_error)
    }

    /// Keeps the first `rows` rows (the allocation stays).
    pub fn truncate(&mut self, rows: usize) {
        self.rows = self.rows.min(rows);
    }

    /// All rows widened to `f32`, row-major, copied to the host.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy fails.
    pub fn to_f32(&self) -> Result<Vec<f32>, MapError> {
        if self.rows == 0 || self.dim == 0 {
            return Ok(Vec::new());
        }
        self.values
            .narrow(0, 0, self.rows)
            .and_then(|rows| rows.to_dtype(DType::F32))
            .and_then(|rows| rows.flatten_all())
            .and_then(|rows| rows.to_vec1::<f32>())
            .map_err(table_error)
    }

    /// Replaces the rows by `values` (`rows × dim`, row-major), keeping at least the current
    /// capacity.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy fails.
    pub fn replace(&mut self, values: &[f32]) -> Result<(), MapError> {
        let rows = values.len().checked_div(self.dim).unwrap_or(0);
        self.rows = 0;
        let copy = |table: &mut Self| -> CandleResult<()> {
            table.ensure_capacity(rows)?;
            for range in chunks(rows) {
                let chunk = Tensor::from_slice(
                    &values[range.start * table.dim..range.end * table.dim],
                    (range.len(), table.dim),
                    table.device(),
                )?
                .to_dtype(table.values.dtype())?;
                table.values.slice_set(&chunk, 0, range.start)?;
            }
            table.rows = rows;
            Ok(())
        };
        copy(self).map_err(table_error)
    }

    /// [`EmbeddingStore::similarity_many`](super::EmbeddingStore::similarity_many) on the device:
    /// per chunk of rows, one matrix product with all texts (in `f32`), the scores copied back.
    ///
    /// # Errors
    /// [`vlem_core::CoreError::DimensionMismatch`] when a text is not `dim` long;
    /// [`MapError::DeviceTable`] (as a stage error) when a tensor operation fails.
    pub fn similarity_many(
        &self,
        texts: &[&[f32]],
        out: &mut Vec<Vec<f32>>,
    ) -> vlem_core::Result<()> {
        vlem_core::query::check_texts(self.rows * self.dim, self.dim, texts)?;
        out.resize_with(texts.len(), Vec::new);
        for scores in out.iter_mut() {
            scores.clear();
            scores.reserve(self.rows);
        }
        if texts.is_empty() || self.rows == 0 {
            return Ok(());
        }
        self.score_chunks(texts, out)
            .map_err(|e| table_error(e).into_core(vlem_core::StageKind::Map, "device table"))
    }

    fn score_chunks(&self, texts: &[&[f32]], out: &mut [Vec<f32>]) -> CandleResult<()> {
        let flat: Vec<f32> = texts.iter().flat_map(|t| t.iter().copied()).collect();
        // `dim × texts`, so that each chunk's product is `rows × texts`.
        let texts_t = Tensor::from_vec(flat, (texts.len(), self.dim), self.device())?
            .t()?
            .contiguous()?;
        for range in chunks(self.rows) {
            let rows = self
                .values
                .narrow(0, range.start, range.len())?
                .to_dtype(DType::F32)?;
            let scores = rows.matmul(&texts_t)?.affine(0.5, 0.5)?.t()?.contiguous()?;
            for (all, chunk) in out.iter_mut().zip(scores.to_vec2::<f32>()?) {
                all.extend_from_slice(&chunk);
            }
        }
        Ok(())
    }
}

/// What removing rows `dead` (descending, distinct) one by one with `swap_remove` from a table of
/// `len` rows does, as row copies `from[i] → to[i]` followed by a truncation to `len - dead.len()`:
/// a row moved into a dead slot may be moved again later, so each copy names the row's original
/// index, and no row is both a source and a destination (what [`DeviceTable::move_rows`] takes).
pub fn swap_removal_moves(len: usize, dead: &[usize]) -> (Vec<u32>, Vec<u32>) {
    // Slot → the original row it now holds, for slots filled by a move.
    let mut filled = std::collections::HashMap::with_capacity(dead.len());
    let mut len = len;
    for &d in dead {
        let last = len - 1;
        let moved = filled.remove(&last).unwrap_or(last);
        if d != last {
            filled.insert(d, moved);
        }
        len -= 1;
    }
    filled
        .into_iter()
        .map(|(to, from)| (from as u32, to as u32))
        .unzip()
}
