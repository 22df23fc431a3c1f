//! Redwood / Open3D `.log` trajectories ([`vlem_datasets::trajectory::log_from_str`]).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_core::types::pose_is_finite;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(poses) = vlem_datasets::trajectory::log_from_str(text, Path::new("trajectory.log")) {
        assert!(!poses.is_empty());
        for pose in &poses {
            assert!(pose_is_finite(pose), "{pose:?}");
            assert!((pose.rotation.norm() - 1.0).abs() < 1e-6, "{pose:?}");
        }
    }
});
