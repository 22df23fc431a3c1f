//! The TOML configuration of a run: which implementation each stage uses, and its parameters.
//!
//! The file is plain data. Sections `[pipeline]` and `[query]` are parsed here with
//! `deny_unknown_fields`. The stage sections `[tracker]`, `[proposer]`, `[encoder]`, `[map]` and
//! `[query.segmenter]` hold `kind = "<registered name>"` plus that implementation's own parameters,
//! which its build step parses (also refusing unknown keys); `[dataset]` likewise, except that core
//! parses the keys every reader shares ([`DatasetConfig`]). `[ros2]` belongs to the ROS 2 node,
//! which parses it. Building never touches the network.
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
use std::sync::Arc;
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
    /// `[ros2]`: the live ROS 2 node of `vlem ros2` (feature `ros2`), which parses and validates
    /// it (`vlem_ros2::Ros2Config`); `None` means every default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<toml::Table>,
    /// The text the config was read from, for [`Config::locate`].
    #[serde(skip)]
    source: ConfigSource,
}

/// The text a config was read from and where it came from (a file's path), kept so that an error
/// found after parsing can name its line: a stage parses its own keys from a table that no longer
/// knows its lines. Not part of the config's value: configs compare equal whatever their source.
#[derive(Clone, Debug, Default)]
struct ConfigSource(Option<Arc<SourceText>>);

#[derive(Debug)]
struct SourceText {
    origin: String,
    text: String,
}

impl PartialEq for ConfigSource {
    fn eq(&self, _other: &Self) -> bool {
        true
    }
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
        let config = parse(&text).map_err(|message| CoreError::Config {
            path: path.to_path_buf(),
            message,
        })?;
        Ok(config.with_source_text(text, &path.display().to_string()))
    }

    /// This config, remembering that it was parsed from `text`, which `origin` names in messages
    /// (a file's path; [`Config::from_file`] sets both): [`Config::locate`] then finds a key's
    /// line.
    pub fn with_source_text(mut self, text: impl Into<String>, origin: &str) -> Self {
        self.source = ConfigSource(Some(Arc::new(SourceText {
            origin: origin.to_owned(),
            text: text.into(),
        })));
        self
    }

    /// `error` with the config's origin and the line of the key it names, where it is an unknown
    /// key of a section that its owner parses (`[map] max_point = …`, a dataset reader's key) and
    /// the config knows its text ([`Config::from_file`], [`Config::with_source_text`]); other
    /// errors come back unchanged.
    /// [`Pipeline::from_config`](crate::pipeline::Pipeline::from_config) does this itself; call it
    /// for what is built from the config elsewhere (the dataset, the query segmenter).
    pub fn locate(&self, error: CoreError) -> CoreError {
        match &self.source.0 {
            Some(source) => with_config_text_line(error, &source.text, &source.origin),
            None => error,
        }
    }

    /// Parses config text (from no file: [`Config::from_file`] names the file in its errors).
    ///
    /// # Errors
    /// [`CoreError::ConfigText`] with the TOML parser's message (line, column, key).
    pub fn from_toml(text: &str) -> Result<Self> {
        parse(text).map_err(|message| CoreError::ConfigText { message })
    }

    /// The config as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }
}

/// Config text parsed, or the TOML parser's message (line, column, key) for an error that names
/// where the text came from.
fn parse(text: &str) -> std::result::Result<Config, String> {
    toml::from_str(text).map_err(|e| e.to_string().trim_end().to_owned())
}

/// `error` with `origin` and the line of `text` that holds the key it names, where it is an
/// unknown key of a section its owner parses (`[map] max_point = …`); other errors, and keys the
/// text does not hold on a line of their own, come back unchanged.
fn with_config_text_line(error: CoreError, text: &str, origin: &str) -> CoreError {
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
    // A key that is a sub-table of its own: `[dataset.synthetic]`.
    let header = format!("[{section}.{key}]");
    text.lines()
        .position(|line| line.trim().replace(' ', "") == header)
        .map(|index| index + 1)
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

/// The depth scales accepted (`[dataset] depth_scale`, `[ros2] depth_scale`), in raw units per
/// metre: 1 (depth in metres) to 1000 (millimetres), 5000 (TUM) and 6553.5 (Replica) lie well
/// inside; the datasets' median-depth check catches a wrong scale within it.
pub const DEPTH_SCALE_RANGE: (f64, f64) = (1e-3, 1e7);

/// The largest time difference accepted between a colour image, its depth image and its pose when
/// a bag or a live stream pairs them (`max_time_difference`), in seconds: more pairs a camera's
/// images with those of another moment.
pub const MAX_TIME_DIFFERENCE_S: f64 = 1.0;

/// `[dataset]`: where frames come from.
///
/// Core keeps what every reader shares; the reader that `kind` names (a registered dataset, see
/// `vlem plugins`) parses the rest of the section, its own keys and sub-tables such as
/// `[dataset.rosbag2]`, from [`DatasetConfig::params`], refusing keys it does not know.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
pub struct DatasetConfig {
    /// Dataset folder, relative to the config file; `--dataset` on the command line overrides it.
    #[serde(default)]
    pub path: Option<PathBuf>,
    /// Registered reader (`icl`, `tum`, `scannet`, `replica`, `rosbag2`, `synthetic`, …); default
    /// [`AUTO_DATASET`]: detected from the folder's content.
    #[serde(default = "default_dataset_kind")]
    pub kind: String,
    /// Raw depth units per metre; default per layout (ICL/ScanNet 1000, TUM 5000, Replica 6553.5).
    #[serde(default)]
    pub depth_scale: Option<f64>,
    /// Use every n-th frame; default 1.
    #[serde(default)]
    pub stride: Option<usize>,
    /// Stop after this many frames (after the stride).
    #[serde(default)]
    pub max_frames: Option<usize>,
    /// Every other key of the section: the reader's own settings, which it parses and validates.
    #[serde(flatten)]
    pub params: toml::Table,
}

/// `[dataset] kind` that detects the reader from the folder's content.
pub const AUTO_DATASET: &str = "auto";

fn default_dataset_kind() -> String {
    AUTO_DATASET.to_owned()
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self::named(AUTO_DATASET)
    }
}

impl DatasetConfig {
    /// The config of reader `kind` with every default.
    pub fn named(kind: &str) -> Self {
        Self {
            path: None,
            kind: kind.to_owned(),
            depth_scale: None,
            stride: None,
            max_frames: None,
            params: toml::Table::new(),
        }
    }

    /// This config with the reader-owned setting `key` (a key of `[dataset]`, or a sub-table such
    /// as `rosbag2`) set to `value`.
    ///
    /// # Errors
    /// [`CoreError::InvalidParams`] when `value` has no TOML form.
    pub fn with_param(mut self, key: &str, value: impl Serialize) -> Result<Self> {
        let value = toml::Value::try_from(value).map_err(|e| CoreError::InvalidParams {
            section: "dataset".to_owned(),
            name: self.kind.clone(),
            message: format!("`{key}` has no TOML form: {e}"),
        })?;
        self.params.insert(key.to_owned(), value);
        Ok(self)
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
             [tracker]\nkind = \"odometry\"\n[tracker.volume]\nmax_point = 1\n",
        )
        .unwrap();
        let error = CoreError::InvalidParams {
            section: "map".into(),
            name: "point-cloud".into(),
            message: "unknown field `max_point`, expected one of `max_points`".into(),
        };
        let located = Config::from_file(&path).unwrap().locate(error).to_string();
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
            Config::from_file(&path).unwrap().locate(other),
            CoreError::Unsupported { .. }
        ));
        // A config that does not know its text leaves errors as they are.
        let error = || CoreError::InvalidParams {
            section: "map".into(),
            name: "point-cloud".into(),
            message: "unknown field `max_point`".into(),
        };
        let text = std::fs::read_to_string(&path).unwrap();
        let unlocated = Config::from_toml(&text).unwrap().locate(error());
        assert_eq!(unlocated.to_string(), error().to_string());
        // Equality ignores the source.
        assert_eq!(
            Config::from_toml(&text).unwrap(),
            Config::from_file(&path).unwrap()
        );
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
        let err = Config::from_toml("[pipeline]\nmode = \"offline\"\nthreds = 2\n").unwrap_err();
        // Text from no file: the crate's error, without a path.
        assert!(matches!(err, CoreError::ConfigText { .. }), "{err:?}");
        let err = err.to_string();
        assert!(
            err.starts_with("config: ") && err.contains("line 3"),
            "{err}"
        );
        assert!(err.contains("unknown field `threds`"), "{err}");
        let err = Config::from_toml("[pipline]\n").unwrap_err().to_string();
        assert!(err.contains("unknown field `pipline`"), "{err}");
        let err = Config::from_toml("[pipeline]\nmode = \"fast\"\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("unknown variant `fast`"), "{err}");
    }

    #[test]
    fn reader_owned_dataset_keys_are_kept_for_the_reader() {
        let c = Config::from_toml(
            "[dataset]\nkind = \"synthetic\"\nstride = 2\n[dataset.synthetic]\nseed = 3\n",
        )
        .unwrap();
        assert_eq!(c.dataset.kind, "synthetic");
        assert_eq!(c.dataset.stride, Some(2));
        let synthetic = c.dataset.params.get("synthetic").and_then(|v| v.as_table());
        assert_eq!(
            synthetic
                .and_then(|t| t.get("seed"))
                .and_then(|v| v.as_integer()),
            Some(3)
        );
        assert_eq!(Config::from_toml(&c.to_toml()).unwrap(), c);
        assert_eq!(Config::from_toml("").unwrap().dataset.kind, AUTO_DATASET);
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
