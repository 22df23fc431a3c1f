//! Trajectory accuracy: how far an estimated camera trajectory is from a reference one.
//!
//! The tracker is the part of the pipeline whose errors every later stage inherits (a drifting
//! pose smears embeddings over the wrong points), so its accuracy is measured with the two metrics
//! of the TUM RGB-D benchmark (Sturm et al., IROS 2012):
//!
//! - **ATE**, absolute trajectory error: the estimated camera positions are aligned to the
//!   reference ones by the least-squares rigid (optionally similarity) transform of Horn /
//!   Umeyama ([`align_umeyama`]), and the remaining position errors are summarised
//!   ([`ate`]). It measures global consistency.
//! - **RPE**, relative pose error: the error of the motion between poses `delta` frames apart,
//!   `E = (Q_i⁻¹ Q_{i+Δ})⁻¹ (P_i⁻¹ P_{i+Δ})` with `Q` the reference and `P` the estimate, split into
//!   its translation (metres) and rotation angle (degrees) ([`rpe`]). It measures local drift and
//!   needs no alignment.
//!
//! Both need the two trajectories paired pose by pose: [`read_trajectory`] reads TUM and `.log`
//! files, [`associate`] pairs their poses (by timestamp, or by frame index when a `.log`, which
//! has no timestamps, is involved).
//!
//! Poses are camera-to-world ([`vlem_core::Pose`]); only relative quantities enter the metrics, so
//! the two trajectories may live in different world frames.

mod align;
mod associate;
mod metrics;

use std::path::{Path, PathBuf};

use vlem_core::Pose;

pub use align::{Alignment, align_umeyama};
pub use associate::{
    Association, AssociationMode, DEFAULT_MAX_TIME_DIFF, MIN_ASSOCIATED, associate,
    associate_stamps,
};
pub use metrics::{AteStats, ErrorStats, RpeStats, ate, relative_error, rpe};

use crate::error::{EvalError, Result};

/// The two trajectory file formats vlem reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TrajectoryFormat {
    /// TUM: `timestamp tx ty tz qx qy qz qw` per line (what `vlem run` writes).
    Tum,
    /// Redwood / Open3D / ICL-NUIM `.log`: `i j k`, then a 4x4 camera-to-world matrix, per frame;
    /// no timestamps.
    Log,
}

impl TrajectoryFormat {
    /// The format's name as users see it (`TUM`, `.log`).
    pub fn label(self) -> &'static str {
        match self {
            Self::Tum => "TUM",
            Self::Log => ".log",
        }
    }
}

/// A trajectory read from a file: poses in file order, each with its stamp.
#[derive(Clone, Debug)]
pub struct Trajectory {
    /// The file it was read from.
    pub path: PathBuf,
    /// The file's format.
    pub format: TrajectoryFormat,
    /// `(stamp, camera-to-world pose)`: the timestamp in seconds for TUM, the frame index
    /// (0, 1, 2, …) for `.log`.
    pub poses: Vec<(f64, Pose)>,
}

impl Trajectory {
    /// A trajectory from poses in memory (`path` only names it in messages).
    pub fn new(
        path: impl Into<PathBuf>,
        format: TrajectoryFormat,
        poses: Vec<(f64, Pose)>,
    ) -> Self {
        Self {
            path: path.into(),
            format,
            poses,
        }
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// True when there is no pose.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The stamps, in file order.
    pub fn stamps(&self) -> Vec<f64> {
        self.poses.iter().map(|(t, _)| *t).collect()
    }

    /// Smallest and largest stamp (`(0, 0)` when empty).
    pub fn stamp_range(&self) -> (f64, f64) {
        let mut range: Option<(f64, f64)> = None;
        for &(t, _) in &self.poses {
            range = Some(match range {
                None => (t, t),
                Some((lo, hi)) => (lo.min(t), hi.max(t)),
            });
        }
        range.unwrap_or((0.0, 0.0))
    }
}

/// Reads a trajectory file, TUM or `.log`; `role` (`estimate`, `reference`) names it in errors.
///
/// The format is told by the first data line (blank and `#` lines skipped): 8 fields is TUM, 3 is
/// a `.log` record header. When that line fits neither, the extension decides (`.log` → `.log`,
/// `.tum` / `.txt` → TUM) so that the reader reports what is wrong with the line; other files are
/// refused with [`EvalError::UnknownFormat`].
///
/// # Errors
/// [`EvalError::MissingFile`] / [`EvalError::Io`] when the file cannot be read,
/// [`EvalError::UnknownFormat`] as above, and [`EvalError::Dataset`] with the reader's error
/// (file and line) for a malformed file.
pub fn read_trajectory(path: &Path, role: &str) -> Result<Trajectory> {
    let text = std::fs::read_to_string(path).map_err(|source| {
        if source.kind() == std::io::ErrorKind::NotFound {
            EvalError::MissingFile {
                path: path.to_path_buf(),
                role: role.to_owned(),
            }
        } else {
            EvalError::Io {
                path: path.to_path_buf(),
                role: role.to_owned(),
                source,
            }
        }
    })?;
    let format = detect_format(path, &text)?;
    let poses = match format {
        TrajectoryFormat::Tum => vlem_datasets::trajectory::read_tum(path)?,
        TrajectoryFormat::Log => vlem_datasets::trajectory::read_log(path)?
            .into_iter()
            .enumerate()
            .map(|(i, pose)| (i as f64, pose))
            .collect(),
    };
    Ok(Trajectory::new(path, format, poses))
}

/// The format of a trajectory file with content `text` (see [`read_trajectory`]).
///
/// # Errors
/// [`EvalError::UnknownFormat`] when neither the first data line nor the extension tells.
pub fn detect_format(path: &Path, text: &str) -> Result<TrajectoryFormat> {
    let first = text
        .lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .find(|(_, line)| !line.is_empty() && !line.starts_with('#'));
    let by_extension = match path.extension().and_then(|e| e.to_str()) {
        Some(e) if e.eq_ignore_ascii_case("log") => Some(TrajectoryFormat::Log),
        Some(e) if e.eq_ignore_ascii_case("tum") || e.eq_ignore_ascii_case("txt") => {
            Some(TrajectoryFormat::Tum)
        }
        _ => None,
    };
    let Some((line, content)) = first else {
        // No data at all: the reader says "holds no poses".
        return Ok(by_extension.unwrap_or(TrajectoryFormat::Tum));
    };
    let fields = content.split_whitespace().count();
    match (fields, by_extension) {
        (8, _) => Ok(TrajectoryFormat::Tum),
        (3, _) => Ok(TrajectoryFormat::Log),
        (_, Some(format)) => Ok(format),
        (_, None) => Err(EvalError::UnknownFormat {
            path: path.to_path_buf(),
            line,
            fields,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_is_told_by_content_then_extension() {
        let tum = "# timestamp tx ty tz qx qy qz qw\n\n0.5 0 0 0 0 0 0 1\n";
        let log = "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n";
        assert_eq!(
            detect_format(Path::new("a.log"), tum).unwrap(),
            TrajectoryFormat::Tum
        );
        assert_eq!(
            detect_format(Path::new("a.txt"), log).unwrap(),
            TrajectoryFormat::Log
        );
        assert_eq!(
            detect_format(Path::new("gt.freiburg"), tum).unwrap(),
            TrajectoryFormat::Tum
        );
        // A broken first line: the extension picks the reader that reports it.
        assert_eq!(
            detect_format(Path::new("a.tum"), "1 2 3 4\n").unwrap(),
            TrajectoryFormat::Tum
        );
        let err = detect_format(Path::new("a.dat"), "# c\n1 2 3 4\n").unwrap_err();
        assert!(
            err.to_string().starts_with(
                "a.dat:2: cannot tell the trajectory format: the first data line has 4 fields"
            ),
            "{err}"
        );
    }

    #[test]
    fn files_are_read_with_their_stamps_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let tum = dir.path().join("est");
        std::fs::write(&tum, "# t\n1.5 1 2 3 0 0 0 1\n2.5 4 5 6 0 0 1 0\n").unwrap();
        let t = read_trajectory(&tum, "estimate").unwrap();
        assert_eq!(t.format, TrajectoryFormat::Tum);
        assert_eq!(t.stamps(), vec![1.5, 2.5]);
        assert_eq!(t.poses[1].1.translation.vector.z, 6.0);

        let log = dir.path().join("gt.log");
        let record = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n";
        std::fs::write(&log, format!("0 0 1\n{record}1 1 2\n{record}")).unwrap();
        let t = read_trajectory(&log, "reference").unwrap();
        assert_eq!(t.format, TrajectoryFormat::Log);
        assert_eq!(t.stamps(), vec![0.0, 1.0]);

        let missing = dir.path().join("missing.tum");
        let err = read_trajectory(&missing, "reference").unwrap_err();
        assert!(matches!(err, EvalError::MissingFile { ref role, .. } if role == "reference"));

        let bad = dir.path().join("bad.tum");
        std::fs::write(&bad, "0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n").unwrap();
        let err = read_trajectory(&bad, "estimate").unwrap_err();
        assert!(
            err.to_string().ends_with("bad.tum:2: `x` is not a number"),
            "{err}"
        );
    }

    #[test]
    fn stamp_range_spans_all_stamps() {
        let t = Trajectory::new(
            "x",
            TrajectoryFormat::Tum,
            vec![(3.0, Pose::identity()), (1.0, Pose::identity())],
        );
        assert_eq!(t.stamp_range(), (1.0, 3.0));
        assert_eq!(t.stamps(), vec![3.0, 1.0]);
    }
}
