//! The one error type of the dataset readers.
//!
//! Every variant names the file (or folder) involved, so a message alone tells the user what to fix.
//! The pipeline sees these errors as [`CoreError::Dataset`], with this error as its `source()`.

use std::path::PathBuf;

use vlem_core::CoreError;

/// Every way reading a dataset can fail.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// A file or folder the layout needs is not there.
    #[error("{}: not found ({hint})", path.display())]
    MissingFile {
        /// The path that was looked for.
        path: PathBuf,
        /// What else was tried and how to fix it.
        hint: String,
    },
    /// A file that exists but cannot be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// An image file that cannot be decoded.
    #[error("{}: cannot decode image: {source}", path.display())]
    UnreadableImage {
        /// The image file.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// An image that decodes but has a pixel format the reader cannot use.
    #[error("{}: {reason}", path.display())]
    UnsupportedImage {
        /// The image file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// The colour and depth images of one frame differ in size.
    #[error(
        "colour image {} is {}x{} but depth image {} is {}x{}; the two must be registered at the same resolution",
        colour.display(), colour_size.0, colour_size.1, depth.display(), depth_size.0, depth_size.1
    )]
    SizeMismatch {
        /// The colour image.
        colour: PathBuf,
        /// Its width and height.
        colour_size: (u32, u32),
        /// The depth image.
        depth: PathBuf,
        /// Its width and height.
        depth_size: (u32, u32),
    },
    /// An image whose size differs from the camera the intrinsics describe.
    #[error(
        "{} is {}x{} but the intrinsics ({origin}) are for {}x{}",
        image.display(), image_size.0, image_size.1, intrinsics_size.0, intrinsics_size.1
    )]
    IntrinsicsMismatch {
        /// The image.
        image: PathBuf,
        /// Its width and height.
        image_size: (u32, u32),
        /// Where the intrinsics came from (a file, or the layout's documented default).
        origin: String,
        /// The size the intrinsics describe.
        intrinsics_size: (u32, u32),
    },
    /// The colour and depth folders hold different numbers of images, so they cannot be paired.
    #[error(
        "{} holds {colour_count} colour images but {} holds {depth_count} depth images; \
         add an rgbd.match file pairing them",
        colour_dir.display(), depth_dir.display()
    )]
    CountMismatch {
        /// The colour folder.
        colour_dir: PathBuf,
        /// Colour images found.
        colour_count: usize,
        /// The depth folder.
        depth_dir: PathBuf,
        /// Depth images found.
        depth_count: usize,
    },
    /// Colour and depth files paired by order whose frame numbers differ.
    #[error(
        "{} is paired with {} by their sorted order, but their frame numbers differ: a colour or \
         depth image is missing; restore it, or pair the files in an rgbd.match file",
        colour.display(),
        depth.display()
    )]
    Unpaired {
        /// The colour image.
        colour: PathBuf,
        /// The depth image.
        depth: PathBuf,
    },
    /// A text file (list, trajectory, calibration) with a malformed line.
    #[error("{}:{line}: {message}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A pose with NaN or infinite entries (ScanNet marks lost frames this way).
    #[error("{}: the pose of frame {frame} is not finite", path.display())]
    NonFinitePose {
        /// The trajectory or pose file.
        path: PathBuf,
        /// The frame (its position in the file, or the requested frame for one-pose files).
        frame: usize,
    },
    /// A pose whose rotation part is not a rotation.
    #[error(
        "{}: the rotation of frame {frame} is not orthonormal (deviation {deviation:.2e}, tolerance {tolerance:.0e})",
        path.display()
    )]
    NotRotation {
        /// The trajectory or pose file.
        path: PathBuf,
        /// The frame.
        frame: usize,
        /// Largest deviation found (|RᵀR − I|, |det R − 1| or |‖q‖ − 1|).
        deviation: f64,
        /// The tolerance it exceeds.
        tolerance: f64,
    },
    /// A trajectory file that holds no pose at all.
    #[error("{}: holds no poses", path.display())]
    NoPoses {
        /// The trajectory file.
        path: PathBuf,
    },
    /// A trajectory with fewer poses than the frames that need one.
    #[error("{}: holds {poses} poses but {needed} frames need one", path.display())]
    TooFewPoses {
        /// The trajectory file.
        path: PathBuf,
        /// Poses in the file.
        poses: usize,
        /// Frames (of the underlying sequence) that need a pose.
        needed: usize,
    },
    /// A frame of a sequence with missing frame numbers that the trajectory has no pose for.
    #[error(
        "{}: frame {frame} has no pose in {}; frames are missing from the folder ({missing}), so \
         poses are matched to the frames by their file numbers, not by position: restore the \
         missing frames, or give a trajectory whose frame ids are the file numbers",
        path.display(),
        trajectory.display()
    )]
    NoPoseForFrame {
        /// The frame's depth image.
        path: PathBuf,
        /// Its frame number.
        frame: u64,
        /// The trajectory file.
        trajectory: PathBuf,
        /// Which numbers are missing, for the message.
        missing: String,
    },
    /// A TUM frame with no ground-truth pose close enough in time and none on both sides.
    #[error(
        "{}: no pose within {tolerance} s of timestamp {timestamp:.6} and none on both sides to interpolate",
        path.display()
    )]
    NoPoseNear {
        /// The ground-truth file.
        path: PathBuf,
        /// The frame's timestamp.
        timestamp: f64,
        /// The association tolerance in seconds.
        tolerance: f64,
    },
    /// A dataset folder without a single frame.
    #[error("{}: the dataset holds no frames", path.display())]
    Empty {
        /// The dataset folder.
        path: PathBuf,
    },
    /// A folder whose layout matches none of the readers.
    #[error("{}: unknown dataset layout; {message}", path.display())]
    UnknownLayout {
        /// The folder.
        path: PathBuf,
        /// What was looked for.
        message: String,
    },
    /// Several files could be the one the reader needs.
    #[error("{}: {message}", path.display())]
    Ambiguous {
        /// The folder.
        path: PathBuf,
        /// The candidates and how to pick one.
        message: String,
    },
    /// A `[dataset]` setting that cannot be used.
    #[error("{}: [dataset] {message}", path.display())]
    BadConfig {
        /// The dataset folder.
        path: PathBuf,
        /// The setting and what is wrong with it.
        message: String,
    },
    /// A reader-owned `[dataset]` setting the reader does not accept (an unknown key, a value of
    /// the wrong type); the pipeline sees it as [`CoreError::InvalidParams`], which front-ends
    /// locate on its line of the config.
    #[error("[dataset] kind = \"{reader}\": {message}")]
    InvalidSettings {
        /// The reader.
        reader: String,
        /// What the parser said, naming the key.
        message: String,
    },
    /// A frame index past the end of the sequence.
    #[error("{}: frame {index} requested but the sequence has {len} frames", path.display())]
    FrameOutOfRange {
        /// The dataset folder.
        path: PathBuf,
        /// The index asked for.
        index: usize,
        /// The number of frames.
        len: usize,
    },
    /// A run with neither a dataset folder given nor `[dataset] path` in its config.
    #[error("no dataset: pass --dataset DIR or set [dataset] path in the config")]
    NoFolder,
    /// A dataset folder that does not exist.
    #[error("dataset folder {} does not exist ({hint})", path.display())]
    NoSuchFolder {
        /// The folder.
        path: PathBuf,
        /// Where the path came from and how to give another.
        hint: String,
    },
    /// A `[dataset.synthetic]` value (or a `[dataset]` setting) the synthetic scene cannot use.
    #[error("[dataset.synthetic] {key}: {message}")]
    SyntheticConfig {
        /// The key, as written in the config.
        key: &'static str,
        /// What is wrong with its value.
        message: String,
    },
    /// A request the synthetic scene cannot answer (a frame past the end, a bad argument).
    #[error("synthetic scene: {message}")]
    Synthetic {
        /// What was asked and why it cannot be answered.
        message: String,
    },
    /// An image that cannot be encoded or written.
    #[error("{}: cannot write image: {source}", path.display())]
    UnwritableImage {
        /// The image file.
        path: PathBuf,
        /// The encoder's error.
        #[source]
        source: image::ImageError,
    },
    /// A ROS 2 bag that cannot be read as configured: its storage, a topic, or a message.
    #[error("{}: {message}", path.display())]
    Bag {
        /// The bag (folder or storage file).
        path: PathBuf,
        /// What is wrong, naming the topic and message where there is one.
        message: String,
    },
    /// A core validation (intrinsics, frame) that failed on data read from a file.
    #[error("{}: {source}", path.display())]
    Core {
        /// The file the data came from.
        path: PathBuf,
        /// The core error.
        #[source]
        source: CoreError,
    },
}

impl DatasetError {
    /// An I/O error on `path`, turning "not found" into [`DatasetError::MissingFile`].
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        let path = path.into();
        if source.kind() == std::io::ErrorKind::NotFound {
            Self::MissingFile {
                path,
                hint: "it was expected by the dataset layout".to_owned(),
            }
        } else {
            Self::Io { path, source }
        }
    }

    /// A parse error at `line` (1-based) of `path`.
    pub(crate) fn parse(path: impl Into<PathBuf>, line: usize, message: impl Into<String>) -> Self {
        Self::Parse {
            path: path.into(),
            line,
            message: message.into(),
        }
    }
}

impl From<DatasetError> for CoreError {
    fn from(e: DatasetError) -> Self {
        match e {
            DatasetError::InvalidSettings { reader, message } => CoreError::InvalidParams {
                section: vlem_core::StageKind::Dataset.section().to_owned(),
                name: reader,
                message,
            },
            e => CoreError::Dataset {
                source: Box::new(e),
            },
        }
    }
}

/// Result with [`DatasetError`].
pub type Result<T, E = DatasetError> = std::result::Result<T, E>;
