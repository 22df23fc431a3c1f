//! The paper's point-cloud embedding map (section "3D Embedding Integration").
//!
//! Per frame:
//! 1. back-project every valid depth pixel that has an embedding into the map frame (the set `P`);
//! 2. for every map point in the current view, find its nearest new point within `max_distance`
//!    (by projective association in a pixel window, or a k-d tree over `P`: see
//!    [`Association`]), and fuse `e_M := (1 - w) e_P + w e_M`, renormalised (w = `map_weight`);
//!    colours are fused with the same weights;
//! 3. insert the new points that no map point chose as its nearest;
//! 4. if the map holds more than `max_points` (the paper's `N_M`), downsample it to a uniform
//!    density: points sharing a voxel are merged (mean position and colour, renormalised mean
//!    embedding) and the voxel is grown until the budget holds. Voxels with one point are left as
//!    they are, so sparse regions are not thinned further.
//!
//! Storage is struct-of-arrays: positions, colours and one contiguous `len x dim` embedding table,
//! so a text query is a single pass over memory.

use std::sync::atomic::{AtomicBool, Ordering};

mod association;
mod voxel_groups;

use rayon::prelude::*;
use vlem_core::embeddings::normalise;
use vlem_core::{
    BuildContext, ColouredMesh, CoreError, EmbeddingMap, IntegrationStats, MapBudget, MapMetadata,
    MapSnapshot, Observation, RigidF32, StageKind, parse_params,
};

pub use self::association::Association;
use self::association::{Cell, FrameView, NONE};
use self::voxel_groups::{GroupingBuffers, KEY_AXIS_VOXELS, bounding_box, runs};
use crate::error::MapError;
use crate::kit::{
    FramePixels, check_observation, check_snapshot, count_in, embedding, invalid_parameter,
    number_in, positive_metres, unit_weight,
};
use crate::storage::{EmbeddingStore, Table, fuse_into};
#[cfg(feature = "candle")]
use crate::storage::{FrameTable, Lookups, swap_removal_moves};

/// A frame's embeddings as uploaded to a device table (nothing in a build without one).
#[cfg(feature = "candle")]
type Uploaded<'a> = FrameTable<'a>;
#[cfg(not(feature = "candle"))]
type Uploaded<'a> = std::marker::PhantomData<&'a ()>;

/// The registered name.
pub const NAME: &str = "point-cloud";

/// The largest [`PointCloudConfig::window`], which bounds the cells one map point may visit
/// (65 × 65); a wider search is what `association = "kd-tree"` is for.
const MAX_WINDOW: u32 = 32;

/// The largest point budget accepted: map rows are indexed with `u32`, and with `device = "cuda"`
/// the whole budget is allocated when the map is built.
pub const MAX_POINT_BUDGET: usize = 1 << 30;

/// The widest fusion radius accepted (`max_distance`), in metres: wider, points of different
/// surfaces fuse.
const MAX_FUSION_DISTANCE_M: f32 = 1.0;

crate::map_config! {
    /// `[map] kind = "point-cloud"` parameters.
    pub struct PointCloudConfig {
        /// Point budget `N_M`; default 1,000,000.
        pub max_points: usize = 1_000_000,
        /// Maximum correspondence distance in metres; default 0.02.
        pub max_distance: f32 = 0.02,
        /// Weight `w` of the map embedding in the fusion; default 0.5 (the paper's value).
        pub map_weight: f32 = 0.5,
        /// How a map point finds its correspondence: `"projective"` (default: the new points
        /// back-projected from the pixels around its projection) or `"kd-tree"` (the exact
        /// nearest neighbour in 3D, several times slower).
        pub association: Association = Association::Projective,
        /// Projective association: the half-width of the pixel window searched around a map
        /// point's projection, in integrated pixels (every `pixel_stride`-th); default 3 (7×7).
        /// The search stops early where `max_distance` or a closer point rules a ring out.
        pub window: u32 = 3,
    }
}

impl PointCloudConfig {
    /// Builds the map for embeddings of dimension `encoder_dim` (`None` without an encoder).
    ///
    /// # Errors
    /// [`MapError::InvalidParameter`] (wrapped as a stage error) for out-of-range values and for a
    /// `dim` that disagrees with the encoder; a stage error naming the device when `device` cannot
    /// be opened (a build without `cuda`, no driver, no such GPU) or cannot hold the table.
    pub fn build(&self, encoder_dim: Option<usize>) -> Result<PointCloudMap, CoreError> {
        let dim = self.validate(encoder_dim)?;
        let table = Table::open(NAME, self.device, dim, self.precision, self.max_points)?;
        Ok(PointCloudMap::with_table(self.clone(), dim, table))
    }

    /// Checks the parameters; returns the embedding dimension.
    fn validate(&self, encoder_dim: Option<usize>) -> Result<usize, CoreError> {
        count_in(
            NAME,
            "max_points",
            self.max_points,
            (1, MAX_POINT_BUDGET),
            "points",
        )?;
        positive_metres(NAME, "max_distance", self.max_distance)?;
        number_in(
            NAME,
            "max_distance",
            self.max_distance,
            (0.0, MAX_FUSION_DISTANCE_M),
            "m",
        )?;
        unit_weight(NAME, "map_weight", self.map_weight)?;
        if self.window > MAX_WINDOW {
            return Err(invalid_parameter(
                NAME,
                "window",
                &format!("must be at most {MAX_WINDOW} pixels"),
            ));
        }
        self.common().validate_for_device(NAME, encoder_dim)
    }

    /// [`PointCloudConfig::build`] with the embedding table on the candle device `device`,
    /// whatever `device` the config names: how the tests run the device table on candle's CPU.
    ///
    /// # Errors
    /// As [`PointCloudConfig::build`]; a stage error when the device cannot hold the table.
    #[cfg(feature = "candle")]
    pub fn build_on(
        &self,
        encoder_dim: Option<usize>,
        device: &candle_core::Device,
    ) -> Result<PointCloudMap, CoreError> {
        let dim = self.validate(encoder_dim)?;
        let table = Table::on_candle(NAME, device, dim, self.precision, self.max_points)?;
        Ok(PointCloudMap::with_table(self.clone(), dim, table))
    }
}

fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn EmbeddingMap>> {
    let config: PointCloudConfig = parse_params(StageKind::Map, NAME, params)?;
    Ok(Box::new(config.build(ctx.embedding_dim)?))
}

vlem_core::register_map!(
    NAME,
    "points with fused embeddings under a point budget (the VLEM paper's map)",
    build
);

/// The point-cloud embedding map.
#[derive(Debug)]
pub struct PointCloudMap {
    config: PointCloudConfig,
    dim: usize,
    positions: Vec<[f32; 3]>,
    colours: Vec<[u8; 3]>,
    embeddings: Table,
    /// Current downsampling resolution in metres (0 until the budget was first exceeded). It only
    /// grows, so the density of the map never rises again once bounded.
    voxel_size: f32,
    frames: usize,
    /// Per-frame buffers, kept for their allocations.
    scratch: Scratch,
}

/// The new points of one frame, in the map frame.
#[derive(Clone, Default)]
struct Observed {
    positions: Vec<[f32; 3]>,
    /// Linear pixel index `v * width + u` of each point.
    pixels: Vec<u32>,
    /// Mean depth, for the first downsampling resolution.
    mean_depth: f32,
}

/// The buffers one integration fills, kept between frames: fresh frame-sized vectors would cost a
/// page fault per 4 KiB on every frame.
#[derive(Clone, Default)]
struct Scratch {
    observed: Observed,
    /// Per map point, its correspondence's index in `observed` ([`NONE`] for none).
    matches: Vec<u32>,
    /// The projective association's pixel grid.
    grid: Vec<Cell>,
    /// Per new point, whether a map point chose it.
    chosen: Vec<bool>,
    /// The downsampling's voxel groupings.
    grouping: GroupingBuffers,
}

impl Scratch {
    /// The heap bytes the kept buffers hold (they are part of the map's memory between frames).
    fn memory_bytes(&self) -> usize {
        use std::mem::size_of;
        self.observed.positions.capacity() * size_of::<[f32; 3]>()
            + self.observed.pixels.capacity() * size_of::<u32>()
            + self.matches.capacity() * size_of::<u32>()
            + self.grid.capacity() * size_of::<Cell>()
            + self.chosen.capacity() * size_of::<bool>()
            + self.grouping.memory_bytes()
    }
}

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Scratch { .. }")
    }
}

/// `x.round() as u8` for `x` in `[0, 255]`, without the libm call `round` is on x86-64's baseline
/// (a quarter of the colour fusion's time): the fractional part `x - trunc(x)` is exact, and
/// halves round up, as `round` does for non-negative values.
#[inline]
fn round_colour(x: f32) -> u8 {
    let whole = x as u8;
    whole.saturating_add(u8::from(x - f32::from(whole) >= 0.5))
}

impl PointCloudMap {
    /// An empty map with its table in host memory, whatever `device` the config names (use
    /// [`PointCloudConfig::build`] for validated parameters and the configured device).
    pub fn new(config: PointCloudConfig, dim: usize) -> Self {
        let table = Table::Host(EmbeddingStore::new(dim, config.precision));
        Self::with_table(config, dim, table)
    }

    fn with_table(config: PointCloudConfig, dim: usize, embeddings: Table) -> Self {
        Self {
            embeddings,
            config,
            dim,
            positions: Vec::new(),
            colours: Vec::new(),
            voxel_size: 0.0,
            frames: 0,
            scratch: Scratch::default(),
        }
    }

    /// Reserves room for at least `additional` more points, like [`Vec::reserve`], so the next
    /// frames' insertions do not reallocate the tables (a map restored from a snapshot holds
    /// exactly its points).
    pub fn reserve(&mut self, additional: usize) {
        self.positions.reserve(additional);
        self.colours.reserve(additional);
        if let Some(store) = self.embeddings.host_mut() {
            store.reserve(additional);
        }
    }

    /// Positions of all points.
    pub fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }

    /// The `len x dim` embedding table, widened to `f32` (copied from the device if it is on
    /// one).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy from the device fails.
    pub fn embeddings(&self) -> Result<Vec<f32>, MapError> {
        self.embeddings.to_f32()
    }

    /// The current downsampling voxel size (0 while under budget so far).
    pub fn voxel_size(&self) -> f32 {
        self.voxel_size
    }

    fn check(&self, obs: &Observation<'_>) -> Result<(), MapError> {
        check_observation(self.dim, obs)
    }

    /// Back-projects the pixels of `obs` into `new`.
    fn observe(&self, obs: &Observation<'_>, new: &mut Observed) {
        let depth_sum = FramePixels::new(obs, &self.config.common())
            .collect_into(&mut new.positions, &mut new.pixels);
        new.mean_depth = if new.positions.is_empty() {
            0.0
        } else {
            (depth_sum / new.positions.len() as f64) as f32
        };
    }

    /// Writes into `matches`, for every map point in the view of `obs`, the index of its nearest
    /// new point within `max_distance` by `association`; [`NONE`] for none.
    fn correspondences(
        &self,
        obs: &Observation<'_>,
        new: &Observed,
        association: Association,
        grid: &mut Vec<Cell>,
        matches: &mut Vec<u32>,
    ) {
        FrameView {
            intrinsics: &obs.frame.intrinsics,
            to_camera: RigidF32::from_pose(&obs.pose.inverse()),
            positions: &new.positions,
            pixels: &new.pixels,
            stride: self.config.pixel_stride,
        }
        .correspondences(
            &self.positions,
            self.config.max_distance,
            association,
            self.config.window,
            grid,
            matches,
        );
    }

    /// The correspondence every map point would take in `obs` by `association`, without
    /// integrating: the linear pixel index (`v * width + u`) of the frame's point it would fuse
    /// with, `None` for map points out of view or without a point within `max_distance`. For
    /// comparing the two associations (`cargo bench -p vlem-maps --bench association`).
    ///
    /// # Errors
    /// As [`EmbeddingMap::integrate`] for an observation that does not fit the map.
    pub fn correspondence_pixels(
        &self,
        obs: &Observation<'_>,
        association: Association,
    ) -> vlem_core::Result<Vec<Option<u32>>> {
        self.check(obs)
            .map_err(|e| CoreError::stage(StageKind::Map, NAME, e))?;
        let (mut new, mut grid, mut matches) = (Observed::default(), Vec::new(), Vec::new());
        self.observe(obs, &mut new);
        self.correspondences(obs, &new, association, &mut grid, &mut matches);
        Ok(matches
            .into_iter()
            .map(|m| (m != NONE).then(|| new.pixels[m as usize]))
            .collect())
    }

    /// One integration (of a checked observation) with the frame buffers in `scratch`.
    fn integrate_with(
        &mut self,
        obs: &Observation<'_>,
        scratch: &mut Scratch,
    ) -> Result<IntegrationStats, MapError> {
        let Scratch {
            observed: new,
            matches,
            grid,
            chosen,
            grouping,
        } = scratch;
        self.observe(obs, new);
        let mut stats = IntegrationStats {
            observed: new.positions.len(),
            ..IntegrationStats::default()
        };
        self.frames += 1;
        if new.positions.is_empty() {
            return Ok(stats);
        }
        let uploaded = self.upload(obs)?;
        chosen.clear();
        chosen.resize(new.positions.len(), false);
        if !self.positions.is_empty() {
            self.correspondences(obs, new, self.config.association, grid, matches);
            for &m in matches.iter().filter(|m| **m != NONE) {
                chosen[m as usize] = true;
                stats.fused += 1;
            }
            self.fuse(obs, new, matches, uploaded.as_ref())?;
        }
        stats.inserted = self.insert(obs, new, chosen, uploaded.as_ref())?;
        let footprint =
            new.mean_depth / obs.frame.intrinsics.fx as f32 * self.config.pixel_stride as f32;
        stats.removed = self.enforce_budget(footprint, grouping)?;
        Ok(stats)
    }

    /// The frame's embeddings copied to the device, when the table is on one.
    #[cfg(feature = "candle")]
    fn upload<'a>(&self, obs: &Observation<'a>) -> Result<Option<Uploaded<'a>>, MapError> {
        match (&self.embeddings, obs.embeddings) {
            (Table::Device(table), Some(embeddings)) => {
                Ok(Some(FrameTable::upload(embeddings, table)?))
            }
            _ => Ok(None),
        }
    }

    #[cfg(not(feature = "candle"))]
    #[allow(
        clippy::unnecessary_wraps,
        clippy::unused_self,
        reason = "the signature of the build with device tables"
    )]
    fn upload<'a>(&self, _obs: &Observation<'a>) -> Result<Option<Uploaded<'a>>, MapError> {
        Ok(None)
    }

    fn fuse(
        &mut self,
        obs: &Observation<'_>,
        new: &Observed,
        matches: &[u32],
        uploaded: Option<&Uploaded<'_>>,
    ) -> Result<(), MapError> {
        let w = self.config.map_weight;
        let colour = &obs.frame.colour;
        let fuse_colour = |c: &mut [u8; 3], pixel: u32| {
            let p = colour.at_index(pixel as usize);
            for k in 0..3 {
                c[k] = round_colour((1.0 - w) * f32::from(p[k]) + w * f32::from(c[k]));
            }
        };
        let fuse_colours = |colours: &mut [[u8; 3]]| {
            colours
                .par_iter_mut()
                .zip(matches.par_iter())
                .with_min_len(1024)
                .filter(|(_, m)| **m != NONE)
                .for_each(|(c, &m)| fuse_colour(c, new.pixels[m as usize]));
        };
        let Some(embeddings) = obs.embeddings.filter(|_| self.dim > 0) else {
            fuse_colours(&mut self.colours);
            return Ok(());
        };
        #[cfg(feature = "candle")]
        if let Table::Device(table) = &mut self.embeddings {
            fuse_colours(&mut self.colours);
            let Some(frame) = uploaded else {
                return Ok(());
            };
            // The map rows that fuse, and how each one's observation is looked up.
            let mut rows = Vec::new();
            let mut lookups = Lookups::default();
            frame.lookups(&mut lookups);
            for (i, &m) in matches.iter().enumerate() {
                if m != NONE && frame.push(new.pixels[m as usize], &mut lookups) {
                    rows.push(i as u32);
                }
            }
            return table.fuse(frame, &rows, &lookups, w);
        }
        #[cfg(not(feature = "candle"))]
        let _ = uploaded;
        let Some(store) = self.embeddings.host_mut() else {
            return Ok(());
        };
        // Colours and embeddings in one pass over the matches.
        let dim = self.dim;
        store.par_update_rows_zip(
            0,
            &mut self.colours,
            || vec![0.0f32; dim],
            |scratch, i, e_map, c| {
                let m = matches[i];
                if m == NONE {
                    return false;
                }
                let pixel = new.pixels[m as usize];
                fuse_colour(c, pixel);
                match embedding(embeddings, pixel, &mut scratch[..]) {
                    Some(e_new) => {
                        fuse_into(e_map, e_new, w);
                        true
                    }
                    None => false,
                }
            },
        );
        Ok(())
    }

    fn insert(
        &mut self,
        obs: &Observation<'_>,
        new: &Observed,
        chosen: &[bool],
        uploaded: Option<&Uploaded<'_>>,
    ) -> Result<usize, MapError> {
        let colour = &obs.frame.colour;
        #[cfg(feature = "candle")]
        if let (Table::Device(table), Some(frame)) = (&mut self.embeddings, uploaded) {
            // Only the points whose embedding can be looked up, as the host table keeps.
            let mut lookups = Lookups::default();
            frame.lookups(&mut lookups);
            let fresh: Vec<usize> = (0..new.positions.len())
                .filter(|&i| !chosen[i] && frame.push(new.pixels[i], &mut lookups))
                .collect();
            self.positions
                .extend(fresh.iter().map(|&i| new.positions[i]));
            self.colours.extend(
                fresh
                    .iter()
                    .map(|&i| colour.at_index(new.pixels[i] as usize)),
            );
            table.append(frame, &lookups)?;
            return Ok(fresh.len());
        }
        #[cfg(not(feature = "candle"))]
        let _ = uploaded;
        let fresh: Vec<usize> = (0..new.positions.len()).filter(|&i| !chosen[i]).collect();
        self.positions
            .extend(fresh.iter().map(|&i| new.positions[i]));
        self.colours.extend(
            fresh
                .iter()
                .map(|&i| colour.at_index(new.pixels[i] as usize)),
        );
        let dim = self.dim;
        if let Some(embeddings) = obs.embeddings
            && dim > 0
            && let Table::Host(store) = &mut self.embeddings
        {
            let start = store.rows();
            store.grow(fresh.len());
            let missing = AtomicBool::new(false);
            store.par_update_rows_with(
                start,
                || vec![0.0f32; dim],
                |scratch, row_index, row| {
                    let pixel = new.pixels[fresh[row_index - start]];
                    // `observe` keeps pixels that have an embedding, but a patch grid's
                    // interpolation can still cancel out (or overflow): that row stays zero.
                    match embedding(embeddings, pixel, &mut scratch[..]) {
                        Some(e) => {
                            row.copy_from_slice(e);
                            true
                        }
                        None => {
                            missing.store(true, Ordering::Relaxed);
                            false
                        }
                    }
                },
            );
            if missing.into_inner() {
                return Ok(fresh.len() - self.drop_zero_rows(start));
            }
        }
        Ok(fresh.len())
    }

    /// Removes the points from `start` on whose embedding row is zero (no embedding could be
    /// looked up), keeping the order of the others. Returns the number removed.
    fn drop_zero_rows(&mut self, start: usize) -> usize {
        let Some(store) = self.embeddings.host_mut() else {
            return 0;
        };
        let before = self.positions.len();
        let mut row = vec![0.0f32; self.dim];
        let mut kept = start;
        for i in start..before {
            store.row_into(i, &mut row);
            if row.iter().all(|x| *x == 0.0) {
                continue;
            }
            if kept != i {
                self.positions[kept] = self.positions[i];
                self.colours[kept] = self.colours[i];
                store.set_row(kept, &row);
            }
            kept += 1;
        }
        self.positions.truncate(kept);
        self.colours.truncate(kept);
        store.truncate(kept);
        before - kept
    }

    /// Merges points per voxel, with the finest voxel size (within 5 %) that meets the budget.
    /// Returns the number of points removed.
    ///
    /// The voxel grid is anchored at the corner of the points' bounding box, so a voxel as large
    /// as the box holds every point and the search always ends (a grid anchored at the origin
    /// keeps points on either side of a coordinate plane apart at every size, so a budget below
    /// the number of occupied octants could never be met). The finest size tried keeps the voxel
    /// coordinates of the box within the key's 21 bits per axis, so distant points never share a
    /// voxel through clamping.
    fn enforce_budget(
        &mut self,
        footprint: f32,
        buffers: &mut GroupingBuffers,
    ) -> Result<usize, MapError> {
        let budget = self.config.max_points;
        let before = self.positions.len();
        if before <= budget {
            return Ok(0);
        }
        let (origin, extent) = bounding_box(&self.positions);
        // Never finer than the density already established (the map's density only falls), and
        // not much finer than this frame's pixel footprint (finer voxels would merge nothing).
        let mut lo = self
            .voxel_size
            .max(footprint * 0.25)
            .max(1e-4)
            .max(extent / KEY_AXIS_VOXELS);
        let GroupingBuffers {
            held, tried, spare, ..
        } = buffers;
        held.group(&self.positions, lo, origin, extent, spare);
        if held.count > budget {
            // Grow until the budget holds; on surfaces the count falls with the voxel area. At
            // the latest a voxel larger than the bounding box holds everything in one.
            // `held` is the last size tried until one holds, then the finest that held.
            let mut hi = lo;
            let found = loop {
                hi *= (held.count as f32 / budget as f32).sqrt().max(1.1);
                if !hi.is_finite() {
                    break false;
                }
                tried.group(&self.positions, hi, origin, extent, spare);
                std::mem::swap(held, tried);
                if held.count <= budget {
                    break true;
                }
                lo = hi;
            };
            if !found {
                // Only for a bounding box beyond f32 (positions near f32::MAX): keep the budget.
                self.voxel_size = lo;
                self.positions.truncate(budget);
                self.colours.truncate(budget);
                self.embeddings.truncate(budget);
                return Ok(before - budget);
            };
            // Bisect geometrically between the last size that failed and the first that held.
            while hi / lo > 1.05 {
                let mid = (lo * hi).sqrt();
                tried.group(&self.positions, mid, origin, extent, spare);
                if tried.count <= budget {
                    hi = mid;
                    std::mem::swap(held, tried);
                } else {
                    lo = mid;
                }
            }
            lo = hi;
        }
        self.voxel_size = lo;
        self.merge(buffers)?;
        Ok(before - self.positions.len())
    }

    /// Replaces every voxel group of two or more points by one point (mean position and colour,
    /// renormalised mean embedding) in the slot of its first member, then removes the other members
    /// by moving points from the end into their slots. The cost is proportional to the points
    /// merged, not to the map size.
    fn merge(&mut self, buffers: &mut GroupingBuffers) -> Result<(), MapError> {
        let GroupingBuffers {
            held,
            members,
            ends,
            ..
        } = buffers;
        held.runs_into(2, members, ends);
        let multi: Vec<&[u32]> = runs(members, ends).collect();
        let merged_points: Vec<(usize, [f32; 3], [u8; 3])> = multi
            .par_iter()
            .map(|run| {
                let (mut p, mut c) = ([0.0f64; 3], [0u32; 3]);
                for &i in run.iter() {
                    for k in 0..3 {
                        p[k] += f64::from(self.positions[i as usize][k]);
                        c[k] += u32::from(self.colours[i as usize][k]);
                    }
                }
                let n = run.len();
                let target = run.iter().map(|&i| i as usize).min().unwrap_or(0);
                (
                    target,
                    p.map(|x| (x / n as f64) as f32),
                    c.map(|x| (x / n as u32) as u8),
                )
            })
            .collect();
        if self.dim > 0 {
            match &mut self.embeddings {
                Table::Host(store) => merge_rows(store, &multi, &merged_points),
                #[cfg(feature = "candle")]
                Table::Device(table) => {
                    let targets: Vec<u32> = merged_points.iter().map(|m| m.0 as u32).collect();
                    table.merge_groups(members, ends, &targets)?;
                }
            }
        }
        let mut dead = Vec::with_capacity(self.positions.len() - held.count);
        for (g, (target, p, c)) in merged_points.into_iter().enumerate() {
            self.positions[target] = p;
            self.colours[target] = c;
            dead.extend(
                multi[g]
                    .iter()
                    .map(|&i| i as usize)
                    .filter(|&i| i != target),
            );
        }
        // Descending, so the point moved into a dead slot is always a live one.
        dead.par_sort_unstable_by(|a, b| b.cmp(a));
        #[cfg(feature = "candle")]
        if let Table::Device(table) = &mut self.embeddings
            && self.dim > 0
        {
            let (from, to) = swap_removal_moves(self.positions.len(), &dead);
            table.move_rows(&from, &to)?;
            table.truncate(self.positions.len() - dead.len());
        }
        for d in dead {
            self.positions.swap_remove(d);
            self.colours.swap_remove(d);
            if self.dim > 0
                && let Table::Host(store) = &mut self.embeddings
            {
                store.swap_remove(d);
            }
        }
        Ok(())
    }
}

/// Sets each merged group's target row of `store` to the renormalised mean of its members' rows
/// (the first member's row where they cancel out).
fn merge_rows(
    store: &mut EmbeddingStore,
    multi: &[&[u32]],
    merged_points: &[(usize, [f32; 3], [u8; 3])],
) {
    let dim = store.dim();
    let mut merged_embeddings = vec![0.0f32; multi.len() * dim];
    merged_embeddings
        .par_chunks_exact_mut(dim)
        .zip(multi.par_iter())
        .for_each_init(
            || vec![0.0f32; dim],
            |member, (row, run)| {
                for &i in run.iter() {
                    store.row_into(i as usize, member);
                    row.iter_mut().zip(member.iter()).for_each(|(a, b)| *a += b);
                }
                // Members that cancel out: keep the first one's embedding.
                if !normalise(row) {
                    store.row_into(run[0] as usize, row);
                }
            },
        );
    for (g, (target, ..)) in merged_points.iter().enumerate() {
        store.set_row(*target, &merged_embeddings[g * dim..(g + 1) * dim]);
    }
}

impl EmbeddingMap for PointCloudMap {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn integrate(&mut self, obs: &Observation<'_>) -> vlem_core::Result<IntegrationStats> {
        self.check(obs)
            .map_err(|e| CoreError::stage(StageKind::Map, NAME, e))?;
        // The buffers are taken out for the frame (so `self` can be borrowed beside them) and put
        // back at the end; a frame that fails its checks above never takes them.
        let mut scratch = std::mem::take(&mut self.scratch);
        let stats = self.integrate_with(obs, &mut scratch);
        self.scratch = scratch;
        stats.map_err(|e| e.into_core(StageKind::Map, NAME))
    }

    fn len(&self) -> usize {
        self.positions.len()
    }

    fn budget(&self) -> Option<MapBudget> {
        Some(MapBudget {
            parameter: "max_points",
            elements: self.config.max_points,
        })
    }

    fn memory_bytes(&self) -> usize {
        self.positions.capacity() * std::mem::size_of::<[f32; 3]>()
            + self.colours.capacity() * 3
            + self.embeddings.host_bytes()
            + self.scratch.memory_bytes()
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
            vertices: self.positions.clone(),
            colours: self.colours.clone(),
            triangles: Vec::new(),
        }
    }

    fn snapshot(&self) -> vlem_core::Result<MapSnapshot> {
        Ok(MapSnapshot {
            map_kind: NAME.into(),
            dim: self.dim,
            positions: self.positions.clone(),
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

    fn restore(&mut self, snapshot: MapSnapshot) -> vlem_core::Result<()> {
        check_snapshot(self.dim, &snapshot)?;
        self.frames = snapshot.metadata.frames_integrated;
        self.positions = snapshot.positions;
        self.colours = snapshot.colours;
        let core = |e: MapError| e.into_core(StageKind::Map, NAME);
        self.embeddings.replace(snapshot.embeddings).map_err(core)?;
        self.voxel_size = 0.0;
        let mut grouping = std::mem::take(&mut self.scratch.grouping);
        let merged = self.enforce_budget(0.0, &mut grouping);
        self.scratch.grouping = grouping;
        merged.map(|_| ()).map_err(core)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::Precision;
    use crate::test_fixtures::*;
    use vlem_core::{PixelEmbeddings, Pose};

    #[cfg(feature = "candle")]
    #[test]
    fn swap_removals_reduce_to_moves_from_the_tail() {
        // Removing [7, 2, 1] from 10 rows moves 9 → 7, then 8 → 2, then (the row now in) 7 → 1.
        for (len, dead) in [
            (10usize, vec![7usize, 2, 1]),
            (10, vec![9, 8, 2]),
            (6, vec![5, 4, 3, 2, 1, 0]),
            (12, vec![11, 6, 5, 3, 0]),
        ] {
            let mut rows: Vec<usize> = (0..len).collect();
            for &d in &dead {
                rows.swap_remove(d);
            }
            let (from, to) = swap_removal_moves(len, &dead);
            let mut moved: Vec<usize> = (0..len).collect();
            let sources: std::collections::HashSet<u32> = from.iter().copied().collect();
            assert!(to.iter().all(|t| !sources.contains(t)), "{dead:?}");
            for (&f, &t) in from.iter().zip(&to) {
                moved[t as usize] = f as usize;
            }
            moved.truncate(len - dead.len());
            assert_eq!(moved, rows, "{dead:?}");
        }
    }

    fn map(config: PointCloudConfig) -> PointCloudMap {
        config.build(Some(DIM)).unwrap()
    }

    #[test]
    fn fusion_is_the_papers_weighted_average_renormalised() {
        let mut m = map(PointCloudConfig {
            map_weight: 0.25,
            ..PointCloudConfig::default()
        });
        let f = plane(1.0);
        let first = integrate(
            &mut m,
            &f,
            &Pose::identity(),
            &uniform([1.0, 0.0, 0.0, 0.0]),
        );
        assert_eq!(first.inserted, 16 * 12);
        let second = integrate(
            &mut m,
            &f,
            &Pose::identity(),
            &uniform([0.0, 1.0, 0.0, 0.0]),
        );
        assert_eq!((second.fused, second.inserted), (16 * 12, 0));
        // e = normalise(0.75 * e_P + 0.25 * e_M)
        let n = (0.75f32 * 0.75 + 0.25 * 0.25).sqrt();
        for row in m.embeddings().unwrap().chunks_exact(DIM) {
            assert!(
                (row[0] - 0.25 / n).abs() < 1e-6 && (row[1] - 0.75 / n).abs() < 1e-6,
                "{row:?}"
            );
        }
        assert_eq!(m.len(), 16 * 12);
    }

    #[test]
    fn points_without_a_correspondence_are_inserted() {
        let mut m = map(PointCloudConfig::default());
        let e = uniform([1.0, 0.0, 0.0, 0.0]);
        integrate(&mut m, &plane(1.0), &Pose::identity(), &e);
        // The same plane 0.5 m further away: out of reach of every map point (max 2 cm).
        let stats = integrate(&mut m, &plane(1.5), &Pose::identity(), &e);
        assert_eq!((stats.fused, stats.inserted), (0, 16 * 12));
        assert_eq!(m.len(), 2 * 16 * 12);
    }

    #[test]
    fn opposite_embeddings_fall_back_to_the_observation() {
        let mut m = map(PointCloudConfig::default());
        let f = plane(1.0);
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
        assert!(
            m.embeddings()
                .unwrap()
                .chunks_exact(DIM)
                .all(|r| r == [-1.0, 0.0, 0.0, 0.0])
        );
    }

    #[test]
    fn downsampling_merges_dense_regions_and_keeps_sparse_points() {
        let mut positions = Vec::new();
        // 1000 points packed into a 1 cm cube.
        for i in 0..1000 {
            let (a, b, c) = (i % 10, i / 10 % 10, i / 100);
            positions.push([a as f32 * 1e-3, b as f32 * 1e-3, c as f32 * 1e-3]);
        }
        // 20 isolated points 1 m apart.
        let sparse: Vec<[f32; 3]> = (0..20).map(|i| [5.0 + i as f32, 0.3, 0.7]).collect();
        positions.extend(&sparse);
        let n = positions.len();
        let mut embeddings = Vec::new();
        for i in 0..n {
            let mut e = [0.0; DIM];
            e[i % DIM] = 1.0;
            embeddings.extend(e);
        }
        let snapshot = MapSnapshot {
            map_kind: NAME.into(),
            dim: DIM,
            positions,
            colours: vec![[10, 20, 30]; n],
            embeddings,
            metadata: MapMetadata::default(),
        };
        let mut m = map(PointCloudConfig {
            max_points: 100,
            ..PointCloudConfig::default()
        });
        m.restore(snapshot).unwrap();
        assert!(m.len() <= 100, "{} points over a budget of 100", m.len());
        for p in &sparse {
            assert!(
                m.positions().contains(p),
                "sparse point {p:?} was moved or dropped"
            );
        }
        for row in m.embeddings().unwrap().chunks_exact(DIM) {
            let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn downsampling_keeps_close_to_the_budget() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let n = 20_000;
        let positions: Vec<[f32; 3]> = (0..n)
            .map(|_| [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0), 2.0])
            .collect();
        let mut embeddings = vec![0.0; n * DIM];
        embeddings.iter_mut().step_by(DIM).for_each(|x| *x = 1.0);
        let snapshot = MapSnapshot {
            map_kind: NAME.into(),
            dim: DIM,
            positions,
            colours: vec![[0, 0, 0]; n],
            embeddings,
            metadata: MapMetadata::default(),
        };
        let mut m = map(PointCloudConfig {
            max_points: 5_000,
            ..PointCloudConfig::default()
        });
        m.restore(snapshot).unwrap();
        // The finest voxel that meets the budget, not one far coarser.
        assert!(
            (4_000..=5_000).contains(&m.len()),
            "{} points for a budget of 5000",
            m.len()
        );
        assert_eq!(m.embeddings().unwrap().len(), m.len() * DIM);
        assert!(m.voxel_size() > 0.0);
    }

    #[test]
    fn f16_storage_halves_embedding_bytes_and_keeps_the_query_ranking() {
        let mut maps = [Precision::F32, Precision::F16].map(|precision| {
            map(PointCloudConfig {
                precision,
                ..PointCloudConfig::default()
            })
        });
        let f = plane(1.0);
        // Two observations with different embeddings on the left and right halves.
        let index: Vec<u32> = (0..16 * 12).map(|i| u32::from(i % 16 >= 8)).collect();
        let a = PixelEmbeddings::from_regions(
            16,
            12,
            DIM,
            index.clone(),
            vec![0.9, 0.1, 0.3, 0.2, 0.1, 0.8, 0.2, 0.4],
        )
        .unwrap();
        let b = PixelEmbeddings::from_regions(
            16,
            12,
            DIM,
            index,
            vec![0.5, 0.5, 0.1, 0.7, 0.3, 0.3, 0.6, 0.2],
        )
        .unwrap();
        for m in &mut maps {
            integrate(m, &f, &Pose::identity(), &a);
            integrate(m, &f, &Pose::identity(), &b);
        }
        let text = [0.6, 0.2, 0.7, 0.3];
        let (mut s32, mut s16) = (Vec::new(), Vec::new());
        maps[0].similarity(&text, &mut s32).unwrap();
        maps[1].similarity(&text, &mut s16).unwrap();
        let tie = 2.0 * 2f32.powi(-12);
        for i in 0..s32.len() {
            for j in 0..s32.len() {
                if s32[i] - s32[j] > tie {
                    assert!(s16[i] > s16[j], "points {i} and {j} swap at f16");
                }
            }
        }
        assert!(
            s32.iter().any(|x| (x - s32[0]).abs() > 0.01),
            "the test needs distinct scores"
        );
        // Positions and colours are 15 bytes a point; the frame buffers are the same at both.
        let embedding_bytes =
            |m: &PointCloudMap| m.memory_bytes() - m.len() * 15 - m.scratch.memory_bytes();
        assert_eq!(embedding_bytes(&maps[0]), 2 * embedding_bytes(&maps[1]));
    }

    #[test]
    fn colour_rounding_is_round_on_every_fused_value() {
        // Every value the fusion can produce at a few weights, and the halves and their neighbours.
        for w in [0.0f32, 0.3, 0.5, 0.7, 1.0] {
            for p in 0..=255u8 {
                for c in 0..=255u8 {
                    let x = (1.0 - w) * f32::from(p) + w * f32::from(c);
                    assert_eq!(round_colour(x), x.round() as u8, "{x}");
                }
            }
        }
        for k in 0..255u16 {
            let half = f32::from(k) + 0.5;
            for x in [half, half.next_down(), half.next_up()] {
                assert_eq!(round_colour(x), x.round() as u8, "{x}");
            }
        }
    }

    #[test]
    fn both_associations_fuse_the_same_points_on_a_plane() {
        let e = uniform([1.0, 0.0, 0.0, 0.0]);
        let f = plane(1.0);
        // A fifth of a pixel (1 cm) to the side: every map point projects between two pixels.
        let shifted = Pose::from_parts(
            nalgebra::Translation3::new(0.01, 0.0, 0.0),
            nalgebra::UnitQuaternion::identity(),
        );
        let mut results = Vec::new();
        for association in [Association::Projective, Association::KdTree] {
            let mut m = map(PointCloudConfig {
                association,
                ..PointCloudConfig::default()
            });
            integrate(&mut m, &f, &Pose::identity(), &e);
            let obs = Observation {
                frame: &f,
                pose: &shifted,
                embeddings: Some(&e),
            };
            results.push(m.correspondence_pixels(&obs, association).unwrap());
        }
        assert_eq!(results[0], results[1]);
        assert!(results[0].iter().filter(|m| m.is_some()).count() > 100);
    }

    #[test]
    fn invalid_parameters_are_named() {
        let err = PointCloudConfig {
            window: 33,
            ..PointCloudConfig::default()
        }
        .build(Some(DIM))
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "map `point-cloud`: parameter `window` must be at most 32 pixels"
        );
        let err = PointCloudConfig {
            map_weight: 1.5,
            ..PointCloudConfig::default()
        }
        .build(Some(DIM))
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "map `point-cloud`: parameter `map_weight` must lie in [0, 1]"
        );
        let err = PointCloudConfig {
            dim: Some(512),
            ..PointCloudConfig::default()
        }
        .build(Some(DIM))
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "map `point-cloud`: parameter `dim` is 512 but the encoder produces 4-d embeddings: \
             remove `dim` or set it to 4"
        );
    }

    #[test]
    fn geometry_only_map_keeps_points_and_colours() {
        let mut m = PointCloudConfig::default().build(None).unwrap();
        assert_eq!(m.dim(), 0);
        let f = plane(1.0);
        let obs = Observation {
            frame: &f,
            pose: &Pose::identity(),
            embeddings: None,
        };
        m.integrate(&obs).unwrap();
        m.integrate(&obs).unwrap();
        assert_eq!(m.len(), 16 * 12);
        assert!(
            m.snapshot()
                .unwrap()
                .colours
                .iter()
                .all(|c| *c == [200, 100, 0])
        );
        let mut out = Vec::new();
        assert!(m.similarity(&[], &mut out).is_err());
    }
}
