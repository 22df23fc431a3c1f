//! vlem-datasets: [`FrameSource`] readers for RGB-D dataset folders, and trajectory files.
//!
//! Layouts (see each module for the files it reads):
//! - [`icl`]: ICL-NUIM (augmented) / Redwood / Open3D folders, depth scale 1000;
//! - [`tum`]: TUM RGB-D, colour associated to depth within 0.02 s, depth scale 5000;
//! - [`scannet`]: ScanNet exports, colour resampled to the depth camera, depth scale 1000;
//! - [`replica`]: Replica as packaged by NICE-SLAM, depth scale 6553.5;
//! - [`rosbag2`] (feature `rosbag2`): a ROS 2 bag, MCAP or SQLite3, topics in `[dataset.rosbag2]`;
//! - [`synthetic`]: no folder: a procedural labelled scene rendered on demand
//!   (`kind = "synthetic"`, settings in `[dataset.synthetic]`), which can also be written out in the
//!   ICL layout with [`synthetic::write_to_disk`].
//!
//! [`open`] builds the reader for a `[dataset]` config, detecting the layout with [`detect_kind`]
//! when `kind = "auto"`. Readers list the files when opened and decode a frame only when it is
//! asked for. Every error ([`DatasetError`]) names the file involved; through [`FrameSource`] it
//! arrives as [`vlem_core::CoreError::Dataset`].
//!
//! Common `[dataset]` settings: frame `i` of a reader is frame `i * stride` of the recording, at
//! most `max_frames` frames are used, `depth_scale` overrides the layout's default, and a frame's
//! timestamp is the dataset's own or, where the layout has none, its index in the recording.

use std::path::Path;

use vlem_core::FrameSource;
use vlem_core::config::{DatasetConfig, DatasetKind};

mod calibration;
mod depth_check;
mod error;
pub mod icl;
mod images;
pub mod replica;
pub mod rosbag2;
pub mod scannet;
mod sequence;
pub mod synthetic;
mod text;
pub mod trajectory;
pub mod tum;

pub use calibration::{
    REPLICA_DEFAULT_INTRINSICS, TUM_DEFAULT_INTRINSICS, open3d_intrinsics_from_str,
    read_open3d_intrinsics,
};
pub use error::{DatasetError, Result};
pub use icl::IclReader;
pub use images::{colour_from_bytes, colour_resized_from_bytes, depth_from_bytes};
pub use replica::ReplicaReader;
#[cfg(feature = "rosbag2")]
pub use rosbag2::Rosbag2Reader;
pub use scannet::ScanNetReader;
pub use synthetic::{SyntheticReader, SyntheticScene};
pub use text::{MatchPair, match_pairs_from_str};
pub use tum::TumReader;

/// What [`detect_kind`] looks for, in the order it checks.
const LAYOUTS_LOOKED_FOR: &str = "looked for metadata.yaml or .mcap/.db3 files (ROS 2 bag), \
    rgb.txt and depth.txt (TUM RGB-D), results/ (Replica, NICE-SLAM), intrinsic/ or pose/ beside depth/ (ScanNet export), and color/ or \
    image/ beside depth/, or rgbd.match (ICL-NUIM/Redwood); set [dataset] kind to skip detection";

/// Detects the layout of the dataset folder `dir` from the files it holds.
///
/// # Errors
/// [`DatasetError::MissingFile`] when `dir` is not a folder, [`DatasetError::Empty`] when it holds
/// nothing, and [`DatasetError::UnknownLayout`] (listing what was looked for and what was found)
/// when it matches no layout.
pub fn detect_kind(dir: &Path) -> Result<DatasetKind> {
    if looks_like_bag(dir) {
        return Ok(DatasetKind::Rosbag2);
    }
    if !dir.is_dir() {
        return Err(DatasetError::MissingFile {
            path: dir.to_path_buf(),
            hint: "the dataset folder does not exist".to_owned(),
        });
    }
    let has_file = |name: &str| dir.join(name).is_file();
    let has_dir = |name: &str| dir.join(name).is_dir();
    let kind = if has_file("rgb.txt") && has_file("depth.txt") {
        DatasetKind::Tum
    } else if has_dir("results") {
        DatasetKind::Replica
    } else if has_dir("depth") && (has_dir("intrinsic") || has_dir("pose")) {
        DatasetKind::Scannet
    } else if has_file("rgbd.match") || (has_dir("depth") && (has_dir("color") || has_dir("image")))
    {
        DatasetKind::Icl
    } else {
        return Err(unknown_layout(dir));
    };
    Ok(kind)
}

/// Whether `path` looks like a ROS 2 bag: a `.mcap` or `.db3` file, or a folder with
/// `metadata.yaml` or such a file.
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

/// [`DatasetError::Empty`] for an empty folder, else [`DatasetError::UnknownLayout`] naming what
/// was looked for and what is there.
fn unknown_layout(dir: &Path) -> DatasetError {
    let mut found: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            if e.path().is_dir() { name + "/" } else { name }
        })
        .collect();
    if found.is_empty() {
        return DatasetError::Empty {
            path: dir.to_path_buf(),
        };
    }
    found.sort();
    const SHOWN: usize = 10;
    let more = found.len().saturating_sub(SHOWN);
    found.truncate(SHOWN);
    let mut listing = found.join(", ");
    if more > 0 {
        listing.push_str(&format!(" and {more} more"));
    }
    DatasetError::UnknownLayout {
        path: dir.to_path_buf(),
        message: format!("{LAYOUTS_LOOKED_FOR}; found {listing}"),
    }
}

/// The dataset folder of a run: `dataset` when given (a command-line override), else
/// `[dataset] path` resolved against the config's folder (`ctx`). A synthetic scene has no folder:
/// it gets the config's folder, which [`open`] ignores.
///
/// # Errors
/// [`DatasetError::NoFolder`] when neither is set, [`DatasetError::NoSuchFolder`] when the folder
/// does not exist.
pub fn dataset_folder(
    config: &vlem_core::Config,
    ctx: &vlem_core::BuildContext,
    dataset: Option<&Path>,
) -> Result<std::path::PathBuf> {
    let synthetic = config.dataset.kind == DatasetKind::Synthetic;
    let (dir, hint) = match (dataset, &config.dataset.path) {
        (Some(dir), _) => (dir.to_path_buf(), "given with --dataset; check the path"),
        (None, Some(path)) => (
            ctx.resolve(path),
            "from [dataset] path in the config, relative to the config's folder; pass --dataset \
             DIR to use another one",
        ),
        (None, None) if synthetic => (ctx.config_dir.clone(), ""),
        (None, None) => return Err(DatasetError::NoFolder),
    };
    // A bag may be one storage file rather than a folder.
    let bag_file = dir.is_file() && looks_like_bag(&dir);
    if !synthetic && !dir.is_dir() && !bag_file {
        return Err(DatasetError::NoSuchFolder {
            path: dir,
            hint: hint.to_owned(),
        });
    }
    Ok(dir)
}

/// Opens the dataset folder `dir` with the reader that `config.kind` names, or the one
/// [`detect_kind`] picks for `auto`. `config.path` is not used: the caller resolves it to `dir`.
/// `kind = "synthetic"` needs no folder: `dir` is ignored and the scene of `[dataset.synthetic]` is
/// generated ([`SyntheticReader::open`]).
///
/// # Errors
/// The errors of [`detect_kind`] and of the reader's `open` (e.g. [`IclReader::open`]); an empty
/// dataset is [`DatasetError::Empty`]; [`DatasetError::BadConfig`] when `[dataset.synthetic]` is set
/// but `kind` is not `synthetic`.
pub fn open(config: &DatasetConfig, dir: &Path) -> Result<Box<dyn FrameSource>> {
    if config.kind == DatasetKind::Synthetic {
        return Ok(Box::new(SyntheticReader::open(config)?));
    }
    if config.rosbag2.is_some() && !matches!(config.kind, DatasetKind::Rosbag2 | DatasetKind::Auto)
    {
        return Err(DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: "rosbag2 is set but kind is not \"rosbag2\"; set kind = \"rosbag2\" or \
                      remove [dataset.rosbag2]"
                .to_owned(),
        });
    }
    if config.synthetic.is_some() {
        return Err(DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: "synthetic is set but kind is not \"synthetic\"; set kind = \"synthetic\" \
                      or remove [dataset.synthetic]"
                .to_owned(),
        });
    }
    let kind = match config.kind {
        DatasetKind::Auto => detect_kind(dir)?,
        kind => kind,
    };
    Ok(match kind {
        DatasetKind::Tum => Box::new(TumReader::open(dir, config)?),
        DatasetKind::Scannet => Box::new(ScanNetReader::open(dir, config)?),
        DatasetKind::Replica => Box::new(ReplicaReader::open(dir, config)?),
        DatasetKind::Synthetic => Box::new(SyntheticReader::open(config)?),
        DatasetKind::Rosbag2 => open_bag(config, dir)?,
        // `detect_kind` never returns `Auto`, so this arm is ICL only.
        DatasetKind::Icl | DatasetKind::Auto => Box::new(IclReader::open(dir, config)?),
    })
}

/// The trajectory file of the dataset folder `dir`, found as its reader finds it: an ICL-NUIM or
/// Redwood folder's `trajectory.log` (else its only `.log` file), a TUM folder's
/// `groundtruth.txt`, a Replica folder's `traj.txt`. For `vlem eval trajectory --reference DIR`
/// and the like, so that a user need not know the file's name.
///
/// # Errors
/// [`DatasetError::MissingFile`] when the folder has no trajectory (naming what was looked for),
/// [`DatasetError::Ambiguous`] for several `.log` files, and [`DatasetError::UnknownLayout`] or
/// [`DatasetError::BadConfig`] for layouts without one trajectory file (ScanNet keeps a pose per
/// frame, bags and the synthetic scene none as a file).
pub fn trajectory_file(dir: &Path) -> Result<std::path::PathBuf> {
    let existing = |name: &str, hint: &str| {
        let path = dir.join(name);
        sequence::require_file(&path, || hint.to_owned()).map(|()| path)
    };
    match detect_kind(dir)? {
        DatasetKind::Tum => existing("groundtruth.txt", "a TUM RGB-D folder's trajectory"),
        DatasetKind::Replica => existing("traj.txt", "a Replica folder's trajectory"),
        DatasetKind::Icl | DatasetKind::Auto => {
            icl::find_trajectory(dir, &DatasetConfig::default())?.ok_or_else(|| {
                DatasetError::MissingFile {
                    path: dir.join("trajectory.log"),
                    hint:
                        "an ICL-NUIM/Redwood folder's trajectory: trajectory.log or one .log file"
                            .to_owned(),
                }
            })
        }
        DatasetKind::Scannet | DatasetKind::Rosbag2 | DatasetKind::Synthetic => {
            Err(DatasetError::BadConfig {
                path: dir.to_path_buf(),
                message: "this dataset keeps no single trajectory file (ScanNet has a pose file \
                          per frame, a bag its poses in messages): pass a trajectory file (TUM \
                          or .log) itself"
                    .to_owned(),
            })
        }
    }
}

/// The reader of a ROS 2 bag, where the `rosbag2` feature is built.
#[cfg(feature = "rosbag2")]
fn open_bag(config: &DatasetConfig, path: &Path) -> Result<Box<dyn FrameSource>> {
    Ok(Box::new(Rosbag2Reader::open(path, config)?))
}

/// Without the `rosbag2` feature: an error that says how to build it.
#[cfg(not(feature = "rosbag2"))]
fn open_bag(_config: &DatasetConfig, path: &Path) -> Result<Box<dyn FrameSource>> {
    Err(DatasetError::BadConfig {
        path: path.to_path_buf(),
        message: "kind = \"rosbag2\" (a ROS 2 bag) needs vlem built with the `rosbag2` feature: \
                  cargo build --release --features rosbag2"
            .to_owned(),
    })
}
