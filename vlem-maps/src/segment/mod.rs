//! `segment`: an Open-Fusion-style map of 3D segments (Yamazaki et al. 2024), one embedding each.
//!
//! The map is a set of 3D segments. Each owns cells of a coarse grid (`point_spacing`); a cell has
//! exactly one owner. Per frame:
//! 1. **2D segments.** Every valid pixel at the `pixel_stride` (finite positive depth, at most
//!    `max_depth`, with an embedding) is back-projected into the map frame and quantised to its
//!    grid cell. Pixels are grouped into 2D segments: by the encoder's segment id in the segment
//!    layout; by the patch whose centre is nearest (the patch containing the pixel) in the
//!    patch-grid layout, which has no segments of its own; and by 32x32-pixel tiles for a
//!    geometry-only map. A 2D segment's embedding is its table row, or the normalised mean of its
//!    pixels' embeddings for patches.
//! 2. **Association** (`association.rs`). `overlap(s, S)` is the number of cells of the 2D
//!    segment `s` owned by the 3D segment `S`, and the score is `overlap / min(|s|, |S ∩ frame|)`,
//!    where `S ∩ frame` are the cells of `S` this frame observed (so occluded and out-of-view
//!    parts of `S` do not count against it, and a segment seen in part again still matches).
//!    Pairs scoring below `min_overlap` are dropped; the rest are assigned one-to-one by the
//!    Hungarian algorithm (`hungarian.rs`), maximising the total score. A matched 3D segment
//!    fuses the observation into its embedding with `e := (1 - w) e_obs + w e`, renormalised
//!    (w = `map_weight`), and takes the unowned cells of the 2D segment (cells of another segment
//!    stay with their owner). An unmatched 2D segment that would own at least `min_cells` unowned
//!    cells becomes a new 3D segment. Observed cells fuse their colour with the same weights.
//! 3. **Budget.** The map's points are its cells; while there are more than `max_points`, the
//!    segments observed least recently (then the smallest, then the oldest) are removed. Segments
//!    seen in the current frame are never evicted: if they alone exceed the budget, the grid is
//!    coarsened instead (spacing doubled, cells merged, a merged cell keeping its first owner) and
//!    the coarser spacing is kept for later frames, like the point-cloud map's voxel size. Only a
//!    budget below the number of octants the frame's cells occupy, which no coarsening of a grid
//!    anchored at the origin can meet, evicts segments of the current frame (the smallest first).
//!
//! Only segments that own an observed cell change: a matched segment's embedding changes for all
//! its cells, including those out of view, as in Open-Fusion; segments not seen are untouched.
//!
//! Points are reported per cell, ordered by segment creation, then cell key; `restore` splits a
//! snapshot into segments at every change of embedding or break in key order, so a map's own
//! snapshot round-trips in the same order.

mod association;
mod hungarian;

use std::collections::{BTreeMap, HashMap};

use vlem_core::embeddings::{EmbeddingLayout, normalise};
use vlem_core::{
    BuildContext, ColouredMesh, CoreError, EmbeddingMap, IntegrationStats, MapBudget, MapMetadata,
    MapSnapshot, Observation, PixelEmbeddings, StageKind, parse_params,
};

pub use self::hungarian::hungarian;
use crate::error::MapError;
use crate::kit::memory::{btree_bytes, hash_buckets};
use crate::kit::{
    FramePixels, check_observation, check_snapshot, count_in, invalid_parameter, number_in,
    unit_weight,
};
use crate::storage::{EmbeddingStore, fuse_into};

/// The registered name.
pub const NAME: &str = "segment";

/// The largest point budget accepted (as the other maps': rows are indexed with `u32`).
pub const MAX_SEGMENT_POINTS: usize = 1 << 30;

/// Tile size (pixels) of the 2D segments of a geometry-only map, which has no segmentation.
const GEOMETRY_TILE: u32 = 32;

crate::map_config! {
    /// `[map] kind = "segment"` parameters.
    pub struct SegmentConfig {
        /// Budget on the number of cells (the map's points); default 1,000,000.
        pub max_points: usize = 1_000_000,
        /// Grid cell size in metres; default 0.02.
        pub point_spacing: f32 = 0.02,
        /// Minimum overlap score for a 2D segment to join a 3D segment, in (0, 1]; default 0.25.
        pub min_overlap: f32 = 0.25,
        /// Minimum number of new cells for an unmatched 2D segment to start a 3D segment; default
        /// 10.
        pub min_cells: usize = 10,
        /// Weight `w` of the map embedding in the fusion; default 0.5 (the paper's value).
        pub map_weight: f32 = 0.5,
    }
}

impl SegmentConfig {
    /// Builds the map for embeddings of dimension `encoder_dim` (`None` without an encoder).
    ///
    /// # Errors
    /// [`MapError::InvalidParameter`] (wrapped as a stage error) for out-of-range values and for a
    /// `dim` that disagrees with the encoder.
    pub fn build(&self, encoder_dim: Option<usize>) -> Result<SegmentMap, CoreError> {
        count_in(
            NAME,
            "max_points",
            self.max_points,
            (1, MAX_SEGMENT_POINTS),
            "points",
        )?;
        // Cells are keyed by i32 coordinates: finer than 0.1 mm they saturate within 200 m.
        number_in(NAME, "point_spacing", self.point_spacing, (1e-4, 10.0), "m")?;
        if !(self.min_overlap > 0.0 && self.min_overlap <= 1.0) {
            return Err(invalid_parameter(NAME, "min_overlap", "must lie in (0, 1]"));
        }
        count_in(NAME, "min_cells", self.min_cells, (1, 1_000_000), "cells")?;
        unit_weight(NAME, "map_weight", self.map_weight)?;
        let dim = self.common().validate(NAME, encoder_dim)?;
        Ok(SegmentMap::new(self.clone(), dim))
    }
}

fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn EmbeddingMap>> {
    let config: SegmentConfig = parse_params(StageKind::Map, NAME, params)?;
    Ok(Box::new(config.build(ctx.embedding_dim)?))
}

vlem_core::register_map!(
    NAME,
    "3D segments with one fused embedding each, associated by overlap (Open-Fusion style)",
    build
);

/// Integer grid coordinates of a cell.
type CellKey = [i32; 3];

/// The cell of `p` at grid spacing `spacing` (saturating far from the origin).
fn cell_key(p: [f32; 3], spacing: f32) -> CellKey {
    p.map(|x| (x / spacing).floor() as i32)
}

fn cell_centre(k: CellKey, spacing: f32) -> [f32; 3] {
    k.map(|i| (i as f32 + 0.5) * spacing)
}

/// One cell of a 3D segment.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Cell {
    /// Reported position: the cell centre (or the restored snapshot position).
    position: [f32; 3],
    colour: [u8; 3],
}

/// A 3D segment.
#[derive(Clone, Debug)]
struct Segment {
    /// Row in the embedding store (unused for a geometry-only map).
    row: usize,
    /// Frame count at the last frame that observed one of its cells.
    last_seen: u64,
    /// Owned cells, sorted by key (the snapshot order within the segment).
    cells: BTreeMap<CellKey, Cell>,
}

/// A 2D segment of the current frame.
struct Segment2d {
    /// Distinct cells, sorted.
    cells: Vec<CellKey>,
    /// Unit-norm embedding (empty for a geometry-only map).
    embedding: Vec<f32>,
}

/// What one frame observed.
struct Observed {
    /// Every observed cell with its colour sum and pixel count.
    cells: HashMap<CellKey, ([u32; 3], u32)>,
    segments: Vec<Segment2d>,
    pixels: usize,
}

/// A 2D segment under construction.
#[derive(Default)]
struct Accumulator {
    cells: Vec<CellKey>,
    embedding: Vec<f32>,
}

/// The segment map.
#[derive(Clone, Debug)]
pub struct SegmentMap {
    config: SegmentConfig,
    dim: usize,
    /// Current grid spacing: `point_spacing` until the budget forced a coarser grid.
    spacing: f32,
    /// Segments by id; ids grow with creation, so iteration is in creation order.
    segments: BTreeMap<u64, Segment>,
    /// The owner of every cell.
    owner: HashMap<CellKey, u64>,
    /// The largest `owner.capacity()` seen after insertions: the table's bucket capacity (removals
    /// leave tombstones that lower `capacity()` without freeing anything).
    owner_capacity: usize,
    /// One embedding row per segment.
    embeddings: EmbeddingStore,
    /// The segment id of every store row (to fix up rows moved by `swap_remove`).
    row_ids: Vec<u64>,
    next_id: u64,
    frames: usize,
}

impl SegmentMap {
    /// An empty map (use [`SegmentConfig::build`] for validated parameters).
    pub fn new(config: SegmentConfig, dim: usize) -> Self {
        Self {
            embeddings: EmbeddingStore::new(dim, config.precision),
            spacing: config.point_spacing,
            config,
            dim,
            segments: BTreeMap::new(),
            owner: HashMap::new(),
            owner_capacity: 0,
            row_ids: Vec::new(),
            next_id: 0,
            frames: 0,
        }
    }

    /// Number of 3D segments.
    pub fn segment_count(&self) -> usize {
        self.segments.len()
    }

    /// The current grid spacing (grows above `point_spacing` only when the budget demands it).
    pub fn spacing(&self) -> f32 {
        self.spacing
    }

    /// The embedding of every segment in creation order, widened to `f32` (`segments x dim`).
    pub fn segment_embeddings(&self) -> Vec<f32> {
        let mut out = vec![0.0; self.segments.len() * self.dim];
        if self.dim > 0 {
            for (row, s) in out.chunks_exact_mut(self.dim).zip(self.segments.values()) {
                self.embeddings.row_into(s.row, row);
            }
        }
        out
    }

    fn check(&self, obs: &Observation<'_>) -> Result<(), MapError> {
        check_observation(self.dim, obs)
    }

    /// Back-projects, quantises and groups the valid pixels into 2D segments.
    fn observe(&self, obs: &Observation<'_>) -> Observed {
        let frame = obs.frame;
        let w = frame.depth.width();
        let dim = self.dim;
        let mut cells: HashMap<CellKey, ([u32; 3], u32)> = HashMap::new();
        // BTreeMap: 2D segments in label order, so integration is deterministic.
        let mut groups: BTreeMap<u32, Accumulator> = BTreeMap::new();
        let mut scratch = vec![0.0f32; dim];
        let mut pixels = 0;
        for pixel in FramePixels::new(obs, &self.config.common()).iter() {
            let (u, v) = (pixel.u, pixel.v);
            let label = match obs.embeddings {
                Some(e) => match pixel_label(e, u, v) {
                    Some(label) => label,
                    None => continue,
                },
                None => (v / GEOMETRY_TILE) * w.div_ceil(GEOMETRY_TILE) + u / GEOMETRY_TILE,
            };
            let acc = groups.entry(label).or_default();
            if let Some(e) = obs.embeddings {
                match e.layout() {
                    EmbeddingLayout::Regions { .. } => {
                        if acc.embedding.is_empty()
                            && let Some(row) = e.region_row(u, v)
                        {
                            acc.embedding.extend_from_slice(row);
                        }
                    }
                    EmbeddingLayout::PatchGrid { .. } => {
                        if !e.embedding_at(u, v, &mut scratch) {
                            continue;
                        }
                        if acc.embedding.is_empty() {
                            acc.embedding.resize(dim, 0.0);
                        }
                        acc.embedding
                            .iter_mut()
                            .zip(&scratch)
                            .for_each(|(a, b)| *a += b);
                    }
                }
            }
            let key = cell_key(pixel.world, self.spacing);
            acc.cells.push(key);
            let c = pixel.colour(&frame.colour);
            let entry = cells.entry(key).or_insert(([0; 3], 0));
            for (s, x) in entry.0.iter_mut().zip(c) {
                *s += u32::from(x);
            }
            entry.1 += 1;
            pixels += 1;
        }
        let segments = groups
            .into_values()
            .filter_map(|mut acc| {
                // A patch mean that cancels out carries no direction: drop the segment.
                if dim > 0 && !normalise(&mut acc.embedding) {
                    return None;
                }
                acc.cells.sort_unstable();
                acc.cells.dedup();
                (!acc.cells.is_empty()).then_some(Segment2d {
                    cells: acc.cells,
                    embedding: acc.embedding,
                })
            })
            .collect();
        Observed {
            cells,
            segments,
            pixels,
        }
    }

    /// Adds `segment` as a new 3D segment; returns its id.
    fn add_segment(&mut self, embedding: &[f32], segment: Segment) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        if self.dim > 0 {
            self.embeddings.push(embedding);
            self.row_ids.push(id);
        }
        for key in segment.cells.keys() {
            self.owner.insert(*key, id);
        }
        self.segments.insert(id, segment);
        id
    }

    fn remove_segment(&mut self, id: u64) {
        let Some(segment) = self.segments.remove(&id) else {
            return;
        };
        for key in segment.cells.keys() {
            self.owner.remove(key);
        }
        if self.dim > 0 {
            let row = segment.row;
            self.embeddings.swap_remove(row);
            self.row_ids.swap_remove(row);
            if let Some(&moved) = self.row_ids.get(row)
                && let Some(s) = self.segments.get_mut(&moved)
            {
                s.row = row;
            }
        }
    }

    /// Evicts stale segments, then coarsens the grid, until the budget holds. Segments seen at
    /// frame `now` or later are not evicted. Returns the number of cells removed.
    fn enforce_budget(&mut self, now: u64) -> usize {
        let budget = self.config.max_points;
        let before = self.owner.len();
        if before <= budget {
            return 0;
        }
        let mut stale: Vec<(u64, usize, u64)> = self
            .segments
            .iter()
            .filter(|(_, s)| s.last_seen < now)
            .map(|(&id, s)| (s.last_seen, s.cells.len(), id))
            .collect();
        stale.sort_unstable();
        for (_, _, id) in stale {
            if self.owner.len() <= budget {
                break;
            }
            self.remove_segment(id);
        }
        while self.owner.len() > budget {
            // The grid is anchored at the origin, so coarsening never merges cells on opposite
            // sides of a coordinate plane: once a cell is larger than every coordinate, it cannot
            // reduce the count any further (and doubling on would overflow the cell centres to
            // infinity). Only a budget below the number of occupied octants gets here: the
            // smallest (then oldest) segments seen in this frame go.
            if self.spacing > self.max_abs_coordinate() {
                let smallest = self
                    .segments
                    .iter()
                    .min_by_key(|(id, s)| (s.cells.len(), **id))
                    .map(|(id, _)| *id);
                match smallest {
                    Some(id) => self.remove_segment(id),
                    None => break,
                }
            } else {
                self.coarsen();
            }
        }
        before - self.owner.len()
    }

    /// The largest absolute coordinate of any cell position (0 for an empty map).
    fn max_abs_coordinate(&self) -> f32 {
        self.segments
            .values()
            .flat_map(|s| s.cells.values())
            .flat_map(|c| c.position)
            .fold(0.0f32, |m, x| m.max(x.abs()))
    }

    /// Doubles the grid spacing: cells are merged into the coarser cell (mean colour, position at
    /// its centre), a coarse cell keeps the first segment (in creation order) that claims it, and
    /// segments left without cells are removed.
    fn coarsen(&mut self) {
        self.spacing *= 2.0;
        let spacing = self.spacing;
        self.owner.clear();
        let mut empty = Vec::new();
        for (&id, segment) in &mut self.segments {
            let mut merged: BTreeMap<CellKey, ([u32; 3], u32)> = BTreeMap::new();
            for cell in segment.cells.values() {
                let key = cell_key(cell.position, spacing);
                match self.owner.get(&key) {
                    Some(&other) if other != id => continue,
                    _ => {}
                }
                self.owner.insert(key, id);
                let entry = merged.entry(key).or_insert(([0; 3], 0));
                for (s, x) in entry.0.iter_mut().zip(cell.colour) {
                    *s += u32::from(x);
                }
                entry.1 += 1;
            }
            segment.cells = merged
                .into_iter()
                .map(|(key, (sum, n))| {
                    let colour = sum.map(|s| (s / n.max(1)) as u8);
                    (
                        key,
                        Cell {
                            position: cell_centre(key, spacing),
                            colour,
                        },
                    )
                })
                .collect();
            if segment.cells.is_empty() {
                empty.push(id);
            }
        }
        for id in empty {
            self.remove_segment(id);
        }
    }

    fn fuse_colour(&self, colour: &mut [u8; 3], observed: [u8; 3]) {
        let w = self.config.map_weight;
        for (c, p) in colour.iter_mut().zip(observed) {
            *c = ((1.0 - w) * f32::from(p) + w * f32::from(*c)).round() as u8;
        }
    }
}

/// The 2D segment label of a pixel: the encoder's segment id, or the patch containing the pixel
/// (nearest patch centre) for a patch grid. `None` for pixels without an embedding.
fn pixel_label(e: &PixelEmbeddings, u: u32, v: u32) -> Option<u32> {
    match e.layout() {
        EmbeddingLayout::Regions { index, .. } => {
            let s = *index.get((v * e.width() + u) as usize)?;
            (s != vlem_core::NO_REGION).then_some(s)
        }
        EmbeddingLayout::PatchGrid {
            grid_width,
            grid_height,
            ..
        } => {
            // Patch centres sit at (i + 0.5) * width / grid_width, so the nearest one to the pixel
            // centre is the patch that contains it.
            let cell = |p: u32, size: u32, n: u32| {
                (((p as f32 + 0.5) * n as f32 / size as f32) as u32).min(n - 1)
            };
            let (i, j) = (
                cell(u, e.width(), *grid_width),
                cell(v, e.height(), *grid_height),
            );
            Some(j * grid_width + i)
        }
    }
}

impl EmbeddingMap for SegmentMap {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn integrate(&mut self, obs: &Observation<'_>) -> vlem_core::Result<IntegrationStats> {
        self.check(obs)
            .map_err(|e| CoreError::stage(StageKind::Map, NAME, e))?;
        let observed = self.observe(obs);
        self.frames += 1;
        let now = self.frames as u64;
        let mut stats = IntegrationStats {
            observed: observed.pixels,
            ..IntegrationStats::default()
        };
        if observed.segments.is_empty() {
            return Ok(stats);
        }
        let matches = self.associate(&observed);
        // Observed cells that already have an owner: fuse their colour, mark the owner seen.
        for (key, (sum, n)) in &observed.cells {
            let Some(&id) = self.owner.get(key) else {
                continue;
            };
            let mean = sum.map(|s| (s / (*n).max(1)) as u8);
            let mut colour = None;
            if let Some(cell) = self.segments.get(&id).and_then(|s| s.cells.get(key)) {
                let mut c = cell.colour;
                self.fuse_colour(&mut c, mean);
                colour = Some(c);
            }
            if let Some(s) = self.segments.get_mut(&id) {
                s.last_seen = now;
                if let (Some(c), Some(cell)) = (colour, s.cells.get_mut(key)) {
                    cell.colour = c;
                }
            }
        }
        let new_cell = |key: CellKey, spacing: f32| {
            let (sum, n) = observed.cells.get(&key).copied().unwrap_or(([0; 3], 1));
            Cell {
                position: cell_centre(key, spacing),
                colour: sum.map(|s| (s / n.max(1)) as u8),
            }
        };
        let mut scratch = vec![0.0f32; self.dim];
        // Matched 2D segments first, so their cells go to the segments they continue.
        for (s2d, id) in observed.segments.iter().zip(&matches) {
            let Some(id) = *id else { continue };
            let Some(row) = self.segments.get(&id).map(|s| s.row) else {
                continue;
            };
            if self.dim > 0 {
                self.embeddings.row_into(row, &mut scratch);
                fuse_into(&mut scratch, &s2d.embedding, self.config.map_weight);
                self.embeddings.set_row(row, &scratch);
            }
            let fresh: Vec<CellKey> = s2d
                .cells
                .iter()
                .filter(|k| !self.owner.contains_key(*k))
                .copied()
                .collect();
            stats.inserted += fresh.len();
            for &key in &fresh {
                self.owner.insert(key, id);
            }
            let spacing = self.spacing;
            if let Some(s) = self.segments.get_mut(&id) {
                s.last_seen = now;
                s.cells
                    .extend(fresh.into_iter().map(|k| (k, new_cell(k, spacing))));
                stats.fused += s.cells.len();
            }
        }
        for (s2d, id) in observed.segments.iter().zip(&matches) {
            if id.is_some() {
                continue;
            }
            let cells: BTreeMap<CellKey, Cell> = s2d
                .cells
                .iter()
                .filter(|k| !self.owner.contains_key(*k))
                .map(|&k| (k, new_cell(k, self.spacing)))
                .collect();
            if cells.len() < self.config.min_cells {
                continue;
            }
            stats.inserted += cells.len();
            let segment = Segment {
                row: self.embeddings.rows(),
                last_seen: now,
                cells,
            };
            self.add_segment(&s2d.embedding, segment);
        }
        self.owner_capacity = self.owner_capacity.max(self.owner.capacity());
        stats.removed = self.enforce_budget(now);
        Ok(stats)
    }

    fn len(&self) -> usize {
        self.owner.len()
    }

    fn budget(&self) -> Option<MapBudget> {
        Some(MapBudget {
            parameter: "max_points",
            elements: self.config.max_points,
        })
    }

    fn memory_bytes(&self) -> usize {
        use std::mem::size_of;
        // Hash map: its buckets (see `hash_buckets`); B-trees: their nodes, a lower bound (see
        // `btree_bytes`), so the report is at most ~1.5x below the heap for tiny segments.
        let buckets = hash_buckets(self.owner_capacity.max(self.owner.capacity()));
        let owner = buckets * (size_of::<(CellKey, u64)>() + 1);
        let cells: usize = self
            .segments
            .values()
            .map(|s| btree_bytes(s.cells.len(), size_of::<CellKey>() + size_of::<Cell>()))
            .sum();
        let segments = btree_bytes(self.segments.len(), size_of::<u64>() + size_of::<Segment>());
        self.embeddings.memory_bytes()
            + self.row_ids.capacity() * size_of::<u64>()
            + owner
            + cells
            + segments
    }

    fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> vlem_core::Result<()> {
        let mut per_segment = Vec::new();
        self.embeddings.similarity(text, &mut per_segment)?;
        self.spread_to_cells(&per_segment, out);
        Ok(())
    }

    fn similarity_many(&self, texts: &[&[f32]], out: &mut Vec<Vec<f32>>) -> vlem_core::Result<()> {
        let mut per_segment = Vec::new();
        self.embeddings.similarity_many(texts, &mut per_segment)?;
        out.resize_with(texts.len(), Vec::new);
        for (scores, cells) in per_segment.iter().zip(out.iter_mut()) {
            self.spread_to_cells(scores, cells);
        }
        Ok(())
    }

    fn coloured_points(&self) -> ColouredMesh {
        let cells = self.segments.values().flat_map(|s| s.cells.values());
        let (vertices, colours) = cells.map(|cell| (cell.position, cell.colour)).unzip();
        ColouredMesh {
            vertices,
            colours,
            triangles: Vec::new(),
        }
    }

    fn snapshot(&self) -> vlem_core::Result<MapSnapshot> {
        let n = self.owner.len();
        let mut positions = Vec::with_capacity(n);
        let mut colours = Vec::with_capacity(n);
        let mut embeddings = Vec::with_capacity(n * self.dim);
        let mut row = vec![0.0f32; self.dim];
        for s in self.segments.values() {
            if self.dim > 0 {
                self.embeddings.row_into(s.row, &mut row);
            }
            for cell in s.cells.values() {
                positions.push(cell.position);
                colours.push(cell.colour);
                embeddings.extend_from_slice(&row);
            }
        }
        Ok(MapSnapshot {
            map_kind: NAME.into(),
            dim: self.dim,
            positions,
            colours,
            embeddings,
            metadata: MapMetadata {
                frames_integrated: self.frames,
                ..MapMetadata::default()
            },
        })
    }

    /// Rebuilds segments from a snapshot: consecutive points with bit-identical embeddings and
    /// increasing cell keys form one segment (a map's own snapshot lists each segment's cells in
    /// key order). A point in a cell already taken is dropped (only foreign snapshots have such).
    fn restore(&mut self, snapshot: MapSnapshot) -> vlem_core::Result<()> {
        check_snapshot(self.dim, &snapshot)?;
        *self = Self::new(self.config.clone(), self.dim);
        self.frames = snapshot.metadata.frames_integrated;
        // Restored segments count as seen in the last frame: over budget, the grid coarsens.
        let now = self.frames as u64;
        let d = self.dim;
        let row_of = |i: usize| &snapshot.embeddings[i * d..(i + 1) * d];
        let mut current: Option<(usize, BTreeMap<CellKey, Cell>, CellKey)> = None;
        for (i, (&position, &colour)) in
            snapshot.positions.iter().zip(&snapshot.colours).enumerate()
        {
            let key = cell_key(position, self.spacing);
            let continues = current.as_ref().is_some_and(|(first, _, last)| {
                key > *last
                    && row_of(*first)
                        .iter()
                        .zip(row_of(i))
                        .all(|(a, b)| a.to_bits() == b.to_bits())
            });
            if !continues && let Some((first, cells, _)) = current.take() {
                self.restore_segment(row_of(first), cells, now);
            }
            let (_, cells, last) = current.get_or_insert_with(|| (i, BTreeMap::new(), key));
            if self.owner.contains_key(&key) || cells.contains_key(&key) {
                continue;
            }
            cells.insert(key, Cell { position, colour });
            *last = key;
        }
        if let Some((first, cells, _)) = current.take() {
            self.restore_segment(row_of(first), cells, now);
        }
        self.owner_capacity = self.owner_capacity.max(self.owner.capacity());
        let _ = self.enforce_budget(now);
        Ok(())
    }
}

impl SegmentMap {
    /// Each cell gets its segment's score (cells in the order of `snapshot`).
    fn spread_to_cells(&self, per_segment: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.reserve(self.owner.len());
        for s in self.segments.values() {
            let score = per_segment.get(s.row).copied().unwrap_or(0.0);
            out.extend(std::iter::repeat_n(score, s.cells.len()));
        }
    }

    fn restore_segment(&mut self, embedding: &[f32], cells: BTreeMap<CellKey, Cell>, now: u64) {
        if cells.is_empty() {
            return;
        }
        let segment = Segment {
            row: self.embeddings.rows(),
            last_seen: now,
            cells,
        };
        self.add_segment(embedding, segment);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::Precision;
    use crate::test_fixtures::{self, *};
    use vlem_core::{Frame, PixelEmbeddings, Pose};

    /// Columns below `split` are segment 0, the rest segment 1.
    fn split(split: u32, a: [f32; DIM], b: [f32; DIM]) -> PixelEmbeddings {
        let index = (0..16 * 12).map(|i| u32::from(i % 16 >= split)).collect();
        PixelEmbeddings::from_regions(16, 12, DIM, index, [a, b].concat()).unwrap()
    }

    fn config() -> SegmentConfig {
        // Cells coarser than the pixel footprint, so every cell is hit in every frame.
        SegmentConfig {
            point_spacing: 0.1,
            min_cells: 3,
            ..SegmentConfig::default()
        }
    }

    /// Integrates `f` seen from the origin (the shared fixture's `integrate`, posed).
    fn integrate(m: &mut SegmentMap, f: &Frame, e: &PixelEmbeddings) -> IntegrationStats {
        test_fixtures::integrate(m, f, &Pose::identity(), e)
    }

    #[test]
    fn re_observing_a_frame_creates_nothing_and_fuses_by_the_formula() {
        let mut m = SegmentConfig {
            map_weight: 0.25,
            ..config()
        }
        .build(Some(DIM))
        .unwrap();
        let f = plane(1.0);
        let first = integrate(
            &mut m,
            &f,
            &split(8, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]),
        );
        assert_eq!(m.segment_count(), 2);
        assert_eq!(first.inserted, m.len());
        let cells = m.len();
        let second = integrate(
            &mut m,
            &f,
            &split(8, [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
        );
        assert_eq!((second.inserted, second.removed), (0, 0));
        assert_eq!((m.segment_count(), m.len()), (2, cells));
        // e = normalise(0.75 e_obs + 0.25 e_map)
        let n = (0.75f32 * 0.75 + 0.25 * 0.25).sqrt();
        let (a, b) = (0.25 / n, 0.75 / n);
        let e = m.segment_embeddings();
        let expected = [a, b, 0.0, 0.0, 0.0, 0.0, a, b];
        for (x, y) in e.iter().zip(expected) {
            assert!((x - y).abs() < 1e-6, "{e:?}");
        }
        // Every point carries its segment's embedding, and scores follow it.
        let mut scores = Vec::new();
        m.similarity(&[0.0, 1.0, 0.0, 0.0], &mut scores).unwrap();
        assert_eq!(scores.len(), m.len());
        assert!(
            scores
                .iter()
                .all(|s| (s - (b + 1.0) / 2.0).abs() < 1e-6 || (s - 0.5).abs() < 1e-6)
        );
    }

    #[test]
    fn a_second_object_without_overlap_becomes_a_new_segment() {
        let mut m = config().build(Some(DIM)).unwrap();
        let e = uniform([1.0, 0.0, 0.0, 0.0]);
        integrate(&mut m, &plane(1.0), &e);
        let (n, before) = (m.len(), m.snapshot().unwrap());
        // Half a metre further away: no cell in common.
        let stats = integrate(&mut m, &plane(1.5), &uniform([0.0, 1.0, 0.0, 0.0]));
        assert_eq!(m.segment_count(), 2);
        assert_eq!(stats.inserted, m.len() - n);
        // The first segment is untouched.
        let after = m.snapshot().unwrap();
        assert_eq!(after.positions[..n], before.positions[..]);
        assert_eq!(after.embeddings[..n * DIM], before.embeddings[..]);
    }

    #[test]
    fn the_budget_evicts_the_stalest_then_the_smallest_segments() {
        let (a_small, a_big) = ([1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]);
        let b = uniform([0.0, 0.0, 1.0, 0.0]);
        let run = |max_points| {
            let mut m = SegmentConfig {
                max_points,
                ..config()
            }
            .build(Some(DIM))
            .unwrap();
            integrate(&mut m, &plane(1.0), &split(4, a_small, a_big));
            let sizes: Vec<usize> = m.segments.values().map(|s| s.cells.len()).collect();
            integrate(&mut m, &plane(3.0), &b);
            (m, sizes)
        };
        let (all, sizes) = run(1_000_000);
        assert_eq!(all.segment_count(), 3);
        assert!(sizes[0] < sizes[1], "{sizes:?}");
        let newest = all.len() - sizes[0] - sizes[1];
        // Room for the newest and the big old segment: the small old one goes.
        let (m, _) = run(newest + sizes[1]);
        assert_eq!(m.len(), newest + sizes[1]);
        assert_eq!(
            m.segment_embeddings(),
            [a_big, [0.0, 0.0, 1.0, 0.0]].concat()
        );
        // Room for the newest only: both old segments go, the grid stays as it is.
        let (m, _) = run(newest);
        assert_eq!(m.segment_embeddings(), vec![0.0, 0.0, 1.0, 0.0]);
        assert_eq!(m.spacing(), 0.1);
    }

    #[test]
    fn a_frame_over_the_budget_coarsens_the_grid() {
        let mut m = SegmentConfig {
            max_points: 10,
            ..config()
        }
        .build(Some(DIM))
        .unwrap();
        let stats = integrate(
            &mut m,
            &plane(1.0),
            &split(8, [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]),
        );
        assert!(m.len() <= 10 && !m.is_empty(), "{} cells", m.len());
        assert!(m.spacing() > 0.1);
        assert_eq!(stats.inserted - stats.removed, m.len());
        let snap = m.snapshot().unwrap();
        for row in snap.embeddings.chunks_exact(DIM) {
            assert!(row == [1.0, 0.0, 0.0, 0.0] || row == [0.0, 1.0, 0.0, 0.0]);
        }
    }

    #[test]
    fn patch_grids_group_pixels_by_patch() {
        let mut m = config().build(Some(DIM)).unwrap();
        // Two patches, left and right half.
        let e = PixelEmbeddings::from_patch_grid(
            16,
            12,
            DIM,
            2,
            1,
            vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        )
        .unwrap();
        integrate(&mut m, &plane(1.0), &e);
        assert_eq!(m.segment_count(), 2);
        let e = m.segment_embeddings();
        // Interpolated pixel embeddings lean towards their own patch.
        assert!(e[0] > e[1] && e[5] > e[4], "{e:?}");
        for row in e.chunks_exact(DIM) {
            assert!((row.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn restore_round_trips_the_snapshot_in_order() {
        let mut m = config().build(Some(DIM)).unwrap();
        integrate(
            &mut m,
            &plane(1.0),
            &split(8, [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]),
        );
        // A later segment with the same embedding as the first stays a segment of its own.
        integrate(&mut m, &plane(2.0), &uniform([1.0, 0.0, 0.0, 0.0]));
        let snap = m.snapshot().unwrap();
        let mut fresh = config().build(Some(DIM)).unwrap();
        fresh.restore(snap.clone()).unwrap();
        assert_eq!(fresh.snapshot().unwrap(), snap);
        assert_eq!(fresh.segment_count(), 3);
    }

    #[test]
    fn f16_storage_keeps_the_query_ranking() {
        let mut maps = [Precision::F32, Precision::F16].map(|precision| {
            SegmentConfig {
                precision,
                ..config()
            }
            .build(Some(DIM))
            .unwrap()
        });
        let f = plane(1.0);
        let a = split(5, [0.9, 0.1, 0.3, 0.2], [0.1, 0.8, 0.2, 0.4]);
        let b = split(5, [0.5, 0.5, 0.1, 0.7], [0.3, 0.3, 0.6, 0.2]);
        for m in &mut maps {
            integrate(m, &f, &a);
            integrate(m, &f, &b);
            integrate(m, &plane(2.0), &uniform([0.2, 0.2, 0.9, 0.1]));
        }
        let text = [0.6, 0.2, 0.7, 0.3];
        let (mut s32, mut s16) = (Vec::new(), Vec::new());
        maps[0].similarity(&text, &mut s32).unwrap();
        maps[1].similarity(&text, &mut s16).unwrap();
        assert_eq!(s32.len(), s16.len());
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
        assert_eq!(
            maps[0].embeddings.memory_bytes(),
            2 * maps[1].embeddings.memory_bytes()
        );
    }

    #[test]
    fn geometry_only_maps_group_pixels_in_tiles() {
        let mut m = config().build(None).unwrap();
        let f = plane(1.0);
        let obs = Observation {
            frame: &f,
            pose: &Pose::identity(),
            embeddings: None,
        };
        m.integrate(&obs).unwrap();
        let n = m.len();
        m.integrate(&obs).unwrap();
        assert_eq!((m.len(), m.segment_count()), (n, 1));
        assert!(
            m.snapshot()
                .unwrap()
                .colours
                .iter()
                .all(|c| *c == [200, 100, 0])
        );
        assert!(m.similarity(&[], &mut Vec::new()).is_err());
        let mut fresh = config().build(None).unwrap();
        fresh.restore(m.snapshot().unwrap()).unwrap();
        assert_eq!(
            fresh.snapshot().unwrap().positions,
            m.snapshot().unwrap().positions
        );
    }

    #[test]
    fn a_device_for_the_table_is_refused_by_name() {
        let config: SegmentConfig = toml::from_str("device = \"cuda:1\"").unwrap();
        let error = config.build(Some(DIM)).err().map(|e| e.to_string());
        let error = error.unwrap_or_default();
        assert!(
            error.contains("segment map") && error.contains("`device`"),
            "{error}"
        );
    }

    #[test]
    fn invalid_parameters_are_named() {
        let cases = [
            (
                SegmentConfig {
                    max_points: 0,
                    ..SegmentConfig::default()
                },
                "max_points",
            ),
            (
                SegmentConfig {
                    point_spacing: 0.0,
                    ..SegmentConfig::default()
                },
                "point_spacing",
            ),
            (
                SegmentConfig {
                    min_overlap: 0.0,
                    ..SegmentConfig::default()
                },
                "min_overlap",
            ),
            (
                SegmentConfig {
                    min_cells: 0,
                    ..SegmentConfig::default()
                },
                "min_cells",
            ),
            (
                SegmentConfig {
                    map_weight: 1.5,
                    ..SegmentConfig::default()
                },
                "map_weight",
            ),
            (
                SegmentConfig {
                    max_depth: f32::NAN,
                    ..SegmentConfig::default()
                },
                "max_depth",
            ),
        ];
        for (config, name) in cases {
            let err = config.build(Some(DIM)).unwrap_err().to_string();
            assert!(
                err.starts_with(&format!("map `segment`: parameter `{name}`")),
                "{err}"
            );
        }
        let err = SegmentConfig {
            dim: Some(512),
            ..SegmentConfig::default()
        }
        .build(Some(DIM))
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "map `segment`: parameter `dim` is 512 but the encoder produces 4-d embeddings: \
             remove `dim` or set it to 4"
        );
        let table: toml::Table = toml::from_str("min_overlap = 0.5\nspacing = 1.0").unwrap();
        assert!(parse_params::<SegmentConfig>(StageKind::Map, NAME, &table).is_err());
    }
}
