//! The TOML configuration of a run: which implementation each stage uses, and its parameters.
//!
//! The file is plain data. Sections `[dataset]`, `[pipeline]` and `[query]` are parsed here with
//! `deny_unknown_fields`; the stage sections `[tracker]`, `[proposer]`, `[encoder]`, `[map]` and
//! `[query.segmenter]` hold `kind = "<registered name>"` plus that implementation's own parameters,
//! which its build step parses (also refusing unknown keys). Building never touches the network.
//!
//! ```toml
//! [dataset]
//! path = "data/living-room"   # relative to this file
//!
//! [tracker]
//! kind = "ground-truth"
//!
//! [encoder]
//! kind = "colour-names"
//!
//! [map]
//! kind = "point-cloud"
//! max_points = 1000000
//!
//! [query]
//! texts = ["red", "white wall"]
//! ```

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};

/// A whole run configuration.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Where frames come from.
    #[serde(default)]
    pub dataset: DatasetConfig,
    /// Threading and real-time behaviour.
    #[serde(default)]
    pub pipeline: PipelineConfig,
    /// Pose source; default `ground-truth`.
    #[serde(default = "default_tracker")]
    pub tracker: StageConfig,
    /// Region proposer, for encoders that need regions.
    #[serde(default)]
    pub proposer: Option<StageConfig>,
    /// Vision-language encoder; leave out for a geometry-only map.
    #[serde(default)]
    pub encoder: Option<StageConfig>,
    /// Embedding map; leave out for tracking only.
    #[serde(default)]
    pub map: Option<StageConfig>,
    /// Queries run after mapping, and how to segment them.
    #[serde(default)]
    pub query: QueryConfig,
    /// The live ROS 2 node of `vlem ros2` (feature `ros2`); `None` means every default of
    /// [`Ros2Config`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<Ros2Config>,
}

fn default_tracker() -> StageConfig {
    StageConfig::named("ground-truth")
}

impl Config {
    /// Reads and parses a config file.
    ///
    /// # Errors
    /// [`CoreError::ConfigRead`] for an unreadable file, [`CoreError::Config`] with the parser's
    /// message, which names the line and key.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| CoreError::ConfigRead {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml(&text).map_err(|message| CoreError::Config {
            path: path.to_path_buf(),
            message,
        })
    }

    /// Parses config text; the error is the parser's message.
    ///
    /// # Errors
    /// The TOML parser's message (line, column, key).
    pub fn from_toml(text: &str) -> std::result::Result<Self, String> {
        toml::from_str(text).map_err(|e| e.to_string().trim_end().to_owned())
    }

    /// The config as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }
}

/// `error` with the config file and line of the key it names, where it is an unknown key of a
/// stage's section (`[map] max_point = …`): the stage parses its own parameters from a table that
/// no longer knows its lines, so the location is found again in the file the config came from.
/// Other errors, and keys the file does not hold on a line of their own, come back unchanged.
pub fn with_config_line(error: CoreError, path: &Path) -> CoreError {
    let text = std::fs::read_to_string(path).ok();
    with_config_text_line(
        error,
        text.as_deref().unwrap_or(""),
        &path.display().to_string(),
    )
}

/// [`with_config_line`] for a config given as TOML `text` rather than a file (Python's
/// `vlem.Pipeline("[map]\n…")`); `origin` names it in the message.
pub fn with_config_text_line(error: CoreError, text: &str, origin: &str) -> CoreError {
    let CoreError::InvalidParams {
        section,
        name,
        message,
    } = error
    else {
        return error;
    };
    let line = message
        .split_once("unknown field `")
        .and_then(|(_, rest)| rest.split_once('`'))
        .and_then(|(key, _)| key_line(text, &section, key));
    let message = match line {
        Some(line) => format!("{message} (config {origin}, line {line})"),
        None => message,
    };
    CoreError::InvalidParams {
        section,
        name,
        message,
    }
}

/// The 1-based line of `key = …` in the table `[section]` (or one of its sub-tables) of TOML
/// `text`.
fn key_line(text: &str, section: &str, key: &str) -> Option<usize> {
    let mut inside = false;
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if let Some(header) = line.strip_prefix('[') {
            let table = header
                .trim_start_matches('[')
                .split(']')
                .next()
                .unwrap_or_default()
                .trim();
            inside = table == section
                || table
                    .strip_prefix(section)
                    .is_some_and(|sub| sub.starts_with('.'));
            continue;
        }
        let named = line
            .split_once('=')
            .is_some_and(|(name, _)| name.trim().trim_matches('"') == key);
        if inside && named {
            return Some(index + 1);
        }
    }
    None
}

/// The folder of a config file, against which its relative paths are resolved.
pub fn config_folder(path: &Path) -> &Path {
    path.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
}

/// Which implementation a stage uses, and its parameters.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
pub struct StageConfig {
    /// Registered implementation name (see `vlem plugins`).
    pub kind: String,
    /// Every other key of the section; the implementation parses and validates them.
    #[serde(flatten)]
    pub params: toml::Table,
}

impl StageConfig {
    /// A stage with default parameters.
    pub fn named(kind: &str) -> Self {
        Self {
            kind: kind.to_owned(),
            params: toml::Table::new(),
        }
    }
}

/// Dataset layouts vlem reads.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum DatasetKind {
    /// Detect from the folder's content.
    #[default]
    Auto,
    /// ICL-NUIM / Redwood / Open3D layout: `color/`, `depth/`, intrinsics JSON, `.log` trajectory.
    Icl,
    /// TUM RGB-D: `rgb.txt`, `depth.txt`, `groundtruth.txt`.
    Tum,
    /// ScanNet export: `color/`, `depth/`, `pose/`, `intrinsic/`.
    Scannet,
    /// Replica as packaged by NICE-SLAM: `results/`, `traj.txt`.
    Replica,
    /// A procedural labelled scene rendered on demand (no folder); see `[dataset.synthetic]`.
    Synthetic,
    /// A ROS 2 bag (rosbag2 folder, or one `.mcap` / `.db3` file); topics in `[dataset.rosbag2]`.
    Rosbag2,
}

/// The depth scales accepted (`[dataset] depth_scale`, `[ros2] depth_scale`), in raw units per
/// metre: 1 (depth in metres) to 1000 (millimetres), 5000 (TUM) and 6553.5 (Replica) lie well
/// inside; the datasets' median-depth check catches a wrong scale within it.
pub const DEPTH_SCALE_RANGE: (f64, f64) = (1e-3, 1e7);

/// The largest time difference accepted between a colour image, its depth image and its pose when
/// a bag or a live stream pairs them (`max_time_difference`), in seconds: more pairs a camera's
/// images with those of another moment.
pub const MAX_TIME_DIFFERENCE_S: f64 = 1.0;

/// `[dataset]`: where frames come from.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DatasetConfig {
    /// Dataset folder, relative to the config file; `--dataset` on the command line overrides it.
    #[serde(default)]
    pub path: Option<PathBuf>,
    /// Layout; default `auto`.
    #[serde(default)]
    pub kind: DatasetKind,
    /// Raw depth units per metre; default per layout (ICL/ScanNet 1000, TUM 5000, Replica 6553.5).
    #[serde(default)]
    pub depth_scale: Option<f64>,
    /// Use every n-th frame; default 1.
    #[serde(default)]
    pub stride: Option<usize>,
    /// Stop after this many frames (after the stride).
    #[serde(default)]
    pub max_frames: Option<usize>,
    /// Intrinsics file for layouts that do not fix its name (ICL/Redwood), relative to the dataset.
    #[serde(default)]
    pub intrinsics: Option<PathBuf>,
    /// Trajectory file for layouts that do not fix its name (ICL/Redwood), relative to the dataset.
    #[serde(default)]
    pub trajectory: Option<PathBuf>,
    /// `[dataset.synthetic]`: the generated scene of `kind = "synthetic"`; `None` means every
    /// default of [`SyntheticConfig`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub synthetic: Option<SyntheticConfig>,
    /// `[dataset.rosbag2]`: the topics of `kind = "rosbag2"`; `None` means every default of
    /// [`Rosbag2Config`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rosbag2: Option<Rosbag2Config>,
}

/// `[dataset.rosbag2]`: which topics of a ROS 2 bag make the frames, and where poses come from.
///
/// Plain data; `vlem-datasets` checks it against the bag (a missing or mistyped topic lists the
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

fn default_rosbag2_colour_topic() -> String {
    "/camera/color/image_raw".to_owned()
}

fn default_rosbag2_depth_topic() -> String {
    "/camera/aligned_depth_to_color/image_raw".to_owned()
}

fn default_rosbag2_camera_info_topic() -> String {
    "/camera/color/camera_info".to_owned()
}

fn default_rosbag2_max_time_difference() -> f64 {
    0.02
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

/// Depth noise of the synthetic scene.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum SyntheticNoise {
    /// Exact depth (default).
    #[default]
    None,
    /// Kinect-like: axial noise σ(z) = 0.0012 + 0.0019 (z − 0.4)² m, disparity quantisation, no
    /// depth before 0.4 m or beyond 8 m, and dropout at grazing angles.
    Kinect,
}

/// `[dataset.synthetic]`: the procedural labelled RGB-D scene of `kind = "synthetic"`.
///
/// Plain data; `vlem-datasets` validates it (and names the key of a bad value). Everything the
/// scene holds, and its camera path, follows from these values alone.
///
/// ```toml
/// [dataset]
/// kind = "synthetic"
///
/// [dataset.synthetic]
/// seed = 7
/// frames = 450
/// ```
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SyntheticConfig {
    /// Seed of the furniture, textures, camera path and noise; default 0.
    #[serde(default)]
    pub seed: u64,
    /// Number of frames; default 450 (15 s at 30 Hz: one full orbit of the room, which takes
    /// 380–440 frames).
    #[serde(default = "default_synthetic_frames")]
    pub frames: usize,
    /// Image width in pixels; default 640 (fx = fy = 525 · width / 640).
    #[serde(default = "default_synthetic_width")]
    pub width: u32,
    /// Image height in pixels; default 480.
    #[serde(default = "default_synthetic_height")]
    pub height: u32,
    /// Depth noise model; default `none` (exact depth).
    #[serde(default)]
    pub noise: SyntheticNoise,
    /// Room size in metres: x extent, y extent, height; default `[5.5, 4.5, 2.7]`.
    #[serde(default = "default_synthetic_room")]
    pub room: [f64; 3],
    /// How many pieces of furniture and wall items to try to place; default 18 (fewer fit in a
    /// small room; pilasters and small props on top of furniture come in addition, and pieces the
    /// camera path would not see are dropped).
    #[serde(default = "default_synthetic_objects")]
    pub objects: usize,
}

fn default_synthetic_frames() -> usize {
    450
}

fn default_synthetic_width() -> u32 {
    640
}

fn default_synthetic_height() -> u32 {
    480
}

fn default_synthetic_room() -> [f64; 3] {
    [5.5, 4.5, 2.7]
}

fn default_synthetic_objects() -> usize {
    18
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            frames: default_synthetic_frames(),
            width: default_synthetic_width(),
            height: default_synthetic_height(),
            noise: SyntheticNoise::None,
            room: default_synthetic_room(),
            objects: default_synthetic_objects(),
        }
    }
}

/// Whether frames may be skipped.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// Every frame is tracked and integrated.
    #[default]
    Offline,
    /// Frames arrive at `frame_rate`; those that arrive while the embedding stage is busy are
    /// tracked but not embedded (counted as skipped), as in the paper.
    RealTime,
}

/// How the embedding stages (proposal, encoding, integration) share threads.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum StageLayout {
    /// Each stage in a worker of its own, joined by bounded queues: while the map integrates frame
    /// k, the encoder embeds frame k+1 and the proposer segments frame k+2, so the embedding rate
    /// is the slowest stage's, not the sum.
    #[default]
    Overlapped,
    /// All stages one after another in one worker (the pipeline before stages overlapped; the
    /// same map, for comparisons).
    Serial,
}

/// `[pipeline]`: threading and real-time behaviour.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PipelineConfig {
    /// `offline` (default) or `real-time`.
    #[serde(default)]
    pub mode: Mode,
    /// Frames that may wait between tracking and embedding; default 2.
    #[serde(default = "default_queue")]
    pub queue_capacity: usize,
    /// Sensor frame rate that real-time mode replays the dataset at; default 30.
    #[serde(default = "default_frame_rate")]
    pub frame_rate: f64,
    /// `overlapped` (default) or `serial`.
    #[serde(default)]
    pub stages: StageLayout,
    /// Frames that may wait between two overlapped embedding stages; default 1.
    #[serde(default = "default_stage_queue")]
    pub stage_queue_capacity: usize,
}

fn default_queue() -> usize {
    2
}

fn default_stage_queue() -> usize {
    1
}

/// The largest queue capacity accepted: a queue's slots are allocated when a run starts, and each
/// waiting frame holds its images (a few MB), so more than this is a mistake, not a buffer.
pub const MAX_QUEUE_CAPACITY: usize = 1024;

impl PipelineConfig {
    /// Checks the values a run cannot use, without building anything: `queue_capacity` and
    /// `stage_queue_capacity` must lie in 1..=[`MAX_QUEUE_CAPACITY`] and, in real-time mode,
    /// `frame_rate` be a positive finite rate whose period (1 / `frame_rate`) a [`Duration`] can
    /// hold.
    ///
    /// # Errors
    /// [`CoreError::MissingStage`] naming the key, the value and the range.
    pub fn validate(&self) -> Result<()> {
        for (key, value) in [
            ("queue_capacity", self.queue_capacity),
            ("stage_queue_capacity", self.stage_queue_capacity),
        ] {
            if !(1..=MAX_QUEUE_CAPACITY).contains(&value) {
                return Err(CoreError::MissingStage {
                    message: format!(
                        "[pipeline] {key} must be at least 1 and at most {MAX_QUEUE_CAPACITY} \
                         frames, got {value}"
                    ),
                });
            }
        }
        let rate = self.frame_rate;
        let representable =
            rate.is_finite() && rate > 0.0 && Duration::try_from_secs_f64(1.0 / rate).is_ok();
        if self.mode == Mode::RealTime && !representable {
            return Err(CoreError::MissingStage {
                message: format!(
                    "[pipeline] frame_rate must be a positive number of frames per second in \
                     real-time mode, got {rate:?}"
                ),
            });
        }
        Ok(())
    }

    /// The time between two frames in real-time mode, 1 / `frame_rate`; zero (no pacing) for a
    /// rate that is not positive, and the longest [`Duration`] for one too small for it to hold
    /// (which [`PipelineConfig::validate`] refuses in real-time mode).
    pub fn frame_period(&self) -> Duration {
        if self.frame_rate > 0.0 {
            Duration::try_from_secs_f64(1.0 / self.frame_rate).unwrap_or(Duration::MAX)
        } else {
            Duration::ZERO
        }
    }
}

fn default_frame_rate() -> f64 {
    30.0
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Offline,
            queue_capacity: default_queue(),
            frame_rate: default_frame_rate(),
            stages: StageLayout::default(),
            stage_queue_capacity: default_stage_queue(),
        }
    }
}

/// `[query]`: what `vlem run` / `vlem demo` ask the finished map, and how answers are segmented.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct QueryConfig {
    /// Queries answered after mapping; default none.
    #[serde(default)]
    pub texts: Vec<String>,
    /// Segmenter; default `threshold`.
    #[serde(default = "default_segmenter")]
    pub segmenter: StageConfig,
}

fn default_segmenter() -> StageConfig {
    StageConfig::named("threshold")
}

impl Default for QueryConfig {
    fn default() -> Self {
        Self {
            texts: Vec::new(),
            segmenter: default_segmenter(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unknown_stage_key_is_located_in_its_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.toml");
        std::fs::write(
            &path,
            "[dataset]\nstride = 1\n\n[map]\nkind = \"point-cloud\"\nmax_point = 5\n\
             [tracker.volume]\nmax_point = 1\n",
        )
        .unwrap();
        let error = CoreError::InvalidParams {
            section: "map".into(),
            name: "point-cloud".into(),
            message: "unknown field `max_point`, expected one of `max_points`".into(),
        };
        let located = with_config_line(error, &path).to_string();
        assert!(
            located.ends_with(&format!("(config {}, line 6)", path.display())),
            "{located}"
        );
        assert_eq!(
            key_line("[tracker]\n[tracker.volume]\nx = 1\n", "tracker", "x"),
            Some(3)
        );
        assert_eq!(key_line("[map]\ny = 1\n", "map", "x"), None);
        // Other errors pass through.
        let other = CoreError::Unsupported {
            implementation: "x".into(),
            capability: "y",
        };
        assert!(matches!(
            with_config_line(other, &path),
            CoreError::Unsupported { .. }
        ));
    }

    #[test]
    fn minimal_config_gets_documented_defaults() {
        let c = Config::from_toml("[map]\nkind = \"point-cloud\"\nmax_points = 10\n").unwrap();
        assert_eq!(c.tracker.kind, "ground-truth");
        assert_eq!(c.pipeline.mode, Mode::Offline);
        assert_eq!(c.pipeline.queue_capacity, 2);
        assert_eq!(c.query.segmenter.kind, "threshold");
        let map = c.map.unwrap();
        assert_eq!(
            map.params.get("max_points").and_then(|v| v.as_integer()),
            Some(10)
        );
        assert!(c.encoder.is_none());
    }

    #[test]
    fn unknown_keys_are_errors_that_name_the_key_and_line() {
        let err = Config::from_toml("[dataset]\npath = \"x\"\ndepth_scael = 1000.0\n").unwrap_err();
        assert!(err.contains("line 3"), "{err}");
        assert!(err.contains("unknown field `depth_scael`"), "{err}");
        let err = Config::from_toml("[pipline]\n").unwrap_err();
        assert!(err.contains("unknown field `pipline`"), "{err}");
        let err = Config::from_toml("[pipeline]\nmode = \"fast\"\n").unwrap_err();
        assert!(err.contains("unknown variant `fast`"), "{err}");
    }

    #[test]
    fn synthetic_section_parses_with_defaults_and_refuses_unknown_keys() {
        let c = Config::from_toml("[dataset]\nkind = \"synthetic\"\n").unwrap();
        assert_eq!(c.dataset.kind, DatasetKind::Synthetic);
        assert!(c.dataset.synthetic.is_none());
        let c = Config::from_toml(
            "[dataset]\nkind = \"synthetic\"\n[dataset.synthetic]\nseed = 3\nnoise = \"kinect\"\n",
        )
        .unwrap();
        let s = c.dataset.synthetic.clone().unwrap();
        assert_eq!(s.seed, 3);
        assert_eq!(s.noise, SyntheticNoise::Kinect);
        assert_eq!((s.frames, s.width, s.height), (450, 640, 480));
        assert_eq!(s.room, [5.5, 4.5, 2.7]);
        assert_eq!(Config::from_toml(&c.to_toml()).unwrap(), c);
        let err = Config::from_toml("[dataset.synthetic]\nfrmaes = 3\n").unwrap_err();
        assert!(err.contains("unknown field `frmaes`"), "{err}");
    }

    #[test]
    fn config_file_errors_name_the_file() {
        let err = Config::from_file(Path::new("/nonexistent/vlem.toml")).unwrap_err();
        assert!(
            err.to_string()
                .starts_with("cannot read config /nonexistent/vlem.toml: "),
            "{err}"
        );
    }
}

/// `[ros2]`: what the live ROS 2 node (`vlem ros2`, feature `ros2`) subscribes to and publishes.
///
/// Plain data; `vlem-ros2` validates it. Input topic defaults are the RealSense wrapper's with
/// depth aligned to colour. An image topic whose name ends in `/compressed` or `/compressedDepth`
/// carries `sensor_msgs/msg/CompressedImage` (image_transport's convention), any other
/// `sensor_msgs/msg/Image`.
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
    #[serde(default = "default_rosbag2_colour_topic")]
    pub colour_topic: String,
    /// Depth registered to colour (`16UC1` in `depth_scale` units per metre, `32FC1` in metres;
    /// 16-bit PNG on `/compressed`, image_transport's format on `/compressedDepth`).
    #[serde(default = "default_rosbag2_depth_topic")]
    pub depth_topic: String,
    /// `sensor_msgs/msg/CameraInfo` of the colour camera.
    #[serde(default = "default_rosbag2_camera_info_topic")]
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
    #[serde(default = "default_rosbag2_max_time_difference")]
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
    /// default 10 ([`crate::stream::StreamSpec::max_stamp_jump`]).
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
    crate::stream::DEFAULT_MAX_STAMP_JUMP
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            domain_id: None,
            localhost_only: false,
            node_name: default_ros2_node_name(),
            colour_topic: default_rosbag2_colour_topic(),
            depth_topic: default_rosbag2_depth_topic(),
            camera_info_topic: default_rosbag2_camera_info_topic(),
            depth_scale: default_ros2_depth_scale(),
            pose_topic: None,
            pose_type: Ros2PoseType::default(),
            tf: None,
            max_time_difference: default_rosbag2_max_time_difference(),
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
