//! `odometry`: frame-to-frame dense RGB-D odometry.
//!
//! Why it exists: the paper's "Localisation" tracks the camera itself, so vlem maps any RGB-D
//! stream without ground-truth poses. Each frame is registered to the previous one with the hybrid
//! photometric + geometric objective (Steinbrücker et al. 2011; Park et al. 2017), coarse to fine
//! over an image pyramid, and the relative motions are chained. Defaults are those of Open3D's
//! `t.pipelines.odometry.rgbd_odometry_multi_scale`, so results compare one to one.
//!
//! What it owns: the previous frame's [`Pyramid`] and pose. A frame with too little valid depth, a
//! singular solve, too few inliers or an implausible jump is reported lost: the pose stays where
//! it was (constant position), the frame is not integrated, and the next frame is registered to
//! the last frame that tracked.
//!
//! ```toml
//! [tracker]
//! kind = "odometry"
//! method = "hybrid"        # or "point-to-plane", "intensity"
//! iterations = [10, 5, 3]  # per pyramid level, coarsest first
//! depth_max = 3.0
//! ```

pub mod pyramid;
pub mod solver;

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use vlem_core::{
    BuildContext, CoreError, Frame, Pose, StageKind, TrackedPose, Tracker, TrackingState,
    parse_params,
};

pub use pyramid::{Pyramid, PyramidParams};
pub use solver::{Method, Registration, SolveFailure, register};

use crate::error::TrackerError;

/// The registered name.
pub const NAME: &str = "odometry";

/// Parameters of dense RGB-D registration and of the tracking-loss tests, shared by `odometry`
/// and `frame-to-model`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OdometryConfig {
    /// Residual terms: `hybrid` (default), `point-to-plane` or `intensity`.
    pub method: Method,
    /// Gauss–Newton iterations per pyramid level, coarsest first; the length is the number of
    /// levels. Default `[10, 5, 3]`.
    pub iterations: Vec<usize>,
    /// Depths beyond this many metres are ignored. Default 3.
    pub depth_max: f32,
    /// Associations whose depths differ by more than this many metres are outliers. Default 0.07.
    pub depth_outlier_trunc: f32,
    /// Huber threshold of depth residuals, metres. Default 0.05.
    pub depth_huber_delta: f32,
    /// Huber threshold of intensity residuals (intensity in `[0, 1]`). Default 0.1.
    pub intensity_huber_delta: f32,
    /// A level stops early when the inlier RMSE changes by less than this fraction (and the
    /// fitness by less than `relative_fitness`). Default 1e-6.
    pub relative_rmse: f64,
    /// See `relative_rmse`. Default 1e-6.
    pub relative_fitness: f64,
    /// A level also stops early when an update moves no point by more than this many metres
    /// at full resolution, `2^level` times this at pyramid level `level` (an extra test Open3D
    /// does not have; 0 disables it). Default 1e-4 (0.1 mm).
    pub min_update: f64,
    /// A frame with valid depth in fewer than this fraction of its pixels is lost. Default 0.05.
    pub min_valid_depth_fraction: f64,
    /// A registration with fewer inliers than this fraction of the frame's valid pixels is
    /// lost. Default 0.1.
    pub min_fitness: f64,
    /// A frame-to-frame translation above this many metres is lost. Default 0.3.
    pub max_translation: f64,
    /// A frame-to-frame rotation above this many degrees is lost. Default 30.
    pub max_rotation_degrees: f64,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self {
            method: Method::Hybrid,
            iterations: vec![10, 5, 3],
            depth_max: 3.0,
            depth_outlier_trunc: 0.07,
            depth_huber_delta: 0.05,
            intensity_huber_delta: 0.1,
            relative_rmse: 1e-6,
            relative_fitness: 1e-6,
            min_update: 1e-4,
            min_valid_depth_fraction: 0.05,
            min_fitness: 0.1,
            max_translation: 0.3,
            max_rotation_degrees: 30.0,
        }
    }
}

/// Gauss-Newton iterations one pyramid level may ask for: the defaults are 10, 5 and 3, and
/// each iteration is a pass over the level, so more than this runs for minutes a frame.
pub const MAX_ITERATIONS: usize = 1000;

impl OdometryConfig {
    /// Checks every parameter; the error names the first bad one.
    ///
    /// # Errors
    /// [`TrackerError::InvalidParameter`].
    pub fn validate(&self) -> Result<(), TrackerError> {
        let bad = |name: &'static str, reason: String| {
            Err(TrackerError::InvalidParameter { name, reason })
        };
        if self.iterations.is_empty() || self.iterations.len() > 8 {
            return bad(
                "iterations",
                format!("needs 1 to 8 pyramid levels, got {}", self.iterations.len()),
            );
        }
        if self.iterations.last() == Some(&0) {
            return bad(
                "iterations",
                "the finest level (the last entry) needs at least one iteration".into(),
            );
        }
        if let Some(&many) = self.iterations.iter().find(|&&n| n > MAX_ITERATIONS) {
            return bad(
                "iterations",
                format!(
                    "at most {MAX_ITERATIONS} per pyramid level (each is a pass over the frame), \
                     got {many}"
                ),
            );
        }
        let positive = [
            ("depth_max", f64::from(self.depth_max)),
            ("depth_outlier_trunc", f64::from(self.depth_outlier_trunc)),
            ("depth_huber_delta", f64::from(self.depth_huber_delta)),
            (
                "intensity_huber_delta",
                f64::from(self.intensity_huber_delta),
            ),
            ("max_translation", self.max_translation),
            ("max_rotation_degrees", self.max_rotation_degrees),
        ];
        for (name, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return bad(name, format!("must be a positive number, got {value}"));
            }
        }
        let fractions = [
            ("relative_rmse", self.relative_rmse),
            ("relative_fitness", self.relative_fitness),
            ("min_update", self.min_update),
            ("min_valid_depth_fraction", self.min_valid_depth_fraction),
            ("min_fitness", self.min_fitness),
        ];
        for (name, value) in fractions {
            if !(0.0..=1.0).contains(&value) {
                return bad(name, format!("must lie in [0, 1], got {value}"));
            }
        }
        Ok(())
    }

    /// How frames are prepared for this configuration, for both roles (registered, and
    /// registered to).
    pub fn pyramid_params(&self) -> PyramidParams {
        PyramidParams {
            levels: self.iterations.len(),
            depth_max: self.depth_max,
            depth_downsample_diff: 2.0 * self.depth_outlier_trunc,
            normals: self.method == Method::PointToPlane,
            as_source: true,
            as_target: true,
        }
    }

    /// Why a frame cannot be tracked before registering it, if it cannot.
    pub fn check_frame(&self, frame: &Frame, pyramid: &Pyramid) -> Option<String> {
        let pixels = frame.intrinsics.width as f64 * frame.intrinsics.height as f64;
        let fraction = pyramid.valid_pixels as f64 / pixels;
        (fraction < self.min_valid_depth_fraction).then(|| {
            format!(
                "too little valid depth: {:.1}% of the pixels within {} m (minimum {:.1}%)",
                100.0 * fraction,
                self.depth_max,
                100.0 * self.min_valid_depth_fraction
            )
        })
    }

    /// Registers `source` to `target` from `init` and applies the tracking-loss tests: the
    /// source-to-target motion, or why tracking is lost.
    pub fn track(
        &self,
        source: &Pyramid,
        target: &Pyramid,
        init: &Isometry3<f64>,
    ) -> Result<Registration, String> {
        let registration = register(source, target, init, self)
            .map_err(|failure| format!("registration failed: {failure}"))?;
        let motion = &registration.source_to_target;
        let translation = motion.translation.vector.norm();
        let rotation = motion.rotation.angle().to_degrees();
        if !(translation.is_finite() && rotation.is_finite()) {
            return Err("registration diverged to a non-finite motion".into());
        }
        if registration.fitness < self.min_fitness {
            return Err(format!(
                "too few inliers: {:.1}% of the valid pixels (minimum {:.1}%)",
                100.0 * registration.fitness,
                100.0 * self.min_fitness
            ));
        }
        if translation > self.max_translation || rotation > self.max_rotation_degrees {
            return Err(format!(
                "implausible motion of {translation:.3} m and {rotation:.1}° in one frame \
                 (limits {} m, {}°)",
                self.max_translation, self.max_rotation_degrees
            ));
        }
        Ok(registration)
    }
}

/// The pose of the first frame: the dataset's where it has one (so the estimate shares the
/// reference's world frame), else the identity.
pub(crate) fn initial_pose(frame: &Frame) -> Pose {
    frame.pose.unwrap_or_else(Pose::identity)
}

/// Frame-to-frame dense RGB-D odometry.
#[derive(Debug)]
pub struct OdometryTracker {
    config: OdometryConfig,
    /// The last frame that tracked, and its pose.
    reference: Option<(Pyramid, Pose)>,
    /// Buffers for the next frame's pyramid (the previous reference's, recycled).
    spare: Pyramid,
    /// Where the camera is believed to be (the last tracked pose).
    pose: Option<Pose>,
}

impl OdometryTracker {
    /// A tracker with validated parameters.
    ///
    /// # Errors
    /// [`TrackerError::InvalidParameter`] naming the bad parameter.
    pub fn new(config: OdometryConfig) -> Result<Self, TrackerError> {
        config.validate()?;
        Ok(Self {
            config,
            reference: None,
            spare: Pyramid::default(),
            pose: None,
        })
    }
}

fn build(params: &toml::Table, _ctx: &BuildContext) -> vlem_core::Result<Box<dyn Tracker>> {
    let config: OdometryConfig = parse_params(StageKind::Tracker, NAME, params)?;
    let tracker =
        OdometryTracker::new(config).map_err(|e| CoreError::stage(StageKind::Tracker, NAME, e))?;
    Ok(Box::new(tracker))
}

vlem_core::register_tracker!(
    NAME,
    "frame-to-frame dense RGB-D odometry (hybrid photometric + geometric, coarse to fine)",
    build
);

impl Tracker for OdometryTracker {
    fn name(&self) -> &'static str {
        NAME
    }

    fn track(&mut self, frame: &Frame) -> vlem_core::Result<TrackedPose> {
        let mut pyramid = std::mem::take(&mut self.spare);
        pyramid.rebuild(
            &frame.colour,
            &frame.depth,
            &frame.intrinsics,
            &self.config.pyramid_params(),
        );
        let fallback = *self.pose.get_or_insert_with(|| initial_pose(frame));
        if let Some(reason) = self.config.check_frame(frame, &pyramid) {
            self.spare = pyramid;
            return Ok(lost(fallback, reason));
        }
        let Some((target, target_pose)) = &self.reference else {
            self.reference = Some((pyramid, fallback));
            return Ok(tracking(fallback));
        };
        match self.config.track(&pyramid, target, &Isometry3::identity()) {
            Ok(registration) => {
                let pose = target_pose * registration.source_to_target;
                if let Some((old, _)) = self.reference.replace((pyramid, pose)) {
                    self.spare = old;
                }
                self.pose = Some(pose);
                Ok(tracking(pose))
            }
            Err(reason) => {
                self.spare = pyramid;
                Ok(lost(fallback, reason))
            }
        }
    }
}

pub(crate) fn tracking(pose: Pose) -> TrackedPose {
    TrackedPose {
        pose,
        state: TrackingState::Tracking,
    }
}

pub(crate) fn lost(pose: Pose, reason: String) -> TrackedPose {
    TrackedPose {
        pose,
        state: TrackingState::Lost { reason },
    }
}
