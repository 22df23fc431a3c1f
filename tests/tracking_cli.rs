//! `vlem run` with the dense trackers: tracking-only configs on a dataset without poses, the
//! frame-to-model colour model, the synthetic scene, and mapping on estimated poses.
#![cfg(feature = "cli")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use common::{ok, repo};

use std::path::Path;

/// The first `n` committed living-room frames without their trajectory.
fn frames_without_poses(dir: &Path, n: usize) {
    let source = repo().join("data/living-room");
    for sub in ["color", "depth"] {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
        let mut names: Vec<_> = std::fs::read_dir(source.join(sub))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        for name in names.into_iter().take(n) {
            std::fs::copy(source.join(sub).join(&name), dir.join(sub).join(&name)).unwrap();
        }
    }
    std::fs::copy(source.join("intrinsics.json"), dir.join("intrinsics.json")).unwrap();
}

fn tum_lines(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
        .collect()
}

#[test]
fn tracking_configs_run_on_a_dataset_without_poses() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("no-poses");
    frames_without_poses(&data, 6);
    for tracker in ["odometry", "frame-to-model"] {
        let out = tmp.path().join(tracker);
        let config = format!("configs/track-{tracker}.toml");
        let printed = ok(&[
            "run",
            "--config",
            &config,
            "--dataset",
            data.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(printed.contains("6 tracked"), "{printed}");
        let poses = tum_lines(&out.join("trajectory.tum"));
        assert_eq!(poses.len(), 6);
        // Without dataset poses tracking starts at the identity, and the camera moves a little.
        assert_eq!(&poses[0][1..], &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        let moved = poses[5][1..4].iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(moved > 1e-3 && moved < 0.2, "{tracker}: {moved} m");
        assert!(
            !out.join("reference.tum").exists(),
            "no reference without poses"
        );
        let stats: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap())
                .unwrap();
        assert_eq!(stats["frames"]["lost"], 0);
        assert_eq!(stats["lost_frames"].as_array().unwrap().len(), 0);
        assert_eq!(
            out.join("colour-model.ply").exists(),
            tracker == "frame-to-model"
        );
    }
    let ply = std::fs::read(tmp.path().join("frame-to-model/colour-model.ply")).unwrap();
    let header = String::from_utf8_lossy(&ply[..300]).into_owned();
    assert!(header.contains("element face"), "{header}");
}

#[test]
fn the_synthetic_scene_is_tracked_against_its_exact_reference() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("synthetic.toml");
    std::fs::write(
        &config,
        "[dataset]\nkind = \"synthetic\"\n[dataset.synthetic]\nseed = 5\nframes = 20\n\
         width = 320\nheight = 240\n[tracker]\nkind = \"frame-to-model\"\n",
    )
    .unwrap();
    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    ok(&[
        "run",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out_s,
        "--no-colour-model",
    ]);
    assert!(!out.join("colour-model.ply").exists());
    let json = tmp.path().join("eval.json");
    ok(&[
        "eval",
        "trajectory",
        "--estimate",
        out.join("trajectory.tum").to_str().unwrap(),
        "--reference",
        out.join("reference.tum").to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    let ate = eval["ate"]["position_m"]["rmse"].as_f64().unwrap();
    assert!(ate < 0.005, "ATE {ate} m");
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn the_embedding_map_can_take_its_poses_from_odometry() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("map-on-odometry.toml");
    let text = std::fs::read_to_string(repo().join("configs/demo.toml"))
        .unwrap()
        .replace("kind = \"ground-truth\"", "kind = \"odometry\"")
        .replace(
            "../data/living-room",
            repo().join("data/living-room").to_str().unwrap(),
        );
    std::fs::write(&config, text).unwrap();
    let out = tmp.path().join("out");
    let printed = ok(&[
        "run",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--max-frames",
        "4",
    ]);
    assert!(printed.contains("4 integrated"), "{printed}");
    assert!(out.join("map.vlem").exists());
    assert_eq!(tum_lines(&out.join("reference.tum")).len(), 4);
}
