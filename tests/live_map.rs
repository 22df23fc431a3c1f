//! The live map handle while a pipeline runs: the committed living-room frames, ground-truth
//! poses, the colour-names encoder and the point-cloud map (the demo's stages), with query,
//! snapshot and save threads working through `LiveMap` while the embedding thread integrates.
//! Checks that concurrent queries succeed, that every snapshot and every answer belongs to one
//! whole integrated frame count, that a map saved mid-run reads back, and that nothing deadlocks
//! when the run ends with queries in flight.
#![cfg(all(feature = "colour-names", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

// Link the crates whose stages the config names (registrations of unreferenced crates vanish).
use vlem_maps as _;
use vlem_plugin_colour_names as _;
use vlem_query as _;
use vlem_trackers as _;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, mpsc};
use std::time::Duration;

use vlem_core::live::{LiveMap, RunState};
use vlem_core::pipeline::{Pipeline, Progress};
use vlem_core::{EmbeddingMap, Frame, Pose, Region, RunObserver};
use vlem_query::answer::{AnswerOptions, Selection, answer_live};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The demo pipeline and its dataset.
fn demo() -> (Pipeline, Box<dyn vlem_core::FrameSource>) {
    let (config, ctx) = vlem_core::load_config(&repo().join("configs/demo.toml")).unwrap();
    let dir = vlem_datasets::dataset_folder(&config, &ctx, None).unwrap();
    let source = vlem_datasets::open(&config.dataset, &dir).unwrap();
    (Pipeline::from_config(&config, &ctx).unwrap(), source)
}

/// Records the map size after every integrated frame: the states a reader may observe.
#[derive(Default)]
struct Sizes(Mutex<BTreeMap<usize, usize>>);

impl RunObserver for Sizes {
    fn frame_integrated(&self, _: &Frame, _: &Pose, _: &[Region], map: &dyn EmbeddingMap) {
        let mut sizes = self.0.lock().unwrap();
        let frames = sizes.len() + 1;
        sizes.insert(frames, map.len());
    }
}

fn no_progress(_: Progress) {}

/// Runs `work` on `threads` threads, each looping until the run is over (and then once more, so
/// some calls are in flight as it ends), while the pipeline maps every frame; fails instead of
/// hanging if anything deadlocks.
fn while_mapping<T: Send>(
    threads: usize,
    work: impl Fn(&LiveMap) -> T + Sync,
) -> (Vec<Vec<T>>, BTreeMap<usize, usize>, LiveMap) {
    let (mut pipeline, mut source) = demo();
    let live = pipeline.live();
    let sizes = Sizes::default();
    let done = AtomicBool::new(false);
    let (finished, watchdog) = mpsc::channel();
    let results = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                let (live, done, work) = (live.clone(), &done, &work);
                scope.spawn(move || {
                    let mut out = Vec::new();
                    loop {
                        let last = done.load(Ordering::Acquire);
                        out.push(work(&live));
                        if last {
                            return out;
                        }
                    }
                })
            })
            .collect();
        let report = pipeline
            .run_observed(source.as_mut(), None, &no_progress, &sizes)
            .unwrap();
        assert_eq!(report.frames_processed, report.frames_total);
        done.store(true, Ordering::Release);
        let guard = scope.spawn(move || {
            watchdog
                .recv_timeout(Duration::from_secs(120))
                .expect("the query threads finish after the run (no deadlock)");
        });
        let results = workers.into_iter().map(|w| w.join().unwrap()).collect();
        finished.send(()).unwrap();
        guard.join().unwrap();
        results
    });
    let sizes = sizes.0.into_inner().unwrap();
    (results, sizes, live)
}

#[test]
fn concurrent_queries_see_whole_frames_and_the_run_ends_cleanly() {
    let selection = Selection::threshold();
    let ctx = vlem_core::BuildContext::default();
    let segmenter = selection.build(&ctx).unwrap();
    let texts = vec!["white wall".to_owned(), "brown".to_owned()];
    let (results, sizes, live) = while_mapping(3, |live| {
        answer_live(live, segmenter.as_ref(), &texts, &AnswerOptions::default())
            .map(|(answered, positions)| (answered.answer, positions.len()))
    });
    let mut answered_during_run = 0;
    for thread in &results {
        let mut last_frames = 0;
        for result in thread {
            let (answer, points) = result.as_ref().unwrap();
            // Each answer is for one state of the map: its point count is the map's size after
            // exactly that many integrated frames.
            let frames = answer.frames_integrated;
            let expected = if frames == 0 { 0 } else { sizes[&frames] };
            assert_eq!(answer.points, expected, "answer after {frames} frames");
            assert_eq!(*points, expected);
            assert_eq!(answer.queries.len(), 2);
            assert!(frames >= last_frames, "frames integrated never go back");
            last_frames = frames;
            if frames > 0 && frames < sizes.len() {
                answered_during_run += 1;
            }
        }
        // The last call came after the run: it sees every frame.
        let (last, _) = thread.last().unwrap().as_ref().unwrap();
        assert_eq!(last.frames_integrated, sizes.len());
    }
    assert!(
        answered_during_run > 0,
        "some queries were answered mid-run"
    );
    let status = live.status();
    assert_eq!(status.state, RunState::Finished);
    assert_eq!(status.frames_integrated, sizes.len());
    assert_eq!(status.frames_tracked, status.frames_total);
    let pose = live.latest_pose().unwrap();
    assert_eq!(pose.index + 1, status.frames_total);
    assert!(!pose.lost);
}

#[test]
fn snapshots_and_saves_mid_run_belong_to_one_frame_count() {
    let dir = tempfile::tempdir().unwrap();
    let counter = std::sync::atomic::AtomicUsize::new(0);
    let (results, sizes, live) = while_mapping(2, |live| {
        let n = counter.fetch_add(1, Ordering::Relaxed);
        if n.is_multiple_of(2) {
            let snapshot = live.snapshot().unwrap();
            (
                snapshot.metadata.frames_integrated,
                snapshot.len(),
                snapshot.embeddings.len() / snapshot.dim.max(1),
                None,
            )
        } else {
            let path = dir.path().join(format!("mid-run-{n}.vlem"));
            let saved = live.save(&path).unwrap();
            (
                saved.frames_integrated,
                saved.points,
                saved.points,
                Some(path),
            )
        }
    });
    let mut saved_files = 0;
    for (frames, points, embedded, path) in results.into_iter().flatten() {
        let expected = if frames == 0 { 0 } else { sizes[&frames] };
        assert_eq!(points, expected, "snapshot after {frames} frames");
        assert_eq!(embedded, expected, "one embedding per point");
        if let Some(path) = path {
            let read = vlem_core::read_map_file(&path).unwrap();
            check_saved(&read, &path, frames, expected);
            saved_files += 1;
        }
    }
    assert!(saved_files > 0);
    // After the run, the saved map carries what `vlem query` needs to rebuild the encoder.
    let final_path = dir.path().join("final.vlem");
    live.save(&final_path).unwrap();
    let read = vlem_core::read_map_file(&final_path).unwrap();
    check_saved(&read, &final_path, sizes.len(), sizes[&sizes.len()]);
    assert_eq!(read.metadata.encoder.as_ref().unwrap().kind, "colour-names");
    assert!(vlem_query::answer::encoder_for_map(&read.metadata, "final.vlem").is_ok());
}

fn check_saved(read: &vlem_core::MapSnapshot, path: &Path, frames: usize, points: usize) {
    assert_eq!(
        read.metadata.frames_integrated,
        frames,
        "{}",
        path.display()
    );
    assert_eq!(read.len(), points, "{}", path.display());
    assert_eq!(read.map_kind, "point-cloud");
    assert_eq!(read.embeddings.len(), read.len() * read.dim);
}

#[test]
fn the_pose_stream_and_counters_are_visible_during_the_run() {
    let (results, sizes, _) = while_mapping(1, |live| live.status());
    let statuses = &results[0];
    let total = statuses.last().unwrap().frames_total;
    assert_eq!(statuses.last().unwrap().frames_integrated, sizes.len());
    for status in statuses {
        assert!(status.frames_integrated <= status.frames_tracked);
        assert!(status.frames_tracked <= total);
        if let Some(pose) = status.latest_pose {
            assert!(pose.index < total);
            assert!(pose.pose.translation.vector.iter().all(|x| x.is_finite()));
        }
    }
}

#[test]
fn a_pipeline_without_a_map_says_so_through_the_handle() {
    let mut config = vlem_core::Config::from_file(&repo().join("configs/demo.toml")).unwrap();
    config.map = None;
    config.encoder = None;
    let ctx = vlem_core::BuildContext::for_config_dir(&repo().join("configs")).unwrap();
    let pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let live = pipeline.live();
    assert!(!live.has_map());
    let err = live.snapshot().unwrap_err().to_string();
    assert!(err.contains("no [map]"), "{err}");
    let segmenter = Selection::threshold().build(&ctx).unwrap();
    let err = answer_live(
        &live,
        segmenter.as_ref(),
        &["x".into()],
        &AnswerOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("without an encoder"), "{err}");
}

/// `LiveMap::summary` (what `/status` reports) never takes the map's lock: it answers while a
/// long read holds the map and the run's next integration waits for it (std's lock then makes
/// every new reader wait too), and it matches the map after the run.
#[test]
fn the_summary_answers_while_a_reader_holds_the_map_and_a_writer_waits() {
    let (mut pipeline, mut source) = demo();
    let live = pipeline.live();
    assert_eq!(live.summary().unwrap().points, 0);
    let (sent, received) = mpsc::channel();
    std::thread::scope(|scope| {
        live.read(|_| {
            scope.spawn(|| pipeline.run(source.as_mut(), None, &no_progress).unwrap());
            // Long enough for the run to reach its first integration and wait for the lock.
            std::thread::sleep(Duration::from_millis(500));
            let reader = live.clone();
            scope.spawn(move || sent.send(reader.summary()).unwrap());
            let summary = received
                .recv_timeout(Duration::from_secs(60))
                .expect("the summary answers without the map's lock")
                .unwrap();
            assert_eq!((summary.kind.as_str(), summary.points), ("point-cloud", 0));
        })
        .unwrap();
    });
    let summary = live.summary().unwrap();
    let status = live.status();
    assert_eq!(summary.points, status.map_len);
    assert_eq!(summary.frames_integrated, status.frames_integrated);
    assert_eq!(summary.dim, 11);
    assert_eq!(status.state, RunState::Finished);
}

/// An owner that writes outputs after the run announces them: the run then ends `saving`, and
/// `finished` only once the owner says they are written.
#[test]
fn announced_outputs_hold_finished_until_they_are_written() {
    let (mut pipeline, mut source) = demo();
    let live = pipeline.live();
    live.announce_outputs();
    pipeline
        .run(source.as_mut(), Some(3), &no_progress)
        .unwrap();
    assert_eq!(live.status().state, RunState::Saving);
    live.outputs_written();
    assert_eq!(live.status().state, RunState::Finished);
    // Without an announcement the next run finishes at once.
    pipeline
        .run(source.as_mut(), Some(3), &no_progress)
        .unwrap();
    assert_eq!(live.status().state, RunState::Finished);
}
