//! `vlem query --interactive`: many queries on one loaded map, commands that change the
//! selection, errors that do not end the session, and a PLY per query.
#![cfg(feature = "cli")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use std::io::Write;
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use std::process::{Command, Stdio};

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
use common::{ok, repo};

/// Runs an interactive session on `map` with `input` on stdin; returns (success, stdout, stderr).
#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn session(args: &[&str], input: &str) -> (bool, String, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_vlem"))
        .args(args)
        .current_dir(repo())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
fn hits(stdout: &str, query: &str) -> Vec<usize> {
    stdout
        .lines()
        .filter(|l| l.starts_with(&format!("\"{query}\": best")))
        .map(|l| {
            l.split("; ")
                .nth(1)
                .and_then(|s| s.split_whitespace().next())
                .unwrap()
                .parse()
                .unwrap()
        })
        .collect()
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn interactive_session_answers_many_queries_on_one_map() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    ok(&["demo", "--out", out.to_str().unwrap()]);
    let map = out.join("map.vlem");
    let ply = tmp.path().join("heat.ply");
    let (success, stdout, stderr) = session(
        &[
            "query",
            "--map",
            map.to_str().unwrap(),
            "--interactive",
            "--ply",
            ply.to_str().unwrap(),
        ],
        "white\n\
         :threshold 0.95\n\
         white\n\
         coffee machine\n\
         :threshold lots\n\
         :frobnicate\n\
         \n\
         brown\n\
         :quit\n\
         red\n",
    );
    assert!(success, "{stdout}\n{stderr}");
    // The map was loaded once, and every query before :quit was answered.
    assert_eq!(
        stdout.matches("points, 11-d embeddings").count(),
        1,
        "{stdout}"
    );
    let white = hits(&stdout, "white");
    assert_eq!(white.len(), 2, "{stdout}");
    assert!(
        white[1] < white[0],
        "a higher threshold must select fewer points: {white:?}\n{stdout}"
    );
    assert_eq!(hits(&stdout, "brown").len(), 1, "{stdout}");
    assert!(
        hits(&stdout, "red").is_empty(),
        "queries after :quit: {stdout}"
    );
    // Errors are reported and the session goes on.
    assert!(
        stdout.contains("error: cannot embed the query \"coffee machine\""),
        "{stdout}"
    );
    assert!(
        stdout.contains("error: :threshold needs a number"),
        "{stdout}"
    );
    assert!(
        stdout.contains("error: unknown command :frobnicate"),
        "{stdout}"
    );
    // One heatmap per query, named after it.
    for name in ["heat-white.ply", "heat-brown.ply"] {
        let bytes = std::fs::read(tmp.path().join(name)).unwrap();
        assert!(bytes.starts_with(b"ply\n"), "{name}");
    }
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn interactive_session_ends_at_end_of_input_and_takes_command_line_queries_first() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    ok(&["demo", "--out", out.to_str().unwrap()]);
    let map = out.join("map.vlem");
    let (success, stdout, stderr) = session(
        &[
            "query",
            "--map",
            map.to_str().unwrap(),
            "--interactive",
            "brown",
        ],
        ":segmenter argmax\n:baseline white\nbrown\n:segmenter nonsense\nbrown\n",
    );
    assert!(success, "{stdout}\n{stderr}");
    let lines: Vec<&str> = stdout
        .lines()
        .filter(|l| l.starts_with("\"brown\": best"))
        .collect();
    assert_eq!(lines.len(), 3, "{stdout}");
    assert!(lines[0].contains("selected by `threshold`"), "{stdout}");
    assert!(lines[1].contains("selected by `argmax`"), "{stdout}");
    // An unknown segmenter is refused with the known names, and the last good one stays.
    assert!(
        stdout.contains("error: ") && stdout.contains("threshold"),
        "{stdout}"
    );
    assert!(lines[2].contains("selected by `argmax`"), "{stdout}");
}

#[test]
fn query_needs_texts_unless_interactive() {
    let tmp = tempfile::tempdir().unwrap();
    let err = common::fails(&[
        "query",
        "--map",
        tmp.path().join("m.vlem").to_str().unwrap(),
    ]);
    assert!(
        err.contains("--interactive") || err.contains("<TEXT>"),
        "{err}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn each_segmenter_keeps_its_own_threshold_and_show_prints_the_settings() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    ok(&["demo", "--out", out.to_str().unwrap()]);
    let map = out.join("map.vlem");
    let (success, stdout, stderr) = session(
        &["query", "--map", map.to_str().unwrap(), "--interactive"],
        ":threshold 0.9\n\
         :segmenter cluster\n\
         :segmenter threshold\n\
         :quit\n",
    );
    assert!(success, "{stdout}\n{stderr}");
    // 0.9 was typed for `threshold`: `cluster` keeps its own default (not a minimum of 0.9), and
    // its baseline is the encoder's generic text; back on `threshold`, 0.9 is back too.
    let expected = "threshold 0.9 for segmenter `threshold`\n\
                    segmenter `cluster`\n\
                    segmenter `cluster`, threshold its default\n\
                    baseline \"grey\"\n\
                    grasp off\n\
                    segmenter `threshold`\n\
                    segmenter `threshold`, threshold 0.9\n\
                    grasp off\n";
    assert!(stdout.contains(expected), "{stdout}");
}
