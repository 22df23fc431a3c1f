//! Ray casting one view of the synthetic scene: nearest analytic hit per pixel, its depth, shaded
//! colour, label and instance, and the optional Kinect-like depth noise.
//!
//! Rows are rendered in parallel; each pixel depends only on the scene, the pose and (for noise)
//! the seed, frame and pixel index, so the result is the same for any number of threads.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use vlem_core::{DepthImage, Pose, RgbImage};

use super::geometry::{T_MIN, to_local};
use super::layout::{CEILING, FLOOR, Layout, Part};
use super::rng::{gaussian, hash, unit};
use super::texture::{shade, to_rgb8};
use super::{SyntheticNoise, SyntheticScene, SyntheticView};
use crate::error::{DatasetError, Result};

/// What a ray hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Surface {
    /// A room surface (see [`super::layout::FLOOR`] etc.).
    Room(usize),
    /// A part of a piece (index into the layout's parts).
    Part(usize),
}

/// The nearest hit of a ray.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit {
    pub(crate) t: f64,
    pub(crate) normal: Vector3<f64>,
    pub(crate) surface: Surface,
}

/// Where the ray `o + t d` from inside the room leaves it, and through which surface.
#[inline]
pub(crate) fn room_exit(layout: &Layout, o: &Vector3<f64>, d: &Vector3<f64>) -> Hit {
    // Per axis: distance to the wall the ray heads for, that wall's face, and its inward normal.
    let axis = |d: f64, o: f64, lo: f64, hi: f64, low_face: usize, high_face: usize| {
        if d > 0.0 {
            ((hi - o) / d, high_face, -1.0)
        } else if d < 0.0 {
            ((lo - o) / d, low_face, 1.0)
        } else {
            (f64::INFINITY, low_face, 1.0)
        }
    };
    let (min, max) = (&layout.min, &layout.max);
    let x = axis(d.x, o.x, min.x, max.x, 2, 3);
    let y = axis(d.y, o.y, min.y, max.y, 4, 5);
    let z = axis(d.z, o.z, min.z, max.z, FLOOR, CEILING);
    let (t, face, normal) = if x.0 <= y.0 && x.0 <= z.0 {
        (x.0, x.1, Vector3::new(x.2, 0.0, 0.0))
    } else if y.0 <= z.0 {
        (y.0, y.1, Vector3::new(0.0, y.2, 0.0))
    } else {
        (z.0, z.1, Vector3::new(0.0, 0.0, z.2))
    };
    Hit {
        t,
        normal,
        surface: Surface::Room(face),
    }
}

/// Tile edge in pixels.
const TILE: i32 = 16;

/// How far outside a projected hull (pixels) a pixel centre still gets tested, for rounding.
const HULL_MARGIN: f64 = 0.01;

/// Hulls are clipped to camera-frame depth `z ≥ NEAR` (metres) before projection.
const NEAR: f64 = 1e-3;

/// Most hull edges kept; a hull with more is culled by its rectangle only.
const MAX_EDGES: usize = 16;

/// A part that may show in the view: its inclusive pixel rectangle, projected hull and smallest
/// camera-frame depth.
#[derive(Clone, Debug)]
struct Candidate {
    part: usize,
    u0: i32,
    u1: i32,
    v0: i32,
    v1: i32,
    z_min: f64,
    /// The camera centre relative to the part (see `Shape::relative_origin`).
    rel: Vector3<f64>,
    /// Edge lines `a u + b v + c ≥ 0` of the projected convex hull (unit normals, so values are
    /// pixels); empty when the hull is degenerate or too complex.
    edges: Vec<[f64; 3]>,
}

impl Candidate {
    /// The candidate for `part` seen with intrinsics `k`, world-to-camera rotation `rt` and camera
    /// centre `o`; `None` when it lies wholly behind the camera or outside the image.
    fn new(
        index: usize,
        part: &Part,
        k: &vlem_core::Intrinsics,
        rt: &Matrix3<f64>,
        o: &Vector3<f64>,
    ) -> Option<Self> {
        let corners = part.shape.hull().map(|c| rt * (c - o));
        // The hull clipped to z ≥ NEAR: corners in front, plus where its edges cross z = NEAR
        // (corner index bits 1, 2, 4 select the x, y, z side, so edges join indices differing
        // in one bit).
        let mut points: Vec<Vector3<f64>> =
            corners.iter().filter(|c| c.z >= NEAR).copied().collect();
        if points.is_empty() {
            return None;
        }
        for i in 0..8 {
            for bit in [1, 2, 4] {
                let j = i | bit;
                if i & bit != 0 {
                    continue;
                }
                let (a, b) = (corners[i], corners[j]);
                if (a.z < NEAR) != (b.z < NEAR) {
                    let t = (NEAR - a.z) / (b.z - a.z);
                    points.push(a + (b - a) * t);
                }
            }
        }
        let (w, h) = (k.width as i32, k.height as i32);
        let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        let mut z_min = f64::INFINITY;
        let projected: Vec<(f64, f64)> = points
            .iter()
            .map(|c| {
                let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                u0 = u0.min(u);
                u1 = u1.max(u);
                v0 = v0.min(v);
                v1 = v1.max(v);
                // Depth is linear, so the clipped hull's nearest depth is at one of its points.
                z_min = z_min.min(c.z);
                (u, v)
            })
            .collect();
        // Clamp before converting, so far-off projections cannot overflow.
        let clamp = |x: f64, hi: i32| x.clamp(-2.0, f64::from(hi) + 2.0) as i32;
        let candidate = Self {
            part: index,
            u0: (clamp(u0, w) - 1).max(0),
            u1: (clamp(u1, w) + 1).min(w - 1),
            v0: (clamp(v0, h) - 1).max(0),
            v1: (clamp(v1, h) + 1).min(h - 1),
            z_min,
            rel: part.shape.relative_origin(o),
            edges: hull_edges(projected),
        };
        (candidate.u0 <= candidate.u1 && candidate.v0 <= candidate.v1).then_some(candidate)
    }

    /// Whether the point `(u, v)` may lie inside the projected hull (with a margin for rounding).
    #[inline]
    fn may_cover(&self, u: f64, v: f64) -> bool {
        self.edges
            .iter()
            .all(|e| e[0] * u + e[1] * v + e[2] >= -HULL_MARGIN)
    }

    /// Whether the pixel rectangle `[u0, u1] × [v0, v1]` lies wholly outside one hull edge.
    fn misses_rect(&self, u0: f64, v0: f64, u1: f64, v1: f64) -> bool {
        self.edges.iter().any(|e| {
            [(u0, v0), (u1, v0), (u0, v1), (u1, v1)]
                .iter()
                .all(|&(u, v)| e[0] * u + e[1] * v + e[2] < -HULL_MARGIN)
        })
    }
}

/// The edges of the convex hull of `points` as unit-normal lines `a u + b v + c ≥ 0` inside; none
/// for a degenerate hull or one with more than [`MAX_EDGES`] edges.
fn hull_edges(mut points: Vec<(f64, f64)>) -> Vec<[f64; 3]> {
    points.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1)));
    let cross = |o: (f64, f64), a: (f64, f64), b: (f64, f64)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    // Andrew's monotone chain: lower hull, then upper hull (counter-clockwise in u-right, v-up
    // terms; the inside is on the left of each edge either way round, see below).
    let mut hull: Vec<(f64, f64)> = Vec::with_capacity(2 * points.len());
    for pass in 0..2 {
        let start = hull.len();
        let mut push = |p: (f64, f64)| {
            while hull.len() >= start + 2 {
                let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
                if cross(a, b, p) > 0.0 {
                    break;
                }
                hull.pop();
            }
            hull.push(p);
        };
        if pass == 0 {
            points.iter().for_each(|&p| push(p));
        } else {
            points.iter().rev().for_each(|&p| push(p));
        }
        hull.pop();
    }
    if hull.len() < 3 || hull.len() > MAX_EDGES {
        return Vec::new();
    }
    let mut edges = Vec::with_capacity(hull.len());
    for (i, &p) in hull.iter().enumerate() {
        let q = hull[(i + 1) % hull.len()];
        let (du, dv) = (q.0 - p.0, q.1 - p.1);
        let length = (du * du + dv * dv).sqrt();
        if length < 1e-9 {
            return Vec::new();
        }
        // The chain turns left at every vertex, so the inside is where cross(q - p, x - p) ≥ 0.
        let (a, b) = (-dv / length, du / length);
        edges.push([a, b, -(a * p.0 + b * p.1)]);
    }
    edges
}

/// The parts that may show in a view, and per image tile the ones whose hull overlaps it,
/// nearest first.
struct Tiles {
    columns: usize,
    candidates: Vec<Candidate>,
    lists: Vec<Vec<u32>>,
}

impl Tiles {
    /// The tiles of a view with camera intrinsics `k`, world-to-camera rotation `rt` and camera
    /// centre `o`.
    fn new(
        layout: &Layout,
        k: &vlem_core::Intrinsics,
        rt: &Matrix3<f64>,
        o: &Vector3<f64>,
    ) -> Self {
        let (w, h) = (k.width as i32, k.height as i32);
        let columns = (w + TILE - 1) / TILE;
        let rows = (h + TILE - 1) / TILE;
        let mut candidates: Vec<Candidate> = layout
            .parts
            .iter()
            .enumerate()
            .filter_map(|(i, part)| Candidate::new(i, part, k, rt, o))
            .collect();
        candidates.sort_by(|a, b| a.z_min.total_cmp(&b.z_min));
        let mut lists = vec![Vec::new(); (columns * rows) as usize];
        for (index, c) in candidates.iter().enumerate() {
            for ty in c.v0 / TILE..=c.v1 / TILE {
                for tx in c.u0 / TILE..=c.u1 / TILE {
                    let (u0, v0) = (f64::from(tx * TILE), f64::from(ty * TILE));
                    let (u1, v1) = (u0 + f64::from(TILE - 1), v0 + f64::from(TILE - 1));
                    if !c.misses_rect(u0, v0, u1, v1) {
                        lists[(ty * columns + tx) as usize].push(index as u32);
                    }
                }
            }
        }
        Self {
            columns: columns as usize,
            candidates,
            lists,
        }
    }

    /// The nearest hit of the ray `o + t d` through pixel `(u, v)`.
    #[inline]
    fn cast(&self, layout: &Layout, o: &Vector3<f64>, d: &Vector3<f64>, u: i32, v: i32) -> Hit {
        let mut best = room_exit(layout, o, d);
        let tile = (v / TILE) as usize * self.columns + (u / TILE) as usize;
        let (uf, vf) = (f64::from(u), f64::from(v));
        for &index in self.lists.get(tile).map_or(&[][..], |l| &l[..]) {
            let Some(c) = self.candidates.get(index as usize) else {
                continue;
            };
            // `t` is the camera-frame depth, so nothing in this part can be nearer than `z_min`.
            if c.z_min >= best.t {
                break;
            }
            if u < c.u0 || u > c.u1 || v < c.v0 || v > c.v1 || !c.may_cover(uf, vf) {
                continue;
            }
            let part = &layout.parts[c.part];
            if let Some(e) = part.shape.entry_relative(&c.rel, d, best.t) {
                best = Hit {
                    t: e.t,
                    normal: e.normal,
                    surface: Surface::Part(c.part),
                };
            }
        }
        best
    }
}

/// Pixels per instance id (index = instance) seen over `poses` with camera `k`, without
/// shading: how much of each piece a camera path shows.
pub(crate) fn coverage(layout: &Layout, k: &vlem_core::Intrinsics, poses: &[Pose]) -> Vec<usize> {
    let instances = layout.objects.len() + 1;
    poses
        .par_iter()
        .map(|pose| {
            let mut counts = vec![0usize; instances];
            let r: Matrix3<f64> = *pose.rotation.to_rotation_matrix().matrix();
            let o = pose.translation.vector;
            let tiles = Tiles::new(layout, k, &r.transpose(), &o);
            for v in 0..k.height {
                for u in 0..k.width {
                    let d = r * Vector3::new(
                        (f64::from(u) - k.cx) / k.fx,
                        (f64::from(v) - k.cy) / k.fy,
                        1.0,
                    );
                    let instance = match tiles.cast(layout, &o, &d, u as i32, v as i32).surface {
                        Surface::Room(face) => Layout::surface_instance(face),
                        Surface::Part(p) => layout.parts[p].instance,
                    };
                    if let Some(count) = counts.get_mut(usize::from(instance)) {
                        *count += 1;
                    }
                }
            }
            counts
        })
        .reduce(
            || vec![0usize; instances],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                a
            },
        )
}

impl SyntheticScene {
    /// Colour, label and instance of the surface point `p` with outward normal `n`.
    pub(crate) fn surface_look(
        &self,
        surface: Surface,
        p: &Vector3<f64>,
        n: &Vector3<f64>,
    ) -> ([u8; 3], u16, u16) {
        let layout = &self.layout;
        match surface {
            Surface::Room(face) => {
                let albedo = layout.surfaces[face].albedo(&self.noise, p, n);
                (
                    to_rgb8(albedo, shade(n)),
                    Layout::surface_label(face),
                    Layout::surface_instance(face),
                )
            }
            Surface::Part(i) => {
                let part = &layout.parts[i];
                let pl = to_local(&(p - part.origin), part.cos, part.sin);
                let nl = to_local(n, part.cos, part.sin);
                let albedo = part.material.albedo(&self.noise, &pl, &nl);
                (to_rgb8(albedo, shade(n)), part.label, part.instance)
            }
        }
    }

    /// Renders the view from `pose`; `index` keys the depth noise.
    pub(crate) fn render_view(&self, index: usize, pose: &Pose) -> Result<SyntheticView> {
        let k = self.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let r: Matrix3<f64> = *pose.rotation.to_rotation_matrix().matrix();
        let o = pose.translation.vector;
        let rt = r.transpose();
        let tiles = Tiles::new(&self.layout, &k, &rt, &o);
        let mut colour = vec![0u8; w * h * 3];
        let mut depth = vec![0f32; w * h];
        let mut labels = vec![0u16; w * h];
        let mut instances = vec![0u16; w * h];
        let noise_model = self.config.noise;
        let seed = self.config.seed;
        colour
            .par_chunks_mut(w * 3)
            .zip(depth.par_chunks_mut(w))
            .zip(labels.par_chunks_mut(w))
            .zip(instances.par_chunks_mut(w))
            .enumerate()
            .for_each(|(v, (((rgb_row, depth_row), label_row), instance_row))| {
                let vi = v as i32;
                let y = (v as f64 - k.cy) / k.fy;
                for u in 0..w {
                    let x = (u as f64 - k.cx) / k.fx;
                    // Camera-frame direction with z = 1, so the ray parameter is the depth.
                    let d = r * Vector3::new(x, y, 1.0);
                    let hit = tiles.cast(&self.layout, &o, &d, u as i32, vi);
                    let p = o + d * hit.t;
                    let (rgb, label, instance) = self.surface_look(hit.surface, &p, &hit.normal);
                    rgb_row[3 * u..3 * u + 3].copy_from_slice(&rgb);
                    label_row[u] = label;
                    instance_row[u] = instance;
                    depth_row[u] = match noise_model {
                        SyntheticNoise::None => hit.t as f32,
                        SyntheticNoise::Kinect => {
                            let cos = hit.normal.dot(&d).abs() / d.norm();
                            let key = hash(&[seed, index as u64, (v * w + u) as u64]);
                            kinect_depth(hit.t, cos, key)
                        }
                    };
                }
            });
        // The buffers have exactly the sizes the constructors check.
        let internal = |e: vlem_core::CoreError| DatasetError::Synthetic {
            message: e.to_string(),
        };
        Ok(SyntheticView {
            index,
            colour: RgbImage::new(k.width, k.height, colour).map_err(internal)?,
            depth: DepthImage::new(k.width, k.height, depth).map_err(internal)?,
            labels,
            instances,
            pose: *pose,
            intrinsics: k,
        })
    }
}

/// Kinect (v1)-like product of baseline and focal length, in metre-pixels: disparity = `FB / z`.
const KINECT_FB: f64 = 0.075 * 580.0;

/// The measured depth for true depth `z` seen at incidence cosine `cos`, keyed by `key`: nothing
/// closer than 0.4 m or beyond 8 m, dropout rising towards grazing angles, axial Gaussian noise
/// σ(z) = 0.0012 + 0.0019 (z − 0.4)², then disparity quantised to 1/8 pixel.
pub(crate) fn kinect_depth(z: f64, cos: f64, key: u64) -> f32 {
    if !(0.4..=8.0).contains(&z) {
        return 0.0;
    }
    // Certain dropout below cos 0.12 (83°), none above cos 0.3 (73°).
    let p_drop = 1.0 - ((cos - 0.12) / 0.18).clamp(0.0, 1.0);
    if unit(hash(&[key, 1])) < p_drop {
        return 0.0;
    }
    let sigma = 0.0012 + 0.0019 * (z - 0.4) * (z - 0.4);
    let noisy = z + sigma * gaussian(hash(&[key, 2]), hash(&[key, 3]));
    if noisy <= T_MIN {
        return 0.0;
    }
    let disparity = (KINECT_FB / noisy * 8.0).round() / 8.0;
    if disparity <= 0.0 {
        return 0.0;
    }
    (KINECT_FB / disparity) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinect_noise_has_the_documented_spread_and_quantisation() {
        let z = 2.0;
        let samples: Vec<f64> = (0..20000)
            .map(|i| f64::from(kinect_depth(z, 1.0, hash(&[i]))))
            .collect();
        assert!(samples.iter().all(|&d| d > 0.0));
        let mean = samples.iter().sum::<f64>() / samples.len() as f64;
        let sd =
            (samples.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / samples.len() as f64).sqrt();
        let sigma = 0.0012 + 0.0019 * 1.6 * 1.6;
        // Quantisation (step about 1.1 cm at 2 m) adds its own spread.
        assert!((mean - z).abs() < 0.002, "{mean}");
        assert!(sd > sigma && sd < sigma + 0.006, "{sd} vs {sigma}");
        let mut levels: Vec<f64> = samples.clone();
        levels.sort_by(f64::total_cmp);
        levels.dedup();
        assert!(levels.len() < 20, "{} distinct depths", levels.len());
        assert_eq!(kinect_depth(0.3, 1.0, 1), 0.0);
        assert_eq!(kinect_depth(2.0, 0.05, 1), 0.0);
    }
}
