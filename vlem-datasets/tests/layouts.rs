//! Every layout on small synthetic folders: pairing, association, scales, intrinsics, detection.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use std::f64::consts::FRAC_PI_2;
use std::path::Path;

use nalgebra::{Point3, Vector3};
use vlem_core::FrameSource;
use vlem_core::config::DatasetConfig;
use vlem_datasets::{
    IclReader, REPLICA_DEFAULT_INTRINSICS, ReplicaReader, ScanNetReader, TUM_DEFAULT_INTRINSICS,
    TumReader, detect_kind, open,
};

#[test]
fn icl_names_need_not_start_at_zero() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 10, 3, true);
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    assert_eq!(reader.len(), 3);
    for k in 0..3 {
        let frame = reader.load(k).unwrap();
        let c = k as u8;
        assert_eq!(frame.colour.get(0, 0), Some([c, 2 * c, 3 * c]));
        assert_eq!(
            frame.depth.get(2, 1),
            Some((1000.0 + 100.0 * k as f32) / 1000.0)
        );
        assert_eq!(frame.timestamp, k as f64);
        assert_eq!(frame.pose.unwrap().translation.vector.x, k as f64);
    }
}

#[test]
fn icl_names_sort_by_number_not_text() {
    let tmp = tempfile::tempdir().unwrap();
    // 8, 9, 10, 11: as text "10" < "8".
    common::write_icl(tmp.path(), 8, 4, false);
    for (from, to) in [
        ("00008", "8"),
        ("00009", "9"),
        ("00010", "10"),
        ("00011", "11"),
    ] {
        for (folder, ext) in [("color", "png"), ("depth", "png")] {
            let dir = tmp.path().join(folder);
            std::fs::rename(
                dir.join(format!("{from}.{ext}")),
                dir.join(format!("{to}.{ext}")),
            )
            .unwrap();
        }
    }
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    assert!(!reader.has_poses());
    let depths: Vec<f32> = (0..4)
        .map(|k| reader.load(k).unwrap().depth.get(0, 0).unwrap())
        .collect();
    assert_eq!(depths, vec![1.0, 1.1, 1.2, 1.3]);
    assert!(reader.load(0).unwrap().pose.is_none());
}

#[test]
fn icl_stride_max_frames_and_depth_scale_override() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 7, true);
    let config = DatasetConfig {
        stride: Some(3),
        max_frames: Some(2),
        depth_scale: Some(500.0),
        ..DatasetConfig::default()
    };
    let mut source = open(&config, tmp.path()).unwrap();
    assert_eq!(source.len(), 2);
    let frame = source.frame(1).unwrap();
    assert_eq!(frame.index, 1);
    assert_eq!(frame.timestamp, 3.0);
    assert_eq!(frame.pose.unwrap().translation.vector.x, 3.0);
    assert_eq!(frame.depth.get(0, 0), Some(1300.0 / 500.0));
    // Without max_frames: 0, 3, 6.
    let config = DatasetConfig {
        stride: Some(3),
        ..DatasetConfig::default()
    };
    assert_eq!(open(&config, tmp.path()).unwrap().len(), 3);
}

#[test]
fn redwood_image_folder_and_match_file() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    common::write_icl(dir, 0, 3, false);
    std::fs::rename(dir.join("color"), dir.join("image")).unwrap();
    std::fs::rename(
        dir.join("intrinsics.json"),
        dir.join("camera_intrinsic.json"),
    )
    .unwrap();
    assert_eq!(detect_kind(dir).unwrap(), "icl");
    assert_eq!(
        IclReader::open(dir, &DatasetConfig::default())
            .unwrap()
            .len(),
        3
    );

    // The match file decides the pairing (here: frames 2 and 0 only, in that order).
    std::fs::write(
        dir.join("rgbd.match"),
        "depth/00002.png image/00002.png\ndepth/00000.png image/00000.png\n",
    )
    .unwrap();
    let reader = IclReader::open(dir, &DatasetConfig::default()).unwrap();
    assert_eq!(reader.len(), 2);
    assert_eq!(reader.load(0).unwrap().colour.get(0, 0), Some([2, 4, 6]));
    assert_eq!(reader.load(1).unwrap().depth.get(0, 0), Some(1.0));
}

#[test]
fn icl_trajectory_from_config_and_only_log_file() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    common::write_icl(dir, 0, 2, false);
    let poses = [
        common::translation(0.0, 1.0, 0.0),
        common::translation(0.0, 2.0, 0.0),
    ];
    common::write_log(&dir.join("poses.log"), &poses);
    let reader = IclReader::open(dir, &DatasetConfig::default()).unwrap();
    assert_eq!(
        reader.load(1).unwrap().pose.unwrap().translation.vector.y,
        2.0
    );

    common::write_log(&dir.join("other.log"), &poses);
    let err = common::open_error(&DatasetConfig::default(), dir);
    assert!(
        err.contains("several trajectories") && err.contains("other.log, poses.log"),
        "{err}"
    );
    let config = DatasetConfig::default()
        .with_param("trajectory", "other.log")
        .unwrap();
    assert!(IclReader::open(dir, &config).unwrap().has_poses());
}

/// A TUM folder: 4x3 frames; colour of frame k is `[10 k, 0, 0]`, depth raw `5000 (k + 1)`.
fn write_tum(dir: &Path, rgb_times: &[f64], depth_times: &[f64], groundtruth: Option<&str>) {
    let mut rgb = String::from("# color images\n# file: 'synthetic'\n# timestamp filename\n");
    for (k, t) in rgb_times.iter().enumerate() {
        let name = format!("rgb/{t:.6}.png");
        common::write_rgb(&dir.join(&name), 4, 3, [10 * k as u8, 0, 0]);
        rgb.push_str(&format!("{t:.6} {name}\n"));
    }
    let mut depth = String::from("# depth maps\n");
    for (k, t) in depth_times.iter().enumerate() {
        let name = format!("depth/{t:.6}.png");
        common::write_flat_depth(&dir.join(&name), 4, 3, 5000 * (k as u16 + 1));
        depth.push_str(&format!("{t:.6} {name}\n"));
    }
    std::fs::write(dir.join("rgb.txt"), rgb).unwrap();
    std::fs::write(dir.join("depth.txt"), depth).unwrap();
    if let Some(text) = groundtruth {
        std::fs::write(dir.join("groundtruth.txt"), text).unwrap();
    }
    common::write_intrinsics(&dir.join("camera.json"), 4, 3, 5.0, 5.0, 1.5, 1.0);
}

fn tum_config() -> DatasetConfig {
    DatasetConfig::default()
        .with_param("intrinsics", "camera.json")
        .unwrap()
}

#[test]
fn tum_associates_within_20_ms_and_drops_the_rest() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // Depth 1.050 has its nearest colour 1.080 (30 ms away): dropped.
    write_tum(dir, &[1.005, 1.080, 1.118], &[1.000, 1.050, 1.100], None);
    assert_eq!(detect_kind(dir).unwrap(), "tum");
    let reader = TumReader::open(dir, &tum_config()).unwrap();
    assert_eq!(reader.len(), 2);
    assert!(!reader.has_poses());
    let first = reader.load(0).unwrap();
    assert_eq!(first.timestamp, 1.0, "frames carry the depth timestamp");
    assert_eq!(first.colour.get(0, 0), Some([0, 0, 0]));
    assert_eq!(first.depth.get(0, 0), Some(1.0), "TUM depth scale is 5000");
    let second = reader.load(1).unwrap();
    assert_eq!(second.timestamp, 1.1);
    assert_eq!(second.colour.get(0, 0), Some([20, 0, 0]));
    assert_eq!(second.depth.get(0, 0), Some(3.0));
}

#[test]
fn tum_groundtruth_quaternion_is_x_y_z_w() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // 90° about z: (qx, qy, qz, qw) = (0, 0, sin 45°, cos 45°).
    let s = (FRAC_PI_2 / 2.0).sin();
    let gt = format!(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n\
         0.990 1 2 3 0 0 {s} {s}\n\
         1.500 5 2 3 0 0 {s} {s}\n"
    );
    write_tum(dir, &[1.0, 1.25], &[1.0, 1.25], Some(&gt));
    let reader = TumReader::open(dir, &tum_config()).unwrap();
    assert!(reader.has_poses());
    let pose = reader.load(0).unwrap().pose.unwrap();
    assert_eq!(pose.translation.vector, Vector3::new(1.0, 2.0, 3.0));
    // The camera's x axis points along world y.
    let x_axis = pose.rotation * Vector3::x();
    assert!((x_axis - Vector3::y()).norm() < 1e-9, "{x_axis}");
    assert!((pose * Point3::origin() - Point3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
    // 1.25 has no ground truth within 20 ms: interpolated between 0.99 and 1.5.
    let pose = reader.load(1).unwrap().pose.unwrap();
    let expected_x = 1.0 + 4.0 * (1.25 - 0.99) / (1.5 - 0.99);
    assert!((pose.translation.vector.x - expected_x).abs() < 1e-9);
}

#[test]
fn tum_defaults_to_the_documented_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_tum(dir, &[1.0], &[1.0], None);
    let reader = TumReader::open(dir, &DatasetConfig::default()).unwrap();
    assert_eq!(reader.intrinsics(), TUM_DEFAULT_INTRINSICS);
    // The synthetic 4x3 frames do not match that camera; the error says where it came from.
    let err = reader.load(0).unwrap_err().to_string();
    assert!(
        err.contains("is 4x3 but the intrinsics (the TUM RGB-D default"),
        "{err}"
    );
}

#[test]
fn tum_frame_without_groundtruth_nearby_is_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_tum(dir, &[2.0], &[2.0], Some("1.0 0 0 0 0 0 0 1\n"));
    let err = TumReader::open(dir, &tum_config()).unwrap_err().to_string();
    assert!(
        err.contains("groundtruth.txt: no pose within 0.02 s of timestamp 2.000000"),
        "{err}"
    );
}

/// A ScanNet export with `n` frames: colour 8x6 of `[20 k, 100, 200]`, depth 4x3 raw `1000 + k`,
/// a pose per frame at z = k.
fn write_scannet(dir: &Path, n: usize) {
    for k in 0..n {
        common::write_rgb(
            &dir.join(format!("color/{k}.png")),
            8,
            6,
            [20 * k as u8, 100, 200],
        );
        common::write_flat_depth(&dir.join(format!("depth/{k}.png")), 4, 3, 1000 + k as u16);
        let pose = common::matrix_rows(&common::translation(0.0, 0.0, k as f64));
        std::fs::create_dir_all(dir.join("pose")).unwrap();
        std::fs::write(dir.join(format!("pose/{k}.txt")), pose).unwrap();
    }
    let depth_k = [
        [4.0, 0.0, 1.5, 0.0],
        [0.0, 4.5, 1.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let colour_k = [
        [9.0, 0.0, 3.5, 0.0],
        [0.0, 9.0, 2.5, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    std::fs::create_dir_all(dir.join("intrinsic")).unwrap();
    std::fs::write(
        dir.join("intrinsic/intrinsic_depth.txt"),
        common::matrix_rows(&depth_k),
    )
    .unwrap();
    std::fs::write(
        dir.join("intrinsic/intrinsic_color.txt"),
        common::matrix_rows(&colour_k),
    )
    .unwrap();
}

#[test]
fn scannet_resizes_colour_to_depth_and_uses_depth_intrinsics() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_scannet(dir, 12);
    assert_eq!(detect_kind(dir).unwrap(), "scannet");
    let mut source = open(&DatasetConfig::default(), dir).unwrap();
    assert_eq!(source.len(), 12);
    let k = source.intrinsics();
    assert_eq!(
        (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
        (4, 3, 4.0, 4.5, 1.5, 1.0)
    );
    // Numeric order: frame 10 is the 11th, not the 3rd.
    let frame = source.frame(10).unwrap();
    assert_eq!((frame.colour.width(), frame.colour.height()), (4, 3));
    assert_eq!(frame.colour.get(3, 2), Some([200, 100, 200]));
    assert_eq!(frame.depth.get(0, 0), Some(1.010));
    assert_eq!(frame.pose.unwrap().translation.vector.z, 10.0);
    assert_eq!(frame.intrinsics, k);
}

#[test]
fn scannet_lost_frame_pose_is_an_error_of_that_frame_only() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_scannet(dir, 3);
    let lost = "-inf -inf -inf -inf\n".repeat(4);
    std::fs::write(dir.join("pose/1.txt"), lost).unwrap();
    let mut source = open(&DatasetConfig::default(), dir).unwrap();
    assert!(source.frame(0).is_ok());
    assert!(source.frame(2).is_ok());
    let err = source.frame(1).unwrap_err();
    let message = err.to_string();
    assert!(
        message.ends_with("pose/1.txt: the pose of frame 1 is not finite"),
        "{message}"
    );
    // Through `FrameSource` the dataset error stays reachable as the source.
    let source_err = std::error::Error::source(&err).unwrap();
    assert!(
        source_err
            .downcast_ref::<vlem_datasets::DatasetError>()
            .is_some()
    );
}

#[test]
fn scannet_without_poses() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_scannet(dir, 2);
    std::fs::remove_dir_all(dir.join("pose")).unwrap();
    let reader = ScanNetReader::open(dir, &DatasetConfig::default()).unwrap();
    assert!(!reader.has_poses());
    assert!(reader.load(1).unwrap().pose.is_none());
}

#[test]
fn replica_scale_poses_and_default_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (w, h) = (1200, 680);
    let mut traj = String::new();
    for k in 0..2 {
        common::write_rgb(
            &dir.join(format!("results/frame{k:06}.jpg")),
            w,
            h,
            [200, 50, 50],
        );
        common::write_flat_depth(
            &dir.join(format!("results/depth{k:06}.png")),
            w,
            h,
            6553 * (k as u16 + 1),
        );
        let m = common::translation(0.5 * k as f64, 0.0, 0.0);
        let row_major: Vec<String> = m.iter().flatten().map(|x| x.to_string()).collect();
        traj.push_str(&row_major.join(" "));
        traj.push('\n');
    }
    std::fs::write(dir.join("traj.txt"), traj).unwrap();
    assert_eq!(detect_kind(dir).unwrap(), "replica");
    let reader = ReplicaReader::open(dir, &DatasetConfig::default()).unwrap();
    assert_eq!(reader.intrinsics(), REPLICA_DEFAULT_INTRINSICS);
    assert_eq!(reader.len(), 2);
    let frame = reader.load(1).unwrap();
    let d = frame.depth.get(600, 340).unwrap();
    assert!((d - 13106.0 / 6553.5).abs() < 1e-6, "{d}");
    assert_eq!(frame.pose.unwrap().translation.vector.x, 0.5);
    assert_eq!(frame.timestamp, 1.0);
    let [r, g, b] = frame.colour.get(10, 10).unwrap();
    assert!(r.abs_diff(200) < 8 && g.abs_diff(50) < 8 && b.abs_diff(50) < 8);
}

#[test]
fn replica_with_too_short_trajectory() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    for k in 0..2 {
        common::write_rgb(
            &dir.join(format!("results/frame{k:06}.png")),
            4,
            3,
            [1, 2, 3],
        );
        common::write_flat_depth(&dir.join(format!("results/depth{k:06}.png")), 4, 3, 6553);
    }
    std::fs::write(dir.join("traj.txt"), "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n").unwrap();
    let err = common::open_error(&DatasetConfig::default(), dir);
    assert!(
        err.ends_with("traj.txt: holds 1 poses but 2 frames need one"),
        "{err}"
    );
    // With one frame it is enough.
    let config = DatasetConfig {
        max_frames: Some(1),
        kind: "replica".into(),
        ..DatasetConfig::default()
    };
    assert!(open(&config, dir).unwrap().has_poses());
}

#[test]
fn explicit_kind_skips_detection() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, false);
    let config = DatasetConfig::named("tum");
    let err = common::open_error(&config, tmp.path());
    assert!(err.contains("rgb.txt: not found"), "{err}");
}
