//! Helpers shared by the end-to-end tests of the `vlem` command.
#![allow(dead_code, reason = "each test file uses part of these")]

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

/// The repository root (the `vlem` package).
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs the `vlem` binary in the repository root.
pub fn vlem(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vlem"))
        .args(args)
        .current_dir(repo())
        .output()
        .expect("the vlem binary runs")
}

/// Runs `vlem`, expects success and returns its stdout.
pub fn ok(args: &[&str]) -> String {
    let out = vlem(args);
    assert!(
        out.status.success(),
        "vlem {args:?} failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `vlem`, expects failure and returns its stderr.
pub fn fails(args: &[&str]) -> String {
    let out = vlem(args);
    assert!(
        !out.status.success(),
        "vlem {args:?} succeeded but should fail:\n{}",
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Starts `vlem ARGS` (a run with `--serve 127.0.0.1:0`) in the repository root and returns the
/// child once it has printed the address it serves on, with that address (`127.0.0.1:PORT`).
pub fn spawn_serving<S: AsRef<OsStr>>(args: &[S]) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_vlem"))
        .args(args)
        .current_dir(repo())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the vlem binary runs");
    let stderr = child.stderr.take().expect("stderr is piped");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("serving the live map on http://").nth(1) {
                let address = rest
                    .split_whitespace()
                    .next()
                    .unwrap_or_default()
                    .to_owned();
                let _ = tx.send(address);
            }
        }
    });
    let address = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("vlem run prints the address it serves on");
    (child, address)
}

/// The shipped GPU config `name` (in `configs/`) with its encoder's `model_dir` set to
/// `model_dir`, and the build context of `configs/`. In a build without `cuda`, building it fails
/// naming the device that was asked for and the feature that brings it (checked here); callers
/// switch the devices to `cpu` ([`on_the_cpu`]) to build it on the CPU.
pub fn gpu_config(name: &str, model_dir: &str) -> (vlem_core::Config, vlem_core::BuildContext) {
    let dir = repo().join("configs");
    let mut config = vlem_core::Config::from_file(&dir.join(name)).expect("the config parses");
    let ctx = vlem_core::BuildContext {
        config_dir: dir,
        embedding_dim: None,
    };
    config
        .encoder
        .as_mut()
        .expect("the config has an [encoder]")
        .params
        .insert("model_dir".into(), model_dir.into());
    if !cfg!(feature = "cuda") {
        let err = vlem_core::pipeline::Pipeline::from_config(&config, &ctx)
            .err()
            .expect("a build without cuda refuses a cuda device")
            .to_string();
        assert!(
            err.contains("device = \"cuda:0\" was asked for"),
            "{name}: {err}"
        );
        assert!(err.contains("--features cuda"), "{name}: {err}");
    }
    let map = config.map.as_ref().expect("the config has a [map]");
    assert_eq!(map.params["device"].as_str(), Some("cuda"), "{name}");
    assert_eq!(map.params["precision"].as_str(), Some("f16"), "{name}");
    (config, ctx)
}

/// Switches every stage of `config` that names a `device` to the CPU.
pub fn on_the_cpu(config: &mut vlem_core::Config) {
    let stages = [
        Some(&mut config.tracker),
        config.proposer.as_mut(),
        config.encoder.as_mut(),
        config.map.as_mut(),
    ];
    for stage in stages.into_iter().flatten() {
        if stage.params.contains_key("device") {
            stage.params.insert("device".into(), "cpu".into());
        }
    }
}
