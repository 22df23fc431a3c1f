//! ICL-NUIM (augmented) / Redwood / Open3D folders.
//!
//! ```text
//! color/ (or image/)   00000.jpg ...  colour, .jpg or .png
//! depth/               00000.png ...  16-bit depth, 1000 units per metre
//! rgbd.match           optional: lines `depth/00000.png color/00000.jpg` pairing the two
//! intrinsics.json      Open3D PinholeCameraIntrinsic (or camera_intrinsic.json, or [dataset] intrinsics)
//! trajectory.log       optional Redwood .log, camera-to-world (or the only *.log, or [dataset] trajectory)
//! labels.json          optional {"<class id>": "<name>", ...}: the folder is labelled, and then
//! label/               00000.png ...  class ids per pixel (16- or 8-bit), named like the depth files
//! ```
//!
//! Without `rgbd.match`, colour and depth files are paired by their sorted order, so numbering may
//! start anywhere; numbered files must then pair equal numbers. Poses go to the frames in order,
//! unless frame numbers are missing (a frame's images deleted): then each frame takes the pose
//! whose `.log` frame id is its file number, and the gap is a warning.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use vlem_core::config::DatasetConfig;
use vlem_core::{DatasetReader, FrameSource, LabelNames};

use crate::calibration::read_open3d_intrinsics;
use crate::error::{DatasetError, Result};
use crate::sequence::{
    Camera, ColourFit, Entry, MissingFrames, Selection, Sequence, attach_trajectory,
    check_settings, depth_scale, frame_number, list_files, reader_settings, reader_via_sequence,
    require_file,
};
use crate::text::{match_pairs_from_str, read_text};
use crate::trajectory::read_numbered_log;

/// Raw depth units per metre of ICL-NUIM and Redwood (millimetres).
pub const ICL_DEPTH_SCALE: f64 = 1000.0;

/// Names tried for the colour folder: Open3D/ICL use `color/`, Redwood `image/`.
const COLOUR_DIRS: [&str; 2] = ["color", "image"];

/// Names tried for the intrinsics file when `[dataset] intrinsics` is not set.
const INTRINSICS_FILES: [&str; 2] = ["intrinsics.json", "camera_intrinsic.json"];

const COLOUR_EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

/// The registered name: `[dataset] kind = "icl"`.
pub const ICL: &str = "icl";

vlem_core::register_dataset!(
    ICL,
    "ICL-NUIM / Redwood / Open3D folders: color/ (or image/), depth/, intrinsics JSON, .log trajectory",
    DatasetReader::new(open_boxed)
        .detected_by(
            40,
            "color/ or image/ beside depth/, or rgbd.match (ICL-NUIM/Redwood)",
            is_icl_folder
        )
        .with_trajectory_file(trajectory_file)
        .with_settings_check(|config| check_settings::<IclSettings>(ICL, config))
);

fn open_boxed(config: &DatasetConfig, dir: &Path) -> vlem_core::Result<Box<dyn FrameSource>> {
    Ok(Box::new(IclReader::open(dir, config)?))
}

/// Whether `dir` looks like an ICL-NUIM/Redwood folder.
fn is_icl_folder(dir: &Path) -> bool {
    dir.join("rgbd.match").is_file()
        || (dir.join("depth").is_dir() && COLOUR_DIRS.iter().any(|c| dir.join(c).is_dir()))
}

/// `[dataset]` keys of this reader, besides the shared ones.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct IclSettings {
    /// Intrinsics file (Open3D JSON) for folders that do not name it as this reader expects,
    /// relative to the dataset folder.
    #[serde(default)]
    intrinsics: Option<PathBuf>,
    /// Trajectory file (Redwood `.log`) likewise.
    #[serde(default)]
    trajectory: Option<PathBuf>,
}

/// A folder's trajectory: `trajectory.log`, else its only `.log` file.
fn trajectory_file(dir: &Path) -> vlem_core::Result<PathBuf> {
    let found = find_trajectory(dir, &IclSettings::default())?;
    Ok(found.ok_or_else(|| DatasetError::MissingFile {
        path: dir.join("trajectory.log"),
        hint: "an ICL-NUIM/Redwood folder's trajectory: trajectory.log or one .log file".to_owned(),
    })?)
}

/// Reader of an ICL-NUIM / Redwood / Open3D folder (see the module docs for the layout).
#[derive(Debug)]
pub struct IclReader {
    seq: Sequence,
}

reader_via_sequence!(IclReader);

impl IclReader {
    /// Opens the folder `dir`: pairs the frame files and reads intrinsics and trajectory; images are
    /// decoded only by [`IclReader::load`] / `frame`.
    ///
    /// # Errors
    /// [`DatasetError::MissingFile`] for a missing `depth/`, colour folder or intrinsics file (the
    /// message lists the names tried), [`DatasetError::CountMismatch`] when the folders cannot be
    /// paired, trajectory errors of [`crate::trajectory::read_log`], [`DatasetError::TooFewPoses`],
    /// [`DatasetError::NoPoseForFrame`] when frames are missing and one has no pose by number,
    /// [`DatasetError::Ambiguous`] for several `.log` files, [`DatasetError::BadConfig`],
    /// [`DatasetError::InvalidSettings`] and [`DatasetError::Empty`].
    pub fn open(dir: &Path, config: &DatasetConfig) -> Result<Self> {
        let settings: IclSettings = reader_settings(ICL, config)?;
        let selection = Selection::from_config(config, dir)?;
        let scale = depth_scale(config, ICL_DEPTH_SCALE, dir)?;
        let (entries, label_names) = attach_labels(dir, frame_files(dir)?)?;
        let missing = MissingFrames::of(&entries);
        let mut selected = selection.apply(entries);
        let intrinsics_path = find_intrinsics(dir, &settings)?;
        let intrinsics = read_open3d_intrinsics(&intrinsics_path)?;
        let trajectory = find_trajectory(dir, &settings)?;
        if let Some(trajectory) = &trajectory {
            let poses = read_numbered_log(trajectory)?;
            attach_trajectory(&mut selected, &missing, &poses, trajectory)?;
        }
        let seq = Sequence::new(
            "ICL-NUIM/Redwood",
            dir,
            selected,
            Camera::from_file(intrinsics, &intrinsics_path),
            scale,
            ColourFit::SameSize,
        )?
        .with_warning(missing.warning(dir, trajectory.is_some()));
        let seq = match label_names {
            Some(names) => seq.with_label_names(names),
            None => seq,
        };
        Ok(Self { seq })
    }
}

/// Where the folder has `labels.json`, the class names and each frame's label image
/// (`label/<depth file name>`); otherwise the entries unchanged and no names.
fn attach_labels(dir: &Path, mut entries: Vec<Entry>) -> Result<(Vec<Entry>, Option<LabelNames>)> {
    let names_path = dir.join("labels.json");
    if !names_path.is_file() {
        return Ok((entries, None));
    }
    let text = read_text(&names_path)?;
    let table: std::collections::BTreeMap<String, String> =
        serde_json::from_str(&text).map_err(|e| {
            DatasetError::parse(
                &names_path,
                e.line(),
                format!("expected {{\"<class id>\": \"<name>\", ...}}: {e}"),
            )
        })?;
    let mut names = Vec::with_capacity(table.len());
    for (id, name) in table {
        let id: u16 = id.trim().parse().map_err(|_| {
            DatasetError::parse(
                &names_path,
                1,
                format!("class id `{id}` is not an integer in 0..=65535"),
            )
        })?;
        names.push((id, name));
    }
    let label_dir = dir.join("label");
    for entry in &mut entries {
        let Some(name) = entry.depth.file_name() else {
            continue;
        };
        let path = label_dir.join(name);
        require_file(&path, || {
            format!(
                "{} is there, so label/ must hold one class-id image per depth image",
                names_path.display()
            )
        })?;
        entry.labels = Some(path);
    }
    Ok((entries, Some(LabelNames::new(names))))
}

/// The colour/depth pairs of the underlying sequence, from `rgbd.match` or by sorted order.
fn frame_files(dir: &Path) -> Result<Vec<Entry>> {
    let matches = dir.join("rgbd.match");
    if matches.is_file() {
        return read_match_file(dir, &matches);
    }
    let colour_dir = COLOUR_DIRS
        .iter()
        .map(|name| dir.join(name))
        .find(|d| d.is_dir())
        .unwrap_or_else(|| dir.join(COLOUR_DIRS[0]));
    let colour = list_files(
        &colour_dir,
        &COLOUR_EXTENSIONS,
        "an ICL-NUIM/Redwood folder needs color/ (or image/) holding .jpg or .png frames",
    )?;
    let depth_dir = dir.join("depth");
    let depth = list_files(
        &depth_dir,
        &["png"],
        "an ICL-NUIM/Redwood folder needs depth/ holding 16-bit .png frames",
    )?;
    if colour.len() != depth.len() {
        return Err(DatasetError::CountMismatch {
            colour_dir,
            colour_count: colour.len(),
            depth_dir,
            depth_count: depth.len(),
        });
    }
    colour
        .into_iter()
        .zip(depth)
        .map(|(c, d)| {
            // Paired by sorted order: numbered files must pair the same number, or one frame's
            // colour would be mapped with another frame's depth.
            match (frame_number(&c), frame_number(&d)) {
                (Some(a), Some(b)) if a != b => Err(DatasetError::Unpaired {
                    colour: c,
                    depth: d,
                }),
                _ => Ok(Entry::new(c, d)),
            }
        })
        .collect()
}

/// Reads `rgbd.match`: one `depth-path colour-path` pair per line, relative to the folder.
fn read_match_file(dir: &Path, path: &Path) -> Result<Vec<Entry>> {
    let text = read_text(path)?;
    let mut entries = Vec::new();
    for pair in match_pairs_from_str(&text, path)? {
        let (depth, colour) = (dir.join(pair.depth), dir.join(pair.colour));
        let listed = || format!("listed in {} line {}", path.display(), pair.line);
        require_file(&depth, listed)?;
        require_file(&colour, listed)?;
        entries.push(Entry::new(colour, depth));
    }
    Ok(entries)
}

/// The intrinsics file: `[dataset] intrinsics`, else the first of [`INTRINSICS_FILES`]. There is
/// deliberately no default camera: a wrong focal length silently bends the whole map.
fn find_intrinsics(dir: &Path, settings: &IclSettings) -> Result<PathBuf> {
    if let Some(path) = &settings.intrinsics {
        let path = dir.join(path);
        require_file(&path, || "set by [dataset] intrinsics".to_owned())?;
        return Ok(path);
    }
    INTRINSICS_FILES
        .iter()
        .map(|name| dir.join(name))
        .find(|p| p.is_file())
        .ok_or_else(|| DatasetError::MissingFile {
            path: dir.join(INTRINSICS_FILES[0]),
            hint: format!(
                "looked for {} in {}; ICL-NUIM/Redwood frames need the camera as an Open3D \
                 PinholeCameraIntrinsic JSON: add one or set [dataset] intrinsics",
                INTRINSICS_FILES.join(" and "),
                dir.display()
            ),
        })
}

/// The trajectory file, if any: `[dataset] trajectory`, else `trajectory.log`, else the folder's
/// only `.log` file.
fn find_trajectory(dir: &Path, settings: &IclSettings) -> Result<Option<PathBuf>> {
    if let Some(path) = &settings.trajectory {
        let path = dir.join(path);
        require_file(&path, || "set by [dataset] trajectory".to_owned())?;
        return Ok(Some(path));
    }
    let default = dir.join("trajectory.log");
    if default.is_file() {
        return Ok(Some(default));
    }
    let mut logs = list_files(dir, &["log"], "the dataset folder")?;
    match logs.len() {
        0 | 1 => Ok(logs.pop()),
        _ => Err(DatasetError::Ambiguous {
            path: dir.to_path_buf(),
            message: format!(
                "several trajectories and none named trajectory.log ({}); choose one with \
                 [dataset] trajectory",
                logs.iter()
                    .filter_map(|p| p.file_name())
                    .map(|n| n.to_string_lossy())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }),
    }
}
