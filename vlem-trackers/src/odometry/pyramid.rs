//! The image pyramid dense odometry works on: per level, depth, intensity and the target-side
//! gradients and normals, packed for the random lookups of projective data association.
//!
//! Built the way Open3D's `t.pipelines.odometry` builds it, so parameters mean the same: depth
//! outside `(0, depth_max]` is invalid (NaN); intensity is `0.299 R + 0.587 G + 0.114 B` in
//! `[0, 1]`; each coarser level is a 5×5 Gaussian (1 4 6 4 1) blur sampled at every second pixel,
//! where for depth only valid neighbours within `2 · depth_outlier_trunc` of the centre count;
//! gradients are 3×3 Sobel responses scaled by 1/8; intrinsics halve with each level.

use rayon::prelude::*;
use vlem_core::{DepthImage, Intrinsics, PinholeF32, RgbImage};

/// What a pixel offers as the *target* of a projective association.
///
/// Packed in one 32-byte record so a lookup touches one cache line.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TargetPixel {
    /// Depth in metres; NaN when invalid.
    pub depth: f32,
    /// Sobel x derivative of depth (scaled by 1/8); NaN next to invalid depth.
    pub depth_dx: f32,
    /// Sobel y derivative of depth (scaled by 1/8).
    pub depth_dy: f32,
    /// Intensity in `[0, 1]`.
    pub intensity: f32,
    /// Sobel x derivative of intensity (scaled by 1/8).
    pub intensity_dx: f32,
    /// Sobel y derivative of intensity (scaled by 1/8).
    pub intensity_dy: f32,
    /// Unused padding that keeps the record at 32 bytes.
    pad: [f32; 2],
}

/// A valid pixel of the *source* frame: its 3D point in the source camera and its intensity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SourcePoint {
    /// Camera-frame point (metres).
    pub point: [f32; 3],
    /// Intensity in `[0, 1]`.
    pub intensity: f32,
}

/// One pyramid level.
#[derive(Clone, Debug, Default)]
pub struct Level {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The level's pinhole parameters.
    pub camera: PinholeF32,
    /// Row-major target records.
    pub target: Vec<TargetPixel>,
    /// Unit normals (camera frame) from the smoothed depth, for point-to-plane; NaN where
    /// unknown. Empty unless asked for.
    pub normals: Vec<[f32; 3]>,
    /// Every valid pixel as a source point.
    pub source: Vec<SourcePoint>,
    /// The largest valid depth of the level (metres), bounding how far a rotation moves a point.
    pub max_depth: f32,
    /// Depth (NaN = invalid), the input of the next level.
    depth: Vec<f32>,
    /// Intensity, the input of the next level.
    intensity: Vec<f32>,
    /// Scratch for smoothed depth (normals).
    smooth: Vec<f32>,
}

/// A frame prepared for odometry, finest level first.
///
/// Rebuilding an existing pyramid ([`Pyramid::rebuild`]) reuses its buffers: a fresh 640×480
/// pyramid is ~15 MB, and first-touch page faults on new allocations cost as much as the
/// arithmetic.
#[derive(Clone, Debug, Default)]
pub struct Pyramid {
    /// Levels, finest (full resolution) first.
    pub levels: Vec<Level>,
    /// Valid depth pixels at full resolution.
    pub valid_pixels: usize,
}

/// How a pyramid is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PyramidParams {
    /// Number of levels (≥ 1).
    pub levels: usize,
    /// Depths beyond this (metres) are dropped.
    pub depth_max: f32,
    /// Depth neighbours further than this from the centre are left out when downsampling.
    pub depth_downsample_diff: f32,
    /// Whether to compute normals (point-to-plane needs them on the target).
    pub normals: bool,
    /// Whether the frame will be registered (needs source points).
    pub as_source: bool,
    /// Whether frames will be registered to it (needs target records and normals).
    pub as_target: bool,
}

impl Pyramid {
    /// Prepares an RGB-D frame.
    pub fn build(
        colour: &RgbImage,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        params: &PyramidParams,
    ) -> Self {
        let mut pyramid = Self::default();
        pyramid.rebuild(colour, depth, intrinsics, params);
        pyramid
    }

    /// Prepares an RGB-D frame in place, reusing this pyramid's buffers.
    pub fn rebuild(
        &mut self,
        colour: &RgbImage,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        params: &PyramidParams,
    ) {
        let (mut w, mut h) = (depth.width() as usize, depth.height() as usize);
        let mut count = 1;
        while count < params.levels && w >= 4 && h >= 4 {
            w /= 2;
            h /= 2;
            count += 1;
        }
        self.levels.resize_with(count, Level::default);
        self.levels.truncate(count);

        let depth_max = params.depth_max;
        let first = &mut self.levels[0];
        first.width = depth.width() as usize;
        first.height = depth.height() as usize;
        first.camera = PinholeF32::from_intrinsics(intrinsics);
        first.depth.clear();
        first.depth.extend(depth.as_raw().iter().map(|&d| {
            if d.is_finite() && d > 0.0 && d <= depth_max {
                d
            } else {
                f32::NAN
            }
        }));
        self.valid_pixels = first.depth.iter().filter(|d| !d.is_nan()).count();
        first.intensity.clear();
        first
            .intensity
            .extend(colour.as_raw().chunks_exact(3).map(|c| {
                (0.299 * f32::from(c[0]) + 0.587 * f32::from(c[1]) + 0.114 * f32::from(c[2]))
                    / 255.0
            }));
        for level in 1..count {
            let (finer, coarser) = self.levels.split_at_mut(level);
            let (from, to) = (&finer[level - 1], &mut coarser[0]);
            to.width = from.width / 2;
            to.height = from.height / 2;
            to.camera = from.camera.scaled(0.5);
            pyr_down_depth_into(
                &from.depth,
                from.width,
                from.height,
                params.depth_downsample_diff,
                &mut to.depth,
            );
            pyr_down_into(&from.intensity, from.width, from.height, &mut to.intensity);
        }
        for level in &mut self.levels {
            level.prepare(params);
        }
    }
}

impl Level {
    /// Fills the target records, source points and (if asked) normals from depth and intensity.
    fn prepare(&mut self, params: &PyramidParams) {
        let (width, height, camera) = (self.width, self.height, self.camera);
        self.target.clear();
        if params.as_target {
            target_records(
                &self.depth,
                &self.intensity,
                width,
                height,
                params.depth_downsample_diff * 0.5,
                &mut self.target,
            );
        }
        self.source.clear();
        if !params.as_source {
            self.max_depth = 0.0;
            self.normals.clear();
            if params.as_target && params.normals {
                self.compute_normals(params);
            }
            return;
        }
        self.source.extend(
            self.depth
                .iter()
                .zip(&self.intensity)
                .enumerate()
                .filter(|(_, (d, _))| !d.is_nan())
                .map(|(i, (&z, &intensity))| {
                    let u = (i % width) as f32;
                    let v = (i / width) as f32;
                    SourcePoint {
                        point: [
                            (u - camera.cx) * z / camera.fx,
                            (v - camera.cy) * z / camera.fy,
                            z,
                        ],
                        intensity,
                    }
                }),
        );
        self.max_depth = self.source.iter().map(|s| s.point[2]).fold(0.0, f32::max);
        self.normals.clear();
        if params.as_target && params.normals {
            self.compute_normals(params);
        }
    }

    fn compute_normals(&mut self, params: &PyramidParams) {
        let (width, height, camera) = (self.width, self.height, self.camera);
        smooth_depth_into(
            &self.depth,
            width,
            height,
            params.depth_downsample_diff,
            &mut self.smooth,
        );
        normal_map_into(&self.smooth, width, height, camera, &mut self.normals);
    }
}

/// Image rows per parallel work item of [`target_records`].
const BAND: usize = 16;

/// The target records: Sobel derivatives of depth and intensity (scaled by 1/8, borders clamped).
/// The depth derivative is unknown (NaN) next to a hole and where the 3×3 window spans a
/// discontinuity (its depths spread over more than `max_diff`): a slope measured across an
/// occluding edge describes neither surface and would pull the solve towards the edge.
///
/// Computed separably (per-row horizontal sums, differences, minima and maxima, then combined
/// over three rows), so each pass is a plain loop over a row that the compiler vectorises. The
/// image goes in bands of [`BAND`] rows whose horizontal passes (and one row above and below)
/// stay in the cache, rather than through eight image-sized intermediate arrays.
fn target_records(
    depth: &[f32],
    intensity: &[f32],
    width: usize,
    height: usize,
    max_diff: f32,
    target: &mut Vec<TargetPixel>,
) {
    target.resize(width * height, TargetPixel::default());
    if width == 0 || height == 0 {
        return;
    }
    target
        .par_chunks_mut(width * BAND)
        .enumerate()
        .for_each_init(
            || [RowPasses::default(), RowPasses::default()],
            |[d, i], (band, out)| {
                let top = band * BAND;
                // The band's rows and the clamped rows above and below it.
                let first = top.saturating_sub(1);
                let last = (top + out.len() / width).min(height - 1);
                let rows = last + 1 - first;
                d.resize(rows * width);
                i.resize(rows * width);
                for (k, y) in (first..=last).enumerate() {
                    let at = y * width..(y + 1) * width;
                    d.horizontal(&depth[at.clone()], k);
                    i.horizontal(&intensity[at], k);
                }
                for (r, row) in out.chunks_mut(width).enumerate() {
                    let y = top + r;
                    // Offsets of rows y - 1, y and y + 1 (clamped) in the band's passes.
                    let rows = [y.saturating_sub(1), y, (y + 1).min(height - 1)]
                        .map(|yy| (yy - first) * width);
                    let (ds, dd) = (
                        three_rows(&d.sum, rows, width),
                        three_rows(&d.diff, rows, width),
                    );
                    let (dmin, dmax) = (
                        three_rows(&d.min, rows, width),
                        three_rows(&d.max, rows, width),
                    );
                    let (is, id) = (
                        three_rows(&i.sum, rows, width),
                        three_rows(&i.diff, rows, width),
                    );
                    let centre_depth = &depth[y * width..(y + 1) * width];
                    let centre_intensity = &intensity[y * width..(y + 1) * width];
                    for (x, out) in row.iter_mut().enumerate() {
                        // A NaN anywhere in the window makes the sums NaN (min/max skip NaN).
                        let window_sum = ds[0][x] + ds[1][x] + ds[2][x];
                        let spread = dmax[0][x].max(dmax[1][x]).max(dmax[2][x])
                            - dmin[0][x].min(dmin[1][x]).min(dmin[2][x]);
                        let smooth = !window_sum.is_nan() && spread <= max_diff;
                        let (dx, dy) = if smooth {
                            (
                                0.125 * (dd[0][x] + 2.0 * dd[1][x] + dd[2][x]),
                                0.125 * (ds[2][x] - ds[0][x]),
                            )
                        } else {
                            (f32::NAN, f32::NAN)
                        };
                        *out = TargetPixel {
                            depth: centre_depth[x],
                            depth_dx: dx,
                            depth_dy: dy,
                            intensity: centre_intensity[x],
                            intensity_dx: 0.125 * (id[0][x] + 2.0 * id[1][x] + id[2][x]),
                            intensity_dy: 0.125 * (is[2][x] - is[0][x]),
                            pad: [0.0; 2],
                        };
                    }
                }
            },
        );
}

/// The rows starting at `starts`, each `width` long.
fn three_rows(values: &[f32], starts: [usize; 3], width: usize) -> [&[f32]; 3] {
    starts.map(|r| &values[r..r + width])
}

/// Horizontal passes of [`target_records`] over the rows of one band.
#[derive(Clone, Debug, Default)]
struct RowPasses {
    sum: Vec<f32>,
    diff: Vec<f32>,
    min: Vec<f32>,
    max: Vec<f32>,
}

impl RowPasses {
    fn resize(&mut self, len: usize) {
        for v in [&mut self.sum, &mut self.diff, &mut self.min, &mut self.max] {
            v.resize(len, 0.0);
        }
    }

    /// Fills row `k` of the passes from image row `row`: the [1 2 1] sum, the [-1 0 1]
    /// difference, and the minimum and maximum over a clamped 3-pixel window.
    fn horizontal(&mut self, row: &[f32], k: usize) {
        let width = row.len();
        let at = k * width..(k + 1) * width;
        let (sum, diff) = (&mut self.sum[at.clone()], &mut self.diff[at.clone()]);
        let (min, max) = (&mut self.min[at.clone()], &mut self.max[at]);
        for x in 0..width {
            let (l, c, r) = (
                row[x.saturating_sub(1)],
                row[x],
                row[(x + 1).min(width - 1)],
            );
            sum[x] = l + 2.0 * c + r;
            diff[x] = r - l;
            min[x] = l.min(c).min(r);
            max[x] = l.max(c).max(r);
        }
    }
}

/// Binomial 5-tap weights (1 4 6 4 1) / 16.
const GAUSS5: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];

/// Gaussian blur + every second pixel, borders clamped.
fn pyr_down_into(image: &[f32], width: usize, height: usize, out: &mut Vec<f32>) {
    let (w2, h2) = (width / 2, height / 2);
    out.clear();
    out.resize(w2 * h2, 0.0);
    out.par_chunks_mut(w2.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let mut sum = 0.0;
                for (dy, wy) in GAUSS5.iter().enumerate() {
                    let yy = (2 * y + dy).saturating_sub(2).min(height - 1);
                    let line = &image[yy * width..(yy + 1) * width];
                    for (dx, wx) in GAUSS5.iter().enumerate() {
                        let xx = (2 * x + dx).saturating_sub(2).min(width - 1);
                        sum += wy * wx * line[xx];
                    }
                }
                *out = sum;
            }
        });
}

/// Gaussian downsampling of depth that ignores invalid neighbours and neighbours further than
/// `max_diff` from the centre; an invalid centre stays invalid.
fn pyr_down_depth_into(
    depth: &[f32],
    width: usize,
    height: usize,
    max_diff: f32,
    out: &mut Vec<f32>,
) {
    let (w2, h2) = (width / 2, height / 2);
    out.clear();
    out.resize(w2 * h2, f32::NAN);
    out.par_chunks_mut(w2.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let centre = depth[2 * y * width + 2 * x];
                if centre.is_nan() {
                    continue;
                }
                *out = weighted_neighbourhood(depth, width, height, 2 * x, 2 * y, centre, max_diff);
            }
        });
}

/// Edge-preserving 5×5 Gaussian smoothing of depth (for normals), same neighbour rule as
/// [`pyr_down_depth`].
fn smooth_depth_into(
    depth: &[f32],
    width: usize,
    height: usize,
    max_diff: f32,
    out: &mut Vec<f32>,
) {
    out.clear();
    out.resize(width * height, f32::NAN);
    out.par_chunks_mut(width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let centre = depth[y * width + x];
                if !centre.is_nan() {
                    *out = weighted_neighbourhood(depth, width, height, x, y, centre, max_diff);
                }
            }
        });
}

#[inline]
fn weighted_neighbourhood(
    depth: &[f32],
    width: usize,
    height: usize,
    x: usize,
    y: usize,
    centre: f32,
    max_diff: f32,
) -> f32 {
    let mut sum = 0.0;
    let mut weight = 0.0;
    let (x0, x1) = (x.saturating_sub(2), (x + 3).min(width));
    let (y0, y1) = (y.saturating_sub(2), (y + 3).min(height));
    for yy in y0..y1 {
        let wy = GAUSS5[yy + 2 - y];
        let line = &depth[yy * width + x0..yy * width + x1];
        for (d, wx) in line.iter().zip(&GAUSS5[x0 + 2 - x..]) {
            // NaN fails the comparison, so invalid neighbours drop out here too.
            if (d - centre).abs() < max_diff {
                sum += wy * wx * d;
                weight += wy * wx;
            }
        }
    }
    sum / weight
}

/// Normals from the cross product of the right and down neighbours' 3D points, oriented
/// towards the camera.
fn normal_map_into(
    depth: &[f32],
    width: usize,
    height: usize,
    camera: PinholeF32,
    normals: &mut Vec<[f32; 3]>,
) {
    let point = |x: usize, y: usize| -> [f32; 3] {
        let z = depth[y * width + x];
        [
            (x as f32 - camera.cx) * z / camera.fx,
            (y as f32 - camera.cy) * z / camera.fy,
            z,
        ]
    };
    normals.clear();
    normals.resize(width * height, [f32::NAN; 3]);
    normals
        .par_chunks_mut(width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            if y + 1 >= height {
                return;
            }
            for (x, n) in row.iter_mut().enumerate().take(width.saturating_sub(1)) {
                let p = point(x, y);
                let a = point(x + 1, y);
                let b = point(x, y + 1);
                let e1 = [a[0] - p[0], a[1] - p[1], a[2] - p[2]];
                let e2 = [b[0] - p[0], b[1] - p[1], b[2] - p[2]];
                let c = [
                    e1[1] * e2[2] - e1[2] * e2[1],
                    e1[2] * e2[0] - e1[0] * e2[2],
                    e1[0] * e2[1] - e1[1] * e2[0],
                ];
                let norm = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                if norm.is_finite() && norm > 0.0 {
                    // Towards the camera: n · p < 0.
                    let sign = if c[0] * p[0] + c[1] * p[1] + c[2] * p[2] > 0.0 {
                        -1.0
                    } else {
                        1.0
                    };
                    *n = [sign * c[0] / norm, sign * c[1] / norm, sign * c[2] / norm];
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference 3×3 Sobel derivatives scaled by 1/8 (so they are per-pixel slopes); NaN inputs make the
    /// neighbouring derivatives NaN, borders are clamped.
    fn sobel(image: &[f32], width: usize, height: usize) -> (Vec<f32>, Vec<f32>) {
        let mut dx = vec![0.0; width * height];
        let mut dy = vec![0.0; width * height];
        dx.par_chunks_mut(width.max(1))
            .zip(dy.par_chunks_mut(width.max(1)))
            .enumerate()
            .for_each(|(y, (row_dx, row_dy))| {
                let up = &image[y.saturating_sub(1) * width..][..width];
                let mid = &image[y * width..][..width];
                let down = &image[(y + 1).min(height - 1) * width..][..width];
                for x in 0..width {
                    let l = x.saturating_sub(1);
                    let r = (x + 1).min(width - 1);
                    let gx = (up[r] - up[l]) + 2.0 * (mid[r] - mid[l]) + (down[r] - down[l]);
                    let gy = (down[l] - up[l]) + 2.0 * (down[x] - up[x]) + (down[r] - up[r]);
                    row_dx[x] = gx * 0.125;
                    row_dy[x] = gy * 0.125;
                }
            });
        (dx, dy)
    }

    #[test]
    fn sobel_of_a_ramp_is_its_slope() {
        let (w, h) = (6, 5);
        let image: Vec<f32> = (0..w * h).map(|i| 0.5 * (i % w) as f32).collect();
        let (dx, dy) = sobel(&image, w, h);
        // Interior: slope 0.5 per pixel along x, 0 along y.
        assert!((dx[2 * w + 2] - 0.5).abs() < 1e-6);
        assert!(dy[2 * w + 2].abs() < 1e-6);
    }

    #[test]
    fn target_records_match_sobel_and_mask_depth_edges() {
        let (w, h) = (9, 7);
        let intensity: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32 / 11.0).collect();
        // A smooth ramp with a 0.5 m step from column 6 on.
        let depth: Vec<f32> = (0..w * h)
            .map(|i| 1.0 + 0.01 * (i % w) as f32 + if i % w >= 6 { 0.5 } else { 0.0 })
            .collect();
        let mut target = Vec::new();
        target_records(&depth, &intensity, w, h, 0.07, &mut target);
        let (ix, iy) = sobel(&intensity, w, h);
        let (dx, _) = sobel(&depth, w, h);
        for k in 0..w * h {
            assert!((target[k].intensity_dx - ix[k]).abs() < 1e-6, "{k}");
            assert!((target[k].intensity_dy - iy[k]).abs() < 1e-6, "{k}");
            assert_eq!(target[k].depth, depth[k]);
        }
        // Taller than several bands, one of them partial: the rows next to the bands' edges
        // see their neighbours in the next band.
        let (w2, h2) = (w, 2 * BAND + 5);
        let tall: Vec<f32> = (0..w2 * h2)
            .map(|i| ((i * 37) % 11) as f32 / 11.0)
            .collect();
        let mut records = Vec::new();
        target_records(&tall, &tall, w2, h2, 0.07, &mut records);
        let (tx, ty) = sobel(&tall, w2, h2);
        for k in 0..w2 * h2 {
            assert!((records[k].intensity_dx - tx[k]).abs() < 1e-6, "{k}");
            assert!((records[k].intensity_dy - ty[k]).abs() < 1e-6, "{k}");
        }
        // On the ramp the slope is 0.01 per pixel; next to the step it is unknown.
        let on_ramp = 3 * w + 2;
        assert!((target[on_ramp].depth_dx - dx[on_ramp]).abs() < 1e-6);
        assert!((target[on_ramp].depth_dx - 0.01).abs() < 1e-5);
        assert!(target[3 * w + 5].depth_dx.is_nan() && target[3 * w + 6].depth_dx.is_nan());
        assert!(!target[3 * w + 7].depth_dx.is_nan());
    }

    #[test]
    fn pyr_down_keeps_a_constant_and_halves_the_size() {
        let image = vec![0.25; 8 * 6];
        let mut down = Vec::new();
        pyr_down_into(&image, 8, 6, &mut down);
        assert_eq!(down.len(), 4 * 3);
        assert!(down.iter().all(|v| (v - 0.25).abs() < 1e-6));
    }

    #[test]
    fn depth_downsampling_ignores_invalid_and_far_neighbours() {
        let (w, h) = (8, 8);
        let mut depth = vec![1.0; w * h];
        depth[2 * w + 3] = f32::NAN; // invalid neighbour of output (1, 1)
        depth[3 * w + 2] = 5.0; // far neighbour
        let mut down = Vec::new();
        pyr_down_depth_into(&depth, w, h, 0.14, &mut down);
        assert!((down[4 + 1] - 1.0).abs() < 1e-6, "{}", down[5]);
        depth[2 * w + 2] = f32::NAN; // the centre of output (1, 1)
        pyr_down_depth_into(&depth, w, h, 0.14, &mut down);
        assert!(down[4 + 1].is_nan());
    }

    #[test]
    fn normals_of_a_fronto_parallel_plane_face_the_camera() {
        let (w, h) = (16, 12);
        let k = Intrinsics::new(w as u32, h as u32, 20.0, 20.0, 7.5, 5.5).unwrap();
        let depth = DepthImage::new(w as u32, h as u32, vec![2.0; w * h]).unwrap();
        let colour = RgbImage::filled(w as u32, h as u32, [10, 20, 30]);
        let pyramid = Pyramid::build(
            &colour,
            &depth,
            &k,
            &PyramidParams {
                levels: 2,
                depth_max: 3.0,
                depth_downsample_diff: 0.14,
                normals: true,
                as_source: true,
                as_target: true,
            },
        );
        assert_eq!(pyramid.levels.len(), 2);
        assert_eq!(pyramid.valid_pixels, w * h);
        let n = pyramid.levels[0].normals[5 * w + 5];
        assert!((n[2] + 1.0).abs() < 1e-5, "{n:?}");
        assert_eq!(pyramid.levels[1].width, 8);
        assert!((pyramid.levels[1].camera.fx - 10.0).abs() < 1e-6);
        let intensity = pyramid.levels[0].target[0].intensity;
        let expected = (0.299 * 10.0 + 0.587 * 20.0 + 0.114 * 30.0) / 255.0;
        assert!((intensity - expected).abs() < 1e-6);
    }

    #[test]
    fn depth_beyond_the_maximum_is_invalid() {
        let k = Intrinsics::new(4, 4, 4.0, 4.0, 1.5, 1.5).unwrap();
        let mut raw = vec![1.0; 16];
        raw[0] = 3.5;
        raw[1] = -1.0;
        raw[2] = f32::NAN;
        let depth = DepthImage::new(4, 4, raw).unwrap();
        let colour = RgbImage::filled(4, 4, [0, 0, 0]);
        let params = PyramidParams {
            levels: 1,
            depth_max: 3.0,
            depth_downsample_diff: 0.14,
            normals: false,
            as_source: true,
            as_target: true,
        };
        let pyramid = Pyramid::build(&colour, &depth, &k, &params);
        assert_eq!(pyramid.valid_pixels, 13);
        assert_eq!(pyramid.levels[0].source.len(), 13);
    }
}
