//! `vlem study`: cells, shards, resuming, failing cells, the CSV and the plot.
#![cfg(feature = "cli")]
#![cfg(all(feature = "colour-names", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use std::path::Path;

use common::{fails, ok};

/// A small labelled synthetic scene mapped with the weight-free colour-names encoder.
const BASE: &str = r#"
[dataset]
kind = "synthetic"

[dataset.synthetic]
seed = 2
frames = 12
width = 96
height = 72

[tracker]
kind = "ground-truth"

[encoder]
kind = "colour-names"

[map]
kind = "point-cloud"
max_distance = 0.05
"#;

/// The colour-names encoder knows only colour words: each class is queried by a colour.
fn write_prompts(dir: &Path) {
    const COLOURS: [&str; 6] = ["white", "brown", "grey", "red", "blue", "green"];
    let prompts: serde_json::Map<String, serde_json::Value> =
        vlem_eval::semseg::classes::NYU40_NAMES
            .iter()
            .enumerate()
            .map(|(i, name)| ((*name).to_owned(), COLOURS[i % COLOURS.len()].into()))
            .collect();
    std::fs::write(
        dir.join("prompts.json"),
        serde_json::Value::Object(prompts).to_string(),
    )
    .unwrap();
}

fn write_study(dir: &Path, axes: &str) -> std::path::PathBuf {
    std::fs::write(dir.join("base.toml"), BASE).unwrap();
    write_prompts(dir);
    let study = dir.join("study.toml");
    std::fs::write(
        &study,
        format!(
            "[study]\nbase = \"base.toml\"\nprotocol = \"vlem\"\nclasses = \"nyu40\"\nprompts = \"prompts.json\"\n{axes}"
        ),
    )
    .unwrap();
    study
}

#[cfg(feature = "voxel")]
const TWO_MAPS: &str = r#"
[[maps]]
name = "point-cloud 5 cm"
kind = "point-cloud"
max_distance = 0.05

[[maps]]
name = "voxel 10 cm"
kind = "voxel"
voxel_size = 0.1
"#;

fn rows(csv: &Path) -> Vec<Vec<String>> {
    let mut reader = csv::Reader::from_path(csv).unwrap();
    let header: Vec<String> = reader
        .headers()
        .unwrap()
        .iter()
        .map(str::to_owned)
        .collect();
    let mut rows = vec![header];
    for record in reader.records() {
        rows.push(record.unwrap().iter().map(str::to_owned).collect());
    }
    rows
}

fn column<'a>(rows: &'a [Vec<String>], name: &str) -> Vec<&'a str> {
    let i = rows[0].iter().position(|h| h == name).unwrap();
    rows[1..].iter().map(|r| r[i].as_str()).collect()
}

#[cfg(feature = "voxel")]
#[test]
fn shards_together_run_every_cell_once_and_the_report_gathers_them() {
    let dir = tempfile::tempdir().unwrap();
    let study = write_study(dir.path(), TWO_MAPS);
    let out = dir.path().join("out");
    let (study, out) = (study.to_str().unwrap(), out.to_str().unwrap());

    let listed = ok(&["study", study, "--list"]);
    assert_eq!(listed.lines().count(), 2, "{listed}");

    ok(&["study", study, "--out", out, "--shard", "2/2"]);
    let after_one = rows(&Path::new(out).join("study.csv"));
    assert_eq!(column(&after_one, "map"), ["voxel 10 cm"]);

    ok(&["study", study, "--out", out, "--shard", "1/2"]);
    let all = rows(&Path::new(out).join("study.csv"));
    assert_eq!(column(&all, "map"), ["point-cloud 5 cm", "voxel 10 cm"]);
    assert_eq!(column(&all, "status"), ["ok", "ok"]);
    for miou in column(&all, "miou") {
        let miou: f64 = miou.parse().unwrap();
        assert!((0.0..=1.0).contains(&miou), "{miou}");
    }
    for bytes in column(&all, "peak_resident_bytes") {
        assert!(bytes.parse::<u64>().unwrap() > 0);
    }
    for points in column(&all, "map_points") {
        assert!(points.parse::<u64>().unwrap() > 0);
    }
    let svg = std::fs::read_to_string(Path::new(out).join("study.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("voxel 10 cm"), "{svg}");

    // Finished cells are not run again: their results stay byte for byte.
    let result = Path::new(out).join("cells/000-base-base-base-point-cloud-5-cm/result.json");
    let before = std::fs::read(&result).unwrap();
    let modified = std::fs::metadata(&result).unwrap().modified().unwrap();
    ok(&["study", study, "--out", out]);
    assert_eq!(std::fs::read(&result).unwrap(), before);
    assert_eq!(
        std::fs::metadata(&result).unwrap().modified().unwrap(),
        modified
    );
    let gathered = ok(&["study", study, "--out", out, "--report"]);
    assert!(gathered.contains("2 of 2 cells have results"), "{gathered}");
}

#[test]
fn a_failing_cell_is_recorded_and_the_others_still_run() {
    let dir = tempfile::tempdir().unwrap();
    let study = write_study(
        dir.path(),
        r#"
[[sequences]]
name = "missing folder"
path = "no-such-dataset"

[[sequences]]
name = "synthetic"
kind = "synthetic"
[sequences.synthetic]
seed = 3
frames = 8
width = 64
height = 48
"#,
    );
    let out = dir.path().join("out");
    let err = fails(&[
        "study",
        study.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(err.contains("1 cell(s) failed"), "{err}");
    let all = rows(&out.join("study.csv"));
    assert_eq!(column(&all, "sequence"), ["missing folder", "synthetic"]);
    assert_eq!(column(&all, "status"), ["failed", "ok"]);
    let error = column(&all, "error")[0];
    assert!(error.contains("no-such-dataset"), "{error}");
}

#[test]
fn a_bad_variant_is_refused_before_any_cell_runs() {
    let dir = tempfile::tempdir().unwrap();
    let study = write_study(
        dir.path(),
        "[[maps]]\nname = \"pc\"\nkind = \"point-cloud\"\n\n[[sequences]]\nname = \"typo\"\nkind = \"synthetic\"\nstrde = 2\n",
    );
    let out = dir.path().join("out");
    let err = fails(&[
        "study",
        study.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(err.contains("typo") && err.contains("strde"), "{err}");
    assert!(!out.exists(), "nothing runs before every cell is checked");

    let unnamed = write_study(dir.path(), "[[maps]]\nkind = \"voxel\"\n");
    let err = fails(&["study", unnamed.to_str().unwrap(), "--list"]);
    assert!(err.contains("needs a `name`"), "{err}");
    let err = fails(&["study", unnamed.to_str().unwrap(), "--shard", "3/2"]);
    assert!(err.contains("i/n"), "{err}");
}
