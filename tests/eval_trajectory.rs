//! End-to-end tests of `vlem eval trajectory`: the committed living-room `.log` against perturbed
//! TUM copies with known errors, a hand-computed case paired by timestamp, and the error messages.
#![cfg(feature = "cli")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use common::{fails, repo, vlem};

use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};
use vlem_core::Pose;
use vlem_datasets::trajectory::{read_log, write_tum};

fn reference_log() -> PathBuf {
    repo().join("data/living-room/trajectory.log")
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Runs `vlem eval trajectory` with `--json`, and returns its stdout and the parsed JSON.
fn eval(estimate: &Path, reference: &Path, extra: &[&str]) -> (String, serde_json::Value) {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("report.json");
    let mut args = vec![
        "eval",
        "trajectory",
        "--estimate",
        s(estimate),
        "--reference",
        s(reference),
        "--json",
        s(&json),
    ];
    args.extend_from_slice(extra);
    let out = vlem(&args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "vlem {args:?} failed:\n{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    (stdout, report)
}

fn num(report: &serde_json::Value, pointer: &str) -> f64 {
    report
        .pointer(pointer)
        .and_then(serde_json::Value::as_f64)
        .unwrap_or_else(|| panic!("no number at {pointer} in {report:#}"))
}

/// The committed reference poses, stamped with their frame index (what `vlem run` writes for a
/// dataset without timestamps).
fn reference_poses() -> Vec<(f64, Pose)> {
    read_log(&reference_log())
        .unwrap()
        .into_iter()
        .enumerate()
        .map(|(i, p)| (i as f64, p))
        .collect()
}

/// The transform from the estimate's world frame to the reference's used below.
fn g() -> Pose {
    Pose::from_parts(
        Vector3::new(2.0, -1.0, 0.5).into(),
        UnitQuaternion::from_euler_angles(0.3, -0.5, 1.2),
    )
}

fn write(dir: &Path, name: &str, poses: &[(f64, Pose)]) -> PathBuf {
    let path = dir.join(name);
    write_tum(&path, poses).unwrap();
    path
}

/// Checks the printed table's row `name` against the JSON statistics at `pointer`.
fn assert_row_matches(stdout: &str, name: &str, report: &serde_json::Value, pointer: &str) {
    let row = stdout
        .lines()
        .find(|l| l.starts_with(name))
        .unwrap_or_else(|| panic!("no row {name} in\n{stdout}"));
    let fields: Vec<&str> = row[name.len()..].split_whitespace().collect();
    assert_eq!(
        fields[0],
        num(report, &format!("{pointer}/count")).to_string()
    );
    for (i, key) in ["rmse", "mean", "median", "std", "min", "max"]
        .iter()
        .enumerate()
    {
        let printed: f64 = fields[i + 1].parse().unwrap();
        let value = num(report, &format!("{pointer}/{key}"));
        assert!(
            (printed - value).abs() <= 5e-7,
            "{name} {key}: printed {printed}, JSON {value}"
        );
    }
}

#[test]
fn a_rigidly_moved_copy_has_no_error_and_its_transform_is_recovered() {
    let dir = tempfile::tempdir().unwrap();
    // The estimate lives in a world frame g⁻¹ away: P_k = g⁻¹ Q_k.
    let moved: Vec<(f64, Pose)> = reference_poses()
        .into_iter()
        .map(|(t, q)| (t, g().inverse() * q))
        .collect();
    let estimate = write(dir.path(), "trajectory.tum", &moved);
    let (stdout, report) = eval(&estimate, &reference_log(), &[]);

    assert!(
        stdout.contains("associated 30 pose pairs by frame index"),
        "{stdout}"
    );
    assert_eq!(num(&report, "/associated"), 30.0);
    assert_eq!(report["association"]["mode"], "frame-index");
    assert_eq!(report["estimate"]["format"], "tum");
    assert_eq!(report["reference"]["format"], "log");
    assert!(num(&report, "/ate/position_m/max") < 1e-6, "{report:#}");
    assert!(num(&report, "/rpe/translation_m/max") < 1e-6);
    assert!(num(&report, "/rpe/rotation_deg/max") < 1e-4);
    // The alignment is g itself.
    let g = g();
    let t = &report["ate"]["alignment"]["translation"];
    for i in 0..3 {
        assert!((t[i].as_f64().unwrap() - g.translation.vector[i]).abs() < 1e-5);
    }
    let r = g.rotation.to_rotation_matrix().into_inner();
    for i in 0..3 {
        for j in 0..3 {
            let fitted = report["ate"]["alignment"]["rotation"][i][j]
                .as_f64()
                .unwrap();
            assert!((fitted - r[(i, j)]).abs() < 1e-5, "R[{i}][{j}] {fitted}");
        }
    }
    assert_eq!(num(&report, "/ate/alignment/scale"), 1.0);
    // The dataset folder as the reference: its trajectory file is found as the reader finds it.
    let (_, by_folder) = eval(&estimate, reference_log().parent().unwrap(), &[]);
    assert_eq!(by_folder["reference"]["path"], report["reference"]["path"]);
    assert_eq!(by_folder["ate"], report["ate"]);
    assert_row_matches(&stdout, "ATE (m)", &report, "/ate/position_m");
    assert_row_matches(&stdout, "RPE trans (m/1f)", &report, "/rpe/translation_m");
    assert_row_matches(&stdout, "RPE rot (deg/1f)", &report, "/rpe/rotation_deg");
}

#[test]
fn a_constant_drift_per_frame_gives_the_known_rpe() {
    let dir = tempfile::tempdir().unwrap();
    // Every frame the estimate drifts a further v (5 mm) in the world: each relative motion is
    // off by exactly |v| (E's translation is v rotated into a camera frame), however the camera
    // turns.
    let v = Vector3::new(0.003, -0.004, 0.0);
    let drifted: Vec<(f64, Pose)> = reference_poses()
        .into_iter()
        .map(|(t, mut q)| {
            q.translation.vector += v * t;
            (t, q)
        })
        .collect();
    let estimate = write(dir.path(), "drift.tum", &drifted);
    let (stdout, report) = eval(&estimate, &reference_log(), &[]);
    for key in ["rmse", "mean", "median", "min", "max"] {
        let e = num(&report, &format!("/rpe/translation_m/{key}"));
        assert!((e - 0.005).abs() < 1e-7, "RPE {key} {e}");
    }
    assert!(num(&report, "/rpe/rotation_deg/max") < 1e-4);
    assert_eq!(num(&report, "/rpe/translation_m/count"), 29.0);
    // ATE: positive, and no worse than the best pure translation (subtracting the mean drift),
    // whose RMSE is |v| √((n² − 1) / 12) for n = 30 frames.
    let ate = num(&report, "/ate/position_m/rmse");
    let translation_only = 0.005 * ((30.0f64 * 30.0 - 1.0) / 12.0).sqrt();
    assert!(ate > 1e-3 && ate <= translation_only + 1e-9, "ATE {ate}");
    assert_row_matches(&stdout, "ATE (m)", &report, "/ate/position_m");

    // Over 3 frames the drift is 15 mm, and there are 27 pairs.
    let (stdout, report) = eval(&estimate, &reference_log(), &["--delta", "3"]);
    assert!((num(&report, "/rpe/translation_m/mean") - 0.015).abs() < 1e-7);
    assert_eq!(num(&report, "/rpe/translation_m/count"), 27.0);
    assert_eq!(num(&report, "/rpe/delta"), 3.0);
    assert_row_matches(&stdout, "RPE trans (m/3f)", &report, "/rpe/translation_m");
}

#[test]
fn a_half_scale_estimate_is_recovered_with_scale_only() {
    let dir = tempfile::tempdir().unwrap();
    let halved: Vec<(f64, Pose)> = reference_poses()
        .into_iter()
        .map(|(t, q)| {
            let mut p = g().inverse() * q;
            p.translation.vector *= 0.5;
            (t, p)
        })
        .collect();
    let estimate = write(dir.path(), "half.tum", &halved);
    let (stdout, report) = eval(&estimate, &reference_log(), &["--scale"]);
    assert!(stdout.contains("alignment (similarity)"), "{stdout}");
    assert!((num(&report, "/ate/alignment/scale") - 2.0).abs() < 1e-4);
    assert_eq!(report["ate"]["with_scale"], true);
    assert!(num(&report, "/ate/position_m/max") < 1e-6);
    // RPE runs on the estimate scaled by the fitted 2: no error left.
    assert!(num(&report, "/rpe/translation_m/max") < 1e-6);

    let (_, rigid) = eval(&estimate, &reference_log(), &[]);
    assert_eq!(num(&rigid, "/ate/alignment/scale"), 1.0);
    assert!(num(&rigid, "/ate/position_m/rmse") > 1e-3, "{rigid:#}");
    assert!(num(&rigid, "/rpe/translation_m/rmse") > 1e-3);
}

#[test]
fn a_strided_estimate_pairs_with_the_log_by_rounded_frame_index() {
    let dir = tempfile::tempdir().unwrap();
    // Frames 0, 2, …, 28 (a stride-2 run), plus one stamp that is no frame index.
    let mut strided: Vec<(f64, Pose)> = reference_poses().into_iter().step_by(2).collect();
    strided.push((29.5, Pose::identity()));
    let estimate = write(dir.path(), "strided.tum", &strided);
    let (stdout, report) = eval(&estimate, &reference_log(), &[]);
    assert_eq!(num(&report, "/associated"), 15.0);
    assert_eq!(num(&report, "/estimate/poses"), 16.0);
    assert!(num(&report, "/ate/position_m/max") < 1e-6);
    assert!(num(&report, "/rpe/translation_m/max") < 1e-6, "{stdout}");
}

#[test]
fn timestamps_pair_within_the_tolerance_and_a_displaced_pose_gives_the_hand_computed_errors() {
    let dir = tempfile::tempdir().unwrap();
    let t0 = 1_305_031_102.175_304;
    // Reference: four positions around the origin, 1/30 s apart.
    let positions = [
        [1.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, -1.0, 0.0],
    ];
    let mut reference = String::from("# timestamp tx ty tz qx qy qz qw\n");
    let mut estimate = String::from("# an estimate with jittered stamps\n");
    for (k, p) in positions.iter().enumerate() {
        let t = t0 + k as f64 / 30.0;
        reference.push_str(&format!("{t:.6} {} {} {} 0 0 0 1\n", p[0], p[1], p[2]));
        // Pose 0 is 0.4 m off along x; stamps are up to 15 ms off.
        let x = if k == 0 { p[0] + 0.4 } else { p[0] };
        let jitter = [0.015, -0.008, 0.005, -0.015][k];
        estimate.push_str(&format!(
            "{:.6} {x} {} {} 0 0 0 1\n",
            t + jitter,
            p[1],
            p[2]
        ));
    }
    let (reference_path, estimate_path) = (dir.path().join("gt.txt"), dir.path().join("e.txt"));
    std::fs::write(&reference_path, reference).unwrap();
    std::fs::write(&estimate_path, &estimate).unwrap();
    let (stdout, report) = eval(&estimate_path, &reference_path, &[]);
    assert!(
        stdout.contains("associated 4 pose pairs by timestamp"),
        "{stdout}"
    );
    assert_eq!(report["association"]["mode"], "timestamp");
    // The best rigid fit shifts by −0.1 m in x: errors 0.3, 0.1, 0.1, 0.1.
    let close = |pointer: &str, expected: f64| {
        let value = num(&report, pointer);
        assert!(
            (value - expected).abs() < 1e-9,
            "{pointer}: {value} ≠ {expected}"
        );
    };
    close("/ate/position_m/rmse", (0.12f64 / 4.0).sqrt());
    close("/ate/position_m/mean", 0.15);
    close("/ate/position_m/median", 0.1);
    close("/ate/position_m/max", 0.3);
    close("/ate/alignment/translation/0", -0.1);
    // RPE: the step 0 → 1 is 2.4 m instead of 2; the other two are exact.
    close("/rpe/translation_m/mean", 0.4 / 3.0);
    close("/rpe/translation_m/rmse", (0.16f64 / 3.0).sqrt());
    close("/rpe/rotation_deg/max", 0.0);

    // With a 10 ms tolerance the two stamps 15 ms off find no partner: 2 pairs are too few.
    let err = fails(&[
        "eval",
        "trajectory",
        "--estimate",
        s(&estimate_path),
        "--reference",
        s(&reference_path),
        "--max-time-diff",
        "0.01",
    ]);
    assert!(
        err.contains("only 2 pose pairs associated by timestamp (at least 3 needed)"),
        "{err}"
    );
}

#[test]
fn errors_name_the_file_and_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let log = reference_log();
    let args = |estimate: &Path| -> Vec<String> {
        [
            "eval",
            "trajectory",
            "--estimate",
            s(estimate),
            "--reference",
            s(&log),
        ]
        .map(str::to_owned)
        .to_vec()
    };
    let run = |a: &[String]| fails(&a.iter().map(String::as_str).collect::<Vec<_>>());

    let missing = dir.path().join("nope.tum");
    let err = run(&args(&missing));
    assert!(
        err.contains(&format!("{} (estimate): no such file", missing.display())),
        "{err}"
    );

    let two = write(dir.path(), "two.tum", &reference_poses()[..2]);
    let err = run(&args(&two));
    assert!(
        err.contains("only 2 pose pairs associated by frame index (at least 3 needed)"),
        "{err}"
    );

    let bad = dir.path().join("bad.tum");
    std::fs::write(
        &bad,
        "# t tx ty tz qx qy qz qw\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n",
    )
    .unwrap();
    let err = run(&args(&bad));
    assert!(
        err.contains(&format!("{}:3: expected 8 numbers, found 7", bad.display())),
        "{err}"
    );

    let timed: Vec<(f64, Pose)> = reference_poses()
        .into_iter()
        .map(|(t, p)| (1.3e9 + t / 30.0, p))
        .collect();
    let timed = write(dir.path(), "timed.tum", &timed);
    let err = run(&args(&timed));
    assert!(err.contains("holds timestamps, not frame indices"), "{err}");

    let copy = write(dir.path(), "copy.tum", &reference_poses());
    let mut a = args(&copy);
    a.extend(["--delta".to_owned(), "30".to_owned()]);
    let err = run(&a);
    assert!(
        err.contains("RPE with delta 30 needs at least 31 poses, found 30"),
        "{err}"
    );
    let mut a = args(&copy);
    a.push("--max-time-diff=-1".to_owned());
    let err = run(&a);
    assert!(err.contains("invalid max time difference -1"), "{err}");
}
