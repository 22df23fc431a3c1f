//! vlem-ros2: vlem on a robot's live ROS 2 topics (`vlem ros2`, feature `ros2`).
//!
//! Why a crate of its own: the node is a front-end (like the HTTP server and the Python module),
//! thin over the pipeline, the live map and the query answers of the library crates; its DDS
//! stack (ros2-client on RustDDS, pure Rust, no ROS installation) stays out of every other build.
//!
//! - [`node::run_node`]: subscribe, map, publish until told to stop;
//! - [`Ros2Config`]: the `[ros2]` section, which this crate owns and parses;
//! - [`frames`]: colour/depth pairing by stamp, camera info, poses, what is dropped and why;
//! - [`msgs`]: the ROS 2 messages as serde structs (what ros2-client speaks);
//! - [`status`]: the counters of everything skipped.

mod config;
mod error;
pub mod frames;
pub mod msgs;
pub mod node;
pub mod status;

pub use config::{Ros2Config, Ros2PoseType};
pub use error::{Result, Ros2Error};
pub use node::{NodeReport, run_node};
