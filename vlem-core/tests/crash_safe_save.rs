//! Crash-safety of the map file, proven with real processes:
//!
//! - `saves_survive_sigkill_at_random_moments`: a child process saves two known multi-megabyte
//!   snapshots A and B alternately to one path and is killed with SIGKILL at a random moment, over
//!   and over (`VLEM_CRASH_ITERATIONS`, default 100; every eighth run starts without a file).
//!   After every kill the file either does not exist (only before the first save completed) or
//!   loads and equals A or B exactly, and precisely the save the child last reported or the one
//!   it was in the middle of. Temporary files left by the killed saves do not disturb later saves.
//! - `concurrent_saves_never_collide`: two processes and two threads save to one path at the same
//!   time while the file is read continuously: every save succeeds, every read is A or B, and no
//!   temporary file is left behind.
//! - `damaged_files_are_refused_with_a_clear_error`: truncations, flipped bytes and foreign files
//!   of a large map file are refused, naming the checksum, the truncation or the foreign format
//!   (the unit tests in `mapfile.rs` do the same on a two-point file).
//!
//! The child is this test binary itself, re-run with `VLEM_CRASH_CHILD_PATH` set and the filter of
//! the ignored test `crash_child_saves_alternately`.
#![cfg(unix)]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use vlem_core::{MapMetadata, MapSnapshot, StageConfig, read_map_file, write_map_file};

/// Where the child saves (set only for the child).
const CHILD_PATH: &str = "VLEM_CRASH_CHILD_PATH";
/// How many saves the child makes before exiting (unset: until killed, at most 60 s).
const CHILD_SAVES: &str = "VLEM_CRASH_CHILD_SAVES";
/// Kill iterations of `saves_survive_sigkill_at_random_moments`.
const ITERATIONS: &str = "VLEM_CRASH_ITERATIONS";
/// What the child prints after each completed save.
const SAVED: &str = "vlem-crash-test-saved";
/// Seed of the kill moments (default: from the clock, printed).
const SEED: &str = "VLEM_CRASH_SEED";

const POINTS: usize = 60_000;
const DIM: usize = 16;

/// Snapshot A (`which == 0`) or B (`which == 1`): 60 000 points of dimension 16, 4.7 MB on disk,
/// different in every array and in the metadata.
fn snapshot(which: u8) -> MapSnapshot {
    let mut state = 0x9E37_79B9_7F4A_7C15u64 ^ u64::from(which);
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let positions = (0..POINTS)
        .map(|_| [next() * 8.0 - 4.0, next() * 3.0, next() * 8.0 - 4.0])
        .collect();
    let colours = (0..POINTS)
        .map(|i| {
            [
                (i % 251) as u8,
                which.wrapping_mul(97),
                (i / 251 % 256) as u8,
            ]
        })
        .collect();
    let mut embeddings: Vec<f32> = (0..POINTS * DIM).map(|_| next() - 0.5).collect();
    for row in embeddings.chunks_exact_mut(DIM) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        row.iter_mut().for_each(|x| *x /= norm);
    }
    MapSnapshot {
        map_kind: if which == 0 { "point-cloud" } else { "voxel" }.into(),
        dim: DIM,
        positions,
        colours,
        embeddings,
        metadata: MapMetadata {
            encoder: Some(StageConfig::named("colour-names")),
            config_dir: None,
            frames_integrated: 1000 + usize::from(which),
            vlem_version: "crash-test".into(),
        },
    }
}

/// Which of A and B `path` holds; panics on anything else.
fn identify(path: &Path, a: &MapSnapshot, b: &MapSnapshot, context: &str) -> u8 {
    let loaded = read_map_file(path).unwrap_or_else(|e| panic!("{context}: the file is torn: {e}"));
    if loaded == *a {
        0
    } else if loaded == *b {
        1
    } else {
        panic!("{context}: the file loads but is neither A nor B")
    }
}

fn temp_files(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().contains(".tmp-"))
        })
        .collect()
}

/// The child: saves A, B, A, ... to `VLEM_CRASH_CHILD_PATH`, printing [`SAVED`] after each
/// completed save. Does nothing without the variable (e.g. under `cargo test -- --ignored`).
#[test]
#[ignore = "the child process of the crash tests; does nothing when run directly"]
fn crash_child_saves_alternately() {
    let Some(path) = std::env::var_os(CHILD_PATH) else {
        return;
    };
    let path = PathBuf::from(path);
    let saves: Option<usize> = std::env::var(CHILD_SAVES).ok().map(|s| s.parse().unwrap());
    let snapshots = [snapshot(0), snapshot(1)];
    // A safety net should the parent die without killing us.
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut k = 0usize;
    while saves.is_none_or(|n| k < n) && Instant::now() < deadline {
        write_map_file(&path, &snapshots[k % 2]).unwrap();
        println!("{SAVED} {k}");
        k += 1;
    }
}

fn spawn_child(path: &Path, saves: Option<usize>) -> Child {
    let mut command = Command::new(std::env::current_exe().unwrap());
    command
        .args([
            "--exact",
            "crash_child_saves_alternately",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_PATH, path)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    if let Some(n) = saves {
        command.env(CHILD_SAVES, n.to_string());
    }
    command.spawn().unwrap()
}

/// The number of completed saves a (finished) child reported.
fn completed_saves(child: &mut Child) -> usize {
    let mut out = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    // Not per line: libtest prints `test <name> ... ` before the test's first output.
    out.matches(SAVED).count()
}

#[test]
fn saves_survive_sigkill_at_random_moments() {
    let iterations: usize = std::env::var(ITERATIONS).map_or(100, |s| s.parse().unwrap());
    let seed: u64 = std::env::var(SEED).map_or_else(
        |_| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64
                | 1
        },
        |s| s.parse().unwrap(),
    );
    println!("{SEED}={seed}");
    let mut rng = seed;
    let mut random = move |below: u64| {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng % below.max(1)
    };
    let (a, b) = (snapshot(0), snapshot(1));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.vlem");

    // Calibrate: one save here, and the child's start-up, bound the kill moments.
    let probe = dir.path().join("probe.vlem");
    let started = Instant::now();
    write_map_file(&probe, &a).unwrap();
    let save = started.elapsed();
    std::fs::remove_file(&probe).unwrap();
    let started = Instant::now();
    let mut child = spawn_child(&dir.path().join("startup.vlem"), Some(1));
    assert!(child.wait().unwrap().success());
    assert_eq!(completed_saves(&mut child), 1);
    let startup = started.elapsed();
    std::fs::remove_file(dir.path().join("startup.vlem")).unwrap();
    let window = (startup + 2 * save).as_micros() as u64;
    println!(
        "one save {save:?}, child start-up and one save {startup:?}: kills within {window} us"
    );

    // What the file holds after the previous iteration (None: no save has completed yet).
    let mut on_disk: Option<u8> = None;
    let (mut absent, mut mid_save, mut killed_after) = (0, 0, [0usize; 4]);
    for iteration in 0..iterations {
        // Now and then start from no file, so kills before the first completed save are seen.
        if iteration % 8 == 0 && path.exists() {
            std::fs::remove_file(&path).unwrap();
            on_disk = None;
        }
        let temps_before = temp_files(dir.path()).len();
        let mut child = spawn_child(&path, None);
        std::thread::sleep(Duration::from_micros(random(window)));
        child.kill().unwrap();
        let status = child.wait().unwrap();
        assert!(!status.success(), "the child finished on its own: {status}");
        let saves = completed_saves(&mut child);
        killed_after[saves.min(3)] += 1;
        let context = format!("iteration {iteration} (seed {seed}), killed after {saves} saves");
        if temp_files(dir.path()).len() > temps_before {
            mid_save += 1;
        }
        if !path.exists() {
            assert!(
                on_disk.is_none() && saves == 0,
                "{context}: the file vanished"
            );
            absent += 1;
            continue;
        }
        let found = identify(&path, &a, &b, &context);
        // The last reported save, or the next one (renamed before the kill, not yet reported);
        // before any report this run, what the last run left, or this run's first save (A).
        let last = match saves {
            0 => on_disk,
            n => Some(((n - 1) % 2) as u8),
        };
        let in_flight = (saves % 2) as u8;
        assert!(
            last == Some(found) || found == in_flight,
            "{context}: the file holds {} but the last completed save was {last:?}",
            ["A", "B"][usize::from(found)]
        );
        on_disk = Some(found);
    }
    let leftovers = temp_files(dir.path());
    println!(
        "{iterations} kills: {absent} before any save completed, killed after 0/1/2/3+ saves: \
         {killed_after:?}, {mid_save} left a temporary file (killed mid-save); {} temporary files \
         left in all",
        leftovers.len()
    );
    // Any kill after a reported save: the file as it stands at the end can be absent even so,
    // since every eighth run starts from no file and the last few may all be killed early.
    assert!(
        killed_after[1..].iter().sum::<usize>() > 0,
        "no save ever completed: the kill window is too short"
    );
    assert!(mid_save > 0, "no kill landed in the middle of a save");

    // Leftover temporary files do not disturb the next saves, nor are they touched.
    write_map_file(&path, &b).unwrap();
    assert_eq!(identify(&path, &a, &b, "save after the kills"), 1);
    let mut child = spawn_child(&path, Some(3));
    assert!(child.wait().unwrap().success(), "a child save failed");
    assert_eq!(completed_saves(&mut child), 3);
    assert_eq!(identify(&path, &a, &b, "child saves after the kills"), 0);
    assert_eq!(temp_files(dir.path()), leftovers);
}

#[test]
fn concurrent_saves_never_collide() {
    let (a, b) = (snapshot(0), snapshot(1));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.vlem");
    write_map_file(&path, &a).unwrap();
    let mut children: Vec<Child> = (0..2).map(|_| spawn_child(&path, Some(12))).collect();
    let mut reads = 0;
    std::thread::scope(|s| {
        let savers: Vec<_> = [&a, &b]
            .into_iter()
            .map(|snap| {
                let path = &path;
                s.spawn(move || {
                    for _ in 0..12 {
                        write_map_file(path, snap).unwrap();
                    }
                })
            })
            .collect();
        while !savers.iter().all(|t| t.is_finished()) {
            identify(&path, &a, &b, "read during concurrent saves");
            reads += 1;
        }
        for t in savers {
            t.join().unwrap();
        }
    });
    for child in &mut children {
        assert!(child.wait().unwrap().success(), "a child's save failed");
        assert_eq!(completed_saves(child), 12);
    }
    identify(&path, &a, &b, "after concurrent saves");
    assert!(reads > 0);
    assert_eq!(temp_files(dir.path()), Vec::<PathBuf>::new());
}

#[test]
fn damaged_files_are_refused_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.vlem");
    write_map_file(&path, &snapshot(1)).unwrap();
    let good = std::fs::read(&path).unwrap();
    let header_end = 16 + u32::from_le_bytes([good[12], good[13], good[14], good[15]]) as usize;
    let refuse = |bytes: &[u8]| -> String {
        std::fs::write(&path, bytes).unwrap();
        read_map_file(&path).unwrap_err().to_string()
    };
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut random = move |below: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % below as u64) as usize
    };

    // Truncated anywhere, including inside the magic bytes and the header.
    let mut cuts = vec![0, 3, 8, 12, 16, header_end, header_end + 4, good.len() - 1];
    cuts.extend((0..24).map(|_| random(good.len())));
    for cut in cuts {
        let err = refuse(&good[..cut]);
        assert!(err.contains("truncated"), "cut at {cut}: {err}");
    }

    // One flipped byte anywhere: refused; in the payload and checksum always as a checksum
    // mismatch, in the prefix and header as that or as a length that no longer fits.
    let mut at = vec![8, 9, 12, 13, 17, header_end - 2, header_end, good.len() - 1];
    at.extend((0..40).map(|_| random(good.len() - 8) + 8));
    for i in at {
        let mut bad = good.clone();
        bad[i] ^= 1 << random(8);
        let err = refuse(&bad);
        if i >= header_end {
            assert!(err.contains("checksum mismatch"), "byte {i}: {err}");
        } else {
            assert!(
                ["checksum mismatch", "truncated", "trailing bytes"]
                    .iter()
                    .any(|m| err.contains(m)),
                "byte {i}: {err}"
            );
        }
        assert!(
            err.contains("corrupted") || err.contains("truncated") || err.contains("trailing"),
            "byte {i}: {err}"
        );
    }

    // Foreign files, including ones longer than a map file's prefix.
    let png = [&b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR"[..], &good[16..4096]].concat();
    let text = &b"hello, this is a text file\n"[..];
    for foreign in [&png[..], &b"x"[..], text, &good[1..]] {
        let err = refuse(foreign);
        assert!(err.contains("not a vlem map file"), "{err}");
    }

    // The intact file still loads, and a save over a damaged file replaces it.
    let err = refuse(&good[..100]);
    assert!(err.contains("truncated"), "{err}");
    write_map_file(&path, &snapshot(0)).unwrap();
    assert!(read_map_file(&path).unwrap() == snapshot(0));
}
