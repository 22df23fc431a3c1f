//! Helpers shared by the end-to-end tests of the `vlem` command.
#![allow(dead_code, reason = "each test file uses part of these")]

use std::path::PathBuf;
use std::process::{Command, Output};

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
