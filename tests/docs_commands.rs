//! Every `sh` block of README.md and docs/*.md runs as written, so the commands a newcomer copies
//! cannot go stale (they did: a README example failed on the data it pointed at).
//!
//! The blocks run with bash (`set -euo pipefail`), README.md first and then the docs pages in
//! name order, all in one fresh folder that holds the repository's inputs as a clone does
//! (`configs/`, `data/`, `studies/`, `examples/`, the test bags of `vlem-datasets/`; `../shared`
//! where the repository has one beside it), so a page may use what the demo wrote, as a reader who
//! ran it would. `vlem` on the `PATH` is the binary built with this test, and `cargo run --release
//! -- ARGS` (or `--example NAME -- ARGS`) runs that binary (or example): the commands are typed
//! as a user types them, not rewritten for the test.
//!
//! A fence may say after `sh`:
//! - `skip: REASON`: not run here (it needs a GPU, weights, a ROS graph, or it builds vlem); the
//!   reason is required;
//! - `features=a,b`: run when this build has those cargo features;
//! - `if-exists=PATH`: run when PATH exists (the sequence beside the repository).
#![cfg(feature = "cli")]
#![cfg(all(
    feature = "point-cloud",
    feature = "voxel",
    feature = "segment",
    feature = "colour-names",
    feature = "graph"
))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// How long one block may run before it counts as hung.
const BLOCK_TIMEOUT: Duration = Duration::from_secs(300);

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// README.md, then docs/*.md in name order.
fn pages() -> Vec<PathBuf> {
    let mut docs: Vec<PathBuf> = std::fs::read_dir(repo().join("docs"))
        .unwrap()
        .map(|entry| entry.unwrap().path())
        .filter(|path| path.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    std::iter::once(repo().join("README.md"))
        .chain(docs)
        .collect()
}

/// What a fence asks of its block.
#[derive(Debug, Default)]
struct Info {
    skip: Option<String>,
    features: Vec<String>,
    if_exists: Option<String>,
}

/// One `sh` block: where it is, what its fence says, its text.
#[derive(Debug)]
struct Block {
    place: String,
    info: Info,
    code: String,
}

fn parse_info(place: &str, info: &str) -> Info {
    let info = info.trim();
    if let Some(reason) = info.strip_prefix("skip:") {
        assert!(!reason.trim().is_empty(), "{place}: `skip:` needs a reason");
        return Info {
            skip: Some(reason.trim().to_owned()),
            ..Info::default()
        };
    }
    let mut parsed = Info::default();
    for word in info.split_whitespace() {
        match word.split_once('=') {
            Some(("features", list)) => {
                parsed.features = list.split(',').map(str::to_owned).collect();
            }
            Some(("if-exists", path)) => parsed.if_exists = Some(path.to_owned()),
            _ => {
                panic!("{place}: unknown fence word {word:?} (skip: REASON, features=, if-exists=)")
            }
        }
    }
    parsed
}

/// The `sh` blocks of a page (fences of other languages are output, synopses or configs).
fn sh_blocks(page: &Path) -> Vec<Block> {
    let text = std::fs::read_to_string(page).unwrap();
    let name = page.strip_prefix(repo()).unwrap().display().to_string();
    let mut blocks = Vec::new();
    let mut lines = text.lines().enumerate();
    while let Some((number, line)) = lines.next() {
        let Some(fence) = line.strip_prefix("```") else {
            continue;
        };
        let mut code = String::new();
        for (_, body) in lines.by_ref() {
            if body.starts_with("```") {
                break;
            }
            code.push_str(body);
            code.push('\n');
        }
        let language = fence.split_whitespace().next().unwrap_or("");
        let place = format!("{name}:{}", number + 1);
        assert!(
            !matches!(language, "bash" | "shell" | "console" | "sh-session"),
            "{place}: write shell commands as ```sh so this test runs them"
        );
        if language == "sh" {
            let info = parse_info(&place, &fence[2..]);
            blocks.push(Block { place, info, code });
        }
    }
    blocks
}

/// Whether this build has a cargo feature a fence names.
fn compiled(feature: &str) -> bool {
    match feature {
        "rerun" => cfg!(feature = "rerun"),
        "rosbag2" => cfg!(feature = "rosbag2"),
        "ros2" => cfg!(feature = "ros2"),
        "label-text" => cfg!(feature = "label-text"),
        "clip" => cfg!(feature = "clip"),
        "onnx" => cfg!(feature = "onnx"),
        "sam" => cfg!(feature = "sam"),
        "dinov3" => cfg!(feature = "dinov3"),
        "naradio" => cfg!(feature = "naradio"),
        "python" => cfg!(feature = "python"),
        other => panic!("a fence names the unknown feature {other:?}"),
    }
}

/// The folder the blocks run in: `root/repo` with the repository's inputs, `root/bin` with
/// `vlem` and the `cargo` stand-in.
fn workspace(root: &Path) -> (PathBuf, PathBuf) {
    let work = root.join("repo");
    let bin = root.join("bin");
    std::fs::create_dir_all(&work).unwrap();
    std::fs::create_dir_all(&bin).unwrap();
    for input in ["configs", "data", "studies", "examples", "vlem-datasets"] {
        std::os::unix::fs::symlink(repo().join(input), work.join(input)).unwrap();
    }
    let shared = repo().join("../shared");
    if shared.is_dir() {
        std::os::unix::fs::symlink(shared.canonicalize().unwrap(), root.join("shared")).unwrap();
    }
    let vlem = PathBuf::from(env!("CARGO_BIN_EXE_vlem"));
    std::os::unix::fs::symlink(&vlem, bin.join("vlem")).unwrap();
    // `cargo test` builds the examples next to the binary's folder.
    let examples = vlem.parent().unwrap().join("examples");
    let cargo = format!(
        "#!/bin/sh\n\
         # The docs' `cargo run --release -- ARGS` and `--example NAME -- ARGS`, on what this test\n\
         # was built with; anything else a runnable block must not ask for.\n\
         if [ \"$1 $2\" = \"run --release\" ]; then\n\
         \x20 shift 2\n\
         \x20 if [ \"$1\" = --example ]; then\n\
         \x20   name=$2; shift 2; [ \"$1\" = -- ] && shift\n\
         \x20   [ -x \"{examples}/$name\" ] || {{ echo \"docs test: no example $name in {examples} \
         (a whole cargo test builds the examples; --test alone does not)\" >&2; exit 2; }}\n\
         \x20   exec \"{examples}/$name\" \"$@\"\n\
         \x20 fi\n\
         \x20 [ \"$1\" = -- ] && shift\n\
         \x20 exec vlem \"$@\"\n\
         fi\n\
         echo \"docs test: 'cargo $*' builds; mark its block 'skip: REASON'\" >&2\n\
         exit 2\n",
        examples = examples.display()
    );
    std::fs::write(bin.join("cargo"), cargo).unwrap();
    let chmod = Command::new("chmod")
        .arg("+x")
        .arg(bin.join("cargo"))
        .status()
        .unwrap();
    assert!(chmod.success());
    (work, bin)
}

/// Runs one block; panics with its output when it fails or hangs.
fn run(block: &Block, work: &Path, bin: &Path) {
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    // Background jobs a block starts (a server) end with it, also when it fails.
    let script = format!(
        "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n{}",
        block.code
    );
    let log = work.join(".block.log");
    let mut child = Command::new("bash")
        .arg("-c")
        .arg(&script)
        .current_dir(work)
        .env("PATH", path)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&log).unwrap())
        .stderr(std::fs::File::options().append(true).open(&log).unwrap())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if start.elapsed() > BLOCK_TIMEOUT {
            child.kill().unwrap();
            child.wait().unwrap();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let output = std::fs::read_to_string(&log).unwrap_or_default();
    let tail: String = output
        .chars()
        .rev()
        .take(4000)
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    match status {
        Some(status) if status.success() => {}
        Some(status) => panic!(
            "{} failed ({status}):\n{}\n--- output:\n{tail}",
            block.place, block.code
        ),
        None => panic!(
            "{} ran past {BLOCK_TIMEOUT:?}:\n{}\n--- output:\n{tail}",
            block.place, block.code
        ),
    }
}

#[test]
fn every_sh_block_of_the_readme_and_docs_runs_as_written() {
    let root = tempfile::tempdir().unwrap();
    let (work, bin) = workspace(root.path());
    let mut ran = Vec::new();
    let mut left_out = Vec::new();
    for page in pages() {
        for block in sh_blocks(&page) {
            if let Some(reason) = &block.info.skip {
                left_out.push(format!("{}: {reason}", block.place));
                continue;
            }
            if let Some(missing) = block.info.features.iter().find(|f| !compiled(f)) {
                left_out.push(format!(
                    "{}: feature `{missing}` not in this build",
                    block.place
                ));
                continue;
            }
            if let Some(path) = &block.info.if_exists
                && !work.join(path).exists()
            {
                left_out.push(format!("{}: no {path}", block.place));
                continue;
            }
            run(&block, &work, &bin);
            ran.push(block.place);
        }
    }
    println!("ran {} blocks: {}", ran.len(), ran.join(", "));
    println!("left out {}:\n  {}", left_out.len(), left_out.join("\n  "));
    // The tour's own outputs, as the README says.
    assert!(work.join("out/demo/map.vlem").is_file());
    assert!(ran.iter().any(|place| place.starts_with("README.md")));
}

#[test]
fn the_readme_test_command_is_the_one_ci_runs() {
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let command = readme
        .lines()
        .find(|line| line.contains("cargo test --profile ci --workspace --features ci"))
        .unwrap();
    let ci = std::fs::read_to_string(repo().join(".ci/run")).unwrap();
    // CI only keeps pip quiet.
    let ci = ci.replace("--quiet --disable-pip-version-check ", "");
    assert!(
        ci.lines().any(|line| line == command),
        "README's test command is not a line of .ci/run:\n{command}"
    );
}
