//! `ground-truth`: poses read from the dataset (ground truth or offline SLAM estimates).
//!
//! What comparison studies and the paper's ScanNet protocol use; it makes mapping independent of
//! tracking quality.

use serde::Deserialize;
use vlem_core::{
    BuildContext, CoreError, Frame, StageKind, TrackedPose, Tracker, TrackingState, parse_params,
};

use crate::error::TrackerError;

/// The registered name.
pub const NAME: &str = "ground-truth";

/// `[tracker] kind = "ground-truth"` takes no parameters.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundTruthConfig {}

/// Returns each frame's dataset pose.
#[derive(Clone, Debug, Default)]
pub struct GroundTruthTracker;

fn build(params: &toml::Table, _ctx: &BuildContext) -> vlem_core::Result<Box<dyn Tracker>> {
    let _: GroundTruthConfig = parse_params(StageKind::Tracker, NAME, params)?;
    Ok(Box::new(GroundTruthTracker))
}

vlem_core::register_tracker!(NAME, "poses from the dataset's trajectory file", build);

impl Tracker for GroundTruthTracker {
    fn name(&self) -> &'static str {
        NAME
    }

    fn needs_dataset_poses(&self) -> bool {
        true
    }

    fn track(&mut self, frame: &Frame) -> vlem_core::Result<TrackedPose> {
        let pose = frame.pose.ok_or_else(|| {
            CoreError::stage(
                StageKind::Tracker,
                NAME,
                TrackerError::MissingPose { frame: frame.index },
            )
        })?;
        Ok(TrackedPose {
            pose,
            state: TrackingState::Tracking,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vlem_core::{DepthImage, Intrinsics, Pose, RgbImage};

    fn frame(pose: Option<Pose>) -> Frame {
        let k = Intrinsics::new(2, 2, 1.0, 1.0, 1.0, 1.0).unwrap();
        Frame::new(
            4,
            0.0,
            RgbImage::filled(2, 2, [0, 0, 0]),
            DepthImage::new(2, 2, vec![1.0; 4]).unwrap(),
            k,
            pose,
        )
        .unwrap()
    }

    #[test]
    fn returns_the_dataset_pose() {
        let pose = Pose::translation(1.0, 2.0, 3.0);
        let tracked = GroundTruthTracker.track(&frame(Some(pose))).unwrap();
        assert_eq!(tracked.pose, pose);
        assert_eq!(tracked.state, TrackingState::Tracking);
    }

    #[test]
    fn missing_pose_is_an_error_naming_the_frame() {
        let err = GroundTruthTracker.track(&frame(None)).unwrap_err();
        assert!(
            err.to_string().starts_with(
                "tracker `ground-truth`: frame 4 has no pose: the dataset has no trajectory"
            ),
            "{err}"
        );
    }
}
