//! Coarse-to-fine Gauss–Newton on SE(3): the rigid motion that aligns a source RGB-D frame with
//! a target one by projective data association.
//!
//! Every valid source pixel is moved by the current estimate and projected into the target. It is
//! an outlier when any of the four target pixels around the projection has no depth within
//! `depth_outlier_trunc` of the point's (point-to-plane: the nearest pixel). Residuals follow
//! Open3D's `t.pipelines.odometry`, so parameters carry over:
//! - photometric: `I_t(π(T p)) − I_s(p)`, Jacobian through the target's intensity gradient;
//! - geometric (hybrid): `D_t(π(T p)) − (T p)_z`, Jacobian through the target's depth gradient;
//! - point-to-plane: `n_t · (T p − q_t)` with the target's point and normal.
//!
//! Two deliberate differences from Open3D: target values are interpolated bilinearly at the
//! projection (Open3D rounds to the nearest pixel, which stalls the solve up to half a pixel from
//! the optimum), and depth slopes across a depth discontinuity are unknown rather than huge.
//!
//! The hybrid method weighs both terms by λ = ½. Each residual gets a Huber weight
//! (iteratively reweighted least squares, where Open3D clips only the gradient); the 6×6 normal
//! equations are summed in parallel over pixel chunks and solved by Cholesky; the update `exp(δ)`
//! multiplies the estimate from the left. A level ends after its iteration budget, when inlier
//! fitness and RMSE change by less than the relative thresholds (Open3D's convergence criteria),
//! or when an update moves no point by more than `min_update` metres at full resolution
//! (`2^level × min_update` at pyramid level `level`).

use nalgebra::{Cholesky, Isometry3, Matrix6, Vector3, Vector6};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use vlem_core::RigidF32;

use super::OdometryConfig;
use super::pyramid::{Level, Pyramid, SourcePoint, TargetPixel};

/// Which residuals the solver minimises.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Photometric + geometric (depth) residuals, λ = ½ each (Steinbrücker / Park et al.).
    #[default]
    Hybrid,
    /// Point-to-plane distance only (KinectFusion-style ICP).
    PointToPlane,
    /// Photometric residual only (Steinbrücker et al. 2011).
    Intensity,
}

/// What [`register`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct Registration {
    /// Maps source camera coordinates to target camera coordinates.
    pub source_to_target: Isometry3<f64>,
    /// Inliers / source pixels at the finest level.
    pub fitness: f64,
    /// Root mean square of the (weighted) inlier residuals at the finest level.
    pub inlier_rmse: f64,
    /// Inlier associations at the finest level.
    pub inliers: usize,
    /// Gauss–Newton iterations run, all levels together.
    pub iterations: usize,
}

/// Why [`register`] gave up.
#[derive(Clone, Debug, PartialEq)]
pub enum SolveFailure {
    /// Too few associations to constrain six degrees of freedom.
    TooFewInliers {
        /// Pyramid level (0 = finest).
        level: usize,
        /// Associations found.
        inliers: usize,
    },
    /// The normal equations were singular or the update was not finite.
    Degenerate {
        /// Pyramid level (0 = finest).
        level: usize,
    },
}

impl std::fmt::Display for SolveFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewInliers { level, inliers } => write!(
                f,
                "only {inliers} pixel associations at pyramid level {level}"
            ),
            Self::Degenerate { level } => {
                write!(
                    f,
                    "the normal equations are singular at pyramid level {level}"
                )
            }
        }
    }
}

/// Fewer inliers than this cannot constrain the solve reliably.
const MIN_INLIERS: usize = 30;
/// Source pixels per parallel work item.
const CHUNK: usize = 2048;
/// √λ of both hybrid terms (λ = ½).
const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// Aligns `source` to `target` starting from `init` (source → target).
///
/// # Errors
/// [`SolveFailure`] when a level has too few associations or a singular system.
pub fn register(
    source: &Pyramid,
    target: &Pyramid,
    init: &Isometry3<f64>,
    params: &OdometryConfig,
) -> Result<Registration, SolveFailure> {
    let levels = source.levels.len().min(target.levels.len());
    let mut transform = *init;
    let mut total_iterations = 0;
    let mut finest = Step::default();
    for (coarse_rank, &budget) in params.iterations.iter().enumerate() {
        // iterations[0] belongs to the coarsest level.
        let Some(level) = levels.checked_sub(1 + coarse_rank) else {
            continue;
        };
        let (src, tgt) = (&source.levels[level], &target.levels[level]);
        // A coarse level's pixels are 2^level times larger and the finer levels redo the
        // sub-pixel part of its work, so it stops at a threshold 2^level times larger: on the
        // shared sequence this saves a fifth of the odometry's coarse iterations, and the
        // trajectories change only in the last digits (BENCHMARKS.md).
        let min_update = params.min_update * f64::from(1_u32 << level.min(31));
        let mut previous: Option<Step> = None;
        for _ in 0..budget {
            let step = linearise(src, tgt, &transform, params);
            total_iterations += 1;
            if step.inliers < MIN_INLIERS {
                return Err(SolveFailure::TooFewInliers {
                    level,
                    inliers: step.inliers,
                });
            }
            let delta = step.solve().ok_or(SolveFailure::Degenerate { level })?;
            transform = exp_se3(&delta) * transform;
            let settled = previous.as_ref().is_some_and(|p| {
                relative_change(p.fitness(src), step.fitness(src)) < params.relative_fitness
                    && relative_change(p.rmse(), step.rmse()) < params.relative_rmse
            });
            // An update that moves no point by more than `min_update` metres changes nothing
            // measurable: further iterations at this level would only cost time.
            let depth_scale = f64::from(src.max_depth);
            let motion =
                delta.fixed_rows::<3>(3).norm() + delta.fixed_rows::<3>(0).norm() * depth_scale;
            let converged = settled || motion < min_update;
            previous = Some(step);
            if converged {
                break;
            }
        }
        if level == 0
            && let Some(step) = previous
        {
            finest = step;
        }
    }
    // The statistics of the last linearisation at full resolution (before its small update),
    // as Open3D reports them; re-scoring would cost another full pass.
    Ok(Registration {
        source_to_target: transform,
        fitness: finest.fitness(&source.levels[0]),
        inlier_rmse: finest.rmse(),
        inliers: finest.inliers,
        iterations: total_iterations,
    })
}

fn relative_change(old: f64, new: f64) -> f64 {
    if old == 0.0 {
        f64::INFINITY
    } else {
        (old - new).abs() / old.abs()
    }
}

/// The small rigid motion `exp(δ)` for `δ = (ω, v)`: rotation by the axis-angle ω, then
/// translation by v (first order equal to the SE(3) exponential, which is all Gauss–Newton uses).
fn exp_se3(delta: &Vector6<f64>) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::new(delta[3], delta[4], delta[5]),
        Vector3::new(delta[0], delta[1], delta[2]),
    )
}

/// The normal equations of one iteration, summed in f64.
#[derive(Clone, Debug, Default, PartialEq)]
struct Step {
    /// Upper triangle of JᵀWJ, row-major.
    h: [f64; 21],
    /// JᵀWr.
    b: [f64; 6],
    /// Σ w r².
    squared: f64,
    inliers: usize,
}

/// Products a residual row adds to the normal equations: JᵀWJ's upper triangle (21), JᵀWr (6)
/// and Σ w r² (1), i.e. the upper triangle of the 7×7 outer product of `(√w·J, √w·r)`.
const PRODUCTS: usize = 28;

/// The normal equations of one chunk of source points, summed in f32 lane by lane.
///
/// Residual rows come in groups of [`LANES`] (one row per lane, as `√w·J` and `√w·r`), and
/// each group adds its 28 products to 28 lane-wise sums: an update the compiler vectorises,
/// where one row at a time would be a scalar 6×6 update. The accumulators fit in the L1 cache,
/// so rows are never written out. Rows added one at a time ([`ChunkSums::add`]) are staged
/// until they fill a group.
struct ChunkSums {
    sums: [[f32; LANES]; PRODUCTS],
    staged: [[f32; LANES]; 7],
    staged_rows: usize,
    inliers: usize,
}

impl ChunkSums {
    fn new() -> Self {
        Self {
            sums: [[0.0; LANES]; PRODUCTS],
            staged: [[0.0; LANES]; 7],
            staged_rows: 0,
            inliers: 0,
        }
    }

    /// Adds residual `r` with Jacobian row `j`, weighted by its Huber weight.
    #[inline(always)]
    fn add(&mut self, j: &[f32; 6], r: f32, huber_delta: f32) {
        let s = huber_sqrt_weight(r, huber_delta);
        let k = self.staged_rows % LANES;
        for (column, x) in self.staged.iter_mut().zip(j) {
            column[k] = s * x;
        }
        self.staged[6][k] = s * r;
        self.staged_rows = k + 1;
        if self.staged_rows == LANES {
            let group = self.staged;
            self.add_group(&group);
            self.staged_rows = 0;
        }
    }

    /// Adds [`LANES`] weighted rows, given column by column: `rows[0..6]` hold `√w·J`, `rows[6]`
    /// holds `√w·r`. All-zero lanes add nothing.
    #[inline(always)]
    fn add_group(&mut self, rows: &[[f32; LANES]; 7]) {
        let mut i = 0;
        for r in 0..7 {
            for c in r..7 {
                let sums = &mut self.sums[i % PRODUCTS];
                for l in 0..LANES {
                    sums[l] += rows[r][l] * rows[c][l];
                }
                i += 1;
            }
        }
    }

    /// The chunk's normal equations (a partly staged group is padded with zero rows).
    fn normal_equations(mut self) -> Step {
        if self.staged_rows > 0 {
            for column in &mut self.staged {
                column[self.staged_rows..].fill(0.0);
            }
            let group = self.staged;
            self.add_group(&group);
        }
        let mut step = Step {
            inliers: self.inliers,
            ..Step::default()
        };
        let mut products = self
            .sums
            .iter()
            .map(|lanes| lanes.iter().map(|&x| f64::from(x)).sum::<f64>());
        let mut h = step.h.iter_mut();
        for r in 0..7 {
            for c in r..7 {
                let sum = products.next().unwrap_or(0.0);
                if r == 6 {
                    step.squared = sum;
                } else if c == 6 {
                    step.b[r] = sum;
                } else if let Some(h) = h.next() {
                    *h = sum;
                }
            }
        }
        step
    }
}

impl Step {
    fn merge(mut self, other: Self) -> Self {
        for (a, b) in self.h.iter_mut().zip(other.h) {
            *a += b;
        }
        for (a, b) in self.b.iter_mut().zip(other.b) {
            *a += b;
        }
        self.squared += other.squared;
        self.inliers += other.inliers;
        self
    }

    fn solve(&self) -> Option<Vector6<f64>> {
        let mut h = Matrix6::zeros();
        let mut i = 0;
        for row in 0..6 {
            for col in row..6 {
                h[(row, col)] = self.h[i];
                h[(col, row)] = self.h[i];
                i += 1;
            }
        }
        let b = Vector6::from_column_slice(&self.b);
        let delta = Cholesky::new(h)?.solve(&(-b));
        delta.iter().all(|x| x.is_finite()).then_some(delta)
    }

    fn fitness(&self, level: &Level) -> f64 {
        self.inliers as f64 / level.source.len().max(1) as f64
    }

    fn rmse(&self) -> f64 {
        (self.squared / self.inliers.max(1) as f64).sqrt()
    }
}

/// Sums the normal equations over all source points at the current estimate.
fn linearise(
    source: &Level,
    target: &Level,
    transform: &Isometry3<f64>,
    params: &OdometryConfig,
) -> Step {
    let ctx = Association::new(target, transform, params);
    let accumulate: Accumulate = match params.method {
        Method::Hybrid => wide::accumulate_hybrid,
        Method::Intensity => accumulate_intensity,
        Method::PointToPlane => accumulate_point_to_plane,
    };
    linearise_with(source, &ctx, accumulate)
}

/// Adds the residual rows of a chunk of source points.
type Accumulate = fn(&Association<'_>, &[SourcePoint], &mut ChunkSums);

/// Sums the normal equations of `accumulate`'s rows over all source points, chunks in parallel.
fn linearise_with(source: &Level, ctx: &Association<'_>, accumulate: Accumulate) -> Step {
    source
        .source
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut sums = ChunkSums::new();
            accumulate(ctx, chunk, &mut sums);
            sums.normal_equations()
        })
        .reduce(Step::default, Step::merge)
}

struct Association<'a> {
    /// Source to target camera.
    transform: RigidF32,
    target: &'a Level,
    trunc: f32,
    /// Huber thresholds on the λ-scaled residuals.
    depth_huber: f32,
    intensity_huber: f32,
}

impl<'a> Association<'a> {
    fn new(target: &'a Level, transform: &Isometry3<f64>, params: &OdometryConfig) -> Self {
        Self {
            transform: RigidF32::from_pose(transform),
            target,
            trunc: params.depth_outlier_trunc,
            depth_huber: params.depth_huber_delta * SQRT_HALF,
            intensity_huber: params.intensity_huber_delta * SQRT_HALF,
        }
    }

    /// The moved point and its continuous pixel coordinates in the target.
    #[inline]
    fn project(&self, p: &[f32; 3]) -> Option<([f32; 3], f32, f32)> {
        let q = self.transform.apply(*p);
        if q[2] <= 0.0 {
            return None;
        }
        let cam = &self.target.camera;
        let inv_z = 1.0 / q[2];
        Some((
            q,
            cam.fx * q[0] * inv_z + cam.cx,
            cam.fy * q[1] * inv_z + cam.cy,
        ))
    }

    /// The moved point and the index of the nearest target pixel it projects to.
    #[inline]
    fn associate_nearest(&self, p: &[f32; 3]) -> Option<([f32; 3], usize)> {
        let (q, u, v) = self.project(p)?;
        // Shifted by ½ so truncation rounds (`f32::round` is a library call on baseline x86-64).
        let (u, v) = (u + 0.5, v + 0.5);
        // NaN fails both comparisons.
        if !(u >= 0.0 && v >= 0.0 && u < self.target.width as f32 && v < self.target.height as f32)
        {
            return None;
        }
        Some((q, v as usize * self.target.width + u as usize))
    }

    /// The moved point and the target record bilinearly interpolated at its projection; `None`
    /// outside the image, or when any of the four neighbours has no depth within the outlier
    /// threshold of the point's (which also keeps interpolation off depth discontinuities).
    ///
    /// Open3D associates with the nearest pixel; that makes the residual piecewise constant
    /// under sub-pixel motion while the Jacobian assumes it varies smoothly, which stalls the
    /// solve half a pixel or more from the optimum. Interpolating keeps the two consistent.
    #[inline(always)]
    fn associate_bilinear(&self, p: &[f32; 3]) -> Option<Bilinear<'_>> {
        let [qx, qy, qz] = self.transform.apply(*p);
        let cam = &self.target.camera;
        let inv_z = 1.0 / qz;
        let u = cam.fx * qx * inv_z + cam.cx;
        let v = cam.fy * qy * inv_z + cam.cy;
        let w = self.target.width;
        let (u_max, v_max) = ((w - 1) as f32, (self.target.height - 1) as f32);
        // NaN and points behind the camera fail too.
        if !(qz > 0.0 && u >= 0.0 && v >= 0.0 && u < u_max && v < v_max) {
            return None;
        }
        // In range and non-negative here, so truncation is floor; via i32 because a float to
        // usize conversion costs several times more on x86-64.
        let (u0, v0) = (u as i32 as usize, v as i32 as usize);
        let (fu, fv) = (u - u0 as f32, v - v0 as f32);
        let i = v0 * w + u0;
        let t = &self.target.target;
        let (top, bottom) = (t.get(i..i + 2)?, t.get(i + w..i + w + 2)?);
        let (c00, c10, c01, c11) = (&top[0], &top[1], &bottom[0], &bottom[1]);
        let near = |c: &TargetPixel| (c.depth - qz).abs() <= self.trunc;
        if !(near(c00) && near(c10) && near(c01) && near(c11)) {
            return None;
        }
        // Values are interpolated (the residual must vary smoothly); slopes come from the
        // nearest corner (the Jacobian only steers the step, and this halves the work).
        let nearest = match (fu >= 0.5, fv >= 0.5) {
            (false, false) => c00,
            (true, false) => c10,
            (false, true) => c01,
            (true, true) => c11,
        };
        Some(Bilinear {
            q: [qx, qy, qz],
            corners: [c00, c10, c01, c11],
            weights: [
                (1.0 - fu) * (1.0 - fv),
                fu * (1.0 - fv),
                (1.0 - fu) * fv,
                fu * fv,
            ],
            nearest,
        })
    }
}

/// A source point moved into the target and the target sampled there.
struct Bilinear<'a> {
    /// The moved point (target camera frame).
    q: [f32; 3],
    /// The four target pixels around the projection and their bilinear weights.
    corners: [&'a TargetPixel; 4],
    weights: [f32; 4],
    /// The nearest of the four corners, whose slopes the Jacobians use.
    nearest: &'a TargetPixel,
}

impl Bilinear<'_> {
    fn interpolate(&self, value: impl Fn(&TargetPixel) -> f32) -> f32 {
        let [c00, c10, c01, c11] = self.corners;
        let [w00, w10, w01, w11] = self.weights;
        w00 * value(c00) + w10 * value(c10) + w01 * value(c01) + w11 * value(c11)
    }

    /// Interpolated target intensity.
    fn intensity(&self) -> f32 {
        self.interpolate(|c| c.intensity)
    }

    /// Interpolated target depth.
    #[cfg(test)]
    fn depth(&self) -> f32 {
        self.interpolate(|c| c.depth)
    }
}

/// d(pixel-space image derivative)/dξ for an image with per-pixel slopes `(gx, gy)` at the
/// projection of camera point `q`: `[q × c, c]` with `c = ∇ · ∂π/∂q`.
#[inline]
fn image_jacobian(gx: f32, gy: f32, q: &[f32; 3], fx: f32, fy: f32) -> [f32; 6] {
    let inv_z = 1.0 / q[2];
    let c0 = gx * fx * inv_z;
    let c1 = gy * fy * inv_z;
    let c2 = -(c0 * q[0] + c1 * q[1]) * inv_z;
    [
        q[1] * c2 - q[2] * c1,
        q[2] * c0 - q[0] * c2,
        q[0] * c1 - q[1] * c0,
        c0,
        c1,
        c2,
    ]
}

/// Source points the hybrid accumulation handles side by side.
const LANES: usize = 8;

/// The hybrid residual rows of one chunk, [`LANES`] source points at a time.
///
/// Each step of the per-point work runs over all lanes in a branch-free loop that the compiler
/// vectorises; only the target lookups are scalar. A lane that fails a test (outside the image,
/// an outlier, an unknown slope, or padding past the chunk's end) keeps computing and is zeroed
/// at the end. Its rows are then exact zeros, which add nothing to the normal equations. It gives
/// the same sums as one point at a time, up to the order of addition (tested against that
/// version). [`wide::accumulate_hybrid`] runs it in 256-bit registers where the CPU has them.
#[inline(always)]
fn accumulate_hybrid(ctx: &Association<'_>, points: &[SourcePoint], step: &mut ChunkSums) {
    let target = ctx.target;
    let cam = target.camera;
    let r = &ctx.transform.rotation;
    let t = &ctx.transform.translation;
    let w = target.width;
    let (u_max, v_max) = ((w - 1) as f32, (target.height - 1) as f32);
    for group in points.chunks(LANES) {
        // Padding lanes: a point behind the camera fails the first test.
        let mut p = [[0.0; LANES]; 3];
        let mut source_intensity = [0.0; LANES];
        p[2] = [-1.0; LANES];
        for (l, s) in group.iter().enumerate() {
            for (axis, &x) in p.iter_mut().zip(&s.point) {
                axis[l] = x;
            }
            source_intensity[l] = s.intensity;
        }
        let mut q = [[0.0; LANES]; 3];
        for (a, qa) in q.iter_mut().enumerate() {
            for l in 0..LANES {
                qa[l] = r[a][0] * p[0][l] + r[a][1] * p[1][l] + r[a][2] * p[2][l] + t[a];
            }
        }
        let mut inv_z = [0.0; LANES];
        let mut u = [0.0; LANES];
        let mut v = [0.0; LANES];
        let mut ok = [false; LANES];
        for l in 0..LANES {
            inv_z[l] = 1.0 / q[2][l];
            let (ul, vl) = (
                cam.fx * q[0][l] * inv_z[l] + cam.cx,
                cam.fy * q[1][l] * inv_z[l] + cam.cy,
            );
            // NaN and points behind the camera fail too.
            ok[l] = q[2][l] > 0.0 && ul >= 0.0 && vl >= 0.0 && ul < u_max && vl < v_max;
            // Failed lanes look up pixel 0, so every lookup stays in bounds.
            u[l] = if ok[l] { ul } else { 0.0 };
            v[l] = if ok[l] { vl } else { 0.0 };
        }
        let mut fu = [0.0; LANES];
        let mut fv = [0.0; LANES];
        let mut index = [0_usize; LANES];
        for l in 0..LANES {
            // Non-negative here, so truncation is the floor; via i32, which is cheaper.
            let (u0, v0) = (u[l] as i32, v[l] as i32);
            fu[l] = u[l] - u0 as f32;
            fv[l] = v[l] - v0 as f32;
            index[l] = v0 as usize * w + u0 as usize;
        }
        // The four corners' depth and intensity, and the slopes of the nearest corner
        // (values are interpolated so the residual varies smoothly; slopes only steer).
        let mut corner_depth = [[0.0; LANES]; 4];
        let mut corner_intensity = [[0.0; LANES]; 4];
        let mut slopes = [[0.0; LANES]; 4];
        for l in 0..LANES {
            let i = index[l];
            let corners = [i, i + 1, i + w, i + w + 1];
            let nearest = usize::from(fu[l] >= 0.5) + 2 * usize::from(fv[l] >= 0.5);
            for (c, &at) in corners.iter().enumerate() {
                let Some(pixel) = target.target.get(at) else {
                    ok[l] = false;
                    continue;
                };
                corner_depth[c][l] = pixel.depth;
                corner_intensity[c][l] = pixel.intensity;
                if c == nearest {
                    slopes[0][l] = pixel.depth_dx;
                    slopes[1][l] = pixel.depth_dy;
                    slopes[2][l] = pixel.intensity_dx;
                    slopes[3][l] = pixel.intensity_dy;
                }
            }
        }
        let mut depth = [0.0; LANES];
        let mut intensity = [0.0; LANES];
        for l in 0..LANES {
            let qz = q[2][l];
            // Any corner without depth within the outlier threshold (NaN fails) makes an
            // outlier; a depth slope next to a hole or across an edge is NaN.
            let mut near = (slopes[0][l] + slopes[1][l]).is_finite();
            for corner in &corner_depth {
                near &= (corner[l] - qz).abs() <= ctx.trunc;
            }
            ok[l] &= near;
            let (a, b) = (fu[l], fv[l]);
            let weights = [(1.0 - a) * (1.0 - b), a * (1.0 - b), (1.0 - a) * b, a * b];
            let mut d = 0.0;
            let mut i = 0.0;
            for c in 0..4 {
                d += weights[c] * corner_depth[c][l];
                i += weights[c] * corner_intensity[c][l];
            }
            depth[l] = d;
            intensity[l] = i;
        }
        // Both rows carry the √λ = √½ weight, folded into slopes and residuals.
        let mut rows = [[[0.0; LANES]; 7]; 2];
        for l in 0..LANES {
            let q_l = [q[0][l], q[1][l], q[2][l]];
            let mut j_d = image_jacobian(
                SQRT_HALF * slopes[0][l],
                SQRT_HALF * slopes[1][l],
                &q_l,
                cam.fx,
                cam.fy,
            );
            // The depth residual also moves with the point's own z:
            // ∂q_z/∂ξ = (q_y, −q_x, 0, 0, 0, 1).
            j_d[0] -= SQRT_HALF * q_l[1];
            j_d[1] += SQRT_HALF * q_l[0];
            j_d[5] -= SQRT_HALF;
            let j_i = image_jacobian(
                SQRT_HALF * slopes[2][l],
                SQRT_HALF * slopes[3][l],
                &q_l,
                cam.fx,
                cam.fy,
            );
            let r_i = SQRT_HALF * (intensity[l] - source_intensity[l]);
            let r_d = SQRT_HALF * (depth[l] - q_l[2]);
            let s_i = if ok[l] {
                huber_sqrt_weight(r_i, ctx.intensity_huber)
            } else {
                0.0
            };
            let s_d = if ok[l] {
                huber_sqrt_weight(r_d, ctx.depth_huber)
            } else {
                0.0
            };
            // Selected rather than multiplied: a failed lane may hold NaN, and 0 · NaN is NaN.
            for k in 0..6 {
                rows[0][k][l] = if ok[l] { s_i * j_i[k] } else { 0.0 };
                rows[1][k][l] = if ok[l] { s_d * j_d[k] } else { 0.0 };
            }
            rows[0][6][l] = if ok[l] { s_i * r_i } else { 0.0 };
            rows[1][6][l] = if ok[l] { s_d * r_d } else { 0.0 };
        }
        step.add_group(&rows[0]);
        step.add_group(&rows[1]);
        step.inliers += ok.iter().filter(|&&ok| ok).count();
    }
}

/// `√w` of the Huber weight `w = min(1, δ/|r|)`, branch-free (`r = 0` gives 1).
#[inline(always)]
fn huber_sqrt_weight(r: f32, delta: f32) -> f32 {
    (delta / r.abs()).sqrt().min(1.0)
}

/// The point-at-a-time hybrid accumulation that [`accumulate_hybrid`] replaced, kept as the
/// reference its lanes are tested against.
#[cfg(test)]
fn accumulate_hybrid_pointwise(
    ctx: &Association<'_>,
    points: &[SourcePoint],
    step: &mut ChunkSums,
) {
    let cam = ctx.target.camera;
    for s in points {
        let Some(sample) = ctx.associate_bilinear(&s.point) else {
            continue;
        };
        let (q, nearest) = (sample.q, sample.nearest);
        let (depth, intensity) = (sample.depth(), sample.intensity());
        // A depth slope next to a hole or across an edge is NaN.
        if !(nearest.depth_dx + nearest.depth_dy).is_finite() {
            continue;
        }
        // Both rows carry the √λ = √½ weight, folded into the slopes.
        let j_i = image_jacobian(
            SQRT_HALF * nearest.intensity_dx,
            SQRT_HALF * nearest.intensity_dy,
            &q,
            cam.fx,
            cam.fy,
        );
        let mut j_d = image_jacobian(
            SQRT_HALF * nearest.depth_dx,
            SQRT_HALF * nearest.depth_dy,
            &q,
            cam.fx,
            cam.fy,
        );
        // The depth residual also moves with the point's own z: ∂q_z/∂ξ = (q_y, −q_x, 0, 0, 0, 1).
        j_d[0] -= SQRT_HALF * q[1];
        j_d[1] += SQRT_HALF * q[0];
        j_d[5] -= SQRT_HALF;
        step.add(
            &j_i,
            SQRT_HALF * (intensity - s.intensity),
            ctx.intensity_huber,
        );
        step.add(&j_d, SQRT_HALF * (depth - q[2]), ctx.depth_huber);
        step.inliers += 1;
    }
}

fn accumulate_intensity(ctx: &Association<'_>, points: &[SourcePoint], step: &mut ChunkSums) {
    let cam = ctx.target.camera;
    let huber = ctx.intensity_huber / SQRT_HALF;
    for s in points {
        let Some(sample) = ctx.associate_bilinear(&s.point) else {
            continue;
        };
        let n = sample.nearest;
        let j = image_jacobian(n.intensity_dx, n.intensity_dy, &sample.q, cam.fx, cam.fy);
        step.add(&j, sample.intensity() - s.intensity, huber);
        step.inliers += 1;
    }
}

fn accumulate_point_to_plane(ctx: &Association<'_>, points: &[SourcePoint], step: &mut ChunkSums) {
    let cam = ctx.target.camera;
    let width = ctx.target.width;
    let huber = ctx.depth_huber / SQRT_HALF;
    for s in points {
        let Some((q, idx)) = ctx.associate_nearest(&s.point) else {
            continue;
        };
        let z = ctx.target.target[idx].depth;
        let Some(n) = ctx.target.normals.get(idx) else {
            continue;
        };
        if z.is_nan() || n[0].is_nan() {
            continue;
        }
        let u = (idx % width) as f32;
        let v = (idx / width) as f32;
        let p = [(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z];
        let r = (q[0] - p[0]) * n[0] + (q[1] - p[1]) * n[1] + (q[2] - p[2]) * n[2];
        if r.is_nan() || r.abs() > ctx.trunc {
            continue;
        }
        let j = [
            q[1] * n[2] - q[2] * n[1],
            q[2] * n[0] - q[0] * n[2],
            q[0] * n[1] - q[1] * n[0],
            n[0],
            n[1],
            n[2],
        ];
        step.add(&j, r, huber);
        step.inliers += 1;
    }
}

/// The hybrid accumulation compiled a second time for AVX2, chosen at run time.
///
/// Why: [`accumulate_hybrid`] works on arrays of [`LANES`] = 8 `f32`, which baseline x86-64 (SSE2)
/// splits into two 128-bit halves; built for AVX2 the same code keeps each in one 256-bit
/// register, and it takes 37 % less time on the shared sequence, where it is two thirds of the
/// odometry's time (BENCHMARKS.md). It is the same IEEE arithmetic lane by lane (no fused
/// multiply-add is enabled), so the sums equal the baseline build's bit for bit (tested). The
/// only `unsafe` is the call into the AVX2 build, made after the CPU was found to have AVX2.
mod wide {
    use super::{Association, ChunkSums, SourcePoint};

    /// [`super::accumulate_hybrid`], in AVX2 where the CPU has it.
    pub(super) fn accumulate_hybrid(
        ctx: &Association<'_>,
        points: &[SourcePoint],
        step: &mut ChunkSums,
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            #[allow(
                unsafe_code,
                reason = "calls a function built for AVX2, on a CPU just found to have it"
            )]
            // SAFETY: `accumulate_hybrid_avx2` needs AVX2 and nothing else, and the CPU has it.
            unsafe {
                accumulate_hybrid_avx2(ctx, points, step);
            }
            return;
        }
        super::accumulate_hybrid(ctx, points, step);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn accumulate_hybrid_avx2(ctx: &Association<'_>, points: &[SourcePoint], step: &mut ChunkSums) {
        super::accumulate_hybrid(ctx, points, step);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test")]

    use std::path::Path;

    use nalgebra::{Translation3, UnitQuaternion};
    use vlem_core::config::DatasetConfig;

    use super::*;

    /// The lanes give the point-at-a-time normal equations: the same inliers, and sums equal up
    /// to f32 rounding in the order of addition; the AVX2 build gives exactly the baseline's.
    /// Motions up to several centimetres push points off the image and onto depth edges, so
    /// every rejection path is taken; level sizes are not multiples of the lane count, so
    /// padding lanes are too.
    #[test]
    fn hybrid_lanes_match_pointwise() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/living-room");
        let mut frames = vlem_datasets::open(&DatasetConfig::default(), &dir).unwrap();
        let config = OdometryConfig::default();
        let params = config.pyramid_params();
        let mut build = |i: usize| {
            let f = frames.frame(i).unwrap();
            Pyramid::build(&f.colour, &f.depth, &f.intrinsics, &params)
        };
        let (source, target) = (build(3), build(0));
        let motions = [
            Isometry3::identity(),
            Isometry3::from_parts(
                Translation3::new(0.01, -0.005, 0.008),
                UnitQuaternion::from_euler_angles(0.01, -0.015, 0.005),
            ),
            Isometry3::from_parts(
                Translation3::new(-0.06, 0.04, 0.05),
                UnitQuaternion::from_euler_angles(-0.05, 0.04, 0.03),
            ),
        ];
        for motion in &motions {
            for (level, (src, tgt)) in source.levels.iter().zip(&target.levels).enumerate() {
                assert_ne!(
                    src.source.len() % LANES,
                    0,
                    "level {level} has no padding lanes"
                );
                let ctx = Association::new(tgt, motion, &config);
                let lanes = linearise_with(src, &ctx, accumulate_hybrid);
                let pointwise = linearise_with(src, &ctx, accumulate_hybrid_pointwise);
                // The AVX2 build (where this CPU has AVX2) sums bit for bit as the baseline
                // build, over the level as one chunk (parallel chunks merge in varying order).
                let whole_level = |accumulate: Accumulate| {
                    let mut sums = ChunkSums::new();
                    accumulate(&ctx, &src.source, &mut sums);
                    let step = sums.normal_equations();
                    (step.h, step.b, step.squared.to_bits(), step.inliers)
                };
                assert_eq!(
                    whole_level(wide::accumulate_hybrid),
                    whole_level(accumulate_hybrid),
                    "level {level}"
                );
                assert!(
                    pointwise.inliers > 1000,
                    "level {level}: {}",
                    pointwise.inliers
                );
                assert!(
                    pointwise.inliers < src.source.len(),
                    "level {level}: no outliers"
                );
                assert_eq!(lanes.inliers, pointwise.inliers, "level {level}");
                let scale = pointwise.h.iter().fold(0.0_f64, |m, x| m.max(x.abs()));
                for (a, b) in lanes.h.iter().zip(&pointwise.h) {
                    assert!((a - b).abs() <= 1e-5 * scale, "level {level}: H {a} vs {b}");
                }
                let scale = pointwise.b.iter().fold(0.0_f64, |m, x| m.max(x.abs()));
                for (a, b) in lanes.b.iter().zip(&pointwise.b) {
                    assert!((a - b).abs() <= 1e-5 * scale, "level {level}: b {a} vs {b}");
                }
                let relative = (lanes.squared - pointwise.squared).abs() / pointwise.squared;
                assert!(
                    relative <= 1e-5,
                    "level {level}: squared residual off by {relative}"
                );
            }
        }
    }
}
