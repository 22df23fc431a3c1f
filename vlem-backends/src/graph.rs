//! `graph`: the weight-free graph-based region proposer of Felzenszwalb and Huttenlocher
//! (`[proposer] kind = "graph"`).
//!
//! Why it exists: region encoders (`clip`, `onnx`) need regions, and SAM needs model weights and
//! seconds per frame on a CPU. "Efficient Graph-Based Image Segmentation" (Felzenszwalb and
//! Huttenlocher, IJCV 2004) needs neither: it gives a full partition of a 640×480 frame in about
//! 50 ms on one core (about 15 ms with `downscale = 2`), so the segment path runs (and is tested)
//! anywhere. Its
//! segments follow colour, not objects: expect walls split by shading and small objects merged
//! into their surroundings where the contrast is low.
//!
//! What it owns: the parameters and the algorithm, in its usual colour form:
//! 1. smooth each channel with a Gaussian of standard deviation `sigma` (clamped borders);
//! 2. build the 8-connected grid graph, each edge weighted by the Euclidean RGB distance of its
//!    two smoothed pixels (0–255 scale);
//! 3. sort the edges by weight (a counting sort of weights quantised to 1/64 of a grey level,
//!    which is far below the smoothing's own effect and keeps the sort linear);
//! 4. take the edges in that order and merge the two components `C1`, `C2` of an edge of weight
//!    `w` when `w <= min(Int(C1) + k/|C1|, Int(C2) + k/|C2|)`, where `Int` is the largest edge
//!    weight inside a component (union-find; the weight of the merging edge becomes the new
//!    `Int`);
//! 5. merge every component smaller than `min_size` pixels into a neighbour, again in edge order.
//!
//! With `downscale = f > 1` the image is first box-averaged by `f × f` blocks, segmented, and the
//! labels are copied back to the pixels of each block; `sigma`, `k` and `min_size` keep their
//! meaning in full-resolution pixels (they are divided by `f`, `f²` and `f²`). The regions are
//! returned largest first, at most `max_regions` of them: with a cap, the pixels of the smaller
//! segments belong to no region (and get no embedding); without one, every pixel lies in exactly
//! one region.
//!
//! ```toml
//! [proposer]
//! kind = "graph"
//! # sigma = 0.8        # Gaussian smoothing, pixels
//! # k = 400.0          # scale: larger k, larger segments
//! # min_size = 800     # pixels; smaller segments are merged into a neighbour
//! # max_regions = 64   # keep the largest; 0 keeps all
//! # downscale = 1      # segment a 1/f-size image (2: ~3.5x faster, finer segments)
//! ```

use serde::Deserialize;
use vlem_core::{BuildContext, PixelRect, Region, RegionProposer, RgbImage, StageKind};

use crate::error::BackendError;

/// The name this proposer is registered under (`[proposer] kind = "graph"`).
pub const NAME: &str = "graph";

/// Largest accepted `sigma`: the kernel has `2 ⌈4 sigma⌉ + 1` taps, and beyond this the image is
/// a blur anyway.
pub const MAX_SIGMA: f32 = 50.0;

/// Largest accepted `downscale` factor.
pub const MAX_DOWNSCALE: u32 = 16;

/// Edge weights are quantised to `1 / WEIGHT_STEPS` grey levels for the counting sort.
const WEIGHT_STEPS: f32 = 64.0;

/// Parameters of the proposer: the `[proposer]` section without `kind`. Sizes are in pixels of
/// the input image, whatever `downscale` is.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GraphConfig {
    /// Standard deviation of the Gaussian smoothing before the graph is built, in pixels; 0 turns
    /// smoothing off. Default 0.8, the paper's value. At most [`MAX_SIGMA`].
    pub sigma: f32,
    /// The scale `k` of the threshold `τ(C) = k / |C|` (colour distances on a 0–255 scale):
    /// larger values give larger segments. Default 400, between the paper's 300 (for 320×240)
    /// and the 500 common for 640×480. Finite and not negative.
    pub k: f32,
    /// Segments smaller than this many pixels are merged into a neighbour. Default 800, about
    /// 0.26 % of a 640×480 frame; 0 or 1 merges nothing.
    pub min_size: u32,
    /// The number of regions kept, largest first; 0 keeps all. Default 64.
    pub max_regions: usize,
    /// Segment an image box-averaged by this factor in each axis (1 = full resolution), then copy
    /// each label back to its block. 1 to [`MAX_DOWNSCALE`]; default 1.
    pub downscale: u32,
}

impl Default for GraphConfig {
    fn default() -> Self {
        Self {
            sigma: 0.8,
            k: 400.0,
            min_size: 800,
            max_regions: 64,
            downscale: 1,
        }
    }
}

impl GraphConfig {
    /// Checks the parameter ranges documented on the fields.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] naming the parameter.
    pub fn validate(&self) -> Result<(), BackendError> {
        if !(self.sigma.is_finite() && (0.0..=MAX_SIGMA).contains(&self.sigma)) {
            return Err(BackendError::InvalidParams(format!(
                "sigma must be between 0 and {MAX_SIGMA} pixels, got {}",
                self.sigma
            )));
        }
        // The merge threshold k / |C| of Felzenszwalb and Huttenlocher: past 1e6 every image is
        // one region.
        if let Err(range) = vlem_core::ranges::number(self.k, 0.0, 1e6, "") {
            return Err(BackendError::InvalidParams(format!("k {range}")));
        }
        if let Err(range) = vlem_core::ranges::count(self.min_size, 0, 1 << 24, "pixels") {
            return Err(BackendError::InvalidParams(format!("min_size {range}")));
        }
        if !(1..=MAX_DOWNSCALE).contains(&self.downscale) {
            return Err(BackendError::InvalidParams(format!(
                "downscale must be between 1 and {MAX_DOWNSCALE}, got {}",
                self.downscale
            )));
        }
        Ok(())
    }
}

/// A partition of an image into segments: one label per pixel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Segmentation {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Row-major label of every pixel, `0..count`, numbered in order of each segment's first
    /// pixel in row-major order.
    pub labels: Vec<u32>,
    /// Number of segments.
    pub count: usize,
}

/// The graph-based proposer. See the [module documentation](self).
#[derive(Clone, Debug)]
pub struct GraphProposer {
    config: GraphConfig,
}

impl GraphProposer {
    /// A proposer with validated parameters.
    ///
    /// # Errors
    /// As [`GraphConfig::validate`].
    pub fn new(config: GraphConfig) -> Result<Self, BackendError> {
        config.validate()?;
        Ok(Self { config })
    }

    /// The parameters.
    pub fn config(&self) -> &GraphConfig {
        &self.config
    }

    /// The full partition of `image`, before the `max_regions` cap.
    pub fn segment(&self, image: &RgbImage) -> Segmentation {
        let (width, height) = (image.width(), image.height());
        let f = self.config.downscale;
        if f <= 1 {
            return segment_planes(planes_of(image), width, height, &self.config, 1);
        }
        let (small_w, small_h) = (width.div_ceil(f), height.div_ceil(f));
        let small = box_downscale(image, f, small_w, small_h);
        let coarse = segment_planes(small, small_w, small_h, &self.config, f);
        // Copy each block's label to its pixels, then renumber in full-resolution scan order
        // (the block order differs), so that the numbering rule of `Segmentation` holds.
        let mut labels = Vec::with_capacity(width as usize * height as usize);
        for v in 0..height {
            let row = (v / f) as usize * small_w as usize;
            labels.extend((0..width).map(|u| {
                coarse
                    .labels
                    .get(row + (u / f) as usize)
                    .copied()
                    .unwrap_or(0)
            }));
        }
        let count = renumber(&mut labels, coarse.count);
        Segmentation {
            width,
            height,
            labels,
            count,
        }
    }
}

impl RegionProposer for GraphProposer {
    fn name(&self) -> &'static str {
        NAME
    }

    fn propose(&self, image: &RgbImage) -> vlem_core::Result<Vec<Region>> {
        Ok(regions_of(&self.segment(image), self.config.max_regions))
    }
}

/// The regions of a segmentation, largest first (ties: the segment whose first pixel comes
/// first), at most `max_regions` of them (0: all), each with its tight bounding box and mask.
pub fn regions_of(segmentation: &Segmentation, max_regions: usize) -> Vec<Region> {
    let width = segmentation.width as usize;
    let mut boxes: Vec<SegmentBox> = vec![SegmentBox::EMPTY; segmentation.count];
    for (v, row) in segmentation.labels.chunks_exact(width.max(1)).enumerate() {
        for (u, &label) in row.iter().enumerate() {
            if let Some(b) = boxes.get_mut(label as usize) {
                b.add(u as u32, v as u32);
            }
        }
    }
    let mut order: Vec<usize> = (0..boxes.len()).filter(|&s| boxes[s].area > 0).collect();
    order.sort_by_key(|&s| std::cmp::Reverse(boxes[s].area));
    if max_regions > 0 {
        order.truncate(max_regions);
    }
    // Slot of each kept segment in the output, so one pass over the labels fills every mask.
    let mut slot = vec![usize::MAX; boxes.len()];
    let mut regions: Vec<Region> = Vec::with_capacity(order.len());
    for (n, &s) in order.iter().enumerate() {
        slot[s] = n;
        let bbox = boxes[s].rect();
        regions.push(Region {
            mask: vec![false; bbox.width as usize * bbox.height as usize],
            bbox,
        });
    }
    for (v, row) in segmentation.labels.chunks_exact(width.max(1)).enumerate() {
        for (u, &label) in row.iter().enumerate() {
            let Some(region) = slot.get(label as usize).and_then(|&n| regions.get_mut(n)) else {
                continue;
            };
            let b = region.bbox;
            // Inside the box: the boxes were grown from these very pixels.
            let at = (v - b.y as usize) * b.width as usize + (u - b.x as usize);
            if let Some(m) = region.mask.get_mut(at) {
                *m = true;
            }
        }
    }
    regions
}

/// Bounding box and pixel count of one segment, grown pixel by pixel.
#[derive(Clone, Copy)]
struct SegmentBox {
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    area: usize,
}

impl SegmentBox {
    const EMPTY: Self = Self {
        x0: u32::MAX,
        y0: u32::MAX,
        x1: 0,
        y1: 0,
        area: 0,
    };

    fn add(&mut self, u: u32, v: u32) {
        self.x0 = self.x0.min(u);
        self.y0 = self.y0.min(v);
        self.x1 = self.x1.max(u);
        self.y1 = self.y1.max(v);
        self.area += 1;
    }

    /// The box; only called on a box with at least one pixel.
    fn rect(&self) -> PixelRect {
        PixelRect {
            x: self.x0,
            y: self.y0,
            width: self.x1 - self.x0 + 1,
            height: self.y1 - self.y0 + 1,
        }
    }
}

/// The image as three row-major `f32` planes on a 0–255 scale.
fn planes_of(image: &RgbImage) -> [Vec<f32>; 3] {
    let raw = image.as_raw();
    [0, 1, 2].map(|c| {
        raw.iter()
            .skip(c)
            .step_by(3)
            .map(|&x| f32::from(x))
            .collect()
    })
}

/// The image averaged over `f × f` blocks (partial blocks at the right and bottom edges average
/// the pixels they have), as three planes of `small_w × small_h`.
fn box_downscale(image: &RgbImage, f: u32, small_w: u32, small_h: u32) -> [Vec<f32>; 3] {
    let n = small_w as usize * small_h as usize;
    let mut sums = [vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]];
    let mut counts = vec![0u32; n];
    let row_bytes = (image.width() as usize * 3).max(1);
    for (v, row) in image.as_raw().chunks_exact(row_bytes).enumerate() {
        let small_row = v / f as usize * small_w as usize;
        for (u, rgb) in row.chunks_exact(3).enumerate() {
            let s = small_row + u / f as usize;
            for (plane, &c) in sums.iter_mut().zip(rgb) {
                if let Some(x) = plane.get_mut(s) {
                    *x += f32::from(c);
                }
            }
            if let Some(count) = counts.get_mut(s) {
                *count += 1;
            }
        }
    }
    for plane in &mut sums {
        for (x, &count) in plane.iter_mut().zip(&counts) {
            *x /= count.max(1) as f32;
        }
    }
    sums
}

/// Felzenszwalb-Huttenlocher on three planes of `width × height`, with the parameters scaled for
/// an image downscaled by `f`.
fn segment_planes(
    planes: [Vec<f32>; 3],
    width: u32,
    height: u32,
    config: &GraphConfig,
    f: u32,
) -> Segmentation {
    let (w, h) = (width as usize, height as usize);
    let n = w * h;
    let scale = f as f32;
    let sigma = config.sigma / scale;
    let k = config.k / (scale * scale);
    let min_size = (config.min_size as f32 / (scale * scale)).round() as u32;
    let smooth = planes.map(|p| gaussian_blur(p, w, h, sigma));
    let edges = SortedEdges::new(&smooth, w, h);
    drop(smooth);

    let mut sets = DisjointSets::new(n, k);
    // Edges that joined two components without merging them: the only candidates of the
    // min_size pass (an edge inside a component stays inside, components only grow).
    let mut unmerged = Vec::new();
    for (key, run) in edges.runs() {
        let weight = f32::from(key) / WEIGHT_STEPS;
        for &e in run {
            let (a, b) = endpoints(e, w);
            let (ra, rb) = (sets.find(a), sets.find(b));
            if ra == rb {
                continue;
            }
            if weight <= sets.threshold(ra) && weight <= sets.threshold(rb) {
                let root = sets.union(ra, rb);
                sets.set_threshold(root, weight + k / sets.size(root) as f32);
            } else if min_size > 1 {
                unmerged.push(e);
            }
        }
    }
    for e in unmerged {
        let (a, b) = endpoints(e, w);
        let (ra, rb) = (sets.find(a), sets.find(b));
        if ra != rb && (sets.size(ra) < min_size || sets.size(rb) < min_size) {
            sets.union(ra, rb);
        }
    }
    let mut labels: Vec<u32> = (0..n).map(|i| sets.find(i) as u32).collect();
    let count = renumber(&mut labels, n);
    Segmentation {
        width,
        height,
        labels,
        count,
    }
}

/// Relabels `labels` (values below `bound`) to `0..count` in order of first appearance; returns
/// `count`.
fn renumber(labels: &mut [u32], bound: usize) -> usize {
    let mut map = vec![u32::MAX; bound];
    let mut count = 0u32;
    for label in labels.iter_mut() {
        if let Some(m) = map.get_mut(*label as usize) {
            if *m == u32::MAX {
                *m = count;
                count += 1;
            }
            *label = *m;
        }
    }
    count as usize
}

/// The two pixels of edge `e` in an image of width `w`. Edge `4 i + d` joins pixel `i` to its
/// neighbour in direction `d`: 0 right, 1 down, 2 down-right, 3 up-right, which covers the
/// 8-neighbourhood once. Only edges inside the image are ever listed.
#[inline]
fn endpoints(e: u32, w: usize) -> (usize, usize) {
    let i = (e >> 2) as usize;
    let j = match e & 3 {
        0 => i + 1,
        1 => i + w,
        2 => i + w + 1,
        _ => (i + 1).wrapping_sub(w),
    };
    (i, j)
}

/// Largest quantised weight: 255·√3 ≈ 441.7 grey levels.
const MAX_KEY: u16 = (441.7 * WEIGHT_STEPS) as u16 + 2;

/// Marks an edge that leaves the image.
const NO_EDGE: u16 = u16::MAX;

/// The edges of the grid graph sorted by quantised weight with a counting sort, which is linear
/// where a comparison sort of ~1.2 M edges would dominate the runtime. Ties are listed by edge
/// number, so the result is deterministic.
struct SortedEdges {
    /// Edge numbers (see [`endpoints`]) by increasing weight.
    sorted: Vec<u32>,
    /// `starts[key]..starts[key + 1]` is the run of `sorted` with quantised weight `key`.
    starts: Vec<u32>,
}

impl SortedEdges {
    /// The sorted edges of the `w × h` image with smoothed channels `planes`.
    fn new(planes: &[Vec<f32>; 3], w: usize, h: usize) -> Self {
        let n = w * h;
        // keys[d * n + i]: quantised weight of edge 4 i + d, or NO_EDGE. Direction-major, so
        // each direction is one pass over shifted copies of the planes (which vectorises).
        let mut keys = vec![NO_EDGE; 4 * n];
        let shifted =
            |from: usize, to: usize| planes.each_ref().map(|p| p.get(from..to).unwrap_or(&[]));
        if n > 0 {
            let (right, rest) = keys.split_at_mut(n);
            let (down, rest) = rest.split_at_mut(n);
            let (down_right, up_right) = rest.split_at_mut(n);
            // Right: i → i + 1; down: i → i + w; down-right: i → i + w + 1; up-right (from the
            // second row on): i → i - w + 1. The pairs that wrap around a row end are marked
            // NO_EDGE below.
            weight_keys(shifted(0, n - 1), shifted(1, n), right);
            if h > 1 {
                weight_keys(shifted(0, n - w), shifted(w, n), down);
                weight_keys(shifted(0, n - w - 1), shifted(w + 1, n), down_right);
                if let Some(from_second_row) = up_right.get_mut(w..) {
                    weight_keys(shifted(w, n), shifted(1, n - w + 1), from_second_row);
                }
            }
            for keys in [right, down_right, up_right] {
                for row in keys.chunks_exact_mut(w) {
                    if let Some(last) = row.last_mut() {
                        *last = NO_EDGE;
                    }
                }
            }
            if let Some(first_row) = up_right.get_mut(..w) {
                first_row.fill(NO_EDGE);
            }
        }
        let mut histogram = vec![0u32; usize::from(MAX_KEY) + 1];
        for &key in &keys {
            if let Some(count) = histogram.get_mut(usize::from(key)) {
                *count += 1;
            }
        }
        // Exclusive prefix sums: where each key's run starts.
        let mut starts = Vec::with_capacity(histogram.len() + 1);
        let mut total = 0u32;
        for &count in &histogram {
            starts.push(total);
            total += count;
        }
        starts.push(total);
        let mut next = starts.clone();
        let mut sorted = vec![0u32; total as usize];
        // Pixel-major, so that the edges of one weight are listed by edge number: neighbouring
        // edges stay together, and the union-find pass reads memory with better locality.
        let directions: Vec<&[u16]> = keys.chunks_exact(n.max(1)).collect();
        for i in 0..n {
            for (d, direction) in directions.iter().enumerate() {
                if let Some(&key) = direction.get(i)
                    && let Some(at) = next.get_mut(usize::from(key))
                    && let Some(out) = sorted.get_mut(*at as usize)
                {
                    *out = (4 * i + d) as u32;
                    *at += 1;
                }
            }
        }
        Self { sorted, starts }
    }

    /// `(key, edges)` for every quantised weight, increasing.
    fn runs(&self) -> impl Iterator<Item = (u16, &[u32])> {
        self.starts.windows(2).enumerate().filter_map(|(key, w)| {
            let run = self.sorted.get(w[0] as usize..w[1] as usize)?;
            (!run.is_empty()).then_some((key as u16, run))
        })
    }
}

/// `out[i]` = the quantised Euclidean distance between pixel `i` of `a` and of `b` (three planes
/// each), over the shortest of the slices.
fn weight_keys(a: [&[f32]; 3], b: [&[f32]; 3], out: &mut [u16]) {
    let len = [a[0], a[1], a[2], b[0], b[1], b[2]]
        .iter()
        .fold(out.len(), |len, p| len.min(p.len()));
    let (ar, ag, ab) = (&a[0][..len], &a[1][..len], &a[2][..len]);
    let (br, bg, bb) = (&b[0][..len], &b[1][..len], &b[2][..len]);
    let out = &mut out[..len];
    for i in 0..len {
        let (dr, dg, db) = (ar[i] - br[i], ag[i] - bg[i], ab[i] - bb[i]);
        let weight = (dr * dr + dg * dg + db * db).sqrt();
        // + 0.5 and truncation: rounding without a libm call, so the loop vectorises.
        out[i] = ((weight * WEIGHT_STEPS + 0.5) as u16).min(MAX_KEY);
    }
}

/// Separable Gaussian blur of one `w × h` plane with clamped borders; `sigma` 0 (or too small to
/// matter) returns the plane unchanged.
fn gaussian_blur(plane: Vec<f32>, w: usize, h: usize, sigma: f32) -> Vec<f32> {
    if sigma < 0.01 || w == 0 || h == 0 || plane.len() != w * h {
        return plane;
    }
    let radius = (4.0 * sigma).ceil() as usize;
    let mut kernel: Vec<f32> = (0..=radius)
        .map(|x| (-0.5 * (x as f32 / sigma).powi(2)).exp())
        .collect();
    let sum = 2.0 * kernel.iter().sum::<f32>() - kernel.first().copied().unwrap_or(0.0);
    for x in &mut kernel {
        *x /= sum;
    }
    let (centre, sides) = kernel
        .split_first()
        .map_or((1.0, &[][..]), |(c, s)| (*c, s));
    // Horizontal pass over rows padded with their edge values.
    let mut tmp = Vec::with_capacity(w * h);
    let mut padded = vec![0.0f32; w + 2 * radius];
    for row in plane.chunks_exact(w) {
        let (first, last) = (row.first().copied(), row.last().copied());
        for (i, p) in padded.iter_mut().enumerate() {
            *p = if i < radius {
                first.unwrap_or(0.0)
            } else {
                row.get(i - radius).copied().or(last).unwrap_or(0.0)
            };
        }
        // Tap by tap over the whole row: straight slice arithmetic, which vectorises.
        let start = tmp.len();
        tmp.extend(padded.iter().skip(radius).take(w).map(|&x| centre * x));
        let out_row = &mut tmp[start..];
        for (t, &kt) in sides.iter().enumerate() {
            let left = padded.get(radius - 1 - t..).unwrap_or(&[]);
            let right = padded.get(radius + 1 + t..).unwrap_or(&[]);
            for ((o, &a), &b) in out_row.iter_mut().zip(left).zip(right) {
                *o += kt * (a + b);
            }
        }
    }
    // Vertical pass, whole rows at a time so that memory is read in order.
    let rows: Vec<&[f32]> = tmp.chunks_exact(w).collect();
    let mut out = Vec::with_capacity(w * h);
    for v in 0..h {
        let start = out.len();
        out.extend(rows[v].iter().map(|&x| centre * x));
        let out_row = &mut out[start..];
        for (t, &kt) in sides.iter().enumerate() {
            let up = rows[v.saturating_sub(t + 1)];
            let down = rows[(v + t + 1).min(h - 1)];
            for ((o, &a), &b) in out_row.iter_mut().zip(up).zip(down) {
                *o += kt * (a + b);
            }
        }
    }
    out
}

/// One pixel of the union-find forest: parent, set size and merge threshold together, so that a
/// `find` touches one cache line per step.
#[derive(Clone, Copy)]
struct Node {
    parent: u32,
    size: u32,
    /// `Int(C) + k / |C|`, meaningful at roots.
    threshold: f32,
}

/// Union-find over pixels with union by size and path halving.
struct DisjointSets {
    nodes: Vec<Node>,
}

impl DisjointSets {
    /// `n` singletons; a singleton's threshold is `0 + k / 1`.
    fn new(n: usize, k: f32) -> Self {
        Self {
            nodes: (0..n as u32)
                .map(|parent| Node {
                    parent,
                    size: 1,
                    threshold: k,
                })
                .collect(),
        }
    }

    #[inline]
    fn find(&mut self, mut x: usize) -> usize {
        loop {
            let Some(p) = self.nodes.get(x).map(|node| node.parent as usize) else {
                return x;
            };
            if p == x {
                return x;
            }
            let grandparent = self.nodes.get(p).map_or(p, |node| node.parent as usize);
            if let Some(node) = self.nodes.get_mut(x) {
                node.parent = grandparent as u32;
            }
            x = grandparent;
        }
    }

    /// Joins two roots; returns the new root (the larger set's, ties the first).
    fn union(&mut self, a: usize, b: usize) -> usize {
        let (big, small) = if self.size(a) >= self.size(b) {
            (a, b)
        } else {
            (b, a)
        };
        let joined = self.size(a) + self.size(b);
        if let Some(node) = self.nodes.get_mut(small) {
            node.parent = big as u32;
        }
        if let Some(node) = self.nodes.get_mut(big) {
            node.size = joined;
        }
        big
    }

    #[inline]
    fn size(&self, root: usize) -> u32 {
        self.nodes.get(root).map_or(1, |node| node.size)
    }

    #[inline]
    fn threshold(&self, root: usize) -> f32 {
        self.nodes.get(root).map_or(0.0, |node| node.threshold)
    }

    fn set_threshold(&mut self, root: usize, value: f32) {
        if let Some(node) = self.nodes.get_mut(root) {
            node.threshold = value;
        }
    }
}

/// Builds the proposer from its `[proposer]` parameters.
fn build(params: &toml::Table, _ctx: &BuildContext) -> vlem_core::Result<Box<dyn RegionProposer>> {
    let config: GraphConfig = vlem_core::parse_params(StageKind::Proposer, NAME, params)?;
    let proposer =
        GraphProposer::new(config).map_err(|e| e.into_core_for(StageKind::Proposer, NAME))?;
    Ok(Box::new(proposer))
}

vlem_core::register_proposer!(
    "graph",
    "Felzenszwalb-Huttenlocher graph-based segmentation: weight-free regions in tens of ms on a CPU",
    build
);
