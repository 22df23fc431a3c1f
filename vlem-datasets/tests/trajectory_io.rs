//! Trajectory files: `.log` reading, TUM reading and writing.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use vlem_core::Pose;
use vlem_datasets::trajectory::{format_tum_line, read_log, read_tum, write_tum};

#[test]
fn living_room_log_has_thirty_camera_to_world_poses() {
    let poses = read_log(&common::living_room().join("trajectory.log")).unwrap();
    assert_eq!(poses.len(), 30);
    assert_eq!(poses[0], Pose::identity());
    let t = poses[29].translation.vector;
    assert!((t - Vector3::new(-0.05687721, -0.52597026, 0.02859923)).norm() < 1e-8);
}

#[test]
fn tum_line_format_is_t_translation_then_xyzw() {
    let pose = Pose::from_parts(
        Translation3::new(1.0, -2.0, 0.5),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
    );
    assert_eq!(
        format_tum_line(12.5, &pose),
        "12.500000 1.000000000 -2.000000000 0.500000000 0.000000000 0.000000000 0.707106781 0.707106781"
    );
}

#[test]
fn tum_round_trip_through_a_renamed_temporary_file() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("trajectory.tum");
    let poses: Vec<(f64, Pose)> = (0..5)
        .map(|k| {
            let k = f64::from(k);
            let rotation = UnitQuaternion::from_euler_angles(0.1 * k, -0.2 * k, 0.3 * k);
            (
                1305031102.0 + k / 30.0,
                Pose::from_parts(Translation3::new(k, 2.0 * k, -k), rotation),
            )
        })
        .collect();
    write_tum(&path, &poses).unwrap();
    let names: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        names,
        vec![std::ffi::OsString::from("trajectory.tum")],
        "no temporary file is left"
    );
    let back = read_tum(&path).unwrap();
    assert_eq!(back.len(), 5);
    for ((t0, p0), (t1, p1)) in poses.iter().zip(&back) {
        assert!((t0 - t1).abs() < 1e-6);
        assert!((p0.translation.vector - p1.translation.vector).norm() < 1e-8);
        assert!(p0.rotation.angle_to(&p1.rotation) < 1e-8);
    }
}

#[test]
fn tum_errors_name_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    // A missing folder is created, as every save of vlem does.
    let nested = tmp.path().join("no-such-dir/trajectory.tum");
    write_tum(&nested, &[(0.0, Pose::identity())]).unwrap();
    assert_eq!(read_tum(&nested).unwrap().len(), 1);
    // A folder that cannot be made (a file is in its place) names the trajectory file.
    std::fs::write(tmp.path().join("a-file"), b"").unwrap();
    let blocked = tmp.path().join("a-file/trajectory.tum");
    let err = write_tum(&blocked, &[(0.0, Pose::identity())])
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with(&format!("{}: ", blocked.display())),
        "{err}"
    );

    let mut nan = Pose::identity();
    nan.translation.vector.x = f64::NAN;
    let path = tmp.path().join("t.tum");
    let err = write_tum(&path, &[(0.0, Pose::identity()), (1.0, nan)])
        .unwrap_err()
        .to_string();
    assert_eq!(
        err,
        format!("{}: the pose of frame 1 is not finite", path.display())
    );
    assert!(!path.exists());

    std::fs::write(&path, "# header\n1.0 0 0 0 0 0 0\n").unwrap();
    let err = read_tum(&path).unwrap_err().to_string();
    assert_eq!(
        err,
        format!("{}:2: expected 8 numbers, found 7", path.display())
    );
    std::fs::write(&path, "1.0 0 0 0 0 0 0 2\n").unwrap();
    let err = read_tum(&path).unwrap_err().to_string();
    assert!(
        err.contains("the rotation of frame 0 is not orthonormal"),
        "{err}"
    );
    std::fs::write(&path, "# nothing\n").unwrap();
    let err = read_tum(&path).unwrap_err().to_string();
    assert_eq!(err, format!("{}: holds no poses", path.display()));
}
