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
//! Each reader registers itself (`vlem_core::register_dataset!`) with its name, its own
//! `[dataset]` keys (parsed by the reader, unknown keys refused) and a probe for `kind = "auto"`;
//! a reader in another crate does the same and is found alike. [`open`] builds the reader for a
//! `[dataset]` config, detecting it with [`detect_kind`] when `kind = "auto"`. Readers list the
//! files when opened and decode a frame only when it is asked for. Every error ([`DatasetError`])
//! names the file involved; through [`FrameSource`] it arrives as
//! [`vlem_core::CoreError::Dataset`].
//!
//! Common `[dataset]` settings: frame `i` of a reader is frame `i * stride` of the recording, at
//! most `max_frames` frames are used, `depth_scale` overrides the layout's default, and a frame's
//! timestamp is the dataset's own or, where the layout has none, its index in the recording.

use std::path::{Path, PathBuf};

use vlem_core::config::{AUTO_DATASET, DatasetConfig};
use vlem_core::{FrameSource, Registry};

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
pub use rosbag2::{Rosbag2Config, looks_like_bag};
pub use scannet::ScanNetReader;
pub use synthetic::{SyntheticConfig, SyntheticNoise, SyntheticReader, SyntheticScene};
pub use text::{MatchPair, match_pairs_from_str};
pub use tum::TumReader;

/// The registry, for functions that return [`DatasetError`].
fn registry(path: &Path) -> Result<&'static Registry> {
    Registry::global().map_err(|source| DatasetError::Core {
        path: path.to_path_buf(),
        source,
    })
}

/// Detects the registered reader of the dataset at `path` (a folder, or a bag's one file) from the
/// files it holds: the first whose probe matches, in the readers' probe order.
///
/// # Errors
/// [`DatasetError::MissingFile`] when `path` is neither a folder nor a file a reader takes,
/// [`DatasetError::Empty`] when the folder holds nothing, and [`DatasetError::UnknownLayout`]
/// (listing what was looked for and what was found) when it matches no reader.
pub fn detect_kind(path: &Path) -> Result<&'static str> {
    let probes = registry(path)?.dataset_probes();
    if let Some((name, _)) = probes.iter().find(|(_, p)| (p.probe)(path)) {
        return Ok(name);
    }
    // A build without the bag reader still names it, so that opening says which feature reads it.
    if looks_like_bag(path) {
        return Ok(rosbag2::ROSBAG2);
    }
    if !path.is_dir() {
        return Err(DatasetError::MissingFile {
            path: path.to_path_buf(),
            hint: "the dataset folder does not exist".to_owned(),
        });
    }
    let mut looked_for: Vec<&str> = probes.iter().map(|(_, p)| p.looks_for).collect();
    if !probes.iter().any(|(name, _)| *name == rosbag2::ROSBAG2) {
        looked_for.insert(0, rosbag2::LOOKS_FOR);
    }
    Err(unknown_layout(path, &looked_for))
}

/// [`DatasetError::Empty`] for an empty folder, else [`DatasetError::UnknownLayout`] naming what
/// was looked for and what is there.
fn unknown_layout(dir: &Path, looked_for: &[&str]) -> DatasetError {
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
        message: format!(
            "looked for {}; set [dataset] kind to skip detection; found {listing}",
            looked_for.join(", ")
        ),
    }
}

/// The dataset folder of a run: `dataset` when given (a command-line override), else
/// `[dataset] path` resolved against the config's folder (`ctx`). A reader that reads no path
/// (the synthetic scene) gets the config's folder, which it ignores.
///
/// # Errors
/// [`DatasetError::NoFolder`] when neither is set, [`DatasetError::NoSuchFolder`] when the folder
/// does not exist (or is a file no reader takes).
pub fn dataset_folder(
    config: &vlem_core::Config,
    ctx: &vlem_core::BuildContext,
    dataset: Option<&Path>,
) -> Result<PathBuf> {
    let registry = registry(&ctx.config_dir)?;
    // An unknown kind is reported by `open`, with the known ones.
    let needs_path = registry
        .dataset(&config.dataset.kind)
        .map_or(true, |reader| reader.needs_path);
    let (dir, hint) = match (dataset, &config.dataset.path) {
        (Some(dir), _) => (dir.to_path_buf(), "given with --dataset; check the path"),
        (None, Some(path)) => (
            ctx.resolve(path),
            "from [dataset] path in the config, relative to the config's folder; pass --dataset \
             DIR to use another one",
        ),
        (None, None) if !needs_path => (ctx.config_dir.clone(), ""),
        (None, None) => return Err(DatasetError::NoFolder),
    };
    // Some readers take one file (a bag's storage file) rather than a folder: one that
    // detection recognises.
    let taken_file = dir.is_file() && detect_kind(&dir).is_ok();
    if needs_path && !dir.is_dir() && !taken_file {
        return Err(DatasetError::NoSuchFolder {
            path: dir,
            hint: hint.to_owned(),
        });
    }
    Ok(dir)
}

/// Opens the dataset at `path` with the registered reader that `config.kind` names, or the one
/// [`detect_kind`] picks for `auto`. `config.path` is not used: the caller resolves it to `path`
/// ([`dataset_folder`]). A reader that reads no path (`kind = "synthetic"`) ignores it.
///
/// # Errors
/// [`vlem_core::CoreError::UnknownImplementation`] for an unknown kind (listing the known ones
/// and the feature that adds a missing one), the errors of [`detect_kind`] and of the reader's
/// `open` (e.g. [`IclReader::open`]) as [`vlem_core::CoreError::Dataset`], and a reader-owned key
/// it does not know as [`vlem_core::CoreError::InvalidParams`].
pub fn open(config: &DatasetConfig, path: &Path) -> vlem_core::Result<Box<dyn FrameSource>> {
    let registry = Registry::global()?;
    let kind = if config.kind == AUTO_DATASET {
        detect_kind(path)?
    } else {
        config.kind.as_str()
    };
    (registry.dataset(kind)?.open)(config, path)
}

/// Checks the reader-owned keys of `config` without opening the dataset, so that a typo is found
/// before a long job starts: the reader `kind` names, or for `auto` the one [`detect_kind`] picks
/// at `path` where that exists (elsewhere the check waits for [`open`]).
///
/// # Errors
/// [`vlem_core::CoreError::UnknownImplementation`] for an unknown kind, and
/// [`vlem_core::CoreError::InvalidParams`] naming a key the reader does not take.
pub fn check_settings(config: &DatasetConfig, path: Option<&Path>) -> vlem_core::Result<()> {
    let kind = if config.kind != AUTO_DATASET {
        config.kind.as_str()
    } else if let Some(kind) = path.and_then(|p| detect_kind(p).ok()) {
        kind
    } else {
        return Ok(());
    };
    match Registry::global()?.dataset(kind)?.check_settings {
        Some(check) => check(config),
        None => Ok(()),
    }
}

/// The trajectory file of the dataset folder `dir`, found as its reader finds it: an ICL-NUIM or
/// Redwood folder's `trajectory.log` (else its only `.log` file), a TUM folder's
/// `groundtruth.txt`, a Replica folder's `traj.txt`. For `vlem eval trajectory --reference DIR`
/// and the like, so that a user need not know the file's name.
///
/// # Errors
/// The errors of [`detect_kind`]; the reader's, naming what was looked for, when the folder has
/// no trajectory; [`DatasetError::BadConfig`] for layouts without one trajectory file (ScanNet
/// keeps a pose per frame, a bag its poses in messages).
pub fn trajectory_file(dir: &Path) -> vlem_core::Result<PathBuf> {
    let kind = detect_kind(dir)?;
    match Registry::global()?.dataset(kind)?.trajectory_file {
        Some(find) => find(dir),
        None => Err(DatasetError::BadConfig {
            path: dir.to_path_buf(),
            message: format!(
                "a {kind} dataset keeps no single trajectory file (ScanNet has a pose file per \
                 frame, a bag its poses in messages): pass a trajectory file (TUM or .log) itself"
            ),
        }
        .into()),
    }
}
