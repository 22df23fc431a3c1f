//! End-to-end tests of the `vlem` command: the demo, run/query on the committed real frames, the
//! plugin list, and the error messages users see.
#![cfg(feature = "cli")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use common::ok;
#[cfg(feature = "point-cloud")]
use common::{fails, repo};

#[cfg(feature = "point-cloud")]
use std::path::Path;

#[cfg(feature = "point-cloud")]
fn write_config(dir: &Path, text: &str) -> String {
    let path = dir.join("test.toml");
    std::fs::write(&path, text).unwrap();
    path.to_string_lossy().into_owned()
}

#[cfg(feature = "point-cloud")]
fn data() -> String {
    repo()
        .join("data/living-room")
        .to_string_lossy()
        .into_owned()
}

#[test]
fn plugins_lists_every_linked_implementation() {
    let out = ok(&["plugins"]);
    // The names listed are those of the implementations this build was compiled with.
    for name in [
        "icl",
        "tum",
        "scannet",
        "replica",
        "synthetic",
        #[cfg(feature = "rosbag2")]
        "rosbag2",
        "ground-truth",
        #[cfg(feature = "colour-names")]
        "colour-names",
        #[cfg(feature = "label-text")]
        "label-text",
        #[cfg(feature = "graph")]
        "graph",
        #[cfg(feature = "point-cloud")]
        "point-cloud",
        #[cfg(feature = "python")]
        "python",
        "threshold",
    ] {
        assert!(
            out.contains(&format!("  {name} ")),
            "`{name}` missing from:\n{out}"
        );
    }
    assert!(
        out.starts_with("datasets ([dataset] kind = ...):\n"),
        "{out}"
    );
    // Optional implementations carry their feature, and those this build lacks are named.
    if cfg!(feature = "point-cloud") {
        assert!(out.contains("[feature `point-cloud`]"), "{out}");
    }
    if !cfg!(feature = "rosbag2") {
        assert!(out.contains("rosbag2 (feature `rosbag2`)"), "{out}");
    }
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn demo_writes_all_outputs_and_its_map_answers_queries() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("demo");
    let stdout = ok(&["demo", "--out", out_dir.to_str().unwrap()]);
    assert!(
        stdout.contains("30 frames: 30 tracked, 30 integrated, 0 skipped, 0 lost"),
        "{stdout}"
    );
    assert!(stdout.contains("\"white wall\": best"), "{stdout}");

    let trajectory = std::fs::read_to_string(out_dir.join("trajectory.tum")).unwrap();
    let lines: Vec<&str> = trajectory.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(lines.len(), 30);
    let last: Vec<f64> = lines[29]
        .split_whitespace()
        .map(|x| x.parse().unwrap())
        .collect();
    assert_eq!(last.len(), 8);
    // Frame 29 of the committed trajectory.log.
    assert!((last[1] + 0.05687721).abs() < 1e-5 && (last[2] + 0.52597026).abs() < 1e-5);

    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("stats.json")).unwrap())
            .unwrap();
    assert_eq!(stats["frames"]["total"], 30);
    assert_eq!(stats["frames"]["processed"], 30);
    assert_eq!(stats["frames"]["skipped"], 0);
    assert_eq!(stats["map"]["kind"], "point-cloud");
    assert_eq!(stats["map"]["dim"], 11);
    let points = stats["map"]["points"].as_u64().unwrap();
    assert!(points > 100_000 && points <= 1_000_000, "{points} points");
    assert!(stats["map"]["memory_bytes"].as_u64().unwrap() >= points * (12 + 3 + 44));
    // The map file's size, apart from the memory the map takes.
    let file_bytes = stats["map"]["file_bytes"].as_u64().unwrap();
    assert_eq!(
        file_bytes,
        std::fs::metadata(out_dir.join("map.vlem")).unwrap().len()
    );
    for stage in ["load", "track", "encode", "integrate"] {
        assert!(stats["mean_ms"][stage].as_f64().unwrap() > 0.0, "{stage}");
    }
    assert!(out_dir.join("query-white-wall.ply").is_file());

    let map = out_dir.join("map.vlem");
    let ply = tmp.path().join("white.ply");
    let answer = ok(&[
        "query",
        "--map",
        map.to_str().unwrap(),
        "--ply",
        ply.to_str().unwrap(),
        "white",
    ]);
    let best: f32 = answer
        .split("best ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        best > 0.9,
        "the living room has white walls, best score {best}:\n{answer}"
    );
    let ply = std::fs::read(&ply).unwrap();
    let header = String::from_utf8_lossy(&ply[..300]);
    assert!(
        header.contains(&format!("element vertex {points}")),
        "{header}"
    );

    // A query the encoder cannot embed is refused with the encoder's reason.
    let err = fails(&["query", "--map", map.to_str().unwrap(), "coffee machine"]);
    assert!(
        err.contains("cannot embed the query \"coffee machine\""),
        "{err}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn run_takes_a_dataset_and_a_frame_limit() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("run");
    let stdout = ok(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--dataset",
        &data(),
        "--max-frames",
        "3",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(
        stdout.contains("3 frames: 3 tracked, 3 integrated"),
        "{stdout}"
    );
    assert!(vlem_core::read_map_file(&out_dir.join("map.vlem")).is_ok());
}

#[cfg(feature = "point-cloud")]
#[test]
fn geometry_only_config_runs_and_its_map_refuses_text_queries() {
    let tmp = tempfile::tempdir().unwrap();
    let config = write_config(
        tmp.path(),
        &format!(
            "[dataset]\npath = \"{}\"\nmax_frames = 2\n[map]\nkind = \"point-cloud\"\n",
            data()
        ),
    );
    let out_dir = tmp.path().join("geo");
    ok(&[
        "run",
        "--config",
        &config,
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let map = out_dir.join("map.vlem");
    let err = fails(&["query", "--map", map.to_str().unwrap(), "red"]);
    assert!(
        err.contains("was mapped without an encoder (geometry only)"),
        "{err}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn config_errors_name_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    let out = out.to_str().unwrap();
    let run = |text: &str| {
        let config = write_config(tmp.path(), text);
        fails(&[
            "run",
            "--config",
            &config,
            "--dataset",
            &data(),
            "--out",
            out,
        ])
    };

    let err = run("[encoder]\nkind = \"siglip\"\n[map]\nkind = \"point-cloud\"\n");
    // The known encoders are those this build was compiled with.
    let known = [
        #[cfg(feature = "clip")]
        "clip",
        "colour-names",
        #[cfg(feature = "dinov3")]
        "dinov3",
        #[cfg(feature = "label-text")]
        "label-text",
        #[cfg(feature = "naradio")]
        "naradio",
        #[cfg(feature = "onnx")]
        "onnx",
    ]
    .join(", ");
    // `python` is registered wherever vlem-plugin-python is built with its feature, which a
    // workspace build does for the Python module whatever the `vlem` package's features are.
    let listed = err.replace(", python)", ")");
    assert!(
        listed.contains(&format!("unknown encoder `siglip` (known: {known})")),
        "{err}"
    );

    let err = run("[map]\nkind = \"point-cloud\"\nmax_pionts = 5\n");
    assert!(
        err.contains("[map] kind = \"point-cloud\": unknown field `max_pionts`"),
        "{err}"
    );
    // A stage's own keys are parsed by the stage; the error still names the file and the line.
    assert!(err.contains("test.toml, line 3)"), "{err}");

    let err = run("[dataset]\nstrid = 2\n");
    assert!(
        err.contains("line 2") && err.contains("unknown field `strid`"),
        "{err}"
    );

    let err = run("[encoder]\nkind = \"colour-names\"\n[map]\nkind = \"point-cloud\"\ndim = 512\n");
    assert!(
        err.contains("parameter `dim` is 512 but the encoder produces 11-d embeddings"),
        "{err}"
    );

    let config = write_config(tmp.path(), "[map]\nkind = \"point-cloud\"\n");
    let err = fails(&[
        "run",
        "--config",
        &config,
        "--dataset",
        "/nonexistent/vlem-data",
        "--out",
        out,
    ]);
    assert!(
        err.contains(
            "dataset folder /nonexistent/vlem-data does not exist (given with --dataset; check \
             the path)"
        ),
        "{err}"
    );
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    let in_config = write_config(
        &other,
        "[dataset]\npath = \"nowhere\"\n[map]\nkind = \"point-cloud\"\n",
    );
    let err = fails(&["run", "--config", &in_config, "--out", out]);
    assert!(
        err.contains("does not exist (from [dataset] path in the config")
            && err.contains("nowhere"),
        "{err}"
    );
    let err = fails(&["run", "--config", &config, "--out", out]);
    assert!(err.contains("no dataset: pass --dataset DIR"), "{err}");
}

#[cfg(feature = "point-cloud")]
#[test]
fn ground_truth_tracker_without_poses_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let dataset = tmp.path().join("no-poses");
    for sub in ["color", "depth"] {
        std::fs::create_dir_all(dataset.join(sub)).unwrap();
    }
    let src = repo().join("data/living-room");
    for (sub, ext) in [("color", "jpg"), ("depth", "png")] {
        let name = format!("00000.{ext}");
        std::fs::copy(src.join(sub).join(&name), dataset.join(sub).join(&name)).unwrap();
    }
    std::fs::copy(src.join("intrinsics.json"), dataset.join("intrinsics.json")).unwrap();
    let config = write_config(tmp.path(), "[map]\nkind = \"point-cloud\"\n");
    let out = tmp.path().join("o");
    let err = fails(&[
        "run",
        "--config",
        &config,
        "--dataset",
        dataset.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("the tracker `ground-truth` reads poses from the dataset"),
        "{err}"
    );
    assert!(err.contains("has no trajectory"), "{err}");
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn broken_map_files_are_refused_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let foreign = tmp.path().join("foreign.vlem");
    std::fs::write(&foreign, b"solid cube\nfacet normal 0 0 1\n").unwrap();
    let err = fails(&["query", "--map", foreign.to_str().unwrap(), "red"]);
    assert!(
        err.contains("not a vlem map file (wrong magic bytes)"),
        "{err}"
    );

    let out_dir = tmp.path().join("small");
    ok(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--max-frames",
        "1",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let map = out_dir.join("map.vlem");
    let bytes = std::fs::read(&map).unwrap();
    std::fs::write(&map, &bytes[..bytes.len() / 2]).unwrap();
    let err = fails(&["query", "--map", map.to_str().unwrap(), "red"]);
    assert!(err.contains("truncated"), "{err}");
    let missing = tmp.path().join("missing.vlem");
    let err = fails(&["query", "--map", missing.to_str().unwrap(), "red"]);
    assert!(
        err.contains("missing.vlem") && err.contains("No such file"),
        "{err}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn query_clusters_and_grasps() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("small");
    ok(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--max-frames",
        "3",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let map = out_dir.join("map.vlem");
    let map = map.to_str().unwrap();
    let plugins = ok(&["plugins"]);
    assert!(
        plugins.contains("  argmax ") && plugins.contains("  cluster "),
        "{plugins}"
    );

    // The default baseline "object" is each encoder's generic text: "grey" for colour-names, which
    // has no word for objects, so the defaults work; the answer is that of `--baseline grey`.
    let defaults = ok(&["query", "--map", map, "--segmenter", "cluster", "white"]);
    let grey = ok(&[
        "query",
        "--map",
        map,
        "--segmenter",
        "cluster",
        "--baseline",
        "grey",
        "white",
    ]);
    assert_eq!(defaults, grey);
    // A baseline it cannot embed: the error suggests one it can.
    let err = fails(&[
        "query",
        "--map",
        map,
        "--segmenter",
        "cluster",
        "--baseline",
        "chair",
        "white",
    ]);
    assert!(
        err.contains("cannot embed the query \"chair\"") && err.contains("e.g. to \"grey\""),
        "{err}"
    );
    let err = fails(&["query", "--map", map, "--segmenter", "kmeans", "white"]);
    assert!(err.contains("kmeans"), "{err}");

    let ply = tmp.path().join("white.ply");
    let stdout = ok(&[
        "query",
        "--map",
        map,
        "--segmenter",
        "cluster",
        "--baseline",
        "grey",
        "--grasp",
        "--ply",
        ply.to_str().unwrap(),
        "white",
    ]);
    assert!(stdout.contains("selected by `cluster`"), "{stdout}");
    let sets: usize = stdout
        .split(" point set")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(sets >= 1, "{stdout}");
    if sets > 1 {
        assert!(stdout.contains("  cluster 1: "), "{stdout}");
    }
    let grasped = stdout.contains("\"white\": grasp at (");
    assert!(
        grasped || stdout.contains("\"white\": no grasp: "),
        "{stdout}"
    );
    let bytes = std::fs::read(&ply).unwrap();
    let header = String::from_utf8_lossy(&bytes[..400]);
    assert_eq!(header.contains("draw the grasp"), grasped, "{header}");

    // argmax: one set per query; the grasp line is always there, with a pose or a reason.
    let stdout = ok(&[
        "query",
        "--map",
        map,
        "--segmenter",
        "argmax",
        "--baseline",
        "grey",
        "--grasp",
        "white",
        "brown",
    ]);
    assert!(
        stdout.contains("in 1 point set selected by `argmax`"),
        "{stdout}"
    );
    for text in ["white", "brown"] {
        assert!(
            stdout.contains(&format!("\"{text}\": grasp at ("))
                || stdout.contains(&format!("\"{text}\": no grasp: ")),
            "{stdout}"
        );
    }
}

#[cfg(all(
    feature = "colour-names",
    feature = "point-cloud",
    feature = "voxel",
    feature = "segment"
))]
#[test]
fn every_map_kind_runs_saves_and_answers_queries_at_f16() {
    for kind in ["point-cloud", "voxel", "segment"] {
        let tmp = tempfile::tempdir().unwrap();
        let config = write_config(
            tmp.path(),
            &format!(
                "[dataset]\npath = \"{}\"\nmax_frames = 2\n[encoder]\nkind = \"colour-names\"\n\
                 [map]\nkind = \"{kind}\"\nprecision = \"f16\"\n",
                data()
            ),
        );
        let out_dir = tmp.path().join(kind);
        ok(&[
            "run",
            "--config",
            &config,
            "--out",
            out_dir.to_str().unwrap(),
        ]);
        let stats: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out_dir.join("stats.json")).unwrap())
                .unwrap();
        assert_eq!(stats["map"]["kind"], kind);
        let points = stats["map"]["points"].as_u64().unwrap();
        assert!(points > 100, "{kind}: {points} points");
        let map = out_dir.join("map.vlem");
        let answer = ok(&["query", "--map", map.to_str().unwrap(), "white"]);
        let best: f32 = answer
            .split("best ")
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .unwrap()
            .parse()
            .unwrap();
        assert!(best > 0.9, "{kind}: best score for white {best}");
        assert!(
            answer.contains(&format!("{points} points")),
            "{kind}: {answer}"
        );
    }
}
