//! The ROS 2 bag reader on bags written by an independent tool (the `rosbags` Python package,
//! `tests/data/rosbag2/make_bags.py`) from the committed living-room frames: the same frames,
//! poses and camera as the folder, in MCAP and SQLite3, raw and compressed.
#![cfg(feature = "rosbag2")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use std::path::PathBuf;

use vlem_core::Frame;
use vlem_core::config::DatasetConfig;
use vlem_datasets::Rosbag2Config;
use vlem_datasets::{detect_kind, open};

/// Seconds of frame `i`'s stamp in the test bags.
fn stamp(i: usize) -> f64 {
    1_700_000_000.0 + (i as f64 * 1e9 / 30.0).round() * 1e-9
}

fn bag(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("tests/data/rosbag2/{name}"))
}

const BAGS: [&str; 2] = ["living-room-mcap", "living-room-sqlite"];

/// The compressed topics of the living-room bags, with `pose_topic` or `tf` set by `poses`.
fn compressed(depth_topic: &str, poses: impl FnOnce(&mut Rosbag2Config)) -> DatasetConfig {
    let mut settings = Rosbag2Config {
        colour_topic: "/camera/color/image_raw/compressed".into(),
        depth_topic: depth_topic.into(),
        ..Rosbag2Config::default()
    };
    poses(&mut settings);
    settings.dataset_config().unwrap()
}

const DEPTH_PNG: &str = "/camera/aligned_depth_to_color/image_raw/compressed";

fn folder_frames(n: usize) -> Vec<Frame> {
    let mut folder = open(&DatasetConfig::default(), &common::living_room()).unwrap();
    (0..n).map(|i| folder.frame(i).unwrap()).collect()
}

fn max_pose_difference(a: &Frame, b: &Frame) -> f64 {
    (a.pose.unwrap().to_homogeneous() - b.pose.unwrap().to_homogeneous())
        .abs()
        .max()
}

#[test]
fn compressed_bags_give_the_folders_frames_and_poses_from_each_source() {
    let expected = folder_frames(5);
    for name in BAGS {
        let path = bag(name);
        assert_eq!(detect_kind(&path).unwrap(), "rosbag2");
        type SetPoses = Box<dyn Fn(&mut Rosbag2Config)>;
        let sources: [(&str, SetPoses); 3] = [
            (
                "PoseStamped",
                Box::new(|s| s.pose_topic = Some("/camera/pose".into())),
            ),
            (
                "Odometry",
                Box::new(|s| s.pose_topic = Some("/odom".into())),
            ),
            (
                "tf",
                Box::new(|s| s.tf = Some(["map".into(), "camera_color_optical_frame".into()])),
            ),
        ];
        for (what, poses) in sources {
            let config = compressed(DEPTH_PNG, poses);
            let mut source = open(&config, &path).unwrap();
            assert_eq!(source.len(), 5, "{name} {what}");
            assert!(source.has_poses());
            let k = source.intrinsics();
            assert_eq!(
                (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
                (640, 480, 525.0, 525.0, 319.5, 239.5)
            );
            // The leading colour image without a depth partner is left out, and said so.
            let warnings = source.warnings();
            assert!(
                warnings
                    .iter()
                    .any(|w| w.contains("1 colour and 0 depth images have no partner")),
                "{name} {what}: {warnings:?}"
            );
            for (i, want) in expected.iter().enumerate() {
                let got = source.frame(i).unwrap();
                assert_eq!(got.index, i);
                assert!((got.timestamp - stamp(i)).abs() < 1e-6, "{}", got.timestamp);
                // The same JPEG and PNG bytes, decoded by the same decoders: identical pixels.
                assert_eq!(got.colour, want.colour, "{name} {what} frame {i}");
                assert_eq!(got.depth, want.depth, "{name} {what} frame {i}");
                let d = max_pose_difference(&got, want);
                assert!(d < 1e-9, "{name} {what} frame {i}: pose differs by {d}");
            }
            // Backwards: the MCAP cursor restarts, SQLite fetches by row.
            assert_eq!(source.frame(1).unwrap().depth, expected[1].depth);
            assert!(source.frame(5).is_err());
        }
    }
}

#[test]
fn compressed_depth_transport_gives_the_same_depth() {
    let expected = folder_frames(2);
    for name in BAGS {
        let config = compressed(
            "/camera/aligned_depth_to_color/image_raw/compressedDepth",
            |_| {},
        );
        let mut source = open(&config, &bag(name)).unwrap();
        assert!(!source.has_poses());
        for (i, want) in expected.iter().enumerate() {
            assert_eq!(
                source.frame(i).unwrap().depth,
                want.depth,
                "{name} frame {i}"
            );
        }
        // 32FC1 goes through the transport's inverse-depth quantisation: within its step
        // (d² / quant_a, with quant_a = 100 · 101), and invalid stays invalid.
        let config = compressed(
            "/camera/aligned_depth_to_color/image_raw/compressedDepth32",
            |_| {},
        );
        let mut source = open(&config, &bag(name)).unwrap();
        let got = source.frame(0).unwrap().depth;
        let want = &expected[0].depth;
        for (g, w) in got.as_raw().iter().zip(want.as_raw()) {
            if *w == 0.0 {
                assert_eq!(*g, 0.0);
            } else {
                let step = w * w / 10100.0;
                assert!((g - w).abs() <= step + 1e-4, "{g} vs {w}");
            }
        }
    }
}

#[test]
fn default_topics_fall_back_to_their_image_transport_names() {
    // The living-room bags hold the colour only as `/camera/color/image_raw/compressed` and the
    // depth as `/compressed` and `/compressedDepth`, as `ros2 bag record` of a camera often does:
    // the default topics find them, depth's own transport first, and say so.
    let expected = folder_frames(5);
    for name in BAGS {
        let config = DatasetConfig::named("rosbag2");
        let mut source = open(&config, &bag(name)).unwrap();
        assert_eq!(source.len(), 5, "{name}");
        let warnings = source.warnings();
        for (key, topic) in [
            ("colour_topic", "/camera/color/image_raw/compressed"),
            (
                "depth_topic",
                "/camera/aligned_depth_to_color/image_raw/compressedDepth",
            ),
        ] {
            assert!(
                warnings.iter().any(|w| w.contains(key)
                    && w.contains(&format!("image_transport topic {topic} instead"))),
                "{name} {key}: {warnings:?}"
            );
        }
        assert!(
            source.describe().contains("/image_raw/compressed +"),
            "{}",
            source.describe()
        );
        for (i, want) in expected.iter().enumerate() {
            let got = source.frame(i).unwrap();
            assert_eq!(got.colour, want.colour, "{name} frame {i}");
            assert_eq!(got.depth, want.depth, "{name} frame {i}");
        }
    }
    // A bag with neither the topic nor its transports names all three.
    let config = Rosbag2Config {
        depth_topic: "/camera/depth".into(),
        ..Rosbag2Config::default()
    }
    .dataset_config()
    .unwrap();
    let message = open(&config, &bag("living-room-mcap"))
        .err()
        .unwrap()
        .to_string();
    assert!(
        message.contains(
            "no topic /camera/depth ([dataset.rosbag2] depth_topic), nor its image_transport \
             names /camera/depth/compressedDepth, /camera/depth/compressed"
        ),
        "{message}"
    );
}

#[test]
fn one_storage_file_opens_without_its_folder() {
    let file = bag("living-room-mcap").join("living-room-mcap.mcap");
    assert_eq!(detect_kind(&file).unwrap(), "rosbag2");
    let config = DatasetConfig {
        max_frames: Some(2),
        stride: Some(2),
        ..compressed(DEPTH_PNG, |_| {})
    };
    let mut source = open(&config, &file).unwrap();
    assert_eq!(source.len(), 2);
    let expected = folder_frames(3);
    let second = source.frame(1).unwrap();
    assert_eq!(second.index, 1);
    assert_eq!(second.depth, expected[2].depth);
    assert!((second.timestamp - stamp(2)).abs() < 1e-6);
}

/// The raw bags: 80×60 images, pixel (x, y) = pixel (8x, 8y) of the folder's frame.
fn raw(colour: &str, depth: &str) -> DatasetConfig {
    Rosbag2Config {
        colour_topic: colour.into(),
        depth_topic: depth.into(),
        camera_info_topic: "/raw/camera_info".into(),
        pose_topic: Some("/raw/pose".into()),
        ..Rosbag2Config::default()
    }
    .dataset_config()
    .unwrap()
}

#[test]
fn raw_encodings_give_the_same_frames() {
    let expected = folder_frames(3);
    for name in ["raw-mcap", "raw-sqlite"] {
        let path = bag(name);
        let mut reference = open(&raw("/raw/rgb8", "/raw/depth_16uc1"), &path).unwrap();
        assert_eq!(reference.len(), 3);
        let k = reference.intrinsics();
        assert_eq!((k.width, k.height), (80, 60));
        assert!((k.fx - 525.0 / 8.0).abs() < 1e-12 && (k.cx - 319.5 / 8.0).abs() < 1e-12);
        for (i, want) in expected.iter().enumerate() {
            let got = reference.frame(i).unwrap();
            assert!(max_pose_difference(&got, want) < 1e-9);
            for y in 0..60 {
                for x in 0..80 {
                    // Depth is lossless; colour went through two JPEG decoders (PIL, image).
                    assert_eq!(got.depth.get(x, y), want.depth.get(8 * x, 8 * y));
                    let (g, w) = (
                        got.colour.get(x, y).unwrap(),
                        want.colour.get(8 * x, 8 * y).unwrap(),
                    );
                    for c in 0..3 {
                        assert!(
                            g[c].abs_diff(w[c]) <= 8,
                            "{name} frame {i} ({x}, {y}): {g:?} vs {w:?}"
                        );
                    }
                }
            }
            for colour in ["/raw/bgr8", "/raw/rgba8", "/raw/bgra8"] {
                let mut other = open(&raw(colour, "/raw/depth_32fc1"), &path).unwrap();
                let frame = other.frame(i).unwrap();
                assert_eq!(frame.colour, got.colour, "{name} {colour} frame {i}");
                for (a, b) in frame.depth.as_raw().iter().zip(got.depth.as_raw()) {
                    assert!((a - b).abs() <= 1e-6, "{name} 32FC1 frame {i}: {a} vs {b}");
                }
            }
        }
    }
}

fn open_error(config: &DatasetConfig, name: &str) -> String {
    match open(config, &bag(name)) {
        Ok(_) => panic!("{name} opened"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn wrong_topics_and_encodings_are_clear_errors() {
    // A missing topic lists the bag's topics with types and counts.
    let err = open_error(&raw("/raw/rgb", "/raw/depth_16uc1"), "raw-mcap");
    assert!(
        err.contains("no topic /raw/rgb ([dataset.rosbag2] colour_topic)"),
        "{err}"
    );
    assert!(
        err.contains("/raw/rgb8 (sensor_msgs/msg/Image, 3 messages)"),
        "{err}"
    );
    // A topic of the wrong type.
    let config = compressed(DEPTH_PNG, |s| s.colour_topic = "/chatter".into());
    let err = open_error(&config, "living-room-sqlite");
    assert!(
        err.contains("topic /chatter has type std_msgs/msg/String"),
        "{err}"
    );
    // An encoding vlem cannot use fails when the frame is decoded, naming the message.
    let mut source = open(&raw("/raw/mono8", "/raw/depth_16uc1"), &bag("raw-mcap")).unwrap();
    let err = source.frame(0).unwrap_err();
    let message = vlem_core::message_chain(&err);
    assert!(
        message.contains("/raw/mono8#0") && message.contains("`mono8` is not supported"),
        "{message}"
    );
    // Two pose sources.
    let config = compressed(DEPTH_PNG, |s| {
        s.pose_topic = Some("/odom".into());
        s.tf = Some(["map".into(), "camera_color_optical_frame".into()]);
    });
    assert!(open_error(&config, "living-room-mcap").contains("set pose_topic or tf, not both"));
    // A tf parent that is not an ancestor of the child.
    let config = compressed(DEPTH_PNG, |s| {
        s.tf = Some(["wheel_left".into(), "camera_color_optical_frame".into()]);
    });
    let err = open_error(&config, "living-room-mcap");
    assert!(
        err.contains("not an ancestor") && err.contains("root `map`"),
        "{err}"
    );
}

#[test]
fn doubtful_calibration_and_frames_are_warnings() {
    let config = compressed(DEPTH_PNG, |s| {
        s.camera_info_topic = "/camera/color/camera_info_distorted".into();
        s.tf = Some(["map".into(), "base_link".into()]);
    });
    let source = open(&config, &bag("living-room-mcap")).unwrap();
    let warnings = source.warnings().join("\n");
    assert!(warnings.contains("plumb_bob distortion"), "{warnings}");
    assert!(warnings.contains("frame `base_link`"), "{warnings}");
    // [dataset] intrinsics replaces the camera info (and needs no camera info topic).
    let config = compressed(DEPTH_PNG, |s| s.camera_info_topic = "/none".into())
        .with_param("intrinsics", common::living_room().join("intrinsics.json"))
        .unwrap();
    let source = open(&config, &bag("living-room-sqlite")).unwrap();
    assert_eq!(source.intrinsics().fx, 525.0);
}

/// A 5.6 kB MCAP file the fuzzer derived from a seed, whose corrupt lengths once made the reader
/// ask for 3.7 GB: now a clean error.
#[test]
fn a_corrupt_mcap_file_is_an_error_not_an_allocation() {
    let file = bag("fuzz-huge-read-request.mcap");
    let err = match open(&raw("/raw/rgb8", "/raw/depth_16uc1"), &file) {
        Ok(_) => panic!("the corrupt file opened"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("cannot read MCAP"), "{err}");
}

/// A 5.0 kB MCAP file the fuzzer found whose zstd chunk stalls before its declared size: the
/// reader once looped on it without end; now a clean error, quickly.
#[test]
fn a_stalled_compressed_chunk_is_an_error_not_a_hang() {
    let file = bag("fuzz-stalled-zstd-chunk.mcap");
    let (done, result) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let outcome = open(&raw("/raw/rgb8", "/raw/depth_16uc1"), &file).map(|_| ());
        let _ = done.send(outcome.map_err(|e| e.to_string()));
    });
    match result.recv_timeout(std::time::Duration::from_secs(60)) {
        Ok(Ok(())) => panic!("the corrupt file opened"),
        Ok(Err(err)) => assert!(err.contains("cannot read MCAP"), "{err}"),
        Err(_) => panic!("opening the file did not finish within 60 s"),
    }
}
