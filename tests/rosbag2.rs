//! `vlem run` on a ROS 2 bag: the committed living-room frames as a folder and as a bag written
//! by the `rosbags` Python package (vlem-datasets/tests/data/rosbag2) give the same trajectory
//! and the same map, with frame-to-frame odometry estimating the poses.
#![cfg(feature = "cli")]
#![cfg(all(feature = "rosbag2", feature = "colour-names", feature = "point-cloud"))]
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use std::path::Path;

use common::repo;

const STAGES: &str = r#"
[tracker]
kind = "odometry"

[encoder]
kind = "colour-names"

[map]
kind = "point-cloud"
"#;

/// The poses of a TUM trajectory file, without their timestamps (the folder has none, the bag
/// has its recording's).
fn poses(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            l.split_whitespace()
                .skip(1)
                .map(|v| v.parse().unwrap())
                .collect()
        })
        .collect()
}

#[test]
fn a_bag_and_its_folder_give_the_same_trajectory_and_map() {
    let tmp = tempfile::tempdir().unwrap();
    let folder = repo().join("data/living-room");
    let bag = repo().join("vlem-datasets/tests/data/rosbag2/living-room-mcap");
    let configs = [
        (
            "folder",
            format!(
                "[dataset]\npath = {:?}\nmax_frames = 5\n{STAGES}",
                folder.display().to_string()
            ),
        ),
        (
            "bag",
            format!(
                "[dataset]\nkind = \"rosbag2\"\npath = {:?}\n\n[dataset.rosbag2]\n\
                 colour_topic = \"/camera/color/image_raw/compressed\"\n\
                 depth_topic = \"/camera/aligned_depth_to_color/image_raw/compressed\"\n\
                 tf = [\"map\", \"camera_color_optical_frame\"]\n{STAGES}",
                bag.display().to_string()
            ),
        ),
    ];
    for (name, text) in &configs {
        let config = tmp.path().join(format!("{name}.toml"));
        std::fs::write(&config, text).unwrap();
        let out = tmp.path().join(name);
        let output = common::vlem(&[
            "run",
            "--config",
            config.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "{name}: {stderr}");
        if *name == "bag" {
            assert!(stderr.contains("5 frames from ROS 2 bag"), "{stderr}");
            assert!(
                stderr.contains("warning: 1 colour and 0 depth images have no partner"),
                "{stderr}"
            );
        }
    }
    let (a, b) = (tmp.path().join("folder"), tmp.path().join("bag"));
    let (poses_a, poses_b) = (
        poses(&a.join("trajectory.tum")),
        poses(&b.join("trajectory.tum")),
    );
    assert_eq!(poses_a.len(), 5);
    for (pa, pb) in poses_a.iter().zip(&poses_b) {
        for (x, y) in pa.iter().zip(pb) {
            assert!((x - y).abs() < 1e-9, "{pa:?} vs {pb:?}");
        }
    }
    // The reference poses (ground truth of the folder, tf of the bag) agree as well.
    let (ref_a, ref_b) = (
        poses(&a.join("reference.tum")),
        poses(&b.join("reference.tum")),
    );
    for (pa, pb) in ref_a.iter().zip(&ref_b) {
        for (x, y) in pa.iter().zip(pb) {
            assert!((x - y).abs() < 1e-6, "{pa:?} vs {pb:?}");
        }
    }
    let map_a = vlem_core::read_map_file(&a.join("map.vlem")).unwrap();
    let map_b = vlem_core::read_map_file(&b.join("map.vlem")).unwrap();
    assert!(map_a.len() > 100_000, "{} points", map_a.len());
    assert_eq!(map_a.positions, map_b.positions);
    assert_eq!(map_a.colours, map_b.colours);
    assert_eq!(map_a.embeddings, map_b.embeddings);
}

#[test]
fn a_bag_without_the_configured_topics_fails_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("bag.toml");
    let bag = repo().join("vlem-datasets/tests/data/rosbag2/raw-sqlite");
    std::fs::write(
        &config,
        format!(
            "[dataset]\nkind = \"rosbag2\"\npath = {:?}\n{STAGES}",
            bag.display().to_string()
        ),
    )
    .unwrap();
    let out = tmp.path().join("out");
    let err = common::fails(&[
        "run",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("no topic /camera/color/image_raw ([dataset.rosbag2] colour_topic)")
            && err.contains("/raw/rgb8 (sensor_msgs/msg/Image, 3 messages)"),
        "{err}"
    );
}
