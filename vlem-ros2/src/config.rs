//! `[ros2]`: what the live node subscribes to and publishes. The section belongs to this crate:
//! core keeps it as a table ([`vlem_core::Config::ros2`]) and [`Ros2Config::from_table`] parses it,
//! refusing unknown keys.

use serde::{Deserialize, Serialize};
use vlem_core::CoreError;
use vlem_datasets::rosbag2::{
    DEFAULT_CAMERA_INFO_TOPIC, DEFAULT_COLOUR_TOPIC, DEFAULT_DEPTH_TOPIC,
    DEFAULT_MAX_TIME_DIFFERENCE,
};

/// `[ros2]`: what the live ROS 2 node (`vlem ros2`, feature `ros2`) subscribes to and publishes.
///
/// Plain data; the node validates it when it starts. Input topic defaults are the RealSense
/// wrapper's with depth aligned to colour. An image topic whose name ends in `/compressed` or
/// `/compressedDepth` carries `sensor_msgs/msg/CompressedImage` (image_transport's convention),
/// any other `sensor_msgs/msg/Image`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// DDS domain; default `$ROS_DOMAIN_ID`, else 0.
    #[serde(default)]
    pub domain_id: Option<u16>,
    /// Only talk over the loopback interface (one machine); default false.
    #[serde(default)]
    pub localhost_only: bool,
    /// Node name; default `vlem`.
    #[serde(default = "default_ros2_node_name")]
    pub node_name: String,
    /// Colour images (`rgb8`, `bgr8`, `rgba8`, `bgra8`, or JPEG/PNG on a `/compressed` topic).
    #[serde(default = "default_colour_topic")]
    pub colour_topic: String,
    /// Depth registered to colour (`16UC1` in `depth_scale` units per metre, `32FC1` in metres;
    /// 16-bit PNG on `/compressed`, image_transport's format on `/compressedDepth`).
    #[serde(default = "default_depth_topic")]
    pub depth_topic: String,
    /// `sensor_msgs/msg/CameraInfo` of the colour camera.
    #[serde(default = "default_camera_info_topic")]
    pub camera_info_topic: String,
    /// Raw depth units per metre of `16UC1` depth; default 1000 (millimetres).
    #[serde(default = "default_ros2_depth_scale")]
    pub depth_scale: f64,
    /// Poses of the camera's optical frame, optional (else the tracker estimates them).
    #[serde(default)]
    pub pose_topic: Option<String>,
    /// Type of `pose_topic`: `odometry` (`nav_msgs/msg/Odometry`, default) or `pose-stamped`.
    #[serde(default)]
    pub pose_type: Ros2PoseType,
    /// Poses from `/tf` and `/tf_static` instead: `[parent, child]` frame ids, e.g.
    /// `["map", "camera_color_optical_frame"]`; the parent must be an ancestor of the child.
    #[serde(default)]
    pub tf: Option<[String; 2]>,
    /// Largest stamp difference (s) between a colour and a depth image paired into a frame, and
    /// between a frame and the pose it takes; default 0.02.
    #[serde(default = "default_max_time_difference")]
    pub max_time_difference: f64,
    /// Frames that may wait for the tracker before new ones are dropped (and counted); default 2.
    #[serde(default = "default_ros2_queue")]
    pub queue: usize,
    /// Fixed frame of everything published; default `map`.
    #[serde(default = "default_ros2_map_frame")]
    pub map_frame: String,
    /// Child frame of the tracked pose on `/tf` (`map_frame` -> this); default
    /// `vlem_camera_optical_frame`, so it never clashes with the camera driver's own frames.
    #[serde(default = "default_ros2_camera_frame")]
    pub camera_frame: String,
    /// Tracked camera pose, `geometry_msgs/msg/PoseStamped`; default `/vlem/pose`.
    #[serde(default = "default_ros2_pose_out")]
    pub pose_out_topic: String,
    /// The map as `sensor_msgs/msg/PointCloud2` (xyz + rgb); default `/vlem/map`.
    #[serde(default = "default_ros2_map_topic")]
    pub map_topic: String,
    /// How often the map is published (Hz); 0 = never; default 1.
    #[serde(default = "default_ros2_map_rate")]
    pub map_rate: f64,
    /// Most points per published cloud (map, heatmap, best set: an even subsample of larger
    /// ones); default 300000.
    #[serde(default = "default_ros2_map_max_points")]
    pub map_max_points: usize,
    /// Queries, `std_msgs/msg/String`: a text, or `grasp: TEXT` for a grasp too; default
    /// `/vlem/query`.
    #[serde(default = "default_ros2_query_topic")]
    pub query_topic: String,
    /// Heatmap of each query, `PointCloud2` with xyz, rgb (jet) and `similarity`; default
    /// `/vlem/heatmap`.
    #[serde(default = "default_ros2_heatmap_topic")]
    pub heatmap_topic: String,
    /// Best point set of each query, `PointCloud2` xyz + rgb; default `/vlem/best`.
    #[serde(default = "default_ros2_best_topic")]
    pub best_topic: String,
    /// Grasp on the best set of a `grasp:` query, `PoseStamped`; default `/vlem/grasp`.
    #[serde(default = "default_ros2_grasp_topic")]
    pub grasp_topic: String,
    /// Seconds without a new image after which the input counts as stalled (logged); default 2.
    #[serde(default = "default_ros2_stall_seconds")]
    pub stall_seconds: f64,
    /// Largest forward jump (s) of a frame's stamp past the previous frame's taken at once; a frame
    /// beyond it is refused and counted, and three in a row make it the stream's new time;
    /// default 10 ([`vlem_core::stream::StreamSpec::max_stamp_jump`]).
    #[serde(default = "default_ros2_max_stamp_jump")]
    pub max_stamp_jump: f64,
}

/// Type of `[ros2] pose_topic`.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Ros2PoseType {
    /// `nav_msgs/msg/Odometry`.
    #[default]
    Odometry,
    /// `geometry_msgs/msg/PoseStamped`.
    PoseStamped,
}

fn default_ros2_node_name() -> String {
    "vlem".to_owned()
}
fn default_ros2_depth_scale() -> f64 {
    1000.0
}
fn default_ros2_queue() -> usize {
    2
}
fn default_ros2_map_frame() -> String {
    "map".to_owned()
}
fn default_ros2_camera_frame() -> String {
    "vlem_camera_optical_frame".to_owned()
}
fn default_ros2_pose_out() -> String {
    "/vlem/pose".to_owned()
}
fn default_ros2_map_topic() -> String {
    "/vlem/map".to_owned()
}
fn default_ros2_map_rate() -> f64 {
    1.0
}
fn default_ros2_map_max_points() -> usize {
    300_000
}
fn default_ros2_query_topic() -> String {
    "/vlem/query".to_owned()
}
fn default_ros2_heatmap_topic() -> String {
    "/vlem/heatmap".to_owned()
}
fn default_ros2_best_topic() -> String {
    "/vlem/best".to_owned()
}
fn default_ros2_grasp_topic() -> String {
    "/vlem/grasp".to_owned()
}
fn default_ros2_stall_seconds() -> f64 {
    2.0
}

fn default_ros2_max_stamp_jump() -> f64 {
    vlem_core::stream::DEFAULT_MAX_STAMP_JUMP
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            domain_id: None,
            localhost_only: false,
            node_name: default_ros2_node_name(),
            colour_topic: DEFAULT_COLOUR_TOPIC.to_owned(),
            depth_topic: DEFAULT_DEPTH_TOPIC.to_owned(),
            camera_info_topic: DEFAULT_CAMERA_INFO_TOPIC.to_owned(),
            depth_scale: default_ros2_depth_scale(),
            pose_topic: None,
            pose_type: Ros2PoseType::default(),
            tf: None,
            max_time_difference: DEFAULT_MAX_TIME_DIFFERENCE,
            queue: default_ros2_queue(),
            map_frame: default_ros2_map_frame(),
            camera_frame: default_ros2_camera_frame(),
            pose_out_topic: default_ros2_pose_out(),
            map_topic: default_ros2_map_topic(),
            map_rate: default_ros2_map_rate(),
            map_max_points: default_ros2_map_max_points(),
            query_topic: default_ros2_query_topic(),
            heatmap_topic: default_ros2_heatmap_topic(),
            best_topic: default_ros2_best_topic(),
            grasp_topic: default_ros2_grasp_topic(),
            stall_seconds: default_ros2_stall_seconds(),
            max_stamp_jump: default_ros2_max_stamp_jump(),
        }
    }
}

fn default_colour_topic() -> String {
    DEFAULT_COLOUR_TOPIC.to_owned()
}
fn default_depth_topic() -> String {
    DEFAULT_DEPTH_TOPIC.to_owned()
}
fn default_camera_info_topic() -> String {
    DEFAULT_CAMERA_INFO_TOPIC.to_owned()
}
fn default_max_time_difference() -> f64 {
    DEFAULT_MAX_TIME_DIFFERENCE
}

impl Ros2Config {
    /// The `[ros2]` section of a config (`None`: every default).
    ///
    /// # Errors
    /// [`CoreError::InvalidParams`] naming an unknown key or a value of the wrong type; front-ends
    /// locate it on its line with [`vlem_core::Config::locate`].
    pub fn from_table(section: Option<&toml::Table>) -> vlem_core::Result<Self> {
        let Some(section) = section else {
            return Ok(Self::default());
        };
        Self::deserialize(toml::Value::Table(section.clone())).map_err(|e| {
            CoreError::InvalidParams {
                section: "ros2".to_owned(),
                name: String::new(),
                message: e.to_string().trim().to_owned(),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_section_parses_with_defaults_and_refuses_unknown_keys() {
        let config = vlem_core::Config::from_toml("[ros2]\nqueue = 5\n").unwrap();
        let settings = Ros2Config::from_table(config.ros2.as_ref()).unwrap();
        assert_eq!(settings.queue, 5);
        assert_eq!(settings.colour_topic, DEFAULT_COLOUR_TOPIC);
        assert_eq!(Ros2Config::from_table(None).unwrap(), Ros2Config::default());

        let text = "[ros2]\nqueue = 5\nnode_nmae = \"x\"\n";
        let config = vlem_core::Config::from_toml(text)
            .unwrap()
            .with_source_text(text, "vlem.toml");
        let err = Ros2Config::from_table(config.ros2.as_ref()).unwrap_err();
        let err = config.locate(err).to_string();
        assert!(
            err.starts_with("[ros2]: unknown field `node_nmae`"),
            "{err}"
        );
        assert!(err.ends_with("(config vlem.toml, line 3)"), "{err}");
    }
}
