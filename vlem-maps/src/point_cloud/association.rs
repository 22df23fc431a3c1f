//! Correspondences between the map's points and a frame's new points: for every map point in the
//! frame's view, the nearest new point within `max_distance`.
//!
//! Why two ways: the paper's rule is the nearest neighbour in 3D, which a k-d tree over the new
//! points answers exactly but at about 0.3 µs a query, so one frame against a 1M-point map costs
//! about 300 ms on two cores. Dense fusion systems instead *project* each map point into the new
//! frame and look only at the new points back-projected from the pixels around it ("projective
//! association"): O(1) per point with an image-sized index, about 10 ms a frame against 1M
//! points on two cores. It finds the same neighbour whenever that neighbour lies within the
//! pixel window, which on a surface seen from nearby it does (`BENCHMARKS.md`: 99.5 % of the
//! correspondences on the shared sequence); the k-d tree stays as `association = "kd-tree"`.
//!
//! The window search is exact within its window and prunes by a bound: every point back-projected
//! from a pixel lies on that pixel's ray, and the distance from a map point `q` to a ray at angle
//! `θ` from `q`'s own is at least `|q| sin θ`; with rays written as `(x, y, 1)`,
//! `|a × b| ≥ |(x_a, y_a) − (x_b, y_b)|`, so for the pixels of ring `k` (Chebyshev distance `k`
//! from the projection's pixel, hence at least `k − ½` pixels away along one axis)
//! `|q| sin θ ≥ z_q (k − ½) s / (f |b|)`, with `z_q` the depth of `q`, `s` the pixel stride, `f`
//! the larger focal length and `|b|` bounded over the window. Rings whose bound exceeds the
//! best distance so far (or `max_distance`) are skipped, so a map point on the observed surface
//! costs one or two rings.

mod wide;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use vlem_core::{Intrinsics, PinholeF32, RigidF32};

/// How a map point finds its correspondence in a new frame (`[map] association`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Association {
    /// Project the map point into the frame and take the nearest new point back-projected from
    /// the pixels within `window` integrated pixels of the projection (the default).
    #[default]
    Projective,
    /// The nearest new point in 3D from a k-d tree over the frame's points (exact, slower).
    KdTree,
}

/// No correspondence.
pub(super) const NONE: u32 = u32::MAX;

/// What the correspondence search needs of a frame: its camera, pose and new points.
pub(super) struct FrameView<'a> {
    pub intrinsics: &'a Intrinsics,
    /// World to camera.
    pub to_camera: RigidF32,
    /// The new points in world coordinates.
    pub positions: &'a [[f32; 3]],
    /// The linear pixel index `v * width + u` of each new point.
    pub pixels: &'a [u32],
    /// The pixel stride the points were taken at (the pixels are multiples of it).
    pub stride: u32,
}

impl FrameView<'_> {
    /// Writes into `out`, for every map point, the index of its nearest new point within
    /// `max_distance` ([`NONE`] for none, and for map points outside the view). `grid` is the
    /// projective association's pixel grid, kept between frames for its allocation.
    pub fn correspondences(
        &self,
        map: &[[f32; 3]],
        max_distance: f32,
        association: Association,
        window: u32,
        grid: &mut Vec<Cell>,
        out: &mut Vec<u32>,
    ) {
        out.clear();
        if self.positions.is_empty() {
            out.resize(map.len(), NONE);
            return;
        }
        let r2 = max_distance * max_distance;
        match association {
            Association::KdTree => {
                let tree: ImmutableKdTree<f32, 3> =
                    match ImmutableKdTree::new_from_slice(self.positions) {
                        Ok(tree) => tree,
                        // Only fails for an empty slice, excluded above.
                        Err(_) => {
                            out.resize(map.len(), NONE);
                            return;
                        }
                    };
                self.for_each_in_view(map, out, |q, _| {
                    let nearest = tree
                        .query(&q)
                        .nearest_one::<SquaredEuclidean<f32>>()
                        .execute();
                    if nearest.distance <= r2 {
                        nearest.item
                    } else {
                        NONE
                    }
                })
            }
            Association::Projective => {
                let grid = PixelGrid::new(self, grid);
                let projector = Projector::new(self);
                let search = ProjectiveSearch {
                    projector: &projector,
                    grid: &grid,
                    r2,
                    window,
                };
                out.resize(map.len(), NONE);
                map.par_chunks(SEARCH_CHUNK)
                    .zip(out.par_chunks_mut(SEARCH_CHUNK))
                    .for_each(|(points, found)| wide::nearest_points(&search, points, found));
            }
        }
    }

    /// Maps `find(world point, its projection)` over the map points in the view
    /// ([`Projector::project`]), [`NONE`] for the others.
    fn for_each_in_view(
        &self,
        map: &[[f32; 3]],
        out: &mut Vec<u32>,
        find: impl Fn([f32; 3], Projection) -> u32 + Sync,
    ) {
        let projector = Projector::new(self);
        map.par_iter()
            .with_min_len(SEARCH_CHUNK)
            .map(|&q| projector.project(q).map_or(NONE, |p| find(q, p)))
            .collect_into_vec(out);
    }
}

/// Map points per parallel task of the search: a few thousand, so two cores share a frame's
/// 1M points evenly at a negligible cost per task.
const SEARCH_CHUNK: usize = 4096;

/// One frame's projective search: where map points land in it, the grid of its new points, and
/// the squared radius and the window of the search.
struct ProjectiveSearch<'a, 'g> {
    projector: &'a Projector,
    grid: &'a PixelGrid<'g>,
    r2: f32,
    window: u32,
}

impl ProjectiveSearch<'_, '_> {
    /// The nearest new point to world point `q`, [`NONE`] for none and out of view.
    #[inline]
    fn nearest(&self, q: [f32; 3]) -> u32 {
        self.projector
            .project(q)
            .map_or(NONE, |p| self.grid.nearest(p, self.r2, self.window))
    }
}

/// Projects map points into a frame: its pose and camera, in `f32`.
struct Projector {
    /// World to camera.
    to_camera: RigidF32,
    k: PinholeF32,
    /// The image's size less half a pixel: a projection in view is below it.
    u_end: f32,
    v_end: f32,
}

impl Projector {
    fn new(view: &FrameView<'_>) -> Self {
        let k = view.intrinsics;
        Self {
            to_camera: view.to_camera,
            k: PinholeF32::from_intrinsics(k),
            u_end: k.width as f32 - 0.5,
            v_end: k.height as f32 - 0.5,
        }
    }

    /// Where world point `q` lands in the frame; `None` out of view. In view: in front of the
    /// camera and projecting within half a pixel of the image (points back-projected from the
    /// border pixels are in view).
    #[inline]
    fn project(&self, q: [f32; 3]) -> Option<Projection> {
        let c = self.to_camera.apply(q);
        if c[2] <= 0.0 {
            return None;
        }
        let inverse_depth = 1.0 / c[2];
        let (x, y) = (c[0] * inverse_depth, c[1] * inverse_depth);
        let (u, v) = (self.k.fx * x + self.k.cx, self.k.fy * y + self.k.cy);
        if !(u >= -0.5 && v >= -0.5 && u < self.u_end && v < self.v_end) {
            return None;
        }
        Some(Projection {
            u,
            v,
            x,
            y,
            camera: c,
        })
    }
}

/// Where a map point lands in the frame.
#[derive(Clone, Copy)]
struct Projection {
    /// Pixel coordinates.
    u: f32,
    v: f32,
    /// Normalised image coordinates `x / z`, `y / z`.
    x: f32,
    y: f32,
    /// The point in the camera frame.
    camera: [f32; 3],
}

/// One cell of the projective association's pixel grid: the camera-frame depth of the new point
/// back-projected from its pixel, which lies on the pixel's ray, and the point's index. Eight
/// bytes rather than the world point's sixteen: a profile puts most of the search's time on the
/// loads of cells, and half the bytes are half the cache lines.
#[derive(Clone, Copy, Debug)]
#[repr(C)] // `wide` gathers the depth at a cell's start and the index 4 bytes on.
pub(super) struct Cell {
    /// NaN for a pixel without a point.
    depth: f32,
    index: u32,
}

/// A candidate correspondence as one integer, squared distance in the high half and index in
/// the low: a squared distance is non-negative, so its bits order like the number, and the
/// nearer candidate is the smaller key (the lower index on a tie). A NaN distance (an empty cell)
/// has bits above every number's and never wins; starting from `Candidate::new(r2, NONE)`, a
/// point exactly `sqrt(r2)` away does.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Candidate(u64);

impl Candidate {
    #[inline]
    fn new(d2: f32, index: u32) -> Self {
        Self((u64::from(d2.to_bits()) << 32) | u64::from(index))
    }

    #[inline]
    fn distance2(self) -> f32 {
        f32::from_bits((self.0 >> 32) as u32)
    }

    #[inline]
    fn index(self) -> u32 {
        self.0 as u32
    }
}

/// The new points on the frame's stride grid: cell `(u / s, v / s)` holds the point
/// back-projected from pixel `(u, v)`, as its depth along the pixel's ray, and its index.
/// Distances are taken in the camera frame, where a rigid pose leaves them as in the world.
struct PixelGrid<'g> {
    cells: &'g [Cell],
    /// `(u - cx) / fx` of each column's pixel `u` and `(v - cy) / fy` of each row's `v`: a cell's
    /// point is `depth · (ray_x, ray_y, 1)`.
    ray_x: Vec<f32>,
    ray_y: Vec<f32>,
    columns: usize,
    rows: usize,
    stride: f32,
    inverse_stride: f32,
    /// `1 / fx`, `1 / fy` and the larger focal length, for the pruning bound.
    inverse_fx: f32,
    inverse_fy: f32,
    focal: f32,
}

impl<'g> PixelGrid<'g> {
    /// The grid of `view`'s points, in `cells` (resized, its allocation reused).
    fn new(view: &FrameView<'_>, cells: &'g mut Vec<Cell>) -> Self {
        let k = view.intrinsics;
        let stride = view.stride.max(1);
        let columns = k.width.div_ceil(stride) as usize;
        let rows = k.height.div_ceil(stride) as usize;
        let empty = Cell {
            depth: f32::NAN,
            index: NONE,
        };
        cells.clear();
        cells.resize(columns * rows, empty);
        for (i, (p, &pixel)) in view.positions.iter().zip(view.pixels).enumerate() {
            let cell = if stride == 1 {
                pixel as usize
            } else {
                let (u, v) = (pixel % k.width, pixel / k.width);
                (v / stride) as usize * columns + (u / stride) as usize
            };
            if let Some(slot) = cells.get_mut(cell) {
                *slot = Cell {
                    depth: view.to_camera.apply(*p)[2],
                    index: i as u32,
                };
            }
        }
        let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
        Self {
            cells: &cells[..],
            ray_x: (0..columns)
                .map(|c| ((c as u32 * stride) as f32 - cx) / fx)
                .collect(),
            ray_y: (0..rows)
                .map(|r| ((r as u32 * stride) as f32 - cy) / fy)
                .collect(),
            columns,
            rows,
            stride: stride as f32,
            inverse_stride: 1.0 / stride as f32,
            inverse_fx: 1.0 / k.fx as f32,
            inverse_fy: 1.0 / k.fy as f32,
            focal: k.fx.max(k.fy) as f32,
        }
    }

    /// The index of the nearest point to `q` within `sqrt(r2)` among the cells within `window`
    /// of the projection's cell, [`NONE`] for none.
    ///
    /// The best candidate so far is one [`Candidate`] key, so taking a nearer one is an integer
    /// minimum the compiler turns into conditional moves: with branches on `d2 <= best`, which
    /// of the nine cells around the projection is nearest is a coin toss the branch predictor
    /// lost about as often as it won. On one core, the 1M points of the fusion bench took 47 ms
    /// with branches and take 30 ms this way.
    #[inline]
    fn nearest(&self, p: Projection, r2: f32, window: u32) -> u32 {
        let (gu, gv) = self.cell_of(&p);
        let mut nearest = Candidate::new(r2, NONE);
        if window == 0 {
            self.visit(gu, gv, p.camera, &mut nearest);
            return nearest.index();
        }
        // Rings 0 and 1 are searched for nearly every point (ring 1's bound is half a pixel's
        // footprint, below any depth noise), so away from the border they are one pass over the
        // 3x3 block.
        let first_ring = if self.is_interior(gu, gv) {
            self.block3(gu as usize, gv as usize, p.camera, &mut nearest);
            2
        } else {
            self.visit(gu, gv, p.camera, &mut nearest);
            1
        };
        self.outer_rings(&p, (gu, gv), first_ring, window, nearest)
            .index()
    }

    /// The cell nearest to the projection `p`, clamped to the grid.
    #[inline]
    fn cell_of(&self, p: &Projection) -> (i64, i64) {
        // `+ 0.5` then truncation rounds the non-negative values exactly like `round` (a
        // projection in view is at least -0.5 pixels), without a libm call.
        let gu = (p.u * self.inverse_stride + 0.5) as i64;
        let gv = (p.v * self.inverse_stride + 0.5) as i64;
        (
            gu.clamp(0, self.columns as i64 - 1),
            gv.clamp(0, self.rows as i64 - 1),
        )
    }

    /// Whether the 3x3 block around cell `(gu, gv)` lies inside the grid.
    #[inline]
    fn is_interior(&self, gu: i64, gv: i64) -> bool {
        (1..self.columns as i64 - 1).contains(&gu) && (1..self.rows as i64 - 1).contains(&gv)
    }

    /// Takes the point of cell `(cu, cv)`, inside the grid, if nearer than `nearest`.
    #[inline]
    fn visit(&self, cu: i64, cv: i64, c: [f32; 3], nearest: &mut Candidate) {
        let (cu, cv) = (cu as usize, cv as usize);
        let cell = self.cells[cv * self.columns + cu];
        let d2 = self.distance2(cell.depth, cu, cv, c);
        *nearest = (*nearest).min(Candidate::new(d2, cell.index));
    }

    /// Searches rings `first_ring..=window` around cell `(gu, gv)` for a point nearer than
    /// `nearest`, from the nearest ring out, until a ring's bound rules out the rest.
    fn outer_rings(
        &self,
        p: &Projection,
        (gu, gv): (i64, i64),
        first_ring: i64,
        window: u32,
        mut nearest: Candidate,
    ) -> Candidate {
        let (columns, rows) = (self.columns as i64, self.rows as i64);
        let per_ring = self.per_ring(p, window);
        for k in first_ring..=i64::from(window) {
            let bound = (k as f32 - 0.5) * per_ring;
            if bound * bound > nearest.distance2() {
                break;
            }
            let (u0, u1) = ((gu - k).max(0), (gu + k).min(columns - 1));
            let (v0, v1) = ((gv - k).max(0), (gv + k).min(rows - 1));
            for cv in [gv - k, gv + k] {
                if (0..rows).contains(&cv) {
                    for cu in u0..=u1 {
                        self.visit(cu, cv, p.camera, &mut nearest);
                    }
                }
            }
            for cu in [gu - k, gu + k] {
                if (0..columns).contains(&cu) {
                    for cv in (gv - k + 1).max(v0)..=(gv + k - 1).min(v1) {
                        self.visit(cu, cv, p.camera, &mut nearest);
                    }
                }
            }
        }
        nearest
    }

    /// How much the distance bound grows per ring of the window around projection `p`:
    /// `z_q s / (f |b|)` of the module docs, with `|b|` the largest ray `(x, y, 1)` of a cell
    /// within `window`.
    #[inline]
    fn per_ring(&self, p: &Projection, window: u32) -> f32 {
        let reach = window as f32 * self.stride;
        let bx = p.x.abs() + reach * self.inverse_fx;
        let by = p.y.abs() + reach * self.inverse_fy;
        p.camera[2] * self.stride / (self.focal * (1.0 + bx * bx + by * by).sqrt())
    }

    /// Rings 0 and 1 around the interior cell `(gu, gv)`: the nearest of the nine cells' points
    /// to camera-frame point `c`, if nearer than `nearest`.
    #[inline]
    fn block3(&self, gu: usize, gv: usize, c: [f32; 3], nearest: &mut Candidate) {
        let Some(ray_x) = self.ray_x.get(gu - 1..gu + 2) else {
            return;
        };
        for cv in gv - 1..=gv + 1 {
            let start = cv * self.columns + gu - 1;
            let (Some(cells), Some(&ray_y)) =
                (self.cells.get(start..start + 3), self.ray_y.get(cv))
            else {
                return;
            };
            for (cell, &ray_x) in cells.iter().zip(ray_x) {
                let d2 = ray_distance2(cell.depth, ray_x, ray_y, c);
                *nearest = (*nearest).min(Candidate::new(d2, cell.index));
            }
        }
    }

    /// The squared distance from camera-frame point `c` to the point at `depth` on the ray of
    /// cell `(cu, cv)`; NaN for a NaN depth.
    #[inline]
    fn distance2(&self, depth: f32, cu: usize, cv: usize, c: [f32; 3]) -> f32 {
        ray_distance2(depth, self.ray_x[cu], self.ray_y[cv], c)
    }
}

/// The squared distance from camera-frame point `c` to the point at `depth` on the ray
/// `(ray_x, ray_y, 1)`; NaN for a NaN depth.
#[inline]
fn ray_distance2(depth: f32, ray_x: f32, ray_y: f32, c: [f32; 3]) -> f32 {
    let d = [depth * ray_x - c[0], depth * ray_y - c[1], depth - c[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The nearest point within `sqrt(r2)` among the cells within Chebyshev distance `window` of
    /// the projection's cell, by looking at every one of them.
    fn brute_force(grid: &PixelGrid<'_>, p: Projection, r2: f32, window: i64) -> u32 {
        let gu = ((p.u * grid.inverse_stride + 0.5) as i64).clamp(0, grid.columns as i64 - 1);
        let gv = ((p.v * grid.inverse_stride + 0.5) as i64).clamp(0, grid.rows as i64 - 1);
        let (mut best, mut found) = (r2, NONE);
        for cv in (gv - window).max(0)..=(gv + window).min(grid.rows as i64 - 1) {
            for cu in (gu - window).max(0)..=(gu + window).min(grid.columns as i64 - 1) {
                let (cu, cv) = (cu as usize, cv as usize);
                let cell = grid.cells[cv * grid.columns + cu];
                let d2 = grid.distance2(cell.depth, cu, cv, p.camera);
                if d2 < best {
                    (best, found) = (d2, cell.index);
                }
            }
        }
        found
    }

    /// A rough surface seen by `intrinsics` from the camera pose `from_camera`: the world points
    /// of the pixels on the `stride` grid, a tenth of them left without depth, and their pixels.
    pub(super) fn rough_surface(
        rng: &mut impl Rng,
        intrinsics: &Intrinsics,
        stride: u32,
        from_camera: &RigidF32,
    ) -> (Vec<[f32; 3]>, Vec<u32>) {
        let k = intrinsics;
        let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
        let (mut positions, mut pixels) = (Vec::new(), Vec::new());
        for v in (0..k.height).step_by(stride as usize) {
            for u in (0..k.width).step_by(stride as usize) {
                if rng.random_bool(0.1) {
                    continue;
                }
                let z = 1.0 + 0.3 * (u as f32 * 0.2).sin() + rng.random_range(0.0..0.05);
                let x = (u as f32 - cx) * z / fx;
                let y = (v as f32 - cy) * z / fy;
                positions.push(from_camera.apply([x, y, z]));
                pixels.push(v * k.width + u);
            }
        }
        (positions, pixels)
    }

    #[test]
    fn the_pruned_window_search_finds_the_nearest_point_in_the_window() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let identity = RigidF32::from_pose(&vlem_core::Pose::identity());
        for stride in [1u32, 2, 3] {
            let intrinsics = Intrinsics {
                width: 64,
                height: 48,
                fx: 52.5,
                fy: 52.0,
                cx: 31.5,
                cy: 23.5,
            };
            let (positions, pixels) = rough_surface(&mut rng, &intrinsics, stride, &identity);
            let view = FrameView {
                intrinsics: &intrinsics,
                to_camera: identity,
                positions: &positions,
                pixels: &pixels,
                stride,
            };
            let mut cells = Vec::new();
            let grid = PixelGrid::new(&view, &mut cells);
            // Map points near the surface (most of them) and anywhere in the view.
            let map: Vec<[f32; 3]> = (0..4000)
                .map(|i| {
                    let p = positions[rng.random_range(0..positions.len())];
                    let jitter = if i % 4 == 0 { 0.2 } else { 0.02 };
                    p.map(|x| x + rng.random_range(-jitter..jitter))
                })
                .collect();
            for window in [0u32, 1, 3] {
                for max_distance in [0.01f32, 0.05, 0.3] {
                    let r2 = max_distance * max_distance;
                    let mut out = Vec::new();
                    view.for_each_in_view(&map, &mut out, |_, p| grid.nearest(p, r2, window));
                    let mut expected = Vec::new();
                    view.for_each_in_view(&map, &mut expected, |_, p| {
                        brute_force(&grid, p, r2, i64::from(window))
                    });
                    // The distance the search compares, to new point `i`.
                    let distance = |i: u32, q: &[f32; 3]| {
                        (i != NONE).then(|| {
                            let pixel = pixels[i as usize];
                            let (cu, cv) = (
                                (pixel % 64 / stride) as usize,
                                (pixel / 64 / stride) as usize,
                            );
                            let depth = grid.cells[cv * grid.columns + cu].depth;
                            grid.distance2(depth, cu, cv, view.to_camera.apply(*q))
                        })
                    };
                    for ((a, b), q) in out.iter().zip(&expected).zip(&map) {
                        // Equal distances may pick different points; the distances must agree.
                        assert_eq!(
                            distance(*a, q),
                            distance(*b, q),
                            "stride {stride}, window {window}, max distance {max_distance}"
                        );
                    }
                    assert!(expected.iter().any(|m| *m != NONE));
                }
            }
        }
    }
}
