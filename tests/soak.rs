//! `vlem soak`, shortened for CI: a few hundred small synthetic frames under a tiny map budget.
//! The full 10,000-frame run is in BENCHMARKS.md ("Soak").
#![cfg(feature = "cli")]
#![cfg(feature = "point-cloud")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

#[cfg(any(feature = "colour-names", feature = "voxel"))]
use common::fails;
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use common::ok;

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use std::path::Path;

/// A soak config: the synthetic scene at 80x60 with its exact poses (odometry loses track on so
/// few pixels), colour names, a point cloud of `max_points`.
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn write_config(dir: &Path, max_points: usize) -> String {
    let path = dir.join("soak.toml");
    std::fs::write(
        &path,
        format!(
            "[dataset]\nkind = \"synthetic\"\n[dataset.synthetic]\nseed = 1\nwidth = 80\n\
             height = 60\n[tracker]\nkind = \"ground-truth\"\n[encoder]\nkind = \"colour-names\"\n\
             [map]\nkind = \"point-cloud\"\nmax_points = {max_points}\n"
        ),
    )
    .unwrap();
    path.to_string_lossy().into_owned()
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn a_short_soak_fills_the_map_to_its_budget_and_memory_stays_flat() {
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(tmp.path(), 8000);
    let out = tmp.path().join("out");
    let stdout = ok(&[
        "soak",
        "--config",
        &config,
        "--frames",
        "400",
        "--sample-every",
        "20",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stdout.contains("soak passed"), "{stdout}");
    assert!(stdout.contains("400 frames: 400 tracked"), "{stdout}");

    let report = read_json(&out.join("soak.json"));
    assert_eq!(report["passed"], true, "{report}");
    assert_eq!(report["failures"].as_array().unwrap().len(), 0);
    assert_eq!(report["frames"]["total"], 400);
    assert_eq!(report["map"]["budget"], 8000);
    // The map reached its budget (it was seen enforcing it) and never went above it.
    let full_at = report["warmup"]["map_full_at_frame"].as_u64().unwrap();
    assert!(full_at < 40, "{report}");
    let max = report["map"]["max_elements"].as_u64().unwrap();
    assert!(max <= 8000 && max > 7000, "{report}");
    // The warm-up is the first 10 % (40 frames), or longer while the map's storage still grows
    // in steps after the budget is reached (its buffers grow once more, around frame 60 here):
    // the reference is the first sample after both.
    let grew = report["warmup"]["storage_last_grew_at_frame"]
        .as_u64()
        .unwrap();
    let end = grew.max(40);
    assert_eq!(report["warmup"]["ends_at_frame"], end, "{report}");
    assert_eq!(
        report["warmup"]["reference"]["frame"],
        end.div_ceil(20) * 20
    );
    let level = report["rss_bytes"]["at_warmup"].as_f64().unwrap();
    for key in ["min_after_warmup", "max_after_warmup", "end"] {
        let rss = report["rss_bytes"][key].as_f64().unwrap();
        assert!((rss - level).abs() <= 0.1 * level, "{key}: {report}");
    }

    let csv = std::fs::read_to_string(out.join("soak-samples.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("frame,rss_bytes,map_elements,map_bytes"));
    let rows: Vec<Vec<u64>> = lines
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    // One sample before the first frame and one after every 20.
    assert_eq!(rows.len(), 21);
    assert_eq!(
        rows.iter().map(|r| r[0]).collect::<Vec<_>>(),
        (0..=400).step_by(20).collect::<Vec<_>>()
    );
    for r in &rows[1..] {
        assert!(r[1] > 0 && r[2] > 0 && r[2] <= 8000 && r[3] > 0, "{r:?}");
    }
    // From the reference on, the map is full: at least 80 % of its budget at every sample.
    assert!(rows[2..].iter().all(|r| r[2] >= 6400), "{rows:?}");
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn a_budget_the_map_never_reaches_fails_the_soak() {
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(tmp.path(), 1_000_000);
    let out = tmp.path().join("out");
    let err = fails(&[
        "soak",
        "--config",
        &config,
        "--frames",
        "20",
        "--sample-every",
        "10",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("error: soak failed: the map never reached its budget of 1000000"),
        "{err}"
    );
    let report = read_json(&out.join("soak.json"));
    assert_eq!(report["passed"], false);
    assert_eq!(
        report["warmup"]["map_full_at_frame"],
        serde_json::Value::Null
    );
}

#[cfg(feature = "voxel")]
#[test]
fn soak_configs_need_a_synthetic_scene_and_an_explicit_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let out = out.to_str().unwrap();
    let config = tmp.path().join("c.toml");
    let c = config.to_str().unwrap();

    std::fs::write(&config, "[map]\nkind = \"point-cloud\"\nmax_points = 10\n").unwrap();
    let err = fails(&["soak", "--config", c, "--out", out]);
    assert!(
        err.contains("vlem soak maps the synthetic scene") && err.contains("kind = \"synthetic\""),
        "{err}"
    );

    std::fs::write(
        &config,
        "[dataset]\nkind = \"synthetic\"\n[map]\nkind = \"voxel\"\n",
    )
    .unwrap();
    let err = fails(&["soak", "--config", c, "--out", out]);
    assert!(err.contains("set [map] max_voxels"), "{err}");

    let err = fails(&["soak", "--config", c, "--sample-every", "0"]);
    assert!(err.contains("--sample-every must be at least 1"), "{err}");
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn the_shipped_soak_config_is_valid() {
    // Only its first frames: the config parses, builds and fills nothing yet, so it fails the
    // budget check rather than anything earlier.
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let err = fails(&[
        "soak",
        "--frames",
        "3",
        "--sample-every",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("the map never reached its budget of 150000"),
        "{err}"
    );
    let report = read_json(&out.join("soak.json"));
    assert_eq!(report["config"], "configs/soak.toml");
    assert_eq!(report["frames"]["integrated"], 3);
}
