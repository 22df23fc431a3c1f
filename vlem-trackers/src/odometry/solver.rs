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
//! or when an update moves no point by more than `min_update` metres.

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
            let converged = settled || motion < params.min_update;
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

/// Residual rows one chunk of source points can produce (two per point for hybrid).
const ROWS: usize = 2 * CHUNK;

/// The weighted residual rows of one chunk of pixels, column by column: `√w·J` (6 columns) and
/// `√w·r`. The normal equations are then 28 dot products over contiguous columns, which
/// vectorise, instead of a scalar 6×6 update per residual.
struct ChunkSums {
    columns: Box<[[f32; ROWS]; 7]>,
    rows: usize,
    inliers: usize,
}

impl ChunkSums {
    fn new() -> Self {
        Self {
            columns: Box::new([[0.0; ROWS]; 7]),
            rows: 0,
            inliers: 0,
        }
    }

    /// Adds residual `r` with Jacobian row `j` and its Huber weight; rows beyond the buffer
    /// (impossible with chunks of at most [`CHUNK`] points) are dropped.
    #[inline(always)]
    fn add(&mut self, j: &[f32; 6], r: f32, huber_delta: f32) {
        let n = self.rows;
        if n >= ROWS {
            return;
        }
        let abs = r.abs();
        // √w of the Huber weight w = min(1, δ/|r|).
        let s = if abs <= huber_delta {
            1.0
        } else {
            (huber_delta / abs).sqrt()
        };
        for (column, x) in self.columns.iter_mut().zip(j) {
            column[n] = s * x;
        }
        self.columns[6][n] = s * r;
        self.rows = n + 1;
    }

    /// The chunk's normal equations.
    fn normal_equations(&self) -> Step {
        let mut step = Step {
            inliers: self.inliers,
            ..Step::default()
        };
        let n = self.rows;
        let c = |k: usize| &self.columns[k][..n];
        let mut i = 0;
        for row in 0..6 {
            for col in row..6 {
                step.h[i] = f64::from(dot(c(row), c(col)));
                i += 1;
            }
            step.b[row] = f64::from(dot(c(row), c(6)));
        }
        step.squared = f64::from(dot(c(6), c(6)));
        step
    }
}

/// Dot product with eight independent partial sums, so the compiler can vectorise it.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = a8
        .remainder()
        .iter()
        .zip(b8.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in a8.zip(b8) {
        for l in 0..8 {
            lanes[l] += x[l] * y[l];
        }
    }
    lanes.iter().sum::<f32>() + tail
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
    let ctx = Association {
        transform: RigidF32::from_pose(transform),
        target,
        trunc: params.depth_outlier_trunc,
        depth_huber: params.depth_huber_delta * SQRT_HALF,
        intensity_huber: params.intensity_huber_delta * SQRT_HALF,
    };
    let accumulate: fn(&Association<'_>, &[SourcePoint], &mut ChunkSums) = match params.method {
        Method::Hybrid => accumulate_hybrid,
        Method::Intensity => accumulate_intensity,
        Method::PointToPlane => accumulate_point_to_plane,
    };
    source
        .source
        .par_chunks(CHUNK)
        .map_init(ChunkSums::new, |sums, chunk| {
            sums.rows = 0;
            sums.inliers = 0;
            accumulate(&ctx, chunk, sums);
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

impl Association<'_> {
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
        let (w00, w10, w01, w11) = (
            (1.0 - fu) * (1.0 - fv),
            fu * (1.0 - fv),
            (1.0 - fu) * fv,
            fu * fv,
        );
        Some(Bilinear {
            q: [qx, qy, qz],
            depth: w00 * c00.depth + w10 * c10.depth + w01 * c01.depth + w11 * c11.depth,
            intensity: w00 * c00.intensity
                + w10 * c10.intensity
                + w01 * c01.intensity
                + w11 * c11.intensity,
            nearest,
        })
    }
}

/// A source point moved into the target and the target sampled there.
struct Bilinear<'a> {
    /// The moved point (target camera frame).
    q: [f32; 3],
    /// Interpolated target depth.
    depth: f32,
    /// Interpolated target intensity.
    intensity: f32,
    /// The nearest of the four corners, whose slopes the Jacobians use.
    nearest: &'a TargetPixel,
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

fn accumulate_hybrid(ctx: &Association<'_>, points: &[SourcePoint], step: &mut ChunkSums) {
    let cam = ctx.target.camera;
    for s in points {
        let Some(Bilinear {
            q,
            depth,
            intensity,
            nearest,
        }) = ctx.associate_bilinear(&s.point)
        else {
            continue;
        };
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
        step.add(&j, sample.intensity - s.intensity, huber);
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
