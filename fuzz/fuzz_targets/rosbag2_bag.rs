//! The rosbag2 reader on a whole storage file: bytes of an MCAP or SQLite3 file (told apart by
//! their magic, as the reader does) are opened as a bag with the raw topics of the test bags,
//! and every frame it finds is decoded.
#![no_main]

use std::path::PathBuf;

use libfuzzer_sys::fuzz_target;
use vlem_core::FrameSource;
use vlem_datasets::{Rosbag2Config, Rosbag2Reader};

/// One file per fuzzing process, rewritten for every input (the reader opens bags by path).
fn scratch() -> PathBuf {
    std::env::temp_dir().join(format!("vlem-fuzz-rosbag2-{}.bag", std::process::id()))
}

fuzz_target!(|data: &[u8]| {
    let path = scratch();
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let Ok(config) = (Rosbag2Config {
        colour_topic: "/raw/rgb8".into(),
        depth_topic: "/raw/depth_16uc1".into(),
        camera_info_topic: "/raw/camera_info".into(),
        pose_topic: Some("/raw/pose".into()),
        ..Rosbag2Config::default()
    })
    .dataset_config() else {
        return;
    };
    if let Ok(mut reader) = Rosbag2Reader::open(&path, &config) {
        for i in 0..reader.len().min(4) {
            if let Ok(frame) = reader.frame(i) {
                assert_eq!(frame.colour.width(), frame.depth.width());
                assert!(frame.pose.is_some());
            }
        }
    }
});
