//! Tracking accuracy against exact ground truth: the project's own ray-cast synthetic scene
//! (`vlem_datasets::synthetic`), whose poses are exact by construction.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use vlem_core::{Pose, Tracker, TrackingState};
use vlem_datasets::SyntheticConfig;
use vlem_datasets::SyntheticScene;
use vlem_trackers::frame_to_model::{FrameToModelConfig, FrameToModelTracker};
use vlem_trackers::odometry::{OdometryConfig, Pyramid, register};

/// A 320×240 scene (a quarter of the pixels keeps the suite fast; the trackers' parameters are
/// in metres and pyramid levels, so they carry over).
fn scene(frames: usize) -> SyntheticScene {
    SyntheticScene::new(&SyntheticConfig {
        seed: 3,
        frames,
        width: 320,
        height: 240,
        ..SyntheticConfig::default()
    })
    .unwrap()
}

#[test]
fn odometry_converges_from_a_5cm_5deg_offset_between_two_frames() {
    let scene = scene(40);
    let config = OdometryConfig::default();
    let (a, b) = (scene.render(20).unwrap(), scene.render(21).unwrap());
    let prepare = |v: &vlem_datasets::synthetic::SyntheticView| {
        Pyramid::build(&v.colour, &v.depth, &v.intrinsics, &config.pyramid_params())
    };
    let (source, target) = (prepare(&b), prepare(&a));
    // Maps frame 21's camera coordinates into frame 20's.
    let truth: Pose = a.pose.inverse() * b.pose;
    for (axis, sign) in [
        (Vector3::x_axis(), 1.0),
        (Vector3::y_axis(), -1.0),
        (Vector3::z_axis(), 1.0),
    ] {
        let offset = Isometry3::from_parts(
            Translation3::new(0.029 * sign, 0.029, -0.029 * sign),
            UnitQuaternion::from_axis_angle(&axis, sign * 5f64.to_radians()),
        );
        assert!((offset.translation.vector.norm() - 0.05).abs() < 1e-3);
        let found = register(&source, &target, &(offset * truth), &config).unwrap();
        let error = truth.inverse() * found.source_to_target;
        let (t, r) = (
            error.translation.vector.norm(),
            error.rotation.angle().to_degrees(),
        );
        assert!(
            t < 1e-3 && r < 0.05,
            "offset about {axis:?}: left {t} m, {r} deg"
        );
    }
}

#[test]
fn frame_to_model_tracks_120_frames_within_1cm_ate() {
    let frames = 120;
    let scene = scene(frames);
    let mut tracker = FrameToModelTracker::new(FrameToModelConfig::default()).unwrap();
    let (mut estimate, mut reference) = (Vec::new(), Vec::new());
    for i in 0..frames {
        let view = scene.render(i).unwrap();
        let truth = view.pose;
        let frame = view.into_frame(i, i as f64).unwrap();
        let tracked = tracker.track(&frame).unwrap();
        assert_eq!(tracked.state, TrackingState::Tracking, "frame {i}");
        estimate.push(tracked.pose);
        reference.push(truth);
    }
    let ate = vlem_eval::trajectory::ate(&estimate, &reference, false).unwrap();
    let rpe = vlem_eval::trajectory::rpe(&estimate, &reference, 1).unwrap();
    eprintln!(
        "frame-to-model on {frames} synthetic frames: ATE rmse {:.2} mm, max {:.2} mm; RPE {:.2} mm, {:.3} deg",
        ate.position.rmse * 1e3,
        ate.position.max * 1e3,
        rpe.translation.rmse * 1e3,
        rpe.rotation.rmse
    );
    assert!(ate.position.max < 0.01, "ATE max {} m", ate.position.max);
}
