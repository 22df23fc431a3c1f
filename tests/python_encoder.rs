//! `vlem run` with an encoder written in Python (the binary embeds the interpreter): the numpy
//! copy of colour-names maps the committed frames and its map answers `vlem query` as the Rust
//! encoder's does; a raising Python encoder stops the run with the exception and its traceback.
//! Needs numpy in the interpreter pyo3 linked (CI installs it).
#![cfg(feature = "cli")]
#![cfg(all(feature = "python", feature = "colour-names", feature = "point-cloud"))]
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use common::{fails, ok, repo};

fn write_config(dir: &std::path::Path, encoder: &str) -> String {
    let frames = repo().join("data/living-room");
    let config = format!(
        "[dataset]\npath = {frames:?}\nmax_frames = 3\n\n[tracker]\nkind = \"ground-truth\"\n\n\
         {encoder}\n[map]\nkind = \"point-cloud\"\nmax_points = 200000\n"
    );
    let path = dir.join("config.toml");
    std::fs::write(&path, config).unwrap();
    path.display().to_string()
}

#[test]
fn a_python_encoder_maps_and_answers_like_the_rust_one() {
    let tmp = tempfile::tempdir().unwrap();
    let script = repo().join("examples/python/colour_names.py");
    let python = tmp.path().join("python");
    let rust = tmp.path().join("rust");
    std::fs::create_dir_all(&python).unwrap();
    std::fs::create_dir_all(&rust).unwrap();
    let python_config = write_config(
        &python,
        &format!("[encoder]\nkind = \"python\"\npath = {script:?}\nclass = \"ColourNames\"\n"),
    );
    let rust_config = write_config(&rust, "[encoder]\nkind = \"colour-names\"\n");
    for (config, out) in [(&python_config, &python), (&rust_config, &rust)] {
        ok(&[
            "run",
            "--config",
            config,
            "--out",
            &out.display().to_string(),
        ]);
    }
    let answer = |dir: &std::path::Path| {
        let map = dir.join("map.vlem").display().to_string();
        let out = ok(&["query", "--map", &map, "white wall", "brown"]);
        // The first line names the file and the encoder; the answers follow.
        out.lines().skip(1).map(str::to_owned).collect::<Vec<_>>()
    };
    assert_eq!(answer(&python), answer(&rust));
}

#[test]
fn an_exception_in_a_python_encoder_ends_the_run_with_its_traceback() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(
        tmp.path().join("boom.py"),
        "class Boom:\n    dim = 2\n    def encode_image(self, rgb, regions):\n        raise RuntimeError('out of GPU memory')\n",
    )
    .unwrap();
    let config = write_config(
        tmp.path(),
        "[encoder]\nkind = \"python\"\npath = \"boom.py\"\nclass = \"Boom\"\n",
    );
    let err = fails(&[
        "run",
        "--config",
        &config,
        "--out",
        &tmp.path().join("out").display().to_string(),
    ]);
    assert!(
        err.contains("Boom.encode_image raised RuntimeError: out of GPU memory"),
        "{err}"
    );
    assert!(err.contains("boom.py\", line 4"), "{err}");
}
