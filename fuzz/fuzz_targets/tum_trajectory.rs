//! TUM trajectories, `t tx ty tz qx qy qz qw` per line
//! ([`vlem_datasets::trajectory::tum_from_str`]).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_core::types::pose_is_finite;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(poses) = vlem_datasets::trajectory::tum_from_str(text, Path::new("groundtruth.txt")) {
        assert!(!poses.is_empty());
        for (t, pose) in &poses {
            assert!(t.is_finite());
            assert!(pose_is_finite(pose), "{pose:?}");
            assert!((pose.rotation.norm() - 1.0).abs() < 1e-6, "{pose:?}");
        }
    }
});
