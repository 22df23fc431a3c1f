//! The one error type of the evaluation crate.
//!
//! Evaluations run on files users pass by hand, so every variant carries what a message needs to
//! tell them what to fix: the file, the counts that were too small, the parameter that was wrong.

use std::path::PathBuf;

use vlem_datasets::DatasetError;

/// Every way an evaluation can fail.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EvalError {
    /// A file that was passed does not exist.
    #[error("{} ({role}): no such file", path.display())]
    MissingFile {
        /// The path given.
        path: PathBuf,
        /// What the file was for (`estimate`, `reference`).
        role: String,
    },
    /// A file that exists but cannot be read.
    #[error("{} ({role}): {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the file was for.
        role: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A trajectory file whose format can be told neither from its extension nor its content.
    #[error(
        "{}:{line}: cannot tell the trajectory format: the first data line has {fields} fields; \
         a TUM trajectory has 8 (`timestamp tx ty tz qx qy qz qw`), a .log trajectory 3 \
         (`i j k` before each 4x4 matrix)",
        path.display()
    )]
    UnknownFormat {
        /// The file.
        path: PathBuf,
        /// 1-based line number of its first data line.
        line: usize,
        /// How many whitespace-separated fields that line has.
        fields: usize,
    },
    /// A trajectory file or dataset that the dataset readers refuse (malformed line, not a
    /// rotation, a missing folder, …); the reader's error names the file and line.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// Two pose lists that should be paired element by element have different lengths.
    #[error("{estimate} estimated poses but {reference} reference poses; pass associated pairs")]
    LengthMismatch {
        /// Estimated poses given.
        estimate: usize,
        /// Reference poses given.
        reference: usize,
    },
    /// Too few poses for a metric to mean anything.
    #[error("{metric} needs at least {needed} poses, found {found}")]
    TooFewPoses {
        /// The metric (`ATE`, `RPE`, `alignment`).
        metric: String,
        /// The minimum.
        needed: usize,
        /// What was given.
        found: usize,
    },
    /// Association left too few pairs; the fields say why that may be.
    #[error(
        "only {associated} pose pairs associated {mode} (at least {needed} needed) out of \
         {estimate_poses} estimated poses with stamps {:.6}..{:.6} and {reference_poses} reference \
         poses with stamps {:.6}..{:.6}, max stamp difference {max_time_diff}{hint}",
        estimate_stamps.0, estimate_stamps.1, reference_stamps.0, reference_stamps.1
    )]
    TooFewAssociated {
        /// Pairs found.
        associated: usize,
        /// Pairs needed.
        needed: usize,
        /// How poses were associated, as prose (`by timestamp`, `by frame index`).
        mode: String,
        /// Poses in the estimate.
        estimate_poses: usize,
        /// First and last stamp of the estimate (frame indices for a `.log`).
        estimate_stamps: (f64, f64),
        /// Poses in the reference.
        reference_poses: usize,
        /// First and last stamp of the reference (frame indices for a `.log`).
        reference_stamps: (f64, f64),
        /// The tolerance used (seconds, or frames by frame index).
        max_time_diff: f64,
        /// A suggestion, empty or starting with `; `.
        hint: String,
    },
    /// A parameter outside its valid range.
    #[error("invalid {name} {value}: {reason}")]
    InvalidParameter {
        /// The parameter.
        name: String,
        /// The value given, as text.
        value: String,
        /// Why it is refused.
        reason: String,
    },
    /// An input pose with NaN or infinite entries.
    #[error("the {role} pose at position {index} is not finite")]
    NonFinitePose {
        /// `estimate` or `reference`.
        role: String,
        /// Its position in the list given.
        index: usize,
    },
    /// A dataset whose frames carry no label images, evaluated for semantic segmentation.
    #[error(
        "{dataset} has no ground-truth labels: use a labelled dataset (kind = \"synthetic\", or a \
         folder with label/ and labels.json)"
    )]
    MissingLabels {
        /// The dataset as its reader describes it.
        dataset: String,
    },
    /// A frame without a pose where the ground truth needs one.
    #[error(
        "frame {frame} of {dataset} has no pose: the 3D ground truth is built from the dataset's \
         poses"
    )]
    MissingPose {
        /// The frame index.
        frame: usize,
        /// The dataset as its reader describes it.
        dataset: String,
    },
    /// An error of vlem-core (reading a frame, a dimension mismatch between text and map
    /// embeddings, …); its message says what failed.
    #[error(transparent)]
    Core(#[from] vlem_core::CoreError),
    /// An error answering a query of the map (e.g. building the encoder a map file names).
    #[error(transparent)]
    Query(#[from] vlem_query::QueryError),
    /// A prompts table (class names to query texts) that cannot be used.
    #[error("prompts {}: {reason}", path.display())]
    Prompts {
        /// The prompts file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A class whose name (or prompt) the encoder cannot embed.
    #[error(
        "cannot embed the class \"{class}\" (query \"{text}\") with encoder `{encoder}`: {source}; \
         give a text the encoder knows as a prompt (--prompts FILE, a JSON object such as \
         {{\"{class}\": \"white\"}})"
    )]
    ClassText {
        /// The class.
        class: String,
        /// The text queried for it.
        text: String,
        /// The encoder.
        encoder: String,
        /// Why the encoder refused (boxed: it is large and rare).
        #[source]
        source: Box<vlem_core::CoreError>,
    },
    /// The encoder failed on a frame being evaluated.
    #[error("encoder `{encoder}` on frame {frame}: {source}")]
    Encode {
        /// The encoder.
        encoder: String,
        /// The frame index.
        frame: usize,
        /// Its error (boxed: it is large and rare).
        #[source]
        source: Box<vlem_core::CoreError>,
    },
    /// A config, map or dataset that does not fit the evaluation asked for (no encoder, no
    /// frames, dimensions that differ); the message says what is missing.
    #[error("{message}")]
    Setup {
        /// What is missing or does not fit.
        message: String,
    },
    /// A study file that cannot be run: the message says what is wrong (and names the cell when
    /// one cell's config is invalid).
    #[error("study file {}: {message}", path.display())]
    Study {
        /// The study file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Input that has no unique answer (e.g. a scale for positions that all coincide).
    #[error("cannot compute {what}: {reason}")]
    Degenerate {
        /// What was being computed.
        what: String,
        /// Why the input does not determine it.
        reason: String,
    },
}

/// `Result` with [`EvalError`].
pub type Result<T> = std::result::Result<T, EvalError>;
