//! Replica as rendered and packaged by NICE-SLAM.
//!
//! ```text
//! results/frame000000.jpg   colour
//! results/depth000000.png   16-bit depth, 6553.5 units per metre
//! traj.txt                  optional: one line per frame, the 16 numbers of the 4x4
//!                           camera-to-world matrix, row-major
//! ```
//!
//! Replica ships no intrinsics file: `[dataset] intrinsics` (Open3D JSON) is used when set,
//! otherwise [`REPLICA_DEFAULT_INTRINSICS`].

use std::path::Path;

use nalgebra::Matrix4;
use vlem_core::config::DatasetConfig;
use vlem_core::{DatasetReader, FrameSource, Pose};

use crate::calibration::REPLICA_DEFAULT_INTRINSICS;
use crate::error::Result;
use crate::sequence::{
    Camera, ColourFit, Entry, IntrinsicsSetting, MissingFrames, Selection, Sequence,
    attach_trajectory, check_settings, depth_scale, list_files, reader_settings,
    reader_via_sequence, require_file,
};
use crate::text::{data_lines, parse_exact, read_text};
use crate::trajectory::pose_from_matrix;

/// Raw depth units per metre of NICE-SLAM's Replica renders.
pub const REPLICA_DEPTH_SCALE: f64 = 6553.5;

/// The registered name: `[dataset] kind = "replica"`.
pub const REPLICA: &str = "replica";

vlem_core::register_dataset!(
    REPLICA,
    "Replica as packaged by NICE-SLAM: results/, traj.txt; depth scale 6553.5",
    DatasetReader::new(open_boxed)
        .detected_by(20, "results/ (Replica, NICE-SLAM)", |dir| dir
            .join("results")
            .is_dir())
        .with_trajectory_file(|dir| {
            let path = dir.join("traj.txt");
            require_file(&path, || "a Replica folder's trajectory".to_owned())?;
            Ok(path)
        })
        .with_settings_check(|config| check_settings::<IntrinsicsSetting>(REPLICA, config))
);

fn open_boxed(config: &DatasetConfig, dir: &Path) -> vlem_core::Result<Box<dyn FrameSource>> {
    Ok(Box::new(ReplicaReader::open(dir, config)?))
}

/// Reader of a NICE-SLAM Replica scene folder (see the module docs).
#[derive(Debug)]
pub struct ReplicaReader {
    seq: Sequence,
}

reader_via_sequence!(ReplicaReader);

impl ReplicaReader {
    /// Opens the folder `dir`: pairs `frameN.jpg` with `depthN.png` and reads `traj.txt`.
    ///
    /// # Errors
    /// [`DatasetError::MissingFile`](crate::DatasetError::MissingFile) for a missing `results/` or depth file of a colour frame,
    /// [`DatasetError::Parse`](crate::DatasetError::Parse) / [`DatasetError::NonFinitePose`](crate::DatasetError::NonFinitePose) / [`DatasetError::NotRotation`](crate::DatasetError::NotRotation)
    /// for a bad `traj.txt` line, [`DatasetError::TooFewPoses`](crate::DatasetError::TooFewPoses), the errors of
    /// [`read_open3d_intrinsics`](crate::read_open3d_intrinsics), [`DatasetError::BadConfig`](crate::DatasetError::BadConfig) and [`DatasetError::Empty`](crate::DatasetError::Empty).
    pub fn open(dir: &Path, config: &DatasetConfig) -> Result<Self> {
        let settings: IntrinsicsSetting = reader_settings(REPLICA, config)?;
        let selection = Selection::from_config(config, dir)?;
        let scale = depth_scale(config, REPLICA_DEPTH_SCALE, dir)?;
        let entries = frame_files(dir)?;
        let missing = MissingFrames::of(&entries);
        let mut selected = selection.apply(entries);
        let trajectory = dir.join("traj.txt");
        let has_trajectory = trajectory.is_file();
        if has_trajectory {
            // traj.txt has no frame ids: line k is frame k.
            let poses: Vec<(u64, Pose)> = (0u64..).zip(read_trajectory(&trajectory)?).collect();
            attach_trajectory(&mut selected, &missing, &poses, &trajectory)?;
        }
        let camera = Camera::from_setting_or_default(
            settings.intrinsics.as_deref(),
            dir,
            REPLICA_DEFAULT_INTRINSICS,
            "the NICE-SLAM Replica default 600/600/599.5/339.5; set [dataset] intrinsics",
        )?;
        let seq = Sequence::new(
            "Replica (NICE-SLAM)",
            dir,
            selected,
            camera,
            scale,
            ColourFit::SameSize,
        )?
        .with_warning(missing.warning(dir, has_trajectory));
        Ok(Self { seq })
    }
}

/// `results/frameN.jpg` (or `.png`) with its `results/depthN.png`, in frame order.
fn frame_files(dir: &Path) -> Result<Vec<Entry>> {
    let results = dir.join("results");
    let files = list_files(
        &results,
        &["jpg", "jpeg", "png"],
        "a NICE-SLAM Replica folder needs results/ holding frameNNNNNN.jpg and depthNNNNNN.png",
    )?;
    let mut entries = Vec::new();
    for colour in files {
        let Some(number) = colour
            .file_stem()
            .and_then(|s| s.to_str())
            .and_then(|s| s.strip_prefix("frame"))
        else {
            continue;
        };
        let depth = results.join(format!("depth{number}.png"));
        require_file(&depth, || {
            format!("the depth frame of {}", colour.display())
        })?;
        entries.push(Entry::new(colour, depth));
    }
    Ok(entries)
}

/// Reads `traj.txt`: one row-major 4x4 camera-to-world matrix per line.
fn read_trajectory(path: &Path) -> Result<Vec<Pose>> {
    let text = read_text(path)?;
    data_lines(&text)
        .enumerate()
        .map(|(frame, (line, content))| {
            let values = parse_exact(path, line, content, 16)?;
            pose_from_matrix(&Matrix4::from_row_slice(&values), path, frame)
        })
        .collect()
}
