//! TUM RGB-D sequences.
//!
//! ```text
//! rgb.txt           `timestamp rgb/<t>.png` per line, `#` comments
//! depth.txt         `timestamp depth/<t>.png`, 16-bit depth, 5000 units per metre
//! groundtruth.txt   optional: `t tx ty tz qx qy qz qw`, camera-to-world
//! ```
//!
//! The colour and depth cameras are not synchronised, so frames are built by association: each
//! depth image (in time order) takes the nearest colour image not yet taken within
//! [`TUM_MAX_TIME_DIFFERENCE`]; a depth image with none is dropped. A frame's timestamp is its depth
//! timestamp, and its pose the ground truth nearest in time within the same tolerance, or
//! interpolated between the poses on both sides.
//!
//! TUM ships no intrinsics file: `[dataset] intrinsics` (Open3D JSON) is used when set, otherwise
//! [`TUM_DEFAULT_INTRINSICS`].

use std::path::{Path, PathBuf};

use vlem_core::config::DatasetConfig;
use vlem_core::{DatasetReader, FrameSource, Pose};

use crate::calibration::TUM_DEFAULT_INTRINSICS;
use crate::error::{DatasetError, Result};
use crate::sequence::{
    Camera, ColourFit, Entry, IntrinsicsSetting, PoseRef, Selection, Sequence, check_settings,
    depth_scale, reader_settings, reader_via_sequence, require_file,
};
use crate::text::{data_lines, parse_number, read_text};
use crate::trajectory::read_tum;

/// Raw depth units per metre of TUM RGB-D.
pub const TUM_DEPTH_SCALE: f64 = 5000.0;

/// Largest time difference, in seconds, between a depth image and the colour image or ground-truth
/// pose associated with it (the value of TUM's own `associate.py`).
pub const TUM_MAX_TIME_DIFFERENCE: f64 = 0.02;

/// The registered name: `[dataset] kind = "tum"`.
pub const TUM: &str = "tum";

vlem_core::register_dataset!(
    TUM,
    "TUM RGB-D: rgb.txt, depth.txt, groundtruth.txt; depth scale 5000",
    DatasetReader::new(open_boxed)
        .detected_by(10, "rgb.txt and depth.txt (TUM RGB-D)", |dir| {
            dir.join("rgb.txt").is_file() && dir.join("depth.txt").is_file()
        })
        .with_trajectory_file(|dir| {
            let path = dir.join("groundtruth.txt");
            require_file(&path, || "a TUM RGB-D folder's trajectory".to_owned())?;
            Ok(path)
        })
        .with_settings_check(|config| check_settings::<IntrinsicsSetting>(TUM, config))
);

fn open_boxed(config: &DatasetConfig, dir: &Path) -> vlem_core::Result<Box<dyn FrameSource>> {
    Ok(Box::new(TumReader::open(dir, config)?))
}

/// Reader of a TUM RGB-D sequence folder (see the module docs).
#[derive(Debug)]
pub struct TumReader {
    seq: Sequence,
}

reader_via_sequence!(TumReader);

/// A file listed with its timestamp.
#[derive(Clone, Debug)]
struct Stamped {
    time: f64,
    path: PathBuf,
}

impl TumReader {
    /// Opens the folder `dir`: reads the lists, associates colour to depth and poses to frames.
    ///
    /// # Errors
    /// [`DatasetError::MissingFile`] for a missing list or listed image,
    /// [`DatasetError::Parse`] for a malformed line, the errors of [`read_tum`] and
    /// [`read_open3d_intrinsics`](crate::read_open3d_intrinsics), [`DatasetError::NoPoseNear`] for a frame without ground truth,
    /// [`DatasetError::BadConfig`] and [`DatasetError::Empty`].
    pub fn open(dir: &Path, config: &DatasetConfig) -> Result<Self> {
        let settings: IntrinsicsSetting = reader_settings(TUM, config)?;
        let selection = Selection::from_config(config, dir)?;
        let scale = depth_scale(config, TUM_DEPTH_SCALE, dir)?;
        let colour = read_list(dir, "rgb.txt")?;
        let depth = read_list(dir, "depth.txt")?;
        let times = |list: &[Stamped]| list.iter().map(|s| s.time).collect::<Vec<f64>>();
        let frames: Vec<Entry> =
            associate(&times(&depth), &times(&colour), TUM_MAX_TIME_DIFFERENCE)
                .into_iter()
                .map(|(d, c)| Entry {
                    timestamp: Some(depth[d].time),
                    ..Entry::new(colour[c].path.clone(), depth[d].path.clone())
                })
                .collect();
        let mut selected = selection.apply(frames);
        let groundtruth = dir.join("groundtruth.txt");
        if groundtruth.is_file() {
            attach_groundtruth(&mut selected, &groundtruth)?;
        }
        let camera = Camera::from_setting_or_default(
            settings.intrinsics.as_deref(),
            dir,
            TUM_DEFAULT_INTRINSICS,
            "the TUM RGB-D default 525/525/319.5/239.5; set [dataset] intrinsics",
        )?;
        let seq = Sequence::new(
            "TUM RGB-D",
            dir,
            selected,
            camera,
            scale,
            ColourFit::SameSize,
        )?;
        Ok(Self { seq })
    }
}

/// Reads `rgb.txt` / `depth.txt`, sorted by time; every listed file must exist.
fn read_list(dir: &Path, name: &str) -> Result<Vec<Stamped>> {
    let path = dir.join(name);
    require_file(&path, || {
        "a TUM RGB-D folder needs rgb.txt and depth.txt (`timestamp file` per line)".to_owned()
    })?;
    let text = read_text(&path)?;
    let mut list = Vec::new();
    for entry in list_from_str(&text, &path)? {
        let file = dir.join(entry.file);
        require_file(&file, || {
            format!("listed in {} line {}", path.display(), entry.line)
        })?;
        list.push(Stamped {
            time: entry.time,
            path: file,
        });
    }
    list.sort_by(|a, b| a.time.total_cmp(&b.time));
    Ok(list)
}

/// One data line of a TUM image list (`rgb.txt` or `depth.txt`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ListEntry<'a> {
    /// 1-based line number in the list.
    pub line: usize,
    /// Timestamp in seconds, finite.
    pub time: f64,
    /// The image file, relative to the sequence folder, as written.
    pub file: &'a str,
}

/// Parses the text of a TUM image list (`rgb.txt` or `depth.txt`: `timestamp file` per line, `#`
/// comments, further fields ignored), in file order; `path` is the file it came from, as errors
/// name it. The listed files are not looked at.
///
/// # Errors
/// [`DatasetError::Parse`] for a line with fewer than two fields or a timestamp that is not a
/// finite number.
pub fn list_from_str<'a>(text: &'a str, path: &Path) -> Result<Vec<ListEntry<'a>>> {
    let mut list = Vec::new();
    for (line, content) in data_lines(text) {
        let mut fields = content.split_whitespace();
        let (Some(time), Some(file)) = (fields.next(), fields.next()) else {
            return Err(DatasetError::parse(path, line, "expected `timestamp file`"));
        };
        let time = parse_number(path, line, time)?;
        if !time.is_finite() {
            return Err(DatasetError::parse(
                path,
                line,
                "the timestamp is not finite",
            ));
        }
        list.push(ListEntry { line, time, file });
    }
    Ok(list)
}

/// Pairs each depth timestamp, in time order, with the nearest colour timestamp not yet taken
/// within `tolerance` seconds, as [`TumReader`] associates its images; returns
/// `(depth index, colour index)` pairs. Both slices must be sorted (ascending).
pub fn associate(depth: &[f64], colour: &[f64], tolerance: f64) -> Vec<(usize, usize)> {
    let mut taken = vec![false; colour.len()];
    let mut pairs = Vec::with_capacity(depth.len());
    for (d, &t) in depth.iter().enumerate() {
        let split = colour.partition_point(|&c| c < t);
        // The nearest free candidate on each side; the lists are sorted, so the scans stop at the
        // first free one or when the tolerance is exceeded.
        let before = (0..split)
            .rev()
            .take_while(|&c| t - colour[c] <= tolerance)
            .find(|&c| !taken[c]);
        let after = (split..colour.len())
            .take_while(|&c| colour[c] - t <= tolerance)
            .find(|&c| !taken[c]);
        let nearest = match (before, after) {
            (Some(b), Some(a)) => Some(if t - colour[b] <= colour[a] - t { b } else { a }),
            (b, a) => b.or(a),
        };
        if let Some(c) = nearest {
            taken[c] = true;
            pairs.push((d, c));
        }
    }
    pairs
}

/// Gives each selected frame its ground-truth pose.
fn attach_groundtruth(selected: &mut [(usize, Entry)], path: &Path) -> Result<()> {
    let mut poses = read_tum(path)?;
    poses.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (_, entry) in selected.iter_mut() {
        let Some(time) = entry.timestamp else {
            continue;
        };
        let pose = pose_at(&poses, time, TUM_MAX_TIME_DIFFERENCE).ok_or_else(|| {
            DatasetError::NoPoseNear {
                path: path.to_path_buf(),
                timestamp: time,
                tolerance: TUM_MAX_TIME_DIFFERENCE,
            }
        })?;
        entry.pose = PoseRef::Known(pose);
    }
    Ok(())
}

/// The pose at `time` from a time-sorted trajectory: the nearest one within `tolerance`, else the
/// interpolation (linear translation, slerp rotation) of the poses on both sides, else `None`.
pub(crate) fn pose_at(poses: &[(f64, Pose)], time: f64, tolerance: f64) -> Option<Pose> {
    let split = poses.partition_point(|(t, _)| *t < time);
    let before = split.checked_sub(1).map(|i| &poses[i]);
    let after = poses.get(split);
    let nearest = [before, after]
        .into_iter()
        .flatten()
        .min_by(|a, b| (a.0 - time).abs().total_cmp(&(b.0 - time).abs()))?;
    if (nearest.0 - time).abs() <= tolerance {
        return Some(nearest.1);
    }
    let ((t0, p0), (t1, p1)) = (before?, after?);
    Some(p0.lerp_slerp(p1, (time - t0) / (t1 - t0)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn association_is_greedy_in_time_order_and_uses_each_colour_once() {
        let depth = [1.000, 1.010, 1.100, 2.000];
        let colour = [1.005, 1.095, 1.950];
        // 1.010 would like 1.005 too but 1.000 took it; 1.095 is too far for it.
        // 2.000 has no colour image within 0.02 s and is dropped.
        assert_eq!(associate(&depth, &colour, 0.02), vec![(0, 0), (2, 1)]);
    }

    #[test]
    fn poses_are_nearest_within_tolerance_else_interpolated() {
        let at = |x: f64| Pose::translation(x, 0.0, 0.0);
        let poses = vec![(1.0, at(0.0)), (2.0, at(1.0))];
        let p = pose_at(&poses, 1.01, 0.02).unwrap();
        assert_eq!(p.translation.vector, Vector3::zeros());
        let p = pose_at(&poses, 1.25, 0.02).unwrap();
        assert!((p.translation.vector.x - 0.25).abs() < 1e-12);
        assert!(pose_at(&poses, 0.5, 0.02).is_none());
        assert!(pose_at(&poses, 2.5, 0.02).is_none());
        assert!(pose_at(&[], 1.0, 0.02).is_none());
    }
}
