//! The vlem-testkit tracker conformance suite for every tracker of this crate, on a few frames of
//! the project's synthetic scene (`vlem_datasets::synthetic`) at 320x240 (the
//! resolution of `synthetic_tracking.rs`: at 160x120 the coarsest pyramid level has too few pixels).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::sync::OnceLock;

use vlem_core::{Frame, Tracker};
use vlem_datasets::SyntheticConfig;
use vlem_datasets::SyntheticScene;
use vlem_trackers::frame_to_model::FrameToModelConfig;
use vlem_trackers::odometry::OdometryConfig;
use vlem_trackers::{FrameToModelTracker, GroundTruthTracker, OdometryTracker};

/// Frames 20 to 25 of the synthetic scene (about 1 cm and 1° apart), with their exact poses.
fn frames() -> Vec<Frame> {
    static FRAMES: OnceLock<Vec<Frame>> = OnceLock::new();
    FRAMES
        .get_or_init(|| {
            let scene = SyntheticScene::new(&SyntheticConfig {
                seed: 3,
                frames: 40,
                width: 320,
                height: 240,
                ..SyntheticConfig::default()
            })
            .unwrap();
            (20..26)
                .map(|i| scene.render(i).unwrap().into_frame(i, i as f64).unwrap())
                .collect()
        })
        .clone()
}

mod ground_truth {
    use super::*;

    fn build() -> Box<dyn Tracker> {
        Box::new(GroundTruthTracker)
    }

    // It returns the dataset's poses: a frame without depth still has one, so nothing is lost.
    vlem_testkit::tracker_conformance!(
        build,
        frames,
        vlem_testkit::tracker::TrackerContract::DatasetPoses
    );
}

mod odometry {
    use super::*;

    fn build() -> Box<dyn Tracker> {
        Box::new(OdometryTracker::new(OdometryConfig::default()).unwrap())
    }

    vlem_testkit::tracker_conformance!(build, frames);
}

mod frame_to_model {
    use super::*;

    fn build() -> Box<dyn Tracker> {
        Box::new(FrameToModelTracker::new(FrameToModelConfig::default()).unwrap())
    }

    vlem_testkit::tracker_conformance!(build, frames);
}
