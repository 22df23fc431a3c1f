//! ScanNet exports (the output of ScanNet's `reader.py` / `SensReader`).
//!
//! ```text
//! color/N.jpg                     colour, 1296x968
//! depth/N.png                     16-bit depth, 640x480, 1000 units per metre
//! pose/N.txt                      optional: 4x4 camera-to-world matrix, one row per line
//! intrinsic/intrinsic_depth.txt   4x4 matrix of the depth camera, one row per line
//! ```
//!
//! The colour camera has a higher resolution than the depth camera it is registered to, so each
//! colour image is resampled (bilinear) to the depth resolution and the frame uses the DEPTH
//! intrinsics. ScanNet writes `-inf` poses for frames its tracking lost; such a pose is reported by
//! [`ScanNetReader::load`] as [`DatasetError::NonFinitePose`] naming the pose file, and only for
//! that frame.

use std::path::Path;

use vlem_core::config::DatasetConfig;
use vlem_core::{DatasetReader, FrameSource, Intrinsics};

use crate::calibration::validated;
use crate::error::{DatasetError, Result};
use crate::images;
use crate::sequence::{
    Camera, ColourFit, Entry, NoSettings, PoseRef, Selection, Sequence, check_settings,
    depth_scale, list_files, reader_settings, reader_via_sequence, require_file,
};
use crate::text::read_text;
use crate::trajectory::matrix_rows_from_str;

/// Raw depth units per metre of ScanNet (millimetres).
pub const SCANNET_DEPTH_SCALE: f64 = 1000.0;

/// The registered name: `[dataset] kind = "scannet"`.
pub const SCANNET: &str = "scannet";

vlem_core::register_dataset!(
    SCANNET,
    "ScanNet exports: color/, depth/, pose/, intrinsic/; depth scale 1000",
    DatasetReader::new(open_boxed)
        .detected_by(
            30,
            "intrinsic/ or pose/ beside depth/ (ScanNet export)",
            |dir| dir.join("depth").is_dir()
                && (dir.join("intrinsic").is_dir() || dir.join("pose").is_dir())
        )
        .with_settings_check(|config| check_settings::<NoSettings>(SCANNET, config))
);

fn open_boxed(config: &DatasetConfig, dir: &Path) -> vlem_core::Result<Box<dyn FrameSource>> {
    Ok(Box::new(ScanNetReader::open(dir, config)?))
}

/// Reader of a ScanNet export folder (see the module docs).
#[derive(Debug)]
pub struct ScanNetReader {
    seq: Sequence,
}

reader_via_sequence!(ScanNetReader);

impl ScanNetReader {
    /// Opens the folder `dir`: pairs depth, colour and pose files by frame number and reads the
    /// depth intrinsics.
    ///
    /// # Errors
    /// [`DatasetError::MissingFile`] for a missing folder, intrinsics file, or the colour or pose
    /// file of a depth frame, [`DatasetError::Parse`] for a malformed intrinsics matrix,
    /// [`DatasetError::Core`] for invalid intrinsics, [`DatasetError::BadConfig`] and
    /// [`DatasetError::Empty`].
    pub fn open(dir: &Path, config: &DatasetConfig) -> Result<Self> {
        let _: NoSettings = reader_settings(SCANNET, config)?;
        let selection = Selection::from_config(config, dir)?;
        let scale = depth_scale(config, SCANNET_DEPTH_SCALE, dir)?;
        let selected = selection.apply(frame_files(dir)?);
        let Some((_, first)) = selected.first() else {
            return Err(DatasetError::Empty {
                path: dir.to_path_buf(),
            });
        };
        let intrinsics_path = dir.join("intrinsic").join("intrinsic_depth.txt");
        let (width, height) = images::dimensions(&first.depth)?;
        let intrinsics = read_depth_intrinsics(&intrinsics_path, width, height)?;
        let seq = Sequence::new(
            "ScanNet",
            dir,
            selected,
            Camera::from_file(intrinsics, &intrinsics_path),
            scale,
            ColourFit::ResizeToDepth,
        )?;
        Ok(Self { seq })
    }
}

/// The frames of the export, in numeric order of their depth files.
fn frame_files(dir: &Path) -> Result<Vec<Entry>> {
    let depth = list_files(
        &dir.join("depth"),
        &["png"],
        "a ScanNet export needs depth/ holding N.png depth frames",
    )?;
    let colour_dir = dir.join("color");
    if !colour_dir.is_dir() {
        return Err(DatasetError::MissingFile {
            path: colour_dir,
            hint: "a ScanNet export needs color/ holding N.jpg colour frames".to_owned(),
        });
    }
    let pose_dir = dir.join("pose");
    let has_poses = pose_dir.is_dir();
    let mut entries = Vec::with_capacity(depth.len());
    for depth in depth {
        let Some(stem) = depth.file_stem().map(|s| s.to_os_string()) else {
            continue;
        };
        let named = |folder: &Path, ext: &str| {
            let mut name = stem.clone();
            name.push(ext);
            folder.join(name)
        };
        let colour = [".jpg", ".png"]
            .iter()
            .map(|ext| named(&colour_dir, ext))
            .find(|p| p.is_file())
            .ok_or_else(|| DatasetError::MissingFile {
                path: named(&colour_dir, ".jpg"),
                hint: format!("the colour frame of {}", depth.display()),
            })?;
        let pose = if has_poses {
            let path = named(&pose_dir, ".txt");
            require_file(&path, || format!("the pose of {}", depth.display()))?;
            PoseRef::File(path)
        } else {
            PoseRef::None
        };
        entries.push(Entry {
            pose,
            ..Entry::new(colour, depth)
        });
    }
    Ok(entries)
}

/// The depth camera from `intrinsic_depth.txt` (a 4x4 matrix whose top-left 3x3 block is K),
/// for depth images of `width` x `height`.
fn read_depth_intrinsics(path: &Path, width: u32, height: u32) -> Result<Intrinsics> {
    require_file(path, || {
        "a ScanNet export needs intrinsic/intrinsic_depth.txt (the depth camera's 4x4 matrix)"
            .to_owned()
    })?;
    depth_intrinsics_from_str(&read_text(path)?, width, height, path)
}

/// Parses the text of a ScanNet `intrinsic_depth.txt` (a 4x4 matrix, one row per line, whose
/// top-left 3x3 block is K) as the camera of depth images of `width` x `height`; `path` is the
/// file it came from, as errors name it.
///
/// # Errors
/// [`DatasetError::Parse`] for a malformed matrix, [`DatasetError::Core`] for intrinsics that fail
/// validation.
pub fn depth_intrinsics_from_str(
    text: &str,
    width: u32,
    height: u32,
    path: &Path,
) -> Result<Intrinsics> {
    let k = matrix_rows_from_str(text, path, 4)?;
    validated(
        Intrinsics::new(width, height, k[0][0], k[1][1], k[0][2], k[1][2]),
        path,
    )
}
