//! `voxel`: a RayFronts-style semantic voxel map (Alama et al. 2025, `SemanticVoxelMap`).
//!
//! The world is cut into cubes of a fixed `voxel_size` (default 5 cm). Per frame:
//! 1. every valid depth pixel (depth at most `max_depth`) that has an embedding is back-projected
//!    into the map frame and binned into its voxel;
//! 2. the frame's pixels are grouped by voxel (a parallel sort), and per voxel the `k` pixel
//!    embeddings are summed;
//! 3. each voxel's embedding is the running mean of every pixel embedding it has seen, stored
//!    unit-normalised: with `n` earlier observations, `e := normalise(n/(n+k) e + k/(n+k) mean)`,
//!    falling back to the frame's mean when the two cancel out. Colours are running means too;
//! 4. with `max_observations = c` the count saturates at `c` (RayFronts' accumulation cap): the new
//!    pixels get weight `min(k, c)` and the old mean `min(n, c - min(k, c))`, so a saturated voxel
//!    keeps adapting like an exponential moving average instead of freezing. Counts are pixels, so
//!    a cap should be large compared with the pixels a voxel receives per frame;
//! 5. when the map holds more than `max_voxels` voxels, the ones observed least recently are
//!    evicted (ties: fewest observations first), so the count never exceeds the budget after an
//!    integration. Stale voxels are evicted before the frame's new voxels are added, so the tables
//!    stay within the budget too. Nothing else ever touches a voxel that is not in the current
//!    view.
//!
//! Storage is struct-of-arrays indexed by a dense voxel index (integer voxel coordinates, colour,
//! count, last-observed frame, and one contiguous embedding table in `f32` or `f16`), plus a hash
//! map from voxel coordinates to that index. A voxel is reported at its centre.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hash, Hasher};

use rayon::prelude::*;
use vlem_core::embeddings::{PatchSampler, normalise};
use vlem_core::{
    BuildContext, ColouredMesh, CoreError, EmbeddingMap, IntegrationStats, MapBudget, MapMetadata,
    MapSnapshot, Observation, PixelEmbeddings, RgbImage, StageKind, parse_params,
};

use crate::error::MapError;
use crate::kit::memory::hash_buckets;
use crate::kit::{FramePixels, check_observation, check_snapshot, invalid_parameter, number_in};
#[cfg(feature = "candle")]
use crate::storage::{CHUNK_ROWS, FrameTable, swap_removal_moves};
use crate::storage::{EmbeddingStore, Table};

/// The registered name.
pub const NAME: &str = "voxel";

/// Smallest accepted voxel size in metres: keeps integer voxel coordinates (`i32`) far from
/// overflow (±214 km at this size).
pub const MIN_VOXEL_SIZE: f32 = 1e-4;

/// Largest accepted voxel size in metres: coarser, a room is a handful of voxels.
pub const MAX_VOXEL_SIZE: f32 = 10.0;

/// Largest accepted voxel budget: dense voxel indices are `u32`, and a frame's new voxels are
/// added before eviction.
pub const MAX_VOXEL_BUDGET: usize = 1 << 30;

crate::map_config! {
    /// `[map] kind = "voxel"` parameters.
    pub struct VoxelConfig {
        /// Edge length of a voxel in metres; default 0.05 (RayFronts' setting in the paper).
        pub voxel_size: f32 = 0.05,
        /// Voxel budget; default 1,000,000. The least recently observed voxels are evicted beyond
        /// it.
        pub max_voxels: usize = 1_000_000,
        /// Cap on a voxel's observation count (pixels), so its mean keeps adapting; default none
        /// (an exact running mean over all observations).
        pub max_observations: Option<u32> = None,
    }
}

impl VoxelConfig {
    /// Builds the map for embeddings of dimension `encoder_dim` (`None` without an encoder).
    ///
    /// # Errors
    /// [`MapError::InvalidParameter`] (wrapped as a stage error) for out-of-range values and for a
    /// `dim` that disagrees with the encoder; a stage error naming the device when `device` cannot
    /// be opened (a build without `cuda`, no driver, no such GPU) or cannot hold the table.
    pub fn build(&self, encoder_dim: Option<usize>) -> Result<VoxelMap, CoreError> {
        let dim = self.validate(encoder_dim)?;
        let table = Table::open(NAME, self.device, dim, self.precision, self.max_voxels)?;
        Ok(VoxelMap::with_table(self.clone(), dim, table))
    }

    /// [`VoxelConfig::build`] with the embedding table on the candle device `device`, whatever
    /// `device` the config names: how the tests run the device table on candle's CPU.
    ///
    /// # Errors
    /// As [`VoxelConfig::build`]; a stage error when the device cannot hold the table.
    #[cfg(feature = "candle")]
    pub fn build_on(
        &self,
        encoder_dim: Option<usize>,
        device: &candle_core::Device,
    ) -> Result<VoxelMap, CoreError> {
        let dim = self.validate(encoder_dim)?;
        let table = Table::on_candle(NAME, device, dim, self.precision, self.max_voxels)?;
        Ok(VoxelMap::with_table(self.clone(), dim, table))
    }

    /// Checks the parameters; returns the embedding dimension.
    fn validate(&self, encoder_dim: Option<usize>) -> Result<usize, CoreError> {
        let invalid = |name: &'static str, reason: &str| invalid_parameter(NAME, name, reason);
        number_in(
            NAME,
            "voxel_size",
            self.voxel_size,
            (MIN_VOXEL_SIZE, MAX_VOXEL_SIZE),
            "m",
        )?;
        if !(1..=MAX_VOXEL_BUDGET).contains(&self.max_voxels) {
            return Err(invalid(
                "max_voxels",
                &format!("must lie in [1, {MAX_VOXEL_BUDGET}]"),
            ));
        }
        if self.max_observations == Some(0) {
            return Err(invalid(
                "max_observations",
                "must be at least 1 (or left out for no cap)",
            ));
        }
        self.common().validate_for_device(NAME, encoder_dim)
    }
}

fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn EmbeddingMap>> {
    let config: VoxelConfig = parse_params(StageKind::Map, NAME, params)?;
    Ok(Box::new(config.build(ctx.embedding_dim)?))
}

vlem_core::register_map!(
    NAME,
    "fixed-size voxels with running-mean embeddings under a voxel budget (RayFronts-style)",
    build
);

/// Integer voxel coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct VoxelKey([i32; 3]);

impl VoxelKey {
    /// The voxel holding `p`, given `1 / voxel_size` (the hot path multiplies instead of dividing).
    #[inline]
    fn of(p: [f32; 3], inverse_size: f32) -> Self {
        // `as` saturates, which only matters hundreds of kilometres away (see MIN_VOXEL_SIZE).
        Self(p.map(|x| (x * inverse_size).floor() as i32))
    }

    /// The voxel holding a saved voxel centre (mid-voxel, so the rounding mode does not matter).
    fn of_centre(p: [f32; 3], size: f32) -> Self {
        Self(p.map(|x| (f64::from(x) / f64::from(size)).floor() as i32))
    }

    fn centre(self, size: f32) -> [f32; 3] {
        self.0
            .map(|i| ((f64::from(i) + 0.5) * f64::from(size)) as f32)
    }
}

impl Hash for VoxelKey {
    fn hash<H: Hasher>(&self, state: &mut H) {
        // One word per key: the hasher's finaliser does the mixing.
        let [x, y, z] = self.0.map(|c| u64::from(c as u32));
        state.write_u64((x | (y << 32)) ^ z.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    }
}

/// A fast hasher for [`VoxelKey`] (SipHash would dominate the per-voxel cost): the splitmix64
/// finaliser over the written words. Not DoS-resistant, which voxel coordinates do not need.
#[derive(Clone, Copy, Debug, Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(23) ^ v).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type VoxelIndex = HashMap<VoxelKey, u32, BuildHasherDefault<KeyHasher>>;

/// Values of the per-frame buffer of merged embeddings, per chunk of voxels: bounds its memory
/// (16 MB) when every pixel lands in its own voxel.
const CHUNK_VALUES: usize = 1 << 22;

/// The semantic voxel map.
#[derive(Debug)]
pub struct VoxelMap {
    config: VoxelConfig,
    dim: usize,
    index: VoxelIndex,
    /// The largest `index.capacity()` seen: the table's bucket capacity. Removals leave
    /// tombstones that lower `capacity()` without freeing anything, so the current value
    /// under-reports the allocation after evictions.
    index_capacity: usize,
    keys: Vec<VoxelKey>,
    colours: Vec<[u8; 3]>,
    /// Observations (pixels) per voxel, at most `max_observations`.
    counts: Vec<u32>,
    /// The value of `frames` when the voxel was last observed (for eviction).
    last_seen: Vec<u32>,
    embeddings: Table,
    frames: usize,
}

/// What one voxel of a frame does to the map.
#[derive(Clone, Copy, Debug)]
enum Outcome {
    /// Nothing usable (no pixel embedding could be looked up, or a new voxel's embeddings cancel).
    Skip,
    /// An existing voxel; its embedding is rewritten from the buffer row when `write_row`.
    Update {
        slot: u32,
        colour: [u8; 3],
        count: u32,
        write_row: bool,
    },
    /// A new voxel with the buffer row as its embedding.
    Insert { colour: [u8; 3], count: u32 },
}

/// One voxel of a frame on the device path (see `VoxelMap::plan_on_device`).
#[cfg(feature = "candle")]
#[derive(Debug, Default)]
struct DevicePlan {
    /// Usable pixels.
    k: u32,
    /// Their colour sum.
    colour: [u64; 3],
    /// The voxel's slot, if it exists.
    slot: Option<u32>,
    /// Frame-table rows and their summed weights.
    pairs: Vec<(u32, f32)>,
}

/// The existing voxels a chunk updates on the device: slot, sum group and the running mean's
/// weights.
#[cfg(feature = "candle")]
#[derive(Debug, Default)]
struct DeviceUpdate {
    slots: Vec<u32>,
    groups: Vec<u32>,
    old_weights: Vec<f32>,
    sum_weights: Vec<f32>,
}

/// Where a frame's pixel embeddings and colours come from.
struct Source<'a> {
    embeddings: Option<&'a PixelEmbeddings>,
    /// For a patch grid: pixels as weights of grid rows (see `accumulate`).
    patches: Option<PatchSampler<'a>>,
    colour: &'a RgbImage,
    width: u32,
}

impl Source<'_> {
    /// Adds the embeddings of the pixels of `run` into `sum` (zeroed by the caller); returns how
    /// many pixels contributed and their colour sum. Pixels whose embedding cannot be looked up do
    /// not count.
    fn accumulate(
        &self,
        run: &[(VoxelKey, u32)],
        sum: &mut [f32],
        scratch: &mut [f32],
    ) -> (u32, [u64; 3]) {
        let mut k = 0u32;
        let mut colour = [0u64; 3];
        // Neighbouring pixels usually share a segment: add each stored row once with its
        // multiplicity instead of once per pixel.
        let mut pending: Option<(&[f32], f32)> = None;
        // Patch grids: a voxel's pixels touch a few grid rows; sum each row's weights over the
        // pixels and add the rows once.
        let mut rows: Vec<(u32, f32)> = Vec::new();
        for &(_, pixel) in run {
            let (u, v) = (pixel % self.width, pixel / self.width);
            if let Some(sampler) = &self.patches {
                let Some(weights) = sampler.weights(u, v) else {
                    continue;
                };
                for (cell, w) in weights.into_iter().filter(|&(_, w)| w != 0.0) {
                    match rows.iter_mut().find(|(c, _)| *c == cell) {
                        Some((_, total)) => *total += w,
                        None => rows.push((cell, w)),
                    }
                }
            } else if let Some(e) = self.embeddings {
                if let Some(row) = e.region_row(u, v) {
                    let same =
                        matches!(pending, Some((p, _)) if std::ptr::eq(p.as_ptr(), row.as_ptr()));
                    if same {
                        if let Some((_, m)) = &mut pending {
                            *m += 1.0;
                        }
                    } else if let Some((p, m)) = pending.replace((row, 1.0)) {
                        axpy(sum, p, m);
                    }
                } else if e.embedding_at(u, v, scratch) {
                    axpy(sum, scratch, 1.0);
                } else {
                    continue;
                }
            }
            let c = self.colour.at_index(pixel as usize);
            for (acc, x) in colour.iter_mut().zip(c) {
                *acc += u64::from(x);
            }
            k = k.saturating_add(1);
        }
        if let Some((p, m)) = pending {
            axpy(sum, p, m);
        }
        if let Some(sampler) = &self.patches {
            for (cell, w) in rows {
                axpy(sum, sampler.row(cell), w);
            }
        }
        (k, colour)
    }
}

#[inline]
fn axpy(y: &mut [f32], x: &[f32], a: f32) {
    for (y, x) in y.iter_mut().zip(x) {
        *y += a * x;
    }
}

/// Effective weights `(old, new)` of the running mean under the cap: the new observations count
/// at most `cap`, the old mean fills what is left.
#[inline]
fn weights(n: u32, k: u32, cap: u32) -> (u32, u32) {
    let k_eff = k.min(cap);
    (n.min(cap - k_eff), k_eff)
}

/// `(n_old * old + n_new * new) / (n_old + n_new)`, rounded, per channel.
fn mean_colour(old: [u8; 3], n_old: u32, new: [f64; 3], n_new: u32) -> [u8; 3] {
    let (a, b) = (f64::from(n_old), f64::from(n_new));
    let mut out = [0u8; 3];
    for ((o, c), x) in out.iter_mut().zip(old).zip(new) {
        *o = ((a * f64::from(c) + b * x) / (a + b))
            .round()
            .clamp(0.0, 255.0) as u8;
    }
    out
}

impl VoxelMap {
    /// An empty map with its table in host memory, whatever `device` the config names (use
    /// [`VoxelConfig::build`] for validated parameters and the configured device).
    pub fn new(config: VoxelConfig, dim: usize) -> Self {
        let table = Table::Host(EmbeddingStore::new(dim, config.precision));
        Self::with_table(config, dim, table)
    }

    fn with_table(config: VoxelConfig, dim: usize, embeddings: Table) -> Self {
        Self {
            embeddings,
            config,
            dim,
            index: VoxelIndex::default(),
            index_capacity: 0,
            keys: Vec::new(),
            colours: Vec::new(),
            counts: Vec::new(),
            last_seen: Vec::new(),
            frames: 0,
        }
    }

    /// The voxel edge length in metres.
    pub fn voxel_size(&self) -> f32 {
        self.config.voxel_size
    }

    /// Centres of all voxels, in the order of [`EmbeddingMap::snapshot`].
    pub fn positions(&self) -> Vec<[f32; 3]> {
        let size = self.config.voxel_size;
        self.keys.iter().map(|k| k.centre(size)).collect()
    }

    /// Observation counts (pixels, capped at `max_observations`) of all voxels.
    pub fn counts(&self) -> &[u32] {
        &self.counts
    }

    /// The `len x dim` embedding table, widened to `f32` (copied from the device if it is on
    /// one).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy from the device fails.
    pub fn embeddings(&self) -> Result<Vec<f32>, MapError> {
        self.embeddings.to_f32()
    }

    /// The host table (`None` on a device), for the host paths below.
    fn host(&self) -> Option<&EmbeddingStore> {
        match &self.embeddings {
            Table::Host(store) => Some(store),
            #[cfg(feature = "candle")]
            Table::Device(_) => None,
        }
    }

    fn cap(&self) -> u32 {
        self.config.max_observations.unwrap_or(u32::MAX)
    }

    fn check(&self, obs: &Observation<'_>) -> Result<(), MapError> {
        check_observation(self.dim, obs)
    }

    /// The voxel and linear pixel index of every usable pixel, sorted by voxel then pixel (so the
    /// sums below are deterministic).
    fn observe(&self, obs: &Observation<'_>) -> Vec<(VoxelKey, u32)> {
        let inverse_size = 1.0 / self.config.voxel_size;
        let mut pixels: Vec<(VoxelKey, u32)> = FramePixels::new(obs, &self.config.common())
            .par_iter()
            .map(|p| (VoxelKey::of(p.world, inverse_size), p.index))
            .collect();
        pixels.par_sort_unstable();
        pixels
    }

    /// The outcome of one voxel's pixels (`run`); the merged embedding goes into `row`.
    fn merge_run(
        &self,
        source: &Source<'_>,
        run: &[(VoxelKey, u32)],
        row: &mut [f32],
        scratch: &mut [f32],
        old: &mut [f32],
    ) -> Outcome {
        let Some(&(key, _)) = run.first() else {
            return Outcome::Skip;
        };
        row.fill(0.0);
        let (k, colour_sum) = source.accumulate(run, row, scratch);
        if k == 0 {
            return Outcome::Skip;
        }
        let frame_colour = colour_sum.map(|c| c as f64 / f64::from(k));
        let cap = self.cap();
        let Some(&slot) = self.index.get(&key) else {
            // A new voxel: the frame's mean, normalised.
            if self.dim > 0 && !normalise(row) {
                return Outcome::Skip;
            }
            return Outcome::Insert {
                colour: mean_colour([0; 3], 0, frame_colour, 1),
                count: k.min(cap),
            };
        };
        let s = slot as usize;
        let (n_old, n_new) = weights(self.counts[s], k, cap);
        let total = n_old + n_new;
        let mut write_row = false;
        if let Some(store) = self.host().filter(|_| self.dim > 0) {
            store.row_into(s, old);
            let w_old = n_old as f32 / total as f32;
            // `row` holds the sum of k embeddings, not their mean.
            let w_new = n_new as f32 / total as f32 / k as f32;
            for (o, x) in old.iter_mut().zip(row.iter()) {
                *o = w_old * *o + w_new * x;
            }
            if normalise(old) {
                row.copy_from_slice(old);
                write_row = true;
            } else {
                // Old and new cancel out: the frame's mean, unless that cancels too.
                write_row = normalise(row);
            }
        }
        Outcome::Update {
            slot,
            colour: mean_colour(self.colours[s], n_old, frame_colour, n_new),
            count: total,
            write_row,
        }
    }

    /// Merges the frame's voxels (`runs` of pixels sharing a voxel) into the map, in chunks that
    /// bound the buffer of merged rows. Returns (voxels updated, voxels inserted).
    fn fuse(
        &mut self,
        obs: &Observation<'_>,
        runs: &[&[(VoxelKey, u32)]],
        stamp: u32,
    ) -> Result<(usize, usize), MapError> {
        #[cfg(feature = "candle")]
        if let (Table::Device(_), Some(embeddings)) =
            (&self.embeddings, obs.embeddings.filter(|_| self.dim > 0))
        {
            return self.fuse_on_device(obs, embeddings, runs, stamp);
        }
        let dim = self.dim;
        let width = dim.max(1);
        let chunk = (CHUNK_VALUES / width).max(64);
        let embeddings = obs.embeddings.filter(|_| dim > 0);
        let source = Source {
            embeddings,
            patches: embeddings.and_then(PixelEmbeddings::patch_sampler),
            colour: &obs.frame.colour,
            width: obs.frame.depth.width(),
        };
        let mut buffer = vec![0.0f32; chunk.min(runs.len()) * width];
        let mut outcomes = Vec::new();
        let (mut fused, mut inserted) = (0, 0);
        for part in runs.chunks(chunk) {
            let rows = &mut buffer[..part.len() * width];
            {
                // Lookups and arithmetic in parallel, reading the map...
                let this = &*self;
                part.par_iter()
                    .zip(rows.par_chunks_mut(width))
                    .with_min_len(16)
                    .map_init(
                        || (vec![0.0f32; dim], vec![0.0f32; dim]),
                        |(scratch, old), (run, row)| {
                            this.merge_run(&source, run, &mut row[..dim], scratch, old)
                        },
                    )
                    .collect_into_vec(&mut outcomes);
            }
            // ...then the writes, which are copies.
            for ((run, outcome), row) in part.iter().zip(&outcomes).zip(rows.chunks(width)) {
                let row = &row[..dim];
                match *outcome {
                    Outcome::Skip => {}
                    Outcome::Update {
                        slot,
                        colour,
                        count,
                        write_row,
                    } => {
                        let s = slot as usize;
                        self.colours[s] = colour;
                        self.counts[s] = count;
                        self.last_seen[s] = stamp;
                        if write_row
                            && dim > 0
                            && let Some(store) = self.embeddings.host_mut()
                        {
                            store.set_row(s, row);
                        }
                        fused += 1;
                    }
                    Outcome::Insert { colour, count } => {
                        let Some(&(key, _)) = run.first() else {
                            continue;
                        };
                        self.push(key, colour, count, stamp, Some(row));
                        inserted += 1;
                    }
                }
            }
        }
        Ok((fused, inserted))
    }

    /// [`VoxelMap::fuse`] with the table on a device: per chunk of voxels, each voxel's usable
    /// pixels as the frame-table rows they are made of (on the host, as `Source::accumulate`
    /// gathers them), then their sums and the running means on the device. The same outcomes as
    /// `merge_run`: a new voxel whose sum cancels out is skipped (the one value copied back per
    /// voxel says which), an existing voxel whose mean and sum both cancel keeps its row.
    #[cfg(feature = "candle")]
    fn fuse_on_device(
        &mut self,
        obs: &Observation<'_>,
        embeddings: &PixelEmbeddings,
        runs: &[&[(VoxelKey, u32)]],
        stamp: u32,
    ) -> Result<(usize, usize), MapError> {
        let frame = match &self.embeddings {
            Table::Device(table) => FrameTable::upload(embeddings, table)?,
            Table::Host(_) => return Ok((0, 0)),
        };
        let (colour, cap) = (&obs.frame.colour, self.cap());
        let (mut fused, mut inserted) = (0, 0);
        for part in runs.chunks(CHUNK_ROWS) {
            let plans: Vec<DevicePlan> = {
                let this = &*self;
                part.par_iter()
                    .with_min_len(16)
                    .map(|run| this.plan_on_device(&frame, colour, run))
                    .collect()
            };
            // The pairs of the voxels with a usable pixel, voxel by voxel.
            let (mut groups, mut cells, mut pair_weights) = (Vec::new(), Vec::new(), Vec::new());
            let mut count = 0u32;
            for plan in plans.iter().filter(|p| p.k > 0) {
                for &(cell, weight) in &plan.pairs {
                    groups.push(count);
                    cells.push(cell);
                    pair_weights.push(weight);
                }
                count += 1;
            }
            let sums = frame.sums(&groups, &cells, &pair_weights, count as usize)?;
            let usable = sums.usable()?;
            let mut update = DeviceUpdate::default();
            let mut appended = Vec::new();
            let mut group = 0u32;
            for (run, plan) in part.iter().zip(&plans) {
                if plan.k == 0 {
                    continue;
                }
                let g = group;
                group += 1;
                let frame_colour = plan.colour.map(|c| c as f64 / f64::from(plan.k));
                match plan.slot {
                    None => {
                        let Some(&(key, _)) = run.first() else {
                            continue;
                        };
                        if !usable[g as usize] {
                            continue;
                        }
                        let colour = mean_colour([0; 3], 0, frame_colour, 1);
                        self.push(key, colour, plan.k.min(cap), stamp, None);
                        appended.push(g);
                        inserted += 1;
                    }
                    Some(slot) => {
                        let s = slot as usize;
                        let (n_old, n_new) = weights(self.counts[s], plan.k, cap);
                        let total = n_old + n_new;
                        update.slots.push(slot);
                        update.groups.push(g);
                        update.old_weights.push(n_old as f32 / total as f32);
                        // The sum of k embeddings, not their mean.
                        update
                            .sum_weights
                            .push(n_new as f32 / total as f32 / plan.k as f32);
                        self.colours[s] = mean_colour(self.colours[s], n_old, frame_colour, n_new);
                        self.counts[s] = total;
                        self.last_seen[s] = stamp;
                        fused += 1;
                    }
                }
            }
            if let Table::Device(table) = &mut self.embeddings {
                table.blend_sums(
                    &update.slots,
                    &sums,
                    &update.groups,
                    &update.old_weights,
                    &update.sum_weights,
                )?;
                table.append_sums(&sums, &appended)?;
            }
        }
        Ok((fused, inserted))
    }

    /// One voxel's usable pixels (`run`) for the device path: their count, colour sum, the
    /// voxel's slot if it exists, and the frame-table rows with their summed weights.
    #[cfg(feature = "candle")]
    fn plan_on_device(
        &self,
        frame: &FrameTable<'_>,
        colour: &RgbImage,
        run: &[(VoxelKey, u32)],
    ) -> DevicePlan {
        let mut plan = DevicePlan {
            slot: run
                .first()
                .and_then(|(key, _)| self.index.get(key).copied()),
            ..DevicePlan::default()
        };
        let taps = frame.taps();
        for &(_, pixel) in run {
            let Some(recipe) = frame.recipe(pixel) else {
                continue;
            };
            // A voxel's pixels share a few segments or grid rows: each row once, weights summed.
            for &(cell, weight) in recipe[..taps].iter().filter(|(_, w)| *w != 0.0) {
                match plan.pairs.iter_mut().find(|(c, _)| *c == cell) {
                    Some((_, total)) => *total += weight,
                    None => plan.pairs.push((cell, weight)),
                }
            }
            let c = colour.at_index(pixel as usize);
            for (acc, x) in plan.colour.iter_mut().zip(c) {
                *acc += u64::from(x);
            }
            plan.k = plan.k.saturating_add(1);
        }
        plan
    }

    /// Adds a voxel; its embedding `row` goes into the host table (a device table's rows are
    /// appended by the caller, `row` then `None`).
    fn push(
        &mut self,
        key: VoxelKey,
        colour: [u8; 3],
        count: u32,
        stamp: u32,
        row: Option<&[f32]>,
    ) {
        // The budget check keeps the count far below u32::MAX.
        self.index.insert(key, self.keys.len() as u32);
        // Right after an insertion that grew the table there are no tombstones: the full capacity.
        self.index_capacity = self.index_capacity.max(self.index.capacity());
        self.keys.push(key);
        self.colours.push(colour);
        self.counts.push(count);
        self.last_seen.push(stamp);
        if self.dim > 0
            && let (Some(store), Some(row)) = (self.embeddings.host_mut(), row)
        {
            store.push(row);
        }
    }

    /// Before a frame's voxels are written: marks the voxels it observes as seen now, and evicts
    /// older voxels (the least recently observed first) to make room for the frame's new ones, so
    /// the tables do not grow past the budget and the memory stays bounded. Returns the number
    /// evicted.
    fn make_room(&mut self, runs: &[&[(VoxelKey, u32)]], stamp: u32) -> Result<usize, MapError> {
        let existing: Vec<Option<u32>> = runs
            .par_iter()
            .with_min_len(1024)
            .map(|run| {
                run.first()
                    .and_then(|(key, _)| self.index.get(key).copied())
            })
            .collect();
        for &slot in existing.iter().flatten() {
            self.last_seen[slot as usize] = stamp;
        }
        let new = existing.iter().filter(|s| s.is_none()).count();
        self.evict(self.config.max_voxels.saturating_sub(new), Some(stamp))
    }

    /// Evicts the least recently observed voxels (ties: fewest observations first; remaining ties
    /// are broken by slot, deterministically) until at most `target` remain, or, with
    /// `seen_before`, until no voxel observed before that stamp is left. Returns the number
    /// evicted.
    fn evict(&mut self, target: usize, seen_before: Option<u32>) -> Result<usize, MapError> {
        let len = self.keys.len();
        if len <= target {
            return Ok(0);
        }
        let limit = seen_before.unwrap_or(u32::MAX);
        // Index stored as u32::MAX - i so that ascending order takes later slots first on ties.
        let mut order: Vec<(u32, u32, u32)> = (0..len)
            .into_par_iter()
            .with_min_len(4096)
            .filter(|&i| seen_before.is_none() || self.last_seen[i] < limit)
            .map(|i| (self.last_seen[i], self.counts[i], u32::MAX - i as u32))
            .collect();
        let excess = (len - target).min(order.len());
        if excess == 0 {
            return Ok(0);
        }
        if excess < order.len() {
            order.select_nth_unstable(excess - 1);
        }
        let mut dead: Vec<usize> = order[..excess]
            .iter()
            .map(|&(_, _, i)| (u32::MAX - i) as usize)
            .collect();
        // Descending, so the voxel moved into a dead slot is always a live one.
        dead.sort_unstable_by(|a, b| b.cmp(a));
        #[cfg(feature = "candle")]
        if let Table::Device(table) = &mut self.embeddings
            && self.dim > 0
        {
            let (from, to) = swap_removal_moves(len, &dead);
            table.move_rows(&from, &to)?;
            table.truncate(len - dead.len());
        }
        for d in dead {
            self.index.remove(&self.keys[d]);
            self.keys.swap_remove(d);
            self.colours.swap_remove(d);
            self.counts.swap_remove(d);
            self.last_seen.swap_remove(d);
            if self.dim > 0
                && let Some(store) = self.embeddings.host_mut()
            {
                store.swap_remove(d);
            }
            if let Some(moved) = self.keys.get(d)
                && let Some(slot) = self.index.get_mut(moved)
            {
                *slot = d as u32;
            }
        }
        Ok(excess)
    }
}

impl EmbeddingMap for VoxelMap {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn integrate(&mut self, obs: &Observation<'_>) -> vlem_core::Result<IntegrationStats> {
        self.check(obs)
            .map_err(|e| CoreError::stage(StageKind::Map, NAME, e))?;
        self.frames += 1;
        let pixels = self.observe(obs);
        let mut stats = IntegrationStats {
            observed: pixels.len(),
            ..IntegrationStats::default()
        };
        if pixels.is_empty() {
            return Ok(stats);
        }
        let runs: Vec<&[(VoxelKey, u32)]> = pixels.chunk_by(|a, b| a.0 == b.0).collect();
        let stamp = u32::try_from(self.frames).unwrap_or(u32::MAX);
        let core = |e: MapError| e.into_core(StageKind::Map, NAME);
        stats.removed = self.make_room(&runs, stamp).map_err(core)?;
        (stats.fused, stats.inserted) = self.fuse(obs, &runs, stamp).map_err(core)?;
        // Only when the frame alone brings more new voxels than the budget.
        stats.removed += self.evict(self.config.max_voxels, None).map_err(core)?;
        Ok(stats)
    }

    fn len(&self) -> usize {
        self.keys.len()
    }

    fn budget(&self) -> Option<MapBudget> {
        Some(MapBudget {
            parameter: "max_voxels",
            elements: self.config.max_voxels,
        })
    }

    fn memory_bytes(&self) -> usize {
        use std::mem::size_of;
        // The hash map: one key, one value and one control byte per bucket.
        let buckets = hash_buckets(self.index_capacity.max(self.index.capacity()));
        let table = buckets * (size_of::<(VoxelKey, u32)>() + 1);
        self.embeddings.host_bytes()
            + self.keys.capacity() * size_of::<VoxelKey>()
            + self.colours.capacity() * 3
            + self.counts.capacity() * 4
            + self.last_seen.capacity() * 4
            + table
    }

    fn device_memory_bytes(&self) -> usize {
        self.embeddings.device_bytes()
    }

    fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> vlem_core::Result<()> {
        self.embeddings.similarity(text, out)
    }

    fn similarity_many(&self, texts: &[&[f32]], out: &mut Vec<Vec<f32>>) -> vlem_core::Result<()> {
        self.embeddings.similarity_many(texts, out)
    }

    fn coloured_points(&self) -> ColouredMesh {
        ColouredMesh {
            vertices: self.positions(),
            colours: self.colours.clone(),
            triangles: Vec::new(),
        }
    }

    fn snapshot(&self) -> vlem_core::Result<MapSnapshot> {
        Ok(MapSnapshot {
            map_kind: NAME.into(),
            dim: self.dim,
            positions: self.positions(),
            colours: self.colours.clone(),
            embeddings: self
                .embeddings
                .to_f32()
                .map_err(|e| e.into_core(StageKind::Map, NAME))?,
            metadata: MapMetadata {
                frames_integrated: self.frames,
                ..MapMetadata::default()
            },
        })
    }

    /// Rebuilds one voxel per distinct voxel of the saved positions, with count 1, last observed
    /// at the saved frame count. Positions that share a voxel (a snapshot of another map) are
    /// merged as a running mean. A snapshot of this map with the same voxel size restores exactly.
    fn restore(&mut self, snapshot: MapSnapshot) -> vlem_core::Result<()> {
        check_snapshot(self.dim, &snapshot)?;
        let mut map = Self::new(self.config.clone(), self.dim);
        map.frames = snapshot.metadata.frames_integrated;
        let stamp = u32::try_from(map.frames).unwrap_or(u32::MAX);
        let (d, size, cap) = (self.dim, self.config.voxel_size, self.cap());
        let mut merged = vec![0.0f32; d];
        for (i, (&p, &colour)) in snapshot.positions.iter().zip(&snapshot.colours).enumerate() {
            let key = VoxelKey::of_centre(p, size);
            let row = &snapshot.embeddings[i * d..(i + 1) * d];
            let Some(&slot) = map.index.get(&key) else {
                map.push(key, colour, 1, stamp, Some(row));
                continue;
            };
            let s = slot as usize;
            let (n_old, n_new) = weights(map.counts[s], 1, cap);
            let total = n_old + n_new;
            if d > 0
                && let Some(store) = map.embeddings.host_mut()
            {
                store.row_into(s, &mut merged);
                let (w_old, w_new) = (n_old as f32 / total as f32, n_new as f32 / total as f32);
                for (m, x) in merged.iter_mut().zip(row) {
                    *m = w_old * *m + w_new * x;
                }
                if !normalise(&mut merged) {
                    merged.copy_from_slice(row);
                }
                store.set_row(s, &merged);
            }
            map.colours[s] = mean_colour(map.colours[s], n_old, colour.map(f64::from), n_new);
            map.counts[s] = total;
        }
        // Built on the host; a device map's rows then go to its table.
        let core = |e: MapError| e.into_core(StageKind::Map, NAME);
        map.evict(map.config.max_voxels, None).map_err(core)?;
        let rows = map.embeddings.to_f32().map_err(core)?;
        let mut table = std::mem::replace(
            &mut self.embeddings,
            Table::Host(EmbeddingStore::new(0, self.config.precision)),
        );
        table.replace(rows).map_err(core)?;
        map.embeddings = table;
        *self = map;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::Precision;
    use crate::test_fixtures::*;
    use vlem_core::{PixelEmbeddings, Pose};

    fn map(config: VoxelConfig) -> VoxelMap {
        config.build(Some(DIM)).unwrap()
    }

    fn assert_rows(m: &VoxelMap, expected: &[f32]) {
        let mut e = expected.to_vec();
        normalise(&mut e);
        for row in m.embeddings().unwrap().chunks_exact(DIM) {
            assert!(
                row.iter().zip(&e).all(|(a, b)| (a - b).abs() < 1e-6),
                "{row:?} != {e:?}"
            );
        }
    }

    #[test]
    fn embeddings_are_the_running_mean_of_observations() {
        let (a, b) = ([1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]);
        let f = plane(1.0);
        let mut m = map(VoxelConfig::default());
        let first = integrate(&mut m, &f, &Pose::identity(), &uniform(a));
        assert_eq!(first.observed, (W * H) as usize);
        assert_eq!(first.inserted, m.len());
        let pixels: u32 = m.counts().iter().sum();
        assert_eq!(pixels, W * H);
        let second = integrate(&mut m, &f, &Pose::identity(), &uniform(b));
        assert_eq!((second.fused, second.inserted), (m.len(), 0));
        // Every voxel saw the same pixels twice: n = k, so the mean is normalise(a + b).
        assert_rows(&m, &[1.0, 1.0, 0.0, 0.0]);
        // A third observation of b: weights 2/3 for the stored (unit) mean and 1/3 for b.
        integrate(&mut m, &f, &Pose::identity(), &uniform(b));
        let h = 0.5f32.sqrt();
        assert_rows(&m, &[2.0 / 3.0 * h, 2.0 / 3.0 * h + 1.0 / 3.0, 0.0, 0.0]);
        assert_eq!(m.counts().iter().sum::<u32>(), 3 * W * H);
        assert!(
            m.snapshot()
                .unwrap()
                .colours
                .iter()
                .all(|c| *c == [200, 100, 0])
        );

        // With a cap of 1 the latest observation replaces the mean.
        let mut capped = map(VoxelConfig {
            max_observations: Some(1),
            ..VoxelConfig::default()
        });
        integrate(&mut capped, &f, &Pose::identity(), &uniform(a));
        integrate(&mut capped, &f, &Pose::identity(), &uniform(b));
        assert_rows(&capped, &b);
        assert!(capped.counts().iter().all(|&n| n == 1));
    }

    #[test]
    fn opposite_embeddings_fall_back_to_the_new_mean() {
        let f = plane(1.0);
        let mut m = map(VoxelConfig::default());
        integrate(
            &mut m,
            &f,
            &Pose::identity(),
            &uniform([1.0, 0.0, 0.0, 0.0]),
        );
        integrate(
            &mut m,
            &f,
            &Pose::identity(),
            &uniform([-1.0, 0.0, 0.0, 0.0]),
        );
        assert_rows(&m, &[-1.0, 0.0, 0.0, 0.0]);
    }

    /// Voxels of 1 m: the 16x12 plane at 1 m covers 4 voxels (x and y either side of 0) of 48
    /// pixels each.
    fn coarse(max_voxels: usize) -> VoxelMap {
        map(VoxelConfig {
            voxel_size: 1.0,
            max_voxels,
            ..VoxelConfig::default()
        })
    }

    #[test]
    fn eviction_removes_the_least_recently_observed_voxels() {
        let mut m = coarse(8);
        let (f, e) = (plane(1.0), uniform([1.0, 0.0, 0.0, 0.0]));
        integrate(&mut m, &f, &translated(0.0), &e); // A
        integrate(&mut m, &f, &translated(10.0), &e); // B
        assert_eq!(m.len(), 8);
        integrate(&mut m, &f, &translated(0.0), &e); // A again: B is now the stalest
        let stats = integrate(&mut m, &f, &translated(20.0), &e); // C
        assert_eq!((stats.inserted, stats.removed), (4, 4));
        assert_eq!(m.len(), 8);
        let xs: Vec<f32> = m.positions().iter().map(|p| p[0]).collect();
        assert!(
            xs.iter().all(|x| x.abs() < 1.0 || (x - 20.0).abs() < 1.0),
            "{xs:?}"
        );
        assert!(m.snapshot().unwrap().validate().is_ok());
        // The index still finds every voxel at its slot after the swaps.
        for (i, k) in m.keys.iter().enumerate() {
            assert_eq!(m.index[k] as usize, i);
        }
        assert_eq!(m.index.len(), m.len());
    }

    #[test]
    fn eviction_ties_go_to_the_least_observed_voxels() {
        let mut m = coarse(2);
        let e = uniform([1.0, 0.0, 0.0, 0.0]);
        // Left half only (u < 8 has x < 0), then the whole plane: all voxels share the last
        // frame, but the left ones hold twice the observations.
        let left: Vec<f32> = (0..W * H)
            .map(|i| if i % W < W / 2 { 1.0 } else { f32::NAN })
            .collect();
        integrate(&mut m, &plane_with(left), &Pose::identity(), &e);
        assert_eq!(m.len(), 2);
        let stats = integrate(&mut m, &plane(1.0), &Pose::identity(), &e);
        assert_eq!((stats.fused, stats.inserted, stats.removed), (2, 2, 2));
        assert!(m.positions().iter().all(|p| p[0] < 0.0));
        assert!(m.counts().iter().all(|&n| n == 96));
    }

    #[test]
    fn depth_beyond_max_depth_is_ignored() {
        let mut m = map(VoxelConfig {
            max_depth: 1.5,
            ..VoxelConfig::default()
        });
        let depth: Vec<f32> = (0..W * H)
            .map(|i| if i % 2 == 0 { 1.0 } else { 2.0 })
            .collect();
        let stats = integrate(
            &mut m,
            &plane_with(depth),
            &Pose::identity(),
            &uniform([0.0, 0.0, 1.0, 0.0]),
        );
        assert_eq!(stats.observed, (W * H / 2) as usize);
        assert!(m.positions().iter().all(|p| p[2] < 1.5));
        assert_eq!(m.counts().iter().sum::<u32>(), W * H / 2);
        let far = integrate(
            &mut m,
            &plane(3.0),
            &Pose::identity(),
            &uniform([0.0, 0.0, 1.0, 0.0]),
        );
        assert_eq!((far.observed, far.inserted, far.fused), (0, 0, 0));
    }

    #[test]
    fn f16_keeps_the_ranking_and_shrinks_the_bytes_per_voxel() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut grid = || {
            let data: Vec<f32> = (0..4 * 3 * DIM)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            PixelEmbeddings::from_patch_grid(W, H, DIM, 4, 3, data).unwrap()
        };
        let (a, b) = (grid(), grid());
        let mut maps = [Precision::F32, Precision::F16].map(|precision| {
            map(VoxelConfig {
                precision,
                voxel_size: 0.1,
                ..VoxelConfig::default()
            })
        });
        for m in &mut maps {
            integrate(m, &plane(1.0), &Pose::identity(), &a);
            integrate(m, &plane(1.2), &translated(0.03), &b);
            integrate(m, &plane(1.0), &Pose::identity(), &b);
        }
        assert_eq!(maps[0].positions(), maps[1].positions());
        let text = [0.6, 0.2, 0.7, 0.3];
        let (mut s32, mut s16) = (Vec::new(), Vec::new());
        maps[0].similarity(&text, &mut s32).unwrap();
        maps[1].similarity(&text, &mut s16).unwrap();
        // As in storage.rs: scores closer than 2 * 2^-12 are ties at f16 (plus the f16
        // rounding of the running mean itself, well inside that bound for unit rows).
        let tie = 2.0 * 2f32.powi(-12);
        for i in 0..s32.len() {
            for j in 0..s32.len() {
                if s32[i] - s32[j] > tie {
                    assert!(s16[i] > s16[j], "voxels {i} and {j} swap at f16");
                }
            }
        }
        let distinct = s32.iter().filter(|x| (**x - s32[0]).abs() > 0.01).count();
        assert!(distinct > 10, "the test needs distinct scores");
        let (full, half) = (&maps[0], &maps[1]);
        assert_eq!(
            full.embeddings.host_bytes(),
            2 * half.embeddings.host_bytes()
        );
        assert_eq!(
            full.memory_bytes() - half.memory_bytes(),
            half.embeddings.host_bytes()
        );
        assert!(half.memory_bytes() / half.len() < full.memory_bytes() / full.len());
    }

    #[test]
    fn invalid_parameters_are_named() {
        let err = VoxelConfig {
            voxel_size: 0.0,
            ..VoxelConfig::default()
        }
        .build(Some(DIM))
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "map `voxel`: parameter `voxel_size` must lie in 1e-4–10 m, got 0"
        );
        let bad = [
            VoxelConfig {
                voxel_size: f32::NAN,
                ..VoxelConfig::default()
            },
            VoxelConfig {
                max_voxels: 0,
                ..VoxelConfig::default()
            },
            VoxelConfig {
                max_depth: -1.0,
                ..VoxelConfig::default()
            },
            VoxelConfig {
                pixel_stride: 0,
                ..VoxelConfig::default()
            },
            VoxelConfig {
                max_observations: Some(0),
                ..VoxelConfig::default()
            },
            VoxelConfig {
                dim: Some(512),
                ..VoxelConfig::default()
            },
        ];
        let names = [
            "voxel_size",
            "max_voxels",
            "max_depth",
            "pixel_stride",
            "max_observations",
            "dim",
        ];
        for (config, name) in bad.iter().zip(names) {
            let err = config.build(Some(DIM)).unwrap_err().to_string();
            assert!(err.contains(&format!("parameter `{name}`")), "{err}");
        }
        let parsed: VoxelConfig = toml::from_str("voxel_size = 0.1\nprecision = \"f16\"").unwrap();
        assert_eq!(parsed.voxel_size, 0.1);
        assert_eq!(parsed.precision, Precision::F16);
        assert!(toml::from_str::<VoxelConfig>("voxelsize = 0.1").is_err());
    }

    #[test]
    fn restore_round_trips_and_merges_shared_voxels() {
        let mut m = map(VoxelConfig {
            precision: Precision::F16,
            ..VoxelConfig::default()
        });
        integrate(
            &mut m,
            &plane(1.0),
            &Pose::identity(),
            &uniform([0.3, 0.1, 0.9, 0.2]),
        );
        integrate(
            &mut m,
            &plane(1.3),
            &translated(0.01),
            &uniform([0.5, 0.7, 0.1, 0.2]),
        );
        let snap = m.snapshot().unwrap();
        let mut fresh = map(VoxelConfig {
            precision: Precision::F16,
            ..VoxelConfig::default()
        });
        fresh.restore(snap.clone()).unwrap();
        assert_eq!(fresh.snapshot().unwrap(), snap);

        // Two points in one voxel (as a point-cloud snapshot might hold) become one voxel.
        let points = MapSnapshot {
            map_kind: "point-cloud".into(),
            dim: DIM,
            positions: vec![[0.01, 0.01, 0.01], [0.02, 0.03, 0.04], [1.0, 1.0, 1.0]],
            colours: vec![[0, 0, 0], [100, 100, 100], [7, 7, 7]],
            embeddings: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            metadata: MapMetadata::default(),
        };
        fresh.restore(points.clone()).unwrap();
        assert_eq!(fresh.len(), 2);
        assert_eq!(fresh.counts(), &[2, 1]);
        assert_eq!(fresh.snapshot().unwrap().colours[0], [50, 50, 50]);
        assert_eq!(fresh.positions()[0], [0.025, 0.025, 0.025]);
        let e = fresh.embeddings().unwrap();
        assert!((e[0] - 0.5f32.sqrt()).abs() < 1e-3 && (e[1] - 0.5f32.sqrt()).abs() < 1e-3);
        // The budget holds after a restore too.
        let mut small = coarse(1);
        small.restore(points).unwrap();
        assert_eq!(small.len(), 1);
        let wrong = MapSnapshot {
            dim: 3,
            ..MapSnapshot::default()
        };
        assert!(fresh.restore(wrong).is_err());
    }

    #[test]
    fn geometry_only_map_keeps_voxels_and_colours() {
        let mut m = VoxelConfig::default().build(None).unwrap();
        assert_eq!(m.dim(), 0);
        let f = plane(1.0);
        let obs = Observation {
            frame: &f,
            pose: &Pose::identity(),
            embeddings: None,
        };
        m.integrate(&obs).unwrap();
        let n = m.len();
        assert!(n > 0);
        m.integrate(&obs).unwrap();
        assert_eq!(m.len(), n);
        assert!(
            m.snapshot()
                .unwrap()
                .colours
                .iter()
                .all(|c| *c == [200, 100, 0])
        );
        assert!(m.similarity(&[], &mut Vec::new()).is_err());
        let mut small = VoxelConfig {
            max_voxels: 3,
            ..VoxelConfig::default()
        }
        .build(None)
        .unwrap();
        small.integrate(&obs).unwrap();
        assert_eq!(small.len(), 3);
    }

    #[test]
    fn segment_and_patch_lookups_agree_with_a_direct_mean() {
        // Two segments with a boundary inside voxels: the running-length shortcut over segment
        // rows must give the same mean as adding every pixel.
        let index: Vec<u32> = (0..W * H).map(|i| u32::from(i % W >= 5)).collect();
        let table = vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.6, 0.8, 0.0];
        let e = PixelEmbeddings::from_regions(W, H, DIM, index, table).unwrap();
        let mut m = map(VoxelConfig {
            voxel_size: 0.2,
            ..VoxelConfig::default()
        });
        integrate(&mut m, &plane(1.0), &Pose::identity(), &e);
        let inverse = 1.0 / 0.2f32;
        let mut expected: HashMap<VoxelKey, Vec<f32>> = HashMap::new();
        let mut out = [0.0; DIM];
        for v in 0..H {
            for u in 0..W {
                let p = [(u as f32 - 7.5) / 20.0, (v as f32 - 5.5) / 20.0, 1.0];
                assert!(e.embedding_at(u, v, &mut out));
                let acc = expected
                    .entry(VoxelKey::of(p, inverse))
                    .or_insert(vec![0.0; DIM]);
                axpy(acc, &out, 1.0);
            }
        }
        assert_eq!(expected.len(), m.len());
        let rows = m.embeddings().unwrap();
        for (i, key) in m.keys.iter().enumerate() {
            let mut want = expected[key].clone();
            normalise(&mut want);
            let got = &rows[i * DIM..(i + 1) * DIM];
            assert!(
                got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6),
                "{got:?} {want:?}"
            );
        }
    }
}
