//! ROS 2 bags (rosbag2, MCAP or SQLite3 storage) as a dataset: `[dataset] kind = "rosbag2"`
//! (feature `rosbag2`), and the ROS 2 messages vlem reads ([`messages`], [`cdr`]: in every build,
//! as the live ROS 2 node decodes the same messages).
//!
//! ```text
//! my_bag/                 a rosbag2 folder: metadata.yaml and my_bag_0.mcap (or .db3), split
//!                         bags as my_bag_1.mcap, ...; or one .mcap / .db3 file on its own
//! [dataset.rosbag2]       colour_topic, depth_topic, camera_info_topic, and optionally
//!                         pose_topic or tf = [parent, child] (see [`Rosbag2Config`])
//! ```
//!
//! Why it exists: "run it on my rosbag" is what robot users ask of every mapping system first.
//! No ROS installation is needed: the storage is read with the `mcap` and `rusqlite` crates and
//! the messages with our own CDR decoding ([`messages`]).
//!
//! How a bag becomes frames, once when it is opened:
//! - Every message of the configured topics is read once; images keep only their stamp and where
//!   they are ([`storage`]), camera info, poses and tf are decoded and kept. A colour or depth
//!   topic that is not in the bag is looked for under image_transport's names (`TOPIC/compressed`;
//!   for depth `TOPIC/compressedDepth` first), which is all `ros2 bag record` of a camera often
//!   keeps; a warning names the topic read instead.
//! - Colour and depth are paired by header stamp: each depth image, in time order, takes the
//!   nearest colour image not yet taken within `max_time_difference` (as TUM's `associate.py`).
//!   Images left unpaired are dropped and counted in [`FrameSource::warnings`].
//! - A frame's timestamp is its depth image's stamp, and its pose the configured pose source's at
//!   that stamp (nearest within the tolerance, else interpolated; tf along the frame chain). Frames
//!   before the first or after the last pose are dropped and counted.
//! - Depth is assumed registered to colour (same size and camera; the camera info of the colour
//!   camera gives K); a frame whose sizes differ is an error that says so. Non-zero distortion is a
//!   warning: vlem does not rectify.
//!
//! Decoding a frame fetches its two images again and converts them: `rgb8`/`bgr8`/`rgba8`/`bgra8`
//! or JPEG/PNG colour; `16UC1` (raw units, `[dataset] depth_scale` per metre, default 1000) or
//! `32FC1` (metres) depth, also as a 16-bit PNG or image_transport's `compressedDepth` (PNG).

use std::path::Path;

pub mod cdr;
mod config;
pub mod messages;
pub mod poses;
#[cfg(feature = "rosbag2")]
mod reader;
#[cfg(feature = "rosbag2")]
pub mod storage;

#[cfg(feature = "rosbag2")]
pub use reader::{ROS_DEPTH_SCALE, Rosbag2Reader};

#[cfg(feature = "rosbag2")]
pub(crate) use config::Rosbag2Settings;
pub use config::{
    DEFAULT_CAMERA_INFO_TOPIC, DEFAULT_COLOUR_TOPIC, DEFAULT_DEPTH_TOPIC,
    DEFAULT_MAX_TIME_DIFFERENCE, ROSBAG2, Rosbag2Config,
};

/// What [`looks_like_bag`] looks for, in the error that lists what `kind = "auto"` tried.
pub(crate) const LOOKS_FOR: &str = "metadata.yaml or .mcap/.db3 files (ROS 2 bag)";

// Probed before every folder layout: a bag may be one file, and a bag folder has nothing else.
#[cfg(feature = "rosbag2")]
vlem_core::register_dataset!(
    ROSBAG2,
    "ROS 2 bags (rosbag2 folder, or one .mcap / .db3 file); topics in [dataset.rosbag2]",
    vlem_core::DatasetReader::new(open_boxed)
        .detected_by(0, LOOKS_FOR, looks_like_bag)
        .with_settings_check(|config| {
            crate::sequence::check_settings::<Rosbag2Settings>(ROSBAG2, config)
        })
);

vlem_core::feature_hint!(Dataset, ROSBAG2, "rosbag2");

#[cfg(feature = "rosbag2")]
fn open_boxed(
    config: &vlem_core::config::DatasetConfig,
    path: &Path,
) -> vlem_core::Result<Box<dyn vlem_core::FrameSource>> {
    Ok(Box::new(Rosbag2Reader::open(path, config)?))
}

/// Whether `path` looks like a ROS 2 bag: a `.mcap` or `.db3` file, or a folder with
/// `metadata.yaml` or such a file. In every build, so that a build without the reader recognises a
/// bag and says which feature reads it.
pub fn looks_like_bag(path: &Path) -> bool {
    let is_storage = |p: &Path| p.extension().is_some_and(|e| e == "mcap" || e == "db3");
    if path.is_file() {
        return is_storage(path);
    }
    path.join("metadata.yaml").is_file()
        || std::fs::read_dir(path)
            .into_iter()
            .flatten()
            .flatten()
            .any(|e| is_storage(&e.path()))
}
