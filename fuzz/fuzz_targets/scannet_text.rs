//! ScanNet text files: `pose/N.txt` ([`vlem_datasets::trajectory::scannet_pose_from_str`]) and
//! `intrinsic/intrinsic_depth.txt` ([`vlem_datasets::scannet::depth_intrinsics_from_str`]), 4x4
//! matrices one row per line.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_core::types::pose_is_finite;
use vlem_datasets::scannet::depth_intrinsics_from_str;
use vlem_datasets::trajectory::scannet_pose_from_str;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(pose) = scannet_pose_from_str(text, Path::new("pose/0.txt"), 0) {
        assert!(pose_is_finite(&pose), "{pose:?}");
        assert!((pose.rotation.norm() - 1.0).abs() < 1e-6, "{pose:?}");
    }
    let path = Path::new("intrinsic/intrinsic_depth.txt");
    if let Ok(k) = depth_intrinsics_from_str(text, 640, 480, path) {
        k.validate().expect("parsed intrinsics are valid");
    }
});
