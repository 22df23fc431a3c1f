//! The one error type of `vlem-core`, shared by every trait in the pipeline.
//!
//! Backends and maps have their own error enums; each converts into [`CoreError::Stage`] so the
//! pipeline handles one type while the original cause stays available through `source()`.

use std::path::PathBuf;

use crate::stage::StageKind;

/// Every way a core operation can fail.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CoreError {
    /// An image buffer does not match the size it claims.
    #[error("{what}: buffer holds {actual} values, {width}x{height} needs {expected}")]
    BufferSize {
        /// Which buffer.
        what: &'static str,
        /// Claimed width in pixels.
        width: u32,
        /// Claimed height in pixels.
        height: u32,
        /// Values needed.
        expected: usize,
        /// Values given.
        actual: usize,
    },
    /// Camera intrinsics that cannot describe a real pinhole camera.
    #[error("invalid intrinsics: {reason}")]
    InvalidIntrinsics {
        /// What is wrong with them.
        reason: String,
    },
    /// Two images of one frame (or an image and its intrinsics) disagree in size.
    #[error(
        "frame {frame}: {what} is {actual_width}x{actual_height}, expected {expected_width}x{expected_height}"
    )]
    SizeMismatch {
        /// Frame index.
        frame: usize,
        /// What disagrees (e.g. "depth image").
        what: &'static str,
        /// Expected width.
        expected_width: u32,
        /// Expected height.
        expected_height: u32,
        /// Actual width.
        actual_width: u32,
        /// Actual height.
        actual_height: u32,
    },
    /// A pose with NaN or infinite entries.
    #[error("frame {frame}: pose is not finite")]
    NonFinitePose {
        /// Frame index.
        frame: usize,
    },
    /// Pixel embeddings that are inconsistent with themselves.
    #[error("invalid pixel embeddings: {reason}")]
    InvalidEmbeddings {
        /// What is wrong with them.
        reason: String,
    },
    /// An embedding vector of the wrong length.
    #[error("{what} has dimension {actual}, expected {expected}")]
    DimensionMismatch {
        /// What has the wrong length.
        what: String,
        /// Expected dimension.
        expected: usize,
        /// Actual dimension.
        actual: usize,
    },
    /// An optional capability that this implementation does not have.
    #[error("{implementation} does not support {capability}")]
    Unsupported {
        /// The implementation asked.
        implementation: String,
        /// The capability it lacks (e.g. "text encoding").
        capability: &'static str,
    },
    /// A label-driven encoder was handed a frame without ground-truth labels.
    #[error(
        "the encoder `{encoder}` embeds ground-truth labels, but frame {frame} has none: use a labelled dataset ([dataset] kind = \"synthetic\", or an ICL-layout folder with label/*.png and labels.json)"
    )]
    MissingLabels {
        /// Encoder name.
        encoder: String,
        /// The frame without labels.
        frame: usize,
    },
    /// A stage name that no linked plugin registered.
    #[error("{}", unknown_message(*.kind, name, known, feature.as_deref()))]
    UnknownImplementation {
        /// The stage that was asked for.
        kind: StageKind,
        /// The name that was asked for.
        name: String,
        /// The names registered for this stage.
        known: Vec<&'static str>,
        /// The cargo feature that would provide `name`, if one is known.
        feature: Option<String>,
    },
    /// Two plugins registered the same name for the same stage.
    #[error("two plugins register the {kind} `{name}`: {first} and {second}")]
    DuplicateImplementation {
        /// Stage.
        kind: StageKind,
        /// The name registered twice.
        name: &'static str,
        /// Description of the first registration.
        first: &'static str,
        /// Description of the second registration.
        second: &'static str,
    },
    /// Parameters of a stage that its implementation does not accept.
    #[error(
        "[{section}]{}: {message}",
        if name.is_empty() { String::new() } else { format!(" kind = \"{name}\"") }
    )]
    InvalidParams {
        /// The config section (e.g. "encoder").
        section: String,
        /// The implementation name; empty for a section that names none (`[ros2]`).
        name: String,
        /// What the parser said, naming the offending key.
        message: String,
    },
    /// A configuration file that cannot be read.
    #[error("cannot read config {}: {source}", path.display())]
    ConfigRead {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A configuration file that cannot be parsed.
    #[error("config {}: {message}", path.display())]
    Config {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the key where possible.
        message: String,
    },
    /// Configuration text that cannot be parsed ([`Config::from_toml`](crate::Config::from_toml):
    /// text from no file).
    #[error("config: {message}")]
    ConfigText {
        /// The TOML parser's message: line, column and key.
        message: String,
    },
    /// The encoder and the map disagree on the embedding dimension.
    #[error(
        "the encoder `{encoder}` produces {encoder_dim}-d embeddings but the map `{map}` stores {map_dim}-d embeddings; set [map] dim = {encoder_dim} or remove it"
    )]
    EmbeddingDimensionMismatch {
        /// Encoder name.
        encoder: String,
        /// Its dimension.
        encoder_dim: usize,
        /// Map name.
        map: String,
        /// Its dimension.
        map_dim: usize,
    },
    /// A stage that needs another one that the config leaves out.
    #[error("{message}")]
    MissingStage {
        /// What is missing and how to add it.
        message: String,
    },
    /// A map file that cannot be read back.
    #[error("map file {}: {reason}", path.display())]
    MapFile {
        /// The file.
        path: PathBuf,
        /// Why it is refused.
        reason: String,
    },
    /// An I/O failure on a named file.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A failure inside a stage implementation (tracker, encoder, map, ...), with its own error.
    #[error("{kind} `{name}`: {source}")]
    Stage {
        /// The stage.
        kind: StageKind,
        /// The implementation.
        name: String,
        /// The implementation's own error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A dataset that cannot be read.
    #[error("{source}")]
    Dataset {
        /// The reader's own error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A live stream refused a frame (out of order, another camera, no pose where poses are
    /// expected); the stream goes on without it.
    #[error("frame refused: {reason}")]
    FrameRefused {
        /// Why.
        reason: String,
    },
    /// A live stream whose pipeline has stopped reading it (the run ended or a stage failed).
    #[error("the pipeline is no longer reading this stream (its run has ended)")]
    StreamClosed,
    /// A worker thread of the pipeline died.
    #[error("pipeline worker failed: {reason}")]
    Worker {
        /// What happened.
        reason: String,
    },
    /// An embedding stage failed on one frame; the run stopped there.
    #[error("{stage} of frame {frame}: {source}")]
    AtFrame {
        /// The stage: `propose`, `encode` or `integrate`.
        stage: &'static str,
        /// The frame's index in the source.
        frame: usize,
        /// The stage's error.
        #[source]
        source: Box<CoreError>,
    },
}

fn unknown_message(kind: StageKind, name: &str, known: &[&str], feature: Option<&str>) -> String {
    let known = if known.is_empty() {
        "none is compiled in".to_owned()
    } else {
        format!("known: {}", known.join(", "))
    };
    match feature {
        Some(feature) => format!(
            "unknown {kind} `{name}` ({known}); `{name}` is provided by the cargo feature `{feature}`, \
             which this binary was built without: rebuild with `cargo build --release --features {feature}`"
        ),
        None => format!("unknown {kind} `{name}` ({known})"),
    }
}

impl CoreError {
    /// Wraps an implementation's own error as a stage failure.
    pub fn stage(
        kind: StageKind,
        name: impl Into<String>,
        source: impl std::error::Error + Send + Sync + 'static,
    ) -> Self {
        Self::Stage {
            kind,
            name: name.into(),
            source: Box::new(source),
        }
    }

    /// The error itself, without the [`CoreError::AtFrame`] that says where in a run it happened.
    pub fn root(&self) -> &Self {
        match self {
            Self::AtFrame { source, .. } => source.root(),
            e => e,
        }
    }

    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }
}

/// An error and its causes on one line, as every front-end reports it (the `vlem` command, the
/// Python package, the query server): causes joined with ": ", skipping a cause whose text the line
/// already contains (library errors that wrap another one usually say its message).
pub fn message_chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut line = String::new();
    let mut cause = Some(error);
    while let Some(e) = cause {
        let text = e.to_string();
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
        cause = e.source();
    }
    line
}

/// Result with [`CoreError`].
pub type Result<T, E = CoreError> = std::result::Result<T, E>;
