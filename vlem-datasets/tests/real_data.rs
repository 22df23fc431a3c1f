//! The readers on real recordings: the committed ICL-NUIM excerpt and the shared samples.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use nalgebra::Vector3;
use vlem_core::FrameSource;
use vlem_core::config::DatasetConfig;
use vlem_datasets::{IclReader, TumReader, detect_kind, open};

#[test]
fn living_room_frames_intrinsics_and_poses() {
    let dir = common::living_room();
    assert_eq!(detect_kind(&dir).unwrap(), "icl");
    let mut source = open(&DatasetConfig::default(), &dir).unwrap();
    assert_eq!(source.len(), 30);
    assert!(source.has_poses());
    assert!(
        source.describe().contains("ICL-NUIM"),
        "{}",
        source.describe()
    );
    let k = source.intrinsics();
    assert_eq!((k.width, k.height), (640, 480));
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (525.0, 525.0, 319.5, 239.5));

    let first = source.frame(0).unwrap();
    assert_eq!((first.colour.width(), first.colour.height()), (640, 480));
    assert_eq!((first.depth.width(), first.depth.height()), (640, 480));
    assert_eq!(first.index, 0);
    assert_eq!(first.timestamp, 0.0);
    let pose = first.pose.unwrap();
    assert!(pose.translation.vector.norm() < 1e-9);
    assert!(pose.rotation.angle() < 1e-9);
    let valid = first.depth.valid_count();
    assert!(valid > 200_000, "{valid} valid depth pixels");
    let centre = first.depth.get(320, 240).unwrap();
    assert!((0.5..6.0).contains(&centre), "centre depth {centre} m");

    let last = source.frame(29).unwrap();
    assert_eq!(last.timestamp, 29.0);
    let t = last.pose.unwrap().translation.vector;
    assert!(
        (t - Vector3::new(-0.0569, -0.5260, 0.0286)).norm() < 1e-3,
        "frame 29 at {t}"
    );
    assert!(source.frame(30).is_err());
}

#[test]
fn living_room_stride_and_max_frames() {
    let config = DatasetConfig {
        stride: Some(10),
        max_frames: Some(2),
        ..DatasetConfig::default()
    };
    let reader = IclReader::open(&common::living_room(), &config).unwrap();
    assert_eq!(reader.len(), 2);
    let second = reader.load(1).unwrap();
    assert_eq!(second.index, 1);
    assert_eq!(
        second.timestamp, 10.0,
        "the timestamp is the recording's frame index"
    );
    let all = IclReader::open(&common::living_room(), &DatasetConfig::default()).unwrap();
    assert_eq!(second.pose, all.load(10).unwrap().pose);
}

#[test]
fn shared_redwood_samples_use_rgbd_match_and_trajectory_log() {
    let Some(dir) = common::shared_data("rgbd-samples") else {
        return;
    };
    // The samples ship no intrinsics file; they are the ICL camera.
    let tmp = tempfile::tempdir().unwrap();
    let intrinsics = tmp.path().join("camera.json");
    common::write_intrinsics(&intrinsics, 640, 480, 525.0, 525.0, 319.5, 239.5);
    let config = DatasetConfig::default()
        .with_param("intrinsics", &intrinsics)
        .unwrap();
    let mut source = open(&config, &dir).unwrap();
    assert_eq!(source.len(), 5);
    let frame = source.frame(0).unwrap();
    // trajectory.log, not odometry.log, is the trajectory.
    let t = frame.pose.unwrap().translation.vector;
    assert!(
        (t - Vector3::new(-0.3106, 0.5730, 2.1265)).norm() < 1e-3,
        "{t}"
    );
    assert!(frame.depth.valid_count() > 100_000);

    let err = common::open_error(&DatasetConfig::default(), &dir);
    assert!(err.contains("intrinsics.json: not found"), "{err}");
}

#[test]
fn shared_tum_frame_reads_at_scale_5000() {
    let Some(dir) = common::shared_data("rgbd-samples/other_formats") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("rgb")).unwrap();
    std::fs::create_dir_all(root.join("depth")).unwrap();
    std::fs::copy(
        dir.join("TUM_color.png"),
        root.join("rgb/1305031102.175304.png"),
    )
    .unwrap();
    std::fs::copy(
        dir.join("TUM_depth.png"),
        root.join("depth/1305031102.160407.png"),
    )
    .unwrap();
    std::fs::write(
        root.join("rgb.txt"),
        "# color images\n1305031102.175304 rgb/1305031102.175304.png\n",
    )
    .unwrap();
    std::fs::write(
        root.join("depth.txt"),
        "# depth maps\n1305031102.160407 depth/1305031102.160407.png\n",
    )
    .unwrap();
    assert_eq!(detect_kind(root).unwrap(), "tum");
    let reader = TumReader::open(root, &DatasetConfig::default()).unwrap();
    assert!(!reader.has_poses());
    let frame = reader.load(0).unwrap();
    assert_eq!(frame.timestamp, 1305031102.160407);
    assert_eq!((frame.colour.width(), frame.colour.height()), (640, 480));
    let depths: Vec<f32> = frame
        .depth
        .as_raw()
        .iter()
        .copied()
        .filter(|d| *d > 0.0)
        .collect();
    let mean = depths.iter().sum::<f32>() / depths.len() as f32;
    assert!((0.5..6.0).contains(&mean), "mean depth {mean} m");
}
