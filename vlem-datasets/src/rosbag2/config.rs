//! `[dataset.rosbag2]`: the topics of a bag, owned by its reader. In every build, so that a
//! config naming them parses (and says which feature reads it) where the reader is not built.

use serde::{Deserialize, Serialize};
use vlem_core::config::DatasetConfig;

use crate::error::{DatasetError, Result};

/// The registered name: `[dataset] kind = "rosbag2"`.
pub const ROSBAG2: &str = "rosbag2";

/// `[dataset.rosbag2]`: which topics of a ROS 2 bag make the frames, and where poses come from.
///
/// Plain data; the reader checks it against the bag (a missing or mistyped topic lists the
/// bag's topics). The topic defaults are those of the RealSense ROS 2 wrapper with depth aligned
/// to colour; append `/compressed` (or `/compressedDepth`) for image_transport's compressed
/// topics, whose type (`sensor_msgs/msg/CompressedImage`) the reader recognises from the bag.
///
/// ```toml
/// [dataset]
/// kind = "rosbag2"
/// path = "my_bag"            # the rosbag2 folder (metadata.yaml + .mcap/.db3), or one file
///
/// [dataset.rosbag2]
/// colour_topic = "/camera/color/image_raw"
/// depth_topic = "/camera/aligned_depth_to_color/image_raw"
/// camera_info_topic = "/camera/color/camera_info"
/// tf = ["map", "camera_color_optical_frame"]   # or pose_topic = "/odom"; or neither
/// ```
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Rosbag2Config {
    /// Colour images: `sensor_msgs/msg/Image` (`rgb8`, `bgr8`, `rgba8`, `bgra8`) or
    /// `sensor_msgs/msg/CompressedImage` (JPEG, PNG).
    #[serde(default = "default_rosbag2_colour_topic")]
    pub colour_topic: String,
    /// Depth images registered to colour: `sensor_msgs/msg/Image` (`16UC1` in raw units, see
    /// `[dataset] depth_scale`, default 1000 = millimetres; `32FC1` in metres) or
    /// `sensor_msgs/msg/CompressedImage` (16-bit PNG, or image_transport's `compressedDepth`).
    #[serde(default = "default_rosbag2_depth_topic")]
    pub depth_topic: String,
    /// `sensor_msgs/msg/CameraInfo` of the colour camera (its K); `[dataset] intrinsics` (an
    /// Open3D JSON file) replaces it when set.
    #[serde(default = "default_rosbag2_camera_info_topic")]
    pub camera_info_topic: String,
    /// Poses of the camera's optical frame from a `nav_msgs/msg/Odometry` or
    /// `geometry_msgs/msg/PoseStamped` topic. Leave it and `tf` out for a bag without poses
    /// (track with `odometry` or `frame-to-model`).
    #[serde(default)]
    pub pose_topic: Option<String>,
    /// Poses from `/tf` and `/tf_static`: `[parent, child]` frame ids, e.g.
    /// `["map", "camera_color_optical_frame"]`; the parent must be an ancestor of the child in the
    /// tf tree.
    #[serde(default)]
    pub tf: Option<[String; 2]>,
    /// Largest difference in seconds between the stamps of a colour and a depth image paired into
    /// one frame, and between a frame and the pose it takes without interpolation; default 0.02.
    #[serde(default = "default_rosbag2_max_time_difference")]
    pub max_time_difference: f64,
}

/// The RealSense ROS 2 wrapper's colour topic, the default here and for the live node.
pub const DEFAULT_COLOUR_TOPIC: &str = "/camera/color/image_raw";
/// The RealSense wrapper's depth topic with depth aligned to colour.
pub const DEFAULT_DEPTH_TOPIC: &str = "/camera/aligned_depth_to_color/image_raw";
/// The RealSense wrapper's colour camera info topic.
pub const DEFAULT_CAMERA_INFO_TOPIC: &str = "/camera/color/camera_info";
/// Default largest stamp difference (s) of a colour and a depth image paired into one frame.
pub const DEFAULT_MAX_TIME_DIFFERENCE: f64 = 0.02;

fn default_rosbag2_colour_topic() -> String {
    DEFAULT_COLOUR_TOPIC.to_owned()
}

fn default_rosbag2_depth_topic() -> String {
    DEFAULT_DEPTH_TOPIC.to_owned()
}

fn default_rosbag2_camera_info_topic() -> String {
    DEFAULT_CAMERA_INFO_TOPIC.to_owned()
}

fn default_rosbag2_max_time_difference() -> f64 {
    DEFAULT_MAX_TIME_DIFFERENCE
}

impl Default for Rosbag2Config {
    fn default() -> Self {
        Self {
            colour_topic: default_rosbag2_colour_topic(),
            depth_topic: default_rosbag2_depth_topic(),
            camera_info_topic: default_rosbag2_camera_info_topic(),
            pose_topic: None,
            tf: None,
            max_time_difference: default_rosbag2_max_time_difference(),
        }
    }
}

impl Rosbag2Config {
    /// The `[dataset]` config of a bag read with these settings: `kind = "rosbag2"`.
    ///
    /// # Errors
    /// [`DatasetError::InvalidSettings`] if the settings have no TOML form (never for finite
    /// values).
    pub fn dataset_config(&self) -> Result<DatasetConfig> {
        DatasetConfig::named(ROSBAG2)
            .with_param("rosbag2", self)
            .map_err(|e| DatasetError::InvalidSettings {
                reader: ROSBAG2.to_owned(),
                message: e.to_string(),
            })
    }
}

/// `[dataset]` keys of the bag reader, besides the shared ones.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg(feature = "rosbag2")]
pub(crate) struct Rosbag2Settings {
    /// An Open3D intrinsics JSON replacing the camera info, relative to the bag's folder.
    #[serde(default)]
    pub(crate) intrinsics: Option<std::path::PathBuf>,
    /// Accepted only to be refused with a reason: a bag's poses come from its messages.
    #[serde(default)]
    pub(crate) trajectory: Option<std::path::PathBuf>,
    /// `[dataset.rosbag2]`.
    #[serde(default)]
    pub(crate) rosbag2: Rosbag2Config,
}
