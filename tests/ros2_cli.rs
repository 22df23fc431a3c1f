//! `vlem ros2` before it touches the network: a build without the feature says how to get it,
//! and settings that cannot work are refused before the node starts. The node itself is tested
//! against a Cyclone DDS peer by tests/ros2/node_peer.py (run by .ci/run).
#![cfg(feature = "cli")]
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

#[test]
fn vlem_ros2_refuses_what_cannot_work() {
    // Tracking only, so the test needs no encoder or map feature.
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("node.toml");
    std::fs::write(&config, "[tracker]\nkind = \"ground-truth\"\n").unwrap();
    let config = config.to_str().unwrap();
    let err = common::fails(&["ros2", "--config", config, "--duration", "5"]);
    if cfg!(feature = "ros2") {
        // Ground truth is the source's poses: live, they must come from a pose topic.
        assert!(
            err.contains("[ros2] has no pose_topic") && err.contains("odometry"),
            "{err}"
        );
    } else {
        assert!(
            err.contains("cargo build --release --features ros2"),
            "{err}"
        );
    }
}
