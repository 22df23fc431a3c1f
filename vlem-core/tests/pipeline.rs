//! The two-thread pipeline with small fake stages: offline and real-time behaviour, lost frames,
//! error propagation, and the start-up checks.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::sync::Mutex;
use std::time::Duration;

use vlem_core::config::{Mode, PipelineConfig};
use vlem_core::pipeline::{Pipeline, Progress};
use vlem_core::{
    CoreError, DepthImage, EmbeddingMap, Encoder, Frame, FrameSource, IntegrationStats, Intrinsics,
    MapSnapshot, Observation, PixelEmbeddings, Pose, Region, RgbImage, TrackedPose, Tracker,
    TrackingState,
};

struct Planes {
    frames: usize,
    poses: bool,
}

impl FrameSource for Planes {
    fn describe(&self) -> String {
        "test planes".into()
    }
    fn len(&self) -> usize {
        self.frames
    }
    fn intrinsics(&self) -> Intrinsics {
        Intrinsics::new(8, 6, 10.0, 10.0, 3.5, 2.5).unwrap()
    }
    fn has_poses(&self) -> bool {
        self.poses
    }
    fn frame(&mut self, index: usize) -> vlem_core::Result<Frame> {
        Frame::new(
            index,
            index as f64 * 0.5,
            RgbImage::filled(8, 6, [1, 2, 3]),
            DepthImage::new(8, 6, vec![1.0; 48])?,
            self.intrinsics(),
            self.poses
                .then(|| Pose::translation(index as f64, 0.0, 0.0)),
        )
    }
}

/// Tracks every frame at the origin; loses every `lose_every`-th frame (0: never).
struct Still {
    lose_every: usize,
    needs_poses: bool,
}

impl Tracker for Still {
    fn name(&self) -> &'static str {
        "still"
    }
    fn needs_dataset_poses(&self) -> bool {
        self.needs_poses
    }
    fn track(&mut self, frame: &Frame) -> vlem_core::Result<TrackedPose> {
        let lost = self.lose_every > 0 && frame.index % self.lose_every == 1;
        Ok(TrackedPose {
            pose: frame.pose.unwrap_or_else(Pose::identity),
            state: if lost {
                TrackingState::Lost {
                    reason: "test".into(),
                }
            } else {
                TrackingState::Tracking
            },
        })
    }
}

/// A 2-d encoder that can be slow, fail at a frame, or need regions.
struct Fake {
    delay: Duration,
    fail_at_call: Option<usize>,
    calls: Mutex<usize>,
    needs_regions: bool,
}

impl Fake {
    fn new() -> Self {
        Self {
            delay: Duration::ZERO,
            fail_at_call: None,
            calls: Mutex::new(0),
            needs_regions: false,
        }
    }
}

impl Encoder for Fake {
    fn name(&self) -> &'static str {
        "fake"
    }
    fn dim(&self) -> usize {
        2
    }
    fn needs_regions(&self) -> bool {
        self.needs_regions
    }
    fn encode_image(&self, image: &RgbImage, _: &[Region]) -> vlem_core::Result<PixelEmbeddings> {
        let mut calls = self.calls.lock().unwrap();
        if Some(*calls) == self.fail_at_call {
            return Err(CoreError::InvalidEmbeddings {
                reason: "fake encoder failure".into(),
            });
        }
        *calls += 1;
        std::thread::sleep(self.delay);
        let n = (image.width() * image.height()) as usize;
        PixelEmbeddings::from_regions(image.width(), image.height(), 2, vec![0; n], vec![1.0, 0.0])
    }
}

/// Counts integrated frames and remembers their poses.
#[derive(Default)]
struct Recorder {
    dim: usize,
    poses: Vec<Pose>,
}

impl EmbeddingMap for Recorder {
    fn name(&self) -> &'static str {
        "recorder"
    }
    fn dim(&self) -> usize {
        self.dim
    }
    fn integrate(&mut self, obs: &Observation<'_>) -> vlem_core::Result<IntegrationStats> {
        self.poses.push(*obs.pose);
        Ok(IntegrationStats::default())
    }
    fn len(&self) -> usize {
        self.poses.len()
    }
    fn memory_bytes(&self) -> usize {
        0
    }
    fn similarity(&self, _: &[f32], out: &mut Vec<f32>) -> vlem_core::Result<()> {
        out.clear();
        Ok(())
    }
    fn snapshot(&self) -> vlem_core::Result<MapSnapshot> {
        Ok(MapSnapshot::default())
    }
}

fn still() -> Box<dyn Tracker> {
    Box::new(Still {
        lose_every: 0,
        needs_poses: false,
    })
}

fn recorder(dim: usize) -> Box<dyn EmbeddingMap> {
    Box::new(Recorder {
        dim,
        ..Recorder::default()
    })
}

fn no_progress(_: Progress) {}

/// Runs `p` over `frames` test planes without poses, until it ends or fails.
fn run_planes(
    p: &mut Pipeline,
    frames: usize,
) -> vlem_core::Result<vlem_core::pipeline::RunReport> {
    p.run(
        &mut Planes {
            frames,
            poses: false,
        },
        None,
        &no_progress,
    )
}

/// The still tracker, the fake 2-d encoder and a recording map, offline.
fn offline_pipeline() -> Pipeline {
    Pipeline::new(
        still(),
        None,
        Some(Box::new(Fake::new())),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .unwrap()
}

#[test]
fn offline_mode_integrates_every_frame_in_order() {
    let mut p = offline_pipeline();
    let mut source = Planes {
        frames: 12,
        poses: true,
    };
    let report = p.run(&mut source, None, &no_progress).unwrap();
    assert_eq!(report.frames_total, 12);
    assert_eq!(report.frames_tracked, 12);
    assert_eq!(report.frames_processed, 12);
    assert_eq!(report.frames_skipped, 0);
    assert_eq!(report.trajectory.len(), 12);
    assert_eq!(report.trajectory[3].timestamp, 1.5);
    assert_eq!(p.map().unwrap().len(), 12);
    for stage in ["load", "track", "encode", "integrate"] {
        assert_eq!(report.stage_ms[stage].count, 12, "{stage}");
    }
    assert!(!report.stage_ms.contains_key("propose"));
    // A frame limit stops early.
    let report = p.run(&mut source, Some(5), &no_progress).unwrap();
    assert_eq!((report.frames_total, report.frames_processed), (5, 5));
}

#[test]
fn a_stop_handle_ends_the_run_after_the_frame_in_hand_and_keeps_the_map() {
    let mut p = offline_pipeline();
    let mut source = Planes {
        frames: 12,
        poses: true,
    };
    let stop = p.stop_handle();
    // Asked while frame 3 is tracked (from the tracking thread, as a signal handler would).
    let on_progress = |event: Progress| {
        if event == (Progress::Tracked { index: 3 }) {
            stop.stop();
        }
    };
    let report = p.run(&mut source, None, &on_progress).unwrap();
    assert!(report.stopped);
    assert_eq!(
        report.frames_tracked, 4,
        "no frame is read after the request"
    );
    // The frames queued between the stages when the stop came are dropped, not run (a slow
    // encoder would otherwise hold the stop for every queued frame); the map keeps every frame
    // integrated before it.
    assert!(report.frames_processed <= 4, "{}", report.frames_processed);
    assert_eq!(p.map().unwrap().len(), report.frames_processed);
    assert!(
        report
            .stats(vlem_core::config::Mode::Offline, None, None)
            .stopped
    );
    // The next run starts afresh.
    let report = p.run(&mut source, None, &no_progress).unwrap();
    assert!(!report.stopped);
    assert_eq!(report.frames_tracked, 12);
}

#[test]
fn real_time_mode_skips_frames_while_the_encoder_is_busy() {
    let slow = Fake {
        delay: Duration::from_millis(150),
        ..Fake::new()
    };
    let config = PipelineConfig {
        mode: Mode::RealTime,
        queue_capacity: 1,
        frame_rate: 200.0,
        ..PipelineConfig::default()
    };
    let mut p = Pipeline::new(
        still(),
        None,
        Some(Box::new(slow)),
        Some(recorder(2)),
        config,
    )
    .unwrap();
    let skipped = Mutex::new(0usize);
    let progress = |e: Progress| {
        if let Progress::Skipped { .. } = e {
            *skipped.lock().unwrap() += 1;
        }
    };
    let mut source = Planes {
        frames: 10,
        poses: false,
    };
    let report = p.run(&mut source, None, &progress).unwrap();
    // 10 frames arrive within 50 ms; each embedding takes 150 ms.
    assert_eq!(report.frames_tracked, 10, "tracking never skips");
    assert!(report.frames_skipped > 0, "nothing skipped: {report:?}");
    assert_eq!(report.frames_processed + report.frames_skipped, 10);
    assert_eq!(*skipped.lock().unwrap(), report.frames_skipped);
}

#[test]
fn lost_frames_are_tracked_but_never_integrated() {
    let tracker = Box::new(Still {
        lose_every: 2,
        needs_poses: false,
    });
    let mut p = Pipeline::new(
        tracker,
        None,
        Some(Box::new(Fake::new())),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .unwrap();
    let report = p
        .run(
            &mut Planes {
                frames: 10,
                poses: false,
            },
            None,
            &no_progress,
        )
        .unwrap();
    assert_eq!(report.frames_lost, 5);
    assert_eq!(report.frames_processed, 5);
    assert_eq!(
        report
            .trajectory
            .iter()
            .filter(|t| t.lost.is_some())
            .count(),
        5
    );
}

#[test]
fn an_encoder_error_stops_the_run_and_is_reported() {
    let failing = Fake {
        fail_at_call: Some(3),
        ..Fake::new()
    };
    let mut p = Pipeline::new(
        still(),
        None,
        Some(Box::new(failing)),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .unwrap();
    let err = run_planes(&mut p, 1000).unwrap_err();
    assert_eq!(
        err.to_string(),
        "encode of frame 3: invalid pixel embeddings: fake encoder failure"
    );
    assert!(matches!(err.root(), CoreError::InvalidEmbeddings { .. }));
    // Every frame encoded before the failure was integrated, and the map stays queryable.
    assert_eq!(p.map().unwrap().len(), 3);
    let status = p.live().status();
    assert_eq!(status.frames_integrated, 3);
    assert!(
        matches!(&status.state, vlem_core::live::RunState::Failed(m) if m.contains("encode of frame 3")),
        "{status:?}"
    );
}

#[test]
fn geometry_only_pipelines_run_without_an_encoder() {
    let mut p = Pipeline::new(
        still(),
        None,
        None,
        Some(recorder(0)),
        PipelineConfig::default(),
    )
    .unwrap();
    let report = p
        .run(
            &mut Planes {
                frames: 4,
                poses: false,
            },
            None,
            &no_progress,
        )
        .unwrap();
    assert_eq!(report.frames_processed, 4);
}

#[test]
fn start_up_checks_name_the_problem() {
    let err = Pipeline::new(
        still(),
        None,
        Some(Box::new(Fake::new())),
        Some(recorder(512)),
        PipelineConfig::default(),
    )
    .err()
    .unwrap();
    assert_eq!(
        err.to_string(),
        "the encoder `fake` produces 2-d embeddings but the map `recorder` stores 512-d embeddings; \
         set [map] dim = 2 or remove it"
    );
    let regions = Fake {
        needs_regions: true,
        ..Fake::new()
    };
    let err = Pipeline::new(
        still(),
        None,
        Some(Box::new(regions)),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .err()
    .unwrap();
    assert_eq!(
        err.to_string(),
        "the encoder `fake` embeds image regions: add a [proposer] section to the config"
    );
    let needs_poses = Box::new(Still {
        lose_every: 0,
        needs_poses: true,
    });
    let mut p = Pipeline::new(needs_poses, None, None, None, PipelineConfig::default()).unwrap();
    let err = p
        .run(
            &mut Planes {
                frames: 2,
                poses: false,
            },
            None,
            &no_progress,
        )
        .unwrap_err();
    assert_eq!(
        err.to_string(),
        "the tracker `still` reads poses from the dataset, but test planes has no trajectory; \
         add one or configure a tracker that estimates poses"
    );
}

/// Proposes one region: the image's top-left pixel.
struct Corner;

impl vlem_core::RegionProposer for Corner {
    fn name(&self) -> &'static str {
        "corner"
    }
    fn propose(&self, _: &RgbImage) -> vlem_core::Result<Vec<Region>> {
        Ok(vec![Region {
            bbox: vlem_core::PixelRect {
                x: 0,
                y: 0,
                width: 1,
                height: 1,
            },
            mask: vec![true],
        }])
    }
}

/// Remembers what it was shown.
#[derive(Default)]
struct Watcher {
    tracked: Mutex<Vec<(usize, bool)>>,
    integrated: Mutex<Vec<(usize, usize, usize)>>,
}

impl vlem_core::RunObserver for Watcher {
    fn frame_tracked(&self, frame: &Frame, tracked: &TrackedPose) {
        let lost = matches!(tracked.state, TrackingState::Lost { .. });
        self.tracked.lock().unwrap().push((frame.index, lost));
    }
    fn frame_integrated(
        &self,
        frame: &Frame,
        _: &Pose,
        regions: &[Region],
        map: &dyn EmbeddingMap,
    ) {
        self.integrated
            .lock()
            .unwrap()
            .push((frame.index, regions.len(), map.len()));
    }
}

#[test]
fn an_observer_sees_every_tracked_and_every_integrated_frame_in_order() {
    let tracker = Box::new(Still {
        lose_every: 3,
        needs_poses: false,
    });
    let encoder = Fake {
        needs_regions: true,
        ..Fake::new()
    };
    let mut p = Pipeline::new(
        tracker,
        Some(Box::new(Corner)),
        Some(Box::new(encoder)),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .unwrap();
    let watcher = Watcher::default();
    let report = p
        .run_observed(
            &mut Planes {
                frames: 7,
                poses: false,
            },
            None,
            &no_progress,
            &watcher,
        )
        .unwrap();
    // Frames 1 and 4 are lost (index % 3 == 1): tracked, never integrated.
    let tracked = watcher.tracked.lock().unwrap().clone();
    assert_eq!(tracked, (0..7).map(|i| (i, i % 3 == 1)).collect::<Vec<_>>());
    let integrated = watcher.integrated.lock().unwrap().clone();
    assert_eq!(
        integrated,
        vec![(0, 1, 1), (2, 1, 2), (3, 1, 3), (5, 1, 4), (6, 1, 5)],
        "index, regions from the proposer, map size after integrating"
    );
    assert_eq!(report.frames_processed, 5);
}

/// A frame of the `Planes` camera at `timestamp`, with or without a pose.
fn pushed(timestamp: f64, pose: bool) -> Frame {
    let mut planes = Planes {
        frames: 1,
        poses: pose,
    };
    let mut frame = planes.frame(0).unwrap();
    frame.timestamp = timestamp;
    frame
}

fn stream_spec(has_poses: bool, capacity: usize) -> vlem_core::stream::StreamSpec {
    vlem_core::stream::StreamSpec {
        description: "a test stream".into(),
        intrinsics: Planes {
            frames: 0,
            poses: false,
        }
        .intrinsics(),
        has_poses,
        capacity,
        max_stamp_jump: vlem_core::stream::DEFAULT_MAX_STAMP_JUMP,
    }
}

#[test]
fn a_live_stream_is_read_in_order_until_every_sender_finishes() {
    use vlem_core::stream::frame_stream;
    let (sender, mut stream) = frame_stream(stream_spec(true, 2)).unwrap();
    let mut p = Pipeline::new(
        Box::new(Still {
            lose_every: 0,
            needs_poses: true,
        }),
        None,
        Some(Box::new(Fake::new())),
        Some(recorder(2)),
        // Real-time mode does not pace a live source: 7 frames at 1 Hz take no 7 s.
        PipelineConfig {
            mode: Mode::RealTime,
            queue_capacity: 8,
            frame_rate: 1.0,
            ..PipelineConfig::default()
        },
    )
    .unwrap();
    let started = std::time::Instant::now();
    let report = std::thread::scope(|scope| {
        let feeder = scope.spawn(move || {
            let second = sender.clone();
            for i in 0..7 {
                let which = if i % 2 == 0 { &sender } else { &second };
                assert_eq!(which.send(pushed(10.0 + i as f64, true)).unwrap(), i);
            }
            // Refused frames do not end the stream and take no index.
            let refused = [
                sender.send(pushed(12.0, true)).unwrap_err(),
                sender.send(pushed(20.0, false)).unwrap_err(),
                sender.send(pushed(f64::NAN, true)).unwrap_err(),
            ];
            for e in &refused {
                assert!(matches!(e, CoreError::FrameRefused { .. }), "{e}");
            }
            assert!(
                refused[0].to_string().contains("not after"),
                "{}",
                refused[0]
            );
            assert!(refused[1].to_string().contains("no pose"), "{}", refused[1]);
            sender.finish();
            second.finish();
        });
        let report = p.run(&mut stream, None, &no_progress);
        feeder.join().unwrap();
        report
    })
    .unwrap();
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "paced like a dataset"
    );
    assert_eq!(report.frames_total, 7);
    assert_eq!(report.frames_tracked, 7);
    let stamps: Vec<f64> = report.trajectory.iter().map(|t| t.timestamp).collect();
    assert_eq!(stamps, [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0]);
    let indices: Vec<usize> = report.trajectory.iter().map(|t| t.index).collect();
    assert_eq!(indices, (0..7).collect::<Vec<_>>());
    assert!(
        !report.stage_ms.contains_key("load"),
        "waiting is not loading"
    );
    // By index, a stream answers with an error that says why.
    assert!(
        stream
            .frame(0)
            .unwrap_err()
            .to_string()
            .contains("live stream")
    );
}

#[test]
fn a_stream_refuses_another_camera_and_says_when_the_pipeline_has_gone() {
    use vlem_core::stream::frame_stream;
    let (sender, stream) = frame_stream(stream_spec(false, 1)).unwrap();
    let mut other = pushed(1.0, false);
    other.intrinsics.fx = 11.0;
    let e = sender.send(other).unwrap_err();
    assert!(e.to_string().contains("not the stream's"), "{e}");
    // A full stream hands the frame back with try_send.
    assert_eq!(sender.try_send(pushed(1.0, false)).unwrap(), Some(0));
    assert_eq!(sender.try_send(pushed(2.0, false)).unwrap(), None);
    drop(stream);
    assert!(matches!(
        sender.send(pushed(3.0, false)).unwrap_err(),
        CoreError::StreamClosed
    ));
    assert!(frame_stream(stream_spec(false, 0)).is_err());
}

#[test]
fn a_frame_stamped_far_ahead_is_refused_without_locking_out_the_next() {
    use vlem_core::stream::frame_stream;
    let (sender, _stream) = frame_stream(stream_spec(false, 16)).unwrap();
    assert_eq!(sender.send(pushed(0.0, false)).unwrap(), 0);
    // One frame stamped in 2038 (a ROS 2 sec of 2147483638) is refused ...
    let e = sender.send(pushed(2_147_483_638.0, false)).unwrap_err();
    assert!(
        e.to_string()
            .contains("more than the stream's max_stamp_jump"),
        "{e}"
    );
    // ... and the stream goes on from the last good frame.
    assert_eq!(sender.send(pushed(0.1, false)).unwrap(), 1);
    // A camera paused for a minute: three frames in a row after the gap set the new time.
    assert!(sender.send(pushed(60.0, false)).is_err());
    assert!(sender.send(pushed(60.1, false)).is_err());
    assert_eq!(sender.send(pushed(60.2, false)).unwrap(), 2);
    assert_eq!(sender.send(pushed(60.3, false)).unwrap(), 3);
    let mut bad = stream_spec(false, 1);
    bad.max_stamp_jump = 0.0;
    assert!(frame_stream(bad).is_err());
}

#[test]
fn a_run_on_a_stream_ends_when_the_encoder_fails_and_senders_hear_of_it() {
    use vlem_core::stream::frame_stream;
    let (sender, mut stream) = frame_stream(stream_spec(false, 1)).unwrap();
    let failing = Fake {
        fail_at_call: Some(2),
        ..Fake::new()
    };
    let mut p = Pipeline::new(
        still(),
        None,
        Some(Box::new(failing)),
        Some(recorder(2)),
        PipelineConfig::default(),
    )
    .unwrap();
    std::thread::scope(|scope| {
        let feeder = scope.spawn(move || {
            // Sends until the pipeline stops reading; never blocks forever.
            (0..1000)
                .map(|i| sender.send(pushed(i as f64, false)))
                .find_map(Result::err)
        });
        let e = p.run(&mut stream, None, &no_progress).unwrap_err();
        assert!(e.to_string().contains("fake encoder failure"), "{e}");
        drop(stream);
        let refused = feeder.join().unwrap();
        assert!(
            matches!(refused, Some(CoreError::StreamClosed)),
            "{refused:?}"
        );
    });
}

/// A proposer that fails on its `fail_at_call`-th call.
struct FailingProposer {
    fail_at_call: usize,
    calls: Mutex<usize>,
}

impl vlem_core::RegionProposer for FailingProposer {
    fn name(&self) -> &'static str {
        "failing"
    }
    fn propose(&self, image: &RgbImage) -> vlem_core::Result<Vec<Region>> {
        let mut calls = self.calls.lock().unwrap();
        if *calls == self.fail_at_call {
            return Err(CoreError::Worker {
                reason: "proposer failure".into(),
            });
        }
        *calls += 1;
        Corner.propose(image)
    }
}

/// A map that refuses frame `fail_at`.
struct FailingMap {
    inner: Recorder,
    fail_at: usize,
}

impl EmbeddingMap for FailingMap {
    fn name(&self) -> &'static str {
        "failing"
    }
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    fn integrate(&mut self, obs: &Observation<'_>) -> vlem_core::Result<IntegrationStats> {
        if obs.frame.index == self.fail_at {
            return Err(CoreError::Worker {
                reason: "map failure".into(),
            });
        }
        self.inner.integrate(obs)
    }
    fn len(&self) -> usize {
        self.inner.len()
    }
    fn memory_bytes(&self) -> usize {
        0
    }
    fn similarity(&self, q: &[f32], out: &mut Vec<f32>) -> vlem_core::Result<()> {
        self.inner.similarity(q, out)
    }
    fn snapshot(&self) -> vlem_core::Result<MapSnapshot> {
        Ok(MapSnapshot::default())
    }
}

fn regions_pipeline(
    proposer: Box<dyn vlem_core::RegionProposer>,
    map: Box<dyn EmbeddingMap>,
    stages: vlem_core::config::StageLayout,
) -> Pipeline {
    let encoder = Fake {
        needs_regions: true,
        ..Fake::new()
    };
    Pipeline::new(
        still(),
        Some(proposer),
        Some(Box::new(encoder)),
        Some(map),
        PipelineConfig {
            stages,
            ..PipelineConfig::default()
        },
    )
    .unwrap()
}

#[test]
fn every_embedding_stage_reports_its_load_and_the_layout_is_in_the_stats() {
    use vlem_core::config::StageLayout;
    for layout in [StageLayout::Overlapped, StageLayout::Serial] {
        let mut p = regions_pipeline(Box::new(Corner), recorder(2), layout);
        let report = p
            .run(
                &mut Planes {
                    frames: 9,
                    poses: false,
                },
                None,
                &no_progress,
            )
            .unwrap();
        assert_eq!(report.frames_processed, 9);
        assert_eq!(report.stages, layout);
        let names: Vec<_> = report.stage_load.keys().copied().collect();
        assert_eq!(names, ["encode", "integrate", "propose"], "{layout:?}");
        for (name, load) in &report.stage_load {
            assert_eq!(load.busy.count, 9, "{name}");
            assert!(load.wait_input_ms >= 0.0 && load.wait_output_ms >= 0.0);
            assert_eq!(report.stage_ms[name], load.busy);
        }
        let stats = serde_json::to_value(report.stats(Mode::Offline, None, None)).unwrap();
        let expected = match layout {
            StageLayout::Overlapped => "overlapped",
            StageLayout::Serial => "serial",
        };
        assert_eq!(stats["stages"], expected);
        assert_eq!(stats["stage_load"]["encode"]["busy"]["count"], 9);
        assert!(stats["stage_load"]["propose"]["wait_output_ms"].is_number());
    }
}

#[test]
fn a_failing_proposer_or_map_names_its_stage_and_frame_and_keeps_the_map_so_far() {
    use vlem_core::config::StageLayout;
    for layout in [StageLayout::Overlapped, StageLayout::Serial] {
        let proposer = FailingProposer {
            fail_at_call: 4,
            calls: Mutex::new(0),
        };
        let mut p = regions_pipeline(Box::new(proposer), recorder(2), layout);
        let err = run_planes(&mut p, 100).unwrap_err();
        assert_eq!(
            err.to_string(),
            "propose of frame 4: pipeline worker failed: proposer failure"
        );
        assert_eq!(p.map().unwrap().len(), 4, "{layout:?}");

        let map = FailingMap {
            inner: Recorder {
                dim: 2,
                ..Recorder::default()
            },
            fail_at: 6,
        };
        let mut p = regions_pipeline(Box::new(Corner), Box::new(map), layout);
        let err = run_planes(&mut p, 100).unwrap_err();
        assert_eq!(
            err.to_string(),
            "integrate of frame 6: pipeline worker failed: map failure"
        );
        assert_eq!(p.map().unwrap().len(), 6, "{layout:?}");
        assert_eq!(p.live().status().frames_integrated, 6);
    }
}

#[test]
fn queue_capacities_are_range_checked() {
    for (capacity, stage_capacity) in [(0, 1), (1, 0), (usize::MAX, 1), (1, 100_000_000)] {
        let err = Pipeline::new(
            still(),
            None,
            Some(Box::new(Fake::new())),
            Some(recorder(2)),
            PipelineConfig {
                queue_capacity: capacity,
                stage_queue_capacity: stage_capacity,
                ..PipelineConfig::default()
            },
        )
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains("at least 1 and at most 1024"), "{err}");
    }
    // A live stream's queue is allocated up front too (Python's `Pipeline.start(capacity=10**9)`).
    for capacity in [0, 1_000_000_000] {
        let err = vlem_core::stream::frame_stream(stream_spec(false, capacity))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("at most 1024"), "{err}");
    }
    assert!(vlem_core::stream::frame_stream(stream_spec(false, 1024)).is_ok());
}
