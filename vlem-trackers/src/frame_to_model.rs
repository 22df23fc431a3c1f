//! `frame-to-model`: dense RGB-D tracking against a TSDF model of everything seen so far.
//!
//! Why it exists: chaining frame-to-frame motions accumulates every registration error. Here each
//! tracked frame is fused into a TSDF voxel-block map ([`TsdfVolume`]), and the next frame is
//! registered to a depth + colour image ray-cast from that map at the previous pose, which
//! averages noise over many frames and cuts drift (KinectFusion; Open3D's `t.pipelines.slam`).
//!
//! What it owns: the volume, the ray-cast model frame and the last pose. Lost frames (see
//! [`OdometryConfig`]) keep the last pose and are neither integrated nor used as a model. The
//! volume's surface can be exported as a coloured mesh ([`Tracker::colour_model`]).
//!
//! ```toml
//! [tracker]
//! kind = "frame-to-model"
//!
//! [tracker.odometry]       # as for `odometry`
//! iterations = [6, 3, 1]
//!
//! [tracker.volume]
//! voxel_size = 0.005859375 # 3/512 m
//! truncation_voxels = 8
//! ```

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use vlem_core::{
    BuildContext, ColouredMesh, CoreError, Frame, Pose, StageKind, TrackedPose, Tracker,
    parse_params,
};

use crate::error::TrackerError;
use crate::odometry::{OdometryConfig, Pyramid, PyramidParams, initial_pose, lost, tracking};
use crate::tsdf::{RaycastOptions, TsdfConfig, TsdfVolume};

/// The registered name.
pub const NAME: &str = "frame-to-model";

/// `[tracker] kind = "frame-to-model"`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct FrameToModelConfig {
    /// Registration and tracking-loss parameters (`[tracker.odometry]`).
    pub odometry: OdometryConfig,
    /// The TSDF volume (`[tracker.volume]`).
    pub volume: VolumeConfig,
}

impl Default for FrameToModelConfig {
    fn default() -> Self {
        Self {
            odometry: OdometryConfig {
                iterations: vec![6, 3, 1],
                ..OdometryConfig::default()
            },
            volume: VolumeConfig::default(),
        }
    }
}

/// `[tracker.volume]`: the TSDF voxel-block map.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct VolumeConfig {
    /// Voxel edge in metres. Default 3/512 m, as Open3D's SLAM model.
    pub voxel_size: f32,
    /// Truncation distance in voxels. Default 8.
    pub truncation_voxels: f32,
    /// Depths beyond this many metres are not integrated. Default 3.
    pub depth_max: f32,
}

impl Default for VolumeConfig {
    fn default() -> Self {
        let defaults = TsdfConfig::default();
        Self {
            voxel_size: defaults.voxel_size,
            truncation_voxels: defaults.truncation_voxels,
            depth_max: defaults.depth_max,
        }
    }
}

impl VolumeConfig {
    fn tsdf_config(&self) -> TsdfConfig {
        TsdfConfig {
            voxel_size: self.voxel_size,
            truncation_voxels: self.truncation_voxels,
            depth_max: self.depth_max,
            ..TsdfConfig::default()
        }
    }
}

/// The model a frame is tracked against: the prepared ray-cast and the pose it was cast from.
#[derive(Debug)]
struct Model {
    pyramid: Pyramid,
    pose: Pose,
}

/// Frame-to-model tracking on a TSDF voxel-block map.
#[derive(Debug)]
pub struct FrameToModelTracker {
    config: FrameToModelConfig,
    volume: TsdfVolume,
    model: Option<Model>,
    /// The current frame's pyramid, rebuilt in place every frame (reusing its buffers).
    current: Pyramid,
    pose: Option<Pose>,
}

impl FrameToModelTracker {
    /// A tracker with validated parameters and an empty volume.
    ///
    /// # Errors
    /// [`TrackerError::InvalidParameter`] naming the bad parameter.
    pub fn new(config: FrameToModelConfig) -> Result<Self, TrackerError> {
        config.odometry.validate()?;
        let volume = TsdfVolume::new(config.volume.tsdf_config())?;
        Ok(Self {
            config,
            volume,
            model: None,
            current: Pyramid::default(),
            pose: None,
        })
    }

    /// The TSDF volume built so far.
    pub fn volume(&self) -> &TsdfVolume {
        &self.volume
    }

    /// Fuses `frame` at `pose` and casts the model the next frame is tracked against.
    fn integrate_and_cast(&mut self, frame: &Frame, pose: Pose) {
        self.volume
            .integrate(&frame.depth, &frame.colour, &frame.intrinsics, &pose);
        // Cast from the pose just fused, so rays may start near the depth just measured.
        let cast = self.volume.raycast_near_depth(
            &frame.intrinsics,
            &pose,
            &RaycastOptions::default(),
            &frame.depth,
        );
        // The previous model's pyramid is rebuilt in place: fresh 15 MB buffers every frame cost
        // as much in page faults as the arithmetic.
        let mut pyramid = self
            .model
            .take()
            .map(|model| model.pyramid)
            .unwrap_or_default();
        // The model is only ever registered to.
        let params = PyramidParams {
            as_source: false,
            ..self.config.odometry.pyramid_params()
        };
        pyramid.rebuild(&cast.colour, &cast.depth, &frame.intrinsics, &params);
        self.model = Some(Model { pyramid, pose });
    }
}

fn build(params: &toml::Table, _ctx: &BuildContext) -> vlem_core::Result<Box<dyn Tracker>> {
    let config: FrameToModelConfig = parse_params(StageKind::Tracker, NAME, params)?;
    let tracker = FrameToModelTracker::new(config)
        .map_err(|e| CoreError::stage(StageKind::Tracker, NAME, e))?;
    Ok(Box::new(tracker))
}

vlem_core::register_tracker!(
    NAME,
    "dense RGB-D tracking against a ray-cast TSDF voxel-block model (less drift than odometry)",
    build
);

impl Tracker for FrameToModelTracker {
    fn name(&self) -> &'static str {
        NAME
    }

    fn track(&mut self, frame: &Frame) -> vlem_core::Result<TrackedPose> {
        let odometry = &self.config.odometry;
        // The frame is only ever registered, never registered to.
        let params = PyramidParams {
            as_target: false,
            ..odometry.pyramid_params()
        };
        self.current
            .rebuild(&frame.colour, &frame.depth, &frame.intrinsics, &params);
        let fallback = *self.pose.get_or_insert_with(|| initial_pose(frame));
        if let Some(reason) = odometry.check_frame(frame, &self.current) {
            return Ok(lost(fallback, reason));
        }
        let Some(model) = &self.model else {
            self.integrate_and_cast(frame, fallback);
            return Ok(tracking(fallback));
        };
        match odometry.track(&self.current, &model.pyramid, &Isometry3::identity()) {
            Ok(registration) => {
                let pose = model.pose * registration.source_to_target;
                self.pose = Some(pose);
                self.integrate_and_cast(frame, pose);
                Ok(tracking(pose))
            }
            Err(reason) => Ok(lost(fallback, reason)),
        }
    }

    fn colour_model(&self) -> vlem_core::Result<ColouredMesh> {
        Ok(self.volume.extract_mesh())
    }
}
