//! What every reader shares: the list of frame files, the stride / `max_frames` selection, and
//! lazy decoding of one frame.
//!
//! A reader's only job is to turn its layout into a list of [`Entry`]s and a camera; decoding, unit
//! conversion and the consistency checks live here so that every layout behaves the same.

use std::path::{Path, PathBuf};

use vlem_core::config::DatasetConfig;
use vlem_core::{Frame, Intrinsics, Pose};

use crate::error::{DatasetError, Result};
use crate::images;

/// Where a frame's pose comes from.
#[derive(Clone, Debug)]
pub(crate) enum PoseRef {
    /// The layout has no poses for this sequence.
    None,
    /// Read when the sequence was opened (whole-trajectory files).
    Known(Pose),
    /// A one-pose file read with the frame (ScanNet), so that one lost frame does not make the
    /// whole sequence unusable.
    File(PathBuf),
}

/// The files of one frame of the underlying sequence.
#[derive(Clone, Debug)]
pub(crate) struct Entry {
    pub(crate) colour: PathBuf,
    pub(crate) depth: PathBuf,
    /// The dataset's own timestamp, where the layout has one.
    pub(crate) timestamp: Option<f64>,
    pub(crate) pose: PoseRef,
    /// Ground-truth class ids, where the dataset is labelled.
    pub(crate) labels: Option<PathBuf>,
}

impl Entry {
    /// A frame without timestamp or pose (yet).
    pub(crate) fn new(colour: PathBuf, depth: PathBuf) -> Self {
        Self {
            colour,
            depth,
            timestamp: None,
            pose: PoseRef::None,
            labels: None,
        }
    }
}

/// How the colour image relates to the depth image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ColourFit {
    /// Both are registered at the same resolution; a difference is an error.
    SameSize,
    /// The colour camera has its own resolution; colour is resampled to the depth resolution.
    ResizeToDepth,
}

/// The camera of a sequence and where its values came from (for error messages).
#[derive(Clone, Debug)]
pub(crate) struct Camera {
    pub(crate) intrinsics: Intrinsics,
    pub(crate) origin: String,
}

impl Camera {
    /// Intrinsics read from `path`.
    pub(crate) fn from_file(intrinsics: Intrinsics, path: &Path) -> Self {
        Self {
            intrinsics,
            origin: path.display().to_string(),
        }
    }

    /// The `[dataset] intrinsics` file (relative to `dir`) if the config names one, else the
    /// layout's documented `default`, described by `origin` in error messages.
    pub(crate) fn from_setting_or_default(
        intrinsics: Option<&Path>,
        dir: &Path,
        default: Intrinsics,
        origin: &str,
    ) -> Result<Self> {
        Ok(match intrinsics {
            Some(path) => {
                let path = dir.join(path);
                Self::from_file(crate::calibration::read_open3d_intrinsics(&path)?, &path)
            }
            None => Self {
                intrinsics: default,
                origin: origin.to_owned(),
            },
        })
    }
}

/// `[dataset]` keys of readers whose only own setting is an intrinsics file.
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct IntrinsicsSetting {
    /// Open3D intrinsics JSON replacing the layout's camera, relative to the dataset folder.
    #[serde(default)]
    pub(crate) intrinsics: Option<std::path::PathBuf>,
}

/// `[dataset]` keys of readers that have no settings of their own.
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NoSettings {}

/// [`reader_settings`] for a registration's settings check: parses and drops them.
///
/// # Errors
/// [`vlem_core::CoreError::InvalidParams`] naming the key.
pub(crate) fn check_settings<T: serde::de::DeserializeOwned>(
    reader: &str,
    config: &DatasetConfig,
) -> vlem_core::Result<()> {
    reader_settings::<T>(reader, config)?;
    Ok(())
}

/// The reader-owned keys of `[dataset]` (everything but the shared ones) as reader `reader`'s
/// settings struct, refusing keys it does not know.
///
/// # Errors
/// [`DatasetError::InvalidSettings`] naming the key.
pub(crate) fn reader_settings<T: serde::de::DeserializeOwned>(
    reader: &str,
    config: &DatasetConfig,
) -> Result<T> {
    T::deserialize(toml::Value::Table(config.params.clone())).map_err(|e| {
        let mut message = e.to_string().trim().to_owned();
        if message.contains("unknown field") {
            message.push_str(
                " (every reader also takes path, kind, depth_scale, stride and max_frames)",
            );
        }
        DatasetError::InvalidSettings {
            reader: reader.to_owned(),
            message,
        }
    })
}

/// Which frames of the underlying sequence are used: every `stride`-th, at most `max_frames`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Selection {
    stride: usize,
    max_frames: Option<usize>,
}

impl Selection {
    /// The selection of `[dataset]`, validated.
    pub(crate) fn from_config(config: &DatasetConfig, dir: &Path) -> Result<Self> {
        let bad = |message: &str| DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: message.to_owned(),
        };
        let stride = config.stride.unwrap_or(1);
        if stride == 0 {
            return Err(bad("stride must be at least 1"));
        }
        if config.max_frames == Some(0) {
            return Err(bad(
                "max_frames must be at least 1 (leave it out to use every frame)",
            ));
        }
        Ok(Self {
            stride,
            max_frames: config.max_frames,
        })
    }

    /// The selected items with their index in the underlying sequence.
    pub(crate) fn apply<T>(&self, items: Vec<T>) -> Vec<(usize, T)> {
        items
            .into_iter()
            .enumerate()
            .step_by(self.stride)
            .take(self.max_frames.unwrap_or(usize::MAX))
            .collect()
    }
}

/// The depth scale of `[dataset] depth_scale`, or the layout's `default`.
pub(crate) fn depth_scale(config: &DatasetConfig, default: f64, dir: &Path) -> Result<f32> {
    let scale = config.depth_scale.unwrap_or(default);
    if !(scale.is_finite() && scale > 0.0) {
        return Err(DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: format!(
                "depth_scale must be a positive number of raw units per metre, got {scale}"
            ),
        });
    }
    let (min, max) = vlem_core::config::DEPTH_SCALE_RANGE;
    vlem_core::ranges::number(scale, min, max, "raw units per metre").map_err(|range| {
        DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: format!("depth_scale {range}"),
        }
    })?;
    // Depth images are f32; the scale only needs that precision.
    Ok(scale as f32)
}

/// The frame numbers missing from a numbered sequence: numbers between the first and the last
/// file's that no frame has (a frame whose images were deleted). None when the files are not all
/// numbered (they are then taken in order) or have no gap.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct MissingFrames {
    /// How many numbers are missing.
    pub(crate) count: u64,
    /// The first few of them.
    pub(crate) first: Vec<u64>,
}

impl MissingFrames {
    /// Numbers listed in [`MissingFrames::first`].
    const LISTED: usize = 8;

    /// The gaps in the depth files' numbers of `entries` (the whole sequence, before selection).
    pub(crate) fn of(entries: &[Entry]) -> Self {
        let numbers: Option<Vec<u64>> = entries.iter().map(|e| frame_number(&e.depth)).collect();
        let Some(mut numbers) = numbers else {
            return Self::default();
        };
        numbers.sort_unstable();
        numbers.dedup();
        let mut missing = Self::default();
        for pair in numbers.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            missing.count += b - a - 1;
            missing
                .first
                .extend((a + 1..b).take(Self::LISTED - missing.first.len().min(Self::LISTED)));
        }
        missing
    }

    /// `5` or `5, 9, 10 and 3 more`.
    pub(crate) fn describe(&self) -> String {
        let listed: Vec<String> = self.first.iter().map(u64::to_string).collect();
        let more = self.count.saturating_sub(self.first.len() as u64);
        let noun = if self.count == 1 { "frame" } else { "frames" };
        if more > 0 {
            format!("{noun} {} and {more} more", listed.join(", "))
        } else {
            format!("{noun} {}", listed.join(", "))
        }
    }

    /// The warning a sequence with gaps gets (`None` without gaps).
    pub(crate) fn warning(&self, dir: &Path, poses: bool) -> Option<String> {
        (self.count > 0).then(|| {
            format!(
                "{}: {} missing (no colour or depth image has the number): {}",
                dir.display(),
                self.describe(),
                if poses {
                    "the other frames get their poses by frame number"
                } else {
                    "the frames on either side of a gap are mapped as neighbours"
                }
            )
        })
    }
}

/// Gives each selected frame its pose from a whole-sequence trajectory whose poses carry frame
/// ids (a `.log` file's metadata lines, or line numbers for files without ids). Without missing
/// frames, poses go to frames in order, so numbering may start anywhere; with missing frames
/// (`missing`), each frame takes the pose whose id is its file number, never the pose at its
/// position, and a frame without one is an error naming its file.
pub(crate) fn attach_trajectory(
    selected: &mut [(usize, Entry)],
    missing: &MissingFrames,
    poses: &[(u64, Pose)],
    trajectory: &Path,
) -> Result<()> {
    if missing.count == 0 {
        let in_order: Vec<Pose> = poses.iter().map(|&(_, pose)| pose).collect();
        return attach_poses(selected, &in_order, trajectory);
    }
    let by_id: std::collections::HashMap<u64, Pose> = poses.iter().copied().collect();
    for (_, entry) in selected.iter_mut() {
        // Every file is numbered when frames are missing.
        let number = frame_number(&entry.depth).unwrap_or(u64::MAX);
        let pose = by_id
            .get(&number)
            .ok_or_else(|| DatasetError::NoPoseForFrame {
                path: entry.depth.clone(),
                frame: number,
                trajectory: trajectory.to_path_buf(),
                missing: missing.describe(),
            })?;
        entry.pose = PoseRef::Known(*pose);
    }
    Ok(())
}

/// Gives each selected frame the pose of its underlying index from a whole-sequence trajectory.
pub(crate) fn attach_poses(
    selected: &mut [(usize, Entry)],
    poses: &[Pose],
    trajectory: &Path,
) -> Result<()> {
    let needed = selected.last().map_or(0, |(i, _)| i + 1);
    if poses.len() < needed {
        return Err(DatasetError::TooFewPoses {
            path: trajectory.to_path_buf(),
            poses: poses.len(),
            needed,
        });
    }
    for (i, entry) in selected.iter_mut() {
        entry.pose = PoseRef::Known(poses[*i]);
    }
    Ok(())
}

/// The files of `dir` with one of `extensions` (lower case, no dot), in natural order
/// (`9.png` before `10.png`, as numbered frames are meant).
///
/// `hint` says what the layout needs `dir` for, in the error when it is missing. An entry with
/// such a name that is not a regular file (or a link to one) is an error naming it.
pub(crate) fn list_files(dir: &Path, extensions: &[&str], hint: &str) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Err(DatasetError::MissingFile {
            path: dir.to_path_buf(),
            hint: hint.to_owned(),
        });
    }
    let io = |e| DatasetError::io(dir, e);
    let mut files = Vec::new();
    for item in std::fs::read_dir(dir).map_err(io)? {
        let path = item.map_err(io)?.path();
        let matches = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| extensions.contains(&e.to_ascii_lowercase().as_str()));
        if !matches {
            continue;
        }
        // An image name on something that is not a file (a FIFO would block the reader forever,
        // a looping link fails later as a count mismatch) is named now, not skipped.
        if let Some(what) = not_a_regular_file(&path) {
            return Err(not_a_file_error(&path, &what));
        }
        files.push(path);
    }
    files.sort_by_cached_key(|p| natural_key(p));
    Ok(files)
}

/// The number at the end of a file stem: `frame000012.jpg` → 12, `00010.png` → 10.
pub(crate) fn frame_number(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_str()?;
    let digits = stem.len() - stem.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    stem[stem.len() - digits..].parse().ok()
}

/// Sort key: the stem's non-numeric prefix, then its trailing number, then the whole name.
fn natural_key(path: &Path) -> (String, Option<u64>, String) {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let prefix = stem
        .trim_end_matches(|c: char| c.is_ascii_digit())
        .to_owned();
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    (prefix, frame_number(path), name)
}

/// Fails with [`DatasetError::MissingFile`] unless `path` is a file; `hint` says who expects it.
/// Something else under that name (a FIFO, a folder, a looping link) is named for what it is.
pub(crate) fn require_file(path: &Path, hint: impl FnOnce() -> String) -> Result<()> {
    if std::fs::symlink_metadata(path).is_err() {
        return Err(DatasetError::MissingFile {
            path: path.to_path_buf(),
            hint: hint(),
        });
    }
    match not_a_regular_file(path) {
        None => Ok(()),
        Some(what) => Err(not_a_file_error(path, &what)),
    }
}

/// What `path` is when it is not a regular file (or a link to one), in words; `None` for a file.
fn not_a_regular_file(path: &Path) -> Option<String> {
    let error = match std::fs::metadata(path) {
        Ok(metadata) if metadata.is_file() => return None,
        Ok(metadata) => return Some(file_kind(&metadata.file_type()).to_owned()),
        Err(error) => error,
    };
    let link = std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
    Some(match (link, error.kind()) {
        (true, std::io::ErrorKind::NotFound) => "a symbolic link to nothing".to_owned(),
        (true, _) => format!("a symbolic link that cannot be followed ({error})"),
        (false, _) => format!("a file that cannot be inspected ({error})"),
    })
}

fn file_kind(kind: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if kind.is_socket() {
            return "a socket";
        }
        if kind.is_block_device() || kind.is_char_device() {
            return "a device";
        }
    }
    if kind.is_dir() {
        "a folder"
    } else {
        "a special file"
    }
}

fn not_a_file_error(path: &Path, what: &str) -> DatasetError {
    DatasetError::UnsupportedImage {
        path: path.to_path_buf(),
        reason: format!(
            "{what}, not a regular file: dataset files are read from regular files (or links to \
             them) only; replace it with the file or remove it"
        ),
    }
}

/// A selected, lazily decoded RGB-D sequence.
#[derive(Debug)]
pub(crate) struct Sequence {
    pub(crate) layout: &'static str,
    pub(crate) root: PathBuf,
    /// Selected frames with their index in the underlying sequence.
    pub(crate) entries: Vec<(usize, Entry)>,
    pub(crate) camera: Camera,
    pub(crate) depth_scale: f32,
    pub(crate) colour_fit: ColourFit,
    /// Class names of a labelled dataset (whose entries carry label files).
    pub(crate) label_names: Option<std::sync::Arc<vlem_core::LabelNames>>,
    /// What a user should know about the folder (missing frames), printed at start-up and kept
    /// in the run's stats.
    pub(crate) warnings: Vec<String>,
}

impl Sequence {
    /// A sequence of `entries`; [`DatasetError::Empty`] when there is none.
    pub(crate) fn new(
        layout: &'static str,
        root: &Path,
        entries: Vec<(usize, Entry)>,
        camera: Camera,
        depth_scale: f32,
        colour_fit: ColourFit,
    ) -> Result<Self> {
        if entries.is_empty() {
            return Err(DatasetError::Empty {
                path: root.to_path_buf(),
            });
        }
        Ok(Self {
            layout,
            root: root.to_path_buf(),
            entries,
            camera,
            depth_scale,
            colour_fit,
            label_names: None,
            warnings: Vec::new(),
        })
    }

    /// Adds a warning (see [`Sequence::warnings`]).
    pub(crate) fn with_warning(mut self, warning: Option<String>) -> Self {
        self.warnings.extend(warning);
        self
    }

    /// Marks the sequence as labelled: frames whose entry has a label file get its labels.
    pub(crate) fn with_label_names(mut self, names: vlem_core::LabelNames) -> Self {
        self.label_names = Some(std::sync::Arc::new(names));
        self
    }

    pub(crate) fn describe(&self) -> String {
        format!(
            "{} folder {} ({} frames)",
            self.layout,
            self.root.display(),
            self.entries.len()
        )
    }

    pub(crate) fn has_poses(&self) -> bool {
        self.entries
            .iter()
            .any(|(_, e)| !matches!(e.pose, PoseRef::None))
    }

    /// Decodes frame `index` of the selection.
    pub(crate) fn frame(&self, index: usize) -> Result<Frame> {
        let Some((source_index, entry)) = self.entries.get(index) else {
            return Err(DatasetError::FrameOutOfRange {
                path: self.root.clone(),
                index,
                len: self.entries.len(),
            });
        };
        // A depth image of another size than the camera is refused from its header, before it is
        // decoded: a small compressed file can claim a size that takes gigabytes to decode.
        let k = self.camera.intrinsics;
        let header_size = images::dimensions(&entry.depth)?;
        if header_size != (k.width, k.height) {
            if self.colour_fit == ColourFit::SameSize {
                let colour_size = images::dimensions(&entry.colour)?;
                if colour_size != header_size {
                    return Err(DatasetError::SizeMismatch {
                        colour: entry.colour.clone(),
                        colour_size,
                        depth: entry.depth.clone(),
                        depth_size: header_size,
                    });
                }
            }
            return Err(DatasetError::IntrinsicsMismatch {
                image: entry.depth.clone(),
                image_size: header_size,
                origin: self.camera.origin.clone(),
                intrinsics_size: (k.width, k.height),
            });
        }
        let depth = images::read_depth(&entry.depth, self.depth_scale)?;
        crate::depth_check::check_depth_scale(&depth, self.depth_scale, &entry.depth)?;
        let depth_size = (depth.width(), depth.height());
        let colour = match self.colour_fit {
            ColourFit::SameSize => images::read_colour(&entry.colour)?,
            ColourFit::ResizeToDepth => {
                images::read_colour_resized(&entry.colour, depth_size.0, depth_size.1)?
            }
        };
        let colour_size = (colour.width(), colour.height());
        if colour_size != depth_size {
            return Err(DatasetError::SizeMismatch {
                colour: entry.colour.clone(),
                colour_size,
                depth: entry.depth.clone(),
                depth_size,
            });
        }
        let pose = match &entry.pose {
            PoseRef::None => None,
            PoseRef::Known(pose) => Some(*pose),
            PoseRef::File(path) => Some(crate::trajectory::read_scannet_pose(path, index)?),
        };
        // Layouts without timestamps use the underlying frame index, so that a strided run still
        // reports where in the recording each frame is.
        let timestamp = entry.timestamp.unwrap_or(*source_index as f64);
        let frame = Frame::new(index, timestamp, colour, depth, k, pose).map_err(|source| {
            DatasetError::Core {
                path: entry.depth.clone(),
                source,
            }
        })?;
        match (&entry.labels, &self.label_names) {
            (Some(path), Some(names)) => frame
                .with_labels(images::read_labels(path, names)?)
                .map_err(|source| DatasetError::Core {
                    path: path.clone(),
                    source,
                }),
            _ => Ok(frame),
        }
    }
}

/// Implements [`vlem_core::FrameSource`] and the typed `load` for a reader struct with a
/// `seq: Sequence` field.
macro_rules! reader_via_sequence {
    ($reader:ty) => {
        impl $reader {
            /// Decodes frame `index` (0-based, after stride and `max_frames`), with the
            /// dataset's own error type; [`vlem_core::FrameSource::frame`] wraps this error.
            ///
            /// # Errors
            /// A [`DatasetError`](crate::DatasetError) naming the file that is missing,
            /// unreadable or inconsistent.
            pub fn load(&self, index: usize) -> crate::Result<vlem_core::Frame> {
                self.seq.frame(index)
            }
        }

        impl vlem_core::FrameSource for $reader {
            fn describe(&self) -> String {
                self.seq.describe()
            }

            fn len(&self) -> usize {
                self.seq.entries.len()
            }

            fn intrinsics(&self) -> vlem_core::Intrinsics {
                self.seq.camera.intrinsics
            }

            fn has_poses(&self) -> bool {
                self.seq.has_poses()
            }

            fn warnings(&self) -> Vec<String> {
                self.seq.warnings.clone()
            }

            fn frame(&mut self, index: usize) -> vlem_core::Result<vlem_core::Frame> {
                Ok(self.seq.frame(index)?)
            }
        }
    };
}
pub(crate) use reader_via_sequence;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order_sorts_numbers_by_value() {
        let mut files: Vec<PathBuf> = ["10.png", "9.png", "frame000002.jpg", "frame000001.jpg"]
            .iter()
            .map(PathBuf::from)
            .collect();
        files.sort_by_cached_key(|p| natural_key(p));
        assert_eq!(
            files,
            ["9.png", "10.png", "frame000001.jpg", "frame000002.jpg"]
                .iter()
                .map(PathBuf::from)
                .collect::<Vec<_>>()
        );
        assert_eq!(frame_number(Path::new("depth000123.png")), Some(123));
        assert_eq!(frame_number(Path::new("depth.png")), None);
    }

    #[test]
    fn selection_strides_then_truncates() {
        let dir = Path::new("/d");
        let config = DatasetConfig {
            stride: Some(3),
            max_frames: Some(2),
            ..DatasetConfig::default()
        };
        let s = Selection::from_config(&config, dir).unwrap();
        assert_eq!(
            s.apply((0..10).collect()),
            vec![(0, 0), (3, 3)],
            "frame i of the source is underlying frame i * stride"
        );
        let zero = DatasetConfig {
            stride: Some(0),
            ..DatasetConfig::default()
        };
        let err = Selection::from_config(&zero, dir).unwrap_err().to_string();
        assert_eq!(err, "/d: [dataset] stride must be at least 1");
    }

    #[test]
    fn missing_frame_numbers_are_found_and_described() {
        let entries = |numbers: &[u64]| -> Vec<Entry> {
            numbers
                .iter()
                .map(|n| {
                    Entry::new(
                        PathBuf::from(format!("c/{n:05}.png")),
                        PathBuf::from(format!("d/{n:05}.png")),
                    )
                })
                .collect()
        };
        assert_eq!(MissingFrames::of(&entries(&[3, 4, 5])).count, 0);
        let m = MissingFrames::of(&entries(&[0, 1, 3, 7]));
        assert_eq!((m.count, m.first.clone()), (4, vec![2, 4, 5, 6]));
        assert_eq!(m.describe(), "frames 2, 4, 5, 6");
        let m = MissingFrames::of(&entries(&[0, 1_000_000_000_000]));
        assert_eq!(m.count, 999_999_999_999);
        assert_eq!(m.first.len(), 8);
        assert!(
            m.describe().ends_with("and 999999999991 more"),
            "{}",
            m.describe()
        );
        // Unnumbered files are taken in order: no gaps to speak of.
        let mut mixed = entries(&[0, 5]);
        mixed.push(Entry::new("c/x.png".into(), "d/x.png".into()));
        assert_eq!(MissingFrames::of(&mixed), MissingFrames::default());
    }
}
