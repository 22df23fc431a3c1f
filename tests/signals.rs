//! Ctrl-C and SIGTERM during `vlem run`: the run stops at the next frame and writes the map, the
//! trajectory and the stats so far (`stopped: true`), as one set that replaces an earlier run's,
//! and exits with status 130; with `--serve-after`, a signal ends the serving once the run has
//! finished, with status 0.
#![cfg(feature = "cli")]
#![cfg(all(unix, feature = "colour-names", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use common::repo;

/// The demo's stages on the committed frames, replayed at `rate` frames a second (so a run lasts
/// long enough to be interrupted), or offline for `None`.
fn config(dir: &Path, rate: Option<f64>) -> std::path::PathBuf {
    let pipeline = match rate {
        Some(rate) => format!("mode = \"real-time\"\nframe_rate = {rate}\nqueue_capacity = 30"),
        None => "mode = \"offline\"".to_owned(),
    };
    let text = format!(
        "[dataset]\npath = \"{}\"\n\n[encoder]\nkind = \"colour-names\"\n\n[map]\nkind = \
         \"point-cloud\"\n\n[pipeline]\n{pipeline}\n",
        repo().join("data/living-room").display()
    );
    let path = dir.join("run.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `vlem run ... --serve 127.0.0.1:0 [extra]` and the address it serves on.
fn start(config: &Path, out: &Path, extra: &[&str]) -> (Child, String) {
    let mut args = vec![
        "run".as_ref(),
        "--config".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ];
    args.extend(["--no-colour-model", "--serve", "127.0.0.1:0"].map(std::ffi::OsStr::new));
    args.extend(extra.iter().map(std::ffi::OsStr::new));
    common::spawn_serving(&args)
}

fn status(address: &str) -> serde_json::Value {
    let mut response = ureq::get(format!("http://{address}/status"))
        .call()
        .unwrap();
    serde_json::from_str(&response.body_mut().read_to_string().unwrap()).unwrap()
}

fn signal(child: &Child, name: &str) {
    let sent = Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success());
}

/// Waits up to a minute for the child to exit; its status code.
fn exit_code(child: &mut Child) -> Option<i32> {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.code();
        }
        if start.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("vlem did not exit within a minute of the signal");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn an_interrupted_run_writes_what_it_has_as_one_set() {
    for signal_name in ["INT", "TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        // An earlier run's outputs that this run's would not overwrite.
        std::fs::write(out.join("reference.tum"), "earlier").unwrap();
        std::fs::write(out.join("query-earlier.ply"), "earlier").unwrap();
        std::fs::write(out.join("notes.txt"), "the user's").unwrap();

        let config = config(dir.path(), Some(3.0));
        let (mut child, address) = start(&config, &out, &[]);
        let start_time = Instant::now();
        while status(&address)["run"]["frames_integrated"].as_u64() < Some(2) {
            assert!(
                start_time.elapsed() < Duration::from_secs(60),
                "the run integrates"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        signal(&child, signal_name);
        assert_eq!(exit_code(&mut child), Some(130), "{signal_name}");

        let stats: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap())
                .unwrap();
        assert_eq!(stats["stopped"], true);
        let tracked = stats["frames"]["tracked"].as_u64().unwrap();
        let processed = stats["frames"]["processed"].as_u64().unwrap();
        assert!((2..30).contains(&processed), "{stats}");
        let trajectory = std::fs::read_to_string(out.join("trajectory.tum")).unwrap();
        let poses = trajectory.lines().filter(|l| !l.starts_with('#')).count() as u64;
        assert_eq!(poses, tracked);
        let map = vlem_core::read_map_file(&out.join("map.vlem")).unwrap();
        assert!(!map.is_empty());
        assert_eq!(map.metadata.frames_integrated as u64, processed);
        // The earlier run's files are gone; the user's file stays.
        assert!(!out.join("reference.tum").exists());
        assert!(!out.join("query-earlier.ply").exists());
        assert!(out.join("notes.txt").exists());
    }
}

#[test]
fn a_signal_ends_serve_after_once_the_run_has_finished() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let config = config(dir.path(), None);
    let (mut child, address) = start(&config, &out, &["--serve-after"]);
    let start_time = Instant::now();
    while !out.join("stats.json").exists() {
        assert!(
            start_time.elapsed() < Duration::from_secs(120),
            "the run finishes"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(status(&address)["run"]["state"], "finished");
    signal(&child, "TERM");
    assert_eq!(exit_code(&mut child), Some(0));
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap()).unwrap();
    assert_eq!(stats["stopped"], false);
    assert_eq!(stats["frames"]["processed"], 30);
}
