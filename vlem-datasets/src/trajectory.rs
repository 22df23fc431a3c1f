//! Trajectory files: Redwood `.log` (read), TUM (read and write), and ScanNet's one pose file per
//! frame (read).
//!
//! All hold camera-to-world poses, the convention of [`vlem_core::Pose`].
//!
//! - `.log` (Redwood / Open3D / ICL-NUIM augmented): per frame a metadata line `i j k`, then the
//!   four rows of the 4x4 camera-to-world matrix.
//! - TUM: one line per pose, `t tx ty tz qx qy qz qw` (scalar part of the quaternion last),
//!   `#` comments allowed.
//! - ScanNet `pose/N.txt`: the 4x4 camera-to-world matrix of one frame, one row per line; read with
//!   the frame, so that one lost frame does not make the whole sequence unusable.

use std::path::Path;

use nalgebra::{Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion};
use vlem_core::Pose;
use vlem_core::types::pose_is_finite;

use crate::error::{DatasetError, Result};
use crate::text::{data_lines, parse_exact, parse_numbers, read_text};

/// How far the rotation block of a pose matrix may be from orthonormal (max |RᵀR − I| and
/// |det R − 1|) before it is refused rather than re-orthonormalised.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// How far a TUM quaternion's norm may be from 1. TUM files print quaternions with 4 decimals,
/// so their norm is off by up to a few 1e-4; anything much larger is not a rotation.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-2;

/// Reads a Redwood `.log` trajectory: one camera-to-world pose per frame, in file order.
///
/// # Errors
/// [`DatasetError::MissingFile`] / [`DatasetError::Io`] when the file cannot be read, and those
/// of [`log_from_str`].
pub fn read_log(path: &Path) -> Result<Vec<Pose>> {
    log_from_str(&read_text(path)?, path)
}

/// Parses the text of a Redwood `.log` trajectory (see [`read_log`]); `path` is the file it came
/// from, as errors name it.
///
/// # Errors
/// [`DatasetError::Parse`] for a malformed line or a truncated record,
/// [`DatasetError::NonFinitePose`] / [`DatasetError::NotRotation`] for an unusable matrix and
/// [`DatasetError::NoPoses`] for a text without poses.
pub fn log_from_str(text: &str, path: &Path) -> Result<Vec<Pose>> {
    Ok(numbered_log_from_str(text, path)?
        .into_iter()
        .map(|(_, pose)| pose)
        .collect())
}

/// Reads a Redwood `.log` trajectory with each pose's frame id: the first number of its metadata
/// line (`i j k`: the frame `i` the pose belongs to).
///
/// # Errors
/// As [`read_log`], and [`DatasetError::Parse`] for a frame id that is not a whole number.
pub fn read_numbered_log(path: &Path) -> Result<Vec<(u64, Pose)>> {
    numbered_log_from_str(&read_text(path)?, path)
}

fn numbered_log_from_str(text: &str, path: &Path) -> Result<Vec<(u64, Pose)>> {
    let lines: Vec<(usize, &str)> = data_lines(text).collect();
    // A record is the metadata line plus four matrix rows.
    let mut poses = Vec::with_capacity(lines.len() / 5);
    for (frame, record) in lines.chunks(5).enumerate() {
        let &[header, ref rows @ ..] = record else {
            continue;
        };
        let (header_line, header_text) = header;
        let id = parse_exact(path, header_line, header_text, 3)?[0];
        if !(id >= 0.0 && id.fract() == 0.0 && id < 2f64.powi(53)) {
            return Err(DatasetError::parse(
                path,
                header_line,
                format!("frame {frame}: the frame id {id} is not a whole number"),
            ));
        }
        if rows.len() != 4 {
            return Err(DatasetError::parse(
                path,
                header_line,
                format!(
                    "frame {frame}: the file ends after {} of the 4 matrix rows",
                    rows.len()
                ),
            ));
        }
        let mut values = Vec::with_capacity(16);
        for &(line, row) in rows {
            values.extend(parse_exact(path, line, row, 4)?);
        }
        let matrix = Matrix4::from_row_slice(&values);
        // A whole number below 2^53, so the conversion is exact.
        #[allow(
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss,
            reason = "checked above"
        )]
        let id = id as u64;
        poses.push((id, pose_from_matrix(&matrix, path, frame)?));
    }
    if poses.is_empty() {
        return Err(DatasetError::NoPoses {
            path: path.to_path_buf(),
        });
    }
    Ok(poses)
}

/// Reads a TUM trajectory (e.g. `groundtruth.txt`): `(timestamp, camera-to-world pose)` per line,
/// in file order.
///
/// # Errors
/// [`DatasetError::MissingFile`] / [`DatasetError::Io`] when the file cannot be read, and those
/// of [`tum_from_str`].
pub fn read_tum(path: &Path) -> Result<Vec<(f64, Pose)>> {
    tum_from_str(&read_text(path)?, path)
}

/// Parses the text of a TUM trajectory (see [`read_tum`]); `path` is the file it came from, as
/// errors name it.
///
/// # Errors
/// [`DatasetError::Parse`] for a line without 8 numbers, [`DatasetError::NonFinitePose`] /
/// [`DatasetError::NotRotation`] for an unusable pose and [`DatasetError::NoPoses`] for a text
/// without poses.
pub fn tum_from_str(text: &str, path: &Path) -> Result<Vec<(f64, Pose)>> {
    let mut poses = Vec::new();
    for (line, content) in data_lines(text) {
        let v = parse_exact(path, line, content, 8)?;
        let frame = poses.len();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(DatasetError::NonFinitePose {
                path: path.to_path_buf(),
                frame,
            });
        }
        // nalgebra's constructor takes the scalar part first; TUM writes it last.
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        let deviation = (q.norm() - 1.0).abs();
        if deviation > QUATERNION_NORM_TOLERANCE {
            return Err(DatasetError::NotRotation {
                path: path.to_path_buf(),
                frame,
                deviation,
                tolerance: QUATERNION_NORM_TOLERANCE,
            });
        }
        let pose = Pose::from_parts(
            Translation3::new(v[1], v[2], v[3]),
            UnitQuaternion::from_quaternion(q),
        );
        poses.push((v[0], pose));
    }
    if poses.is_empty() {
        return Err(DatasetError::NoPoses {
            path: path.to_path_buf(),
        });
    }
    Ok(poses)
}

/// One TUM trajectory line, `t tx ty tz qx qy qz qw`, without a line break. The timestamp has 6
/// decimals (microseconds, as TUM itself), translation and quaternion 9.
pub fn format_tum_line(timestamp: f64, pose: &Pose) -> String {
    let t = &pose.translation.vector;
    let q = pose.rotation.quaternion();
    format!(
        "{timestamp:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
        t.x, t.y, t.z, q.i, q.j, q.k, q.w
    )
}

/// Writes a TUM trajectory. The text goes to a temporary file beside `path` that is then renamed,
/// so a reader never sees a half-written trajectory.
///
/// # Errors
/// [`DatasetError::NonFinitePose`] when a pose is not finite (nothing is written), and
/// [`DatasetError::Core`] when the file cannot be written or renamed.
pub fn write_tum(path: &Path, poses: &[(f64, Pose)]) -> Result<()> {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for (frame, (t, pose)) in poses.iter().enumerate() {
        if !t.is_finite() || !pose_is_finite(pose) {
            return Err(DatasetError::NonFinitePose {
                path: path.to_path_buf(),
                frame,
            });
        }
        text.push_str(&format_tum_line(*t, pose));
        text.push('\n');
    }
    // The one crash-safe way vlem writes a file (unique temporary name, synced, renamed, the
    // folder synced), so two runs writing into one folder never share a temporary file.
    vlem_core::files::write_atomically(path, text.as_bytes()).map_err(|source| DatasetError::Core {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads one ScanNet pose file (4x4 camera-to-world, rows) for frame `frame`.
pub(crate) fn read_scannet_pose(path: &Path, frame: usize) -> Result<Pose> {
    scannet_pose_from_str(&read_text(path)?, path, frame)
}

/// Parses the text of one ScanNet pose file (`pose/N.txt`: a 4x4 camera-to-world matrix, one row
/// per line) as the pose of frame `frame`; `path` is the file it came from, as errors name it.
///
/// # Errors
/// [`DatasetError::Parse`] for a malformed matrix, [`DatasetError::NonFinitePose`] for the `-inf`
/// poses ScanNet writes for lost frames, [`DatasetError::NotRotation`] for a matrix whose rotation
/// block is not a rotation.
pub fn scannet_pose_from_str(text: &str, path: &Path, frame: usize) -> Result<Pose> {
    let rows = matrix_rows_from_str(text, path, 4)?;
    let values: Vec<f64> = rows.into_iter().flatten().collect();
    pose_from_matrix(&Matrix4::from_row_slice(&values), path, frame)
}

/// A camera-to-world pose from a 4x4 matrix read from `path` (frame `frame`): refused when not
/// finite or when the rotation block is not a rotation within [`ROTATION_TOLERANCE`], otherwise
/// re-orthonormalised (text files round the matrix, and `Pose` needs an exact rotation).
pub(crate) fn pose_from_matrix(m: &Matrix4<f64>, path: &Path, frame: usize) -> Result<Pose> {
    if m.iter().any(|x| !x.is_finite()) {
        return Err(DatasetError::NonFinitePose {
            path: path.to_path_buf(),
            frame,
        });
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let deviation = rotation_deviation(&r);
    if deviation > ROTATION_TOLERANCE {
        return Err(DatasetError::NotRotation {
            path: path.to_path_buf(),
            frame,
            deviation,
            tolerance: ROTATION_TOLERANCE,
        });
    }
    let rotation = nearest_rotation(&r);
    let t = m.fixed_view::<3, 1>(0, 3);
    Ok(Pose::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        rotation,
    ))
}

/// Largest of |RᵀR − I| (entry-wise) and |det R − 1|: zero for an exact rotation; the
/// determinant catches reflections, which are orthonormal too.
fn rotation_deviation(r: &Matrix3<f64>) -> f64 {
    let orthogonality = (r.transpose() * r - Matrix3::identity()).abs().max();
    orthogonality.max((r.determinant() - 1.0).abs())
}

/// The rotation closest to a nearly orthonormal `r`.
fn nearest_rotation(r: &Matrix3<f64>) -> UnitQuaternion<f64> {
    // The trace-based (Shepperd) conversion is robust for every angle, including 180°, where the
    // iterative method of `Rotation3::from_matrix` started from the identity cannot move; its
    // normalised result then seeds a few iterations that make the rotation the closest one.
    let guess = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    let guess = UnitQuaternion::new_normalize(guess.into_inner());
    let refined = Rotation3::from_matrix_eps(r, 1e-12, 32, guess.to_rotation_matrix());
    UnitQuaternion::new_normalize(UnitQuaternion::from_rotation_matrix(&refined).into_inner())
}

/// Parses a `size` x `size` matrix from the text of a file whose lines hold its rows (ScanNet pose
/// and intrinsic files); `path` names the file in errors.
pub(crate) fn matrix_rows_from_str(text: &str, path: &Path, size: usize) -> Result<Vec<Vec<f64>>> {
    let mut rows = Vec::with_capacity(size);
    for (line, content) in data_lines(text) {
        let row = parse_numbers(path, line, content)?;
        if row.len() != size {
            return Err(DatasetError::parse(
                path,
                line,
                format!(
                    "expected a row of {size} numbers (a {size}x{size} matrix), found {}",
                    row.len()
                ),
            ));
        }
        rows.push(row);
    }
    if rows.len() != size {
        return Err(DatasetError::parse(
            path,
            text.lines().count().max(1),
            format!(
                "expected {size} rows (a {size}x{size} matrix), found {}",
                rows.len()
            ),
        ));
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn half_turn_matrices_keep_their_rotation() {
        let m = Matrix4::new(
            -1.0, 0.0, 0.0, 1.0, //
            0.0, -1.0, 0.0, 2.0, //
            0.0, 0.0, 1.0, 3.0, //
            0.0, 0.0, 0.0, 1.0,
        );
        let pose = pose_from_matrix(&m, Path::new("x.log"), 0).unwrap();
        let p = pose * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!(
            (p.coords - Vector3::new(0.0, 2.0, 3.0)).norm() < 1e-9,
            "{p}"
        );
    }

    #[test]
    fn slightly_rounded_rotations_are_re_orthonormalised() {
        let exact = Rotation3::from_euler_angles(0.3, -0.2, 1.1);
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&exact.matrix().map(|x: f64| (x * 1e4).round() / 1e4));
        let pose = pose_from_matrix(&m, Path::new("x.log"), 0).unwrap();
        assert!(pose_is_finite(&pose));
        assert!(
            pose.rotation
                .angle_to(&UnitQuaternion::from_rotation_matrix(&exact))
                < 1e-4
        );
    }

    #[test]
    fn reflections_and_scaled_matrices_are_refused() {
        let mut m = Matrix4::identity();
        m[(0, 0)] = -1.0;
        let err = pose_from_matrix(&m, Path::new("/d/t.log"), 4).unwrap_err();
        assert!(
            err.to_string()
                .starts_with("/d/t.log: the rotation of frame 4 is not orthonormal"),
            "{err}"
        );
        let m = Matrix4::identity() * 1.01;
        assert!(pose_from_matrix(&m, Path::new("t.log"), 0).is_err());
    }
}
