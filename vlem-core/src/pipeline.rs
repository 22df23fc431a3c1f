//! The pipeline: tracking and embedding in threads joined by bounded queues (paper, Fig. 2).
//!
//! The tracking thread reads frames from the [`FrameSource`] and tracks every one of them, so the
//! trajectory is complete. Tracked frames go through a bounded queue to the embedding stages
//! (region proposer → encoder → map), which may run slower:
//! - [`Mode::Offline`]: the tracking thread waits for room in the queue; every frame is embedded.
//! - [`Mode::RealTime`]: frames are released at the sensor rate; a frame that finds the queue full
//!   (the first embedding stage is busy) is not embedded and is counted as skipped, as in the
//!   paper.
//!
//! The embedding stages run each in a worker of their own by default, so the embedding rate is the
//! slowest stage's rather than their sum (`[pipeline] stages`; `stages.rs` says how).
//!
//! Frames the tracker reports as lost are never integrated.
//!
//! The map lives in a [`LiveMap`]: other threads query, snapshot and save it through
//! [`Pipeline::live`] while the run integrates, and see the run's counters and latest pose.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering as AtomicOrdering};
use std::sync::mpsc::{SyncSender, TrySendError, sync_channel};
use std::time::Instant;

use serde::Serialize;

use crate::config::{Config, Mode, PipelineConfig, StageLayout};
use crate::error::{CoreError, Result, message_chain};
use crate::live::{LiveMap, MapRead, PoseStamp, RunState};
use crate::mapfile::MapMetadata;
use crate::registry::{BuildContext, Registry};
use crate::traits::embedding_map::{EmbeddingMap, IntegrationStats, Observation};
use crate::traits::encoder::Encoder;
use crate::traits::frame_source::FrameSource;
use crate::traits::observer::{NoObserver, RunObserver};
use crate::traits::region_proposer::RegionProposer;
use crate::traits::tracker::{Tracker, TrackingState};
use crate::types::Pose;

mod stages;

pub use stages::StageLoad;
use stages::{Stage, StageFn, Work};

/// The built stages of a run.
pub struct Pipeline {
    tracker: Box<dyn Tracker>,
    proposer: Option<Box<dyn RegionProposer>>,
    encoder: Option<Arc<dyn Encoder>>,
    live: LiveMap,
    config: PipelineConfig,
    stop: StopHandle,
    /// What the config asked for that this pipeline does not use.
    warnings: Vec<String>,
}

/// Ends a run of its pipeline early from another thread (a Ctrl-C handler, a front-end's
/// cancel button): the run reads no further frame, lets the embedding stage finish the frames
/// already tracked, and returns its report with [`RunReport::stopped`] set. The map up to the last
/// integrated frame stays, as after any run.
#[derive(Clone, Debug, Default)]
pub struct StopHandle(Arc<AtomicBool>);

impl StopHandle {
    /// Asks the current run to stop (a run clears the request when it starts).
    pub fn stop(&self) {
        self.0.store(true, AtomicOrdering::Relaxed);
    }

    fn requested(&self) -> bool {
        self.0.load(AtomicOrdering::Relaxed)
    }

    fn clear(&self) {
        self.0.store(false, AtomicOrdering::Relaxed);
    }
}

/// Something that happened, for progress displays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// Frame `index` was tracked (lost or not).
    Tracked {
        /// Frame index.
        index: usize,
    },
    /// Frame `index` was integrated into the map.
    Integrated {
        /// Frame index.
        index: usize,
        /// Map size afterwards.
        map_len: usize,
    },
    /// Frame `index` was skipped because the embedding stage was busy.
    Skipped {
        /// Frame index.
        index: usize,
    },
}

/// One entry of the estimated trajectory.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryEntry {
    /// Frame index.
    pub index: usize,
    /// Frame timestamp (seconds, or the frame index where the dataset has none).
    pub timestamp: f64,
    /// Camera-to-world pose.
    pub pose: Pose,
    /// Why tracking was lost at this frame; `None` when it tracked.
    pub lost: Option<String>,
    /// The dataset's pose of this frame, where it has one (the reference to evaluate against).
    pub reference: Option<Pose>,
}

/// Mean wall time of one stage.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageTiming {
    /// Calls timed.
    pub count: usize,
    /// Mean milliseconds per call.
    pub mean_ms: f64,
    total_ms: f64,
}

impl StageTiming {
    /// Milliseconds of all calls together.
    pub fn total_ms(&self) -> f64 {
        self.total_ms
    }

    fn add(&mut self, since: Instant) {
        self.total_ms += since.elapsed().as_secs_f64() * 1e3;
        self.count += 1;
        self.mean_ms = self.total_ms / self.count as f64;
    }
}

/// What a run did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RunReport {
    /// Frames the source offered.
    pub frames_total: usize,
    /// Frames tracked (lost ones included).
    pub frames_tracked: usize,
    /// Frames where tracking was lost (not integrated).
    pub frames_lost: usize,
    /// Frames integrated into the map.
    pub frames_processed: usize,
    /// Frames skipped in real-time mode because the embedding stage was busy.
    pub frames_skipped: usize,
    /// Mean milliseconds per stage: `load`, `track`, `propose`, `encode`, `integrate`.
    pub stage_ms: BTreeMap<&'static str, StageTiming>,
    /// The embedding stages' busy time and their workers' waits: the stage that sets the
    /// embedding rate is the one that never waits.
    pub stage_load: BTreeMap<&'static str, StageLoad>,
    /// How the embedding stages shared threads.
    pub stages: StageLayout,
    /// Wall time of the whole run in seconds.
    pub wall_seconds: f64,
    /// Whether the run ended early because its [`StopHandle`] was used.
    pub stopped: bool,
    /// What the pipeline's config and the source warned about (a section the pipeline does not
    /// use; missing frames, a bag's dropped messages, …).
    pub warnings: Vec<String>,
    /// The trajectory, one entry per tracked frame.
    #[serde(skip)]
    pub trajectory: Vec<TrajectoryEntry>,
}

/// The frame counters of a run, as `stats.json` writes them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct FrameCounts {
    /// Frames the source offered.
    pub total: usize,
    /// Frames tracked (lost ones included).
    pub tracked: usize,
    /// Frames integrated into the map.
    pub processed: usize,
    /// Frames skipped in real-time mode.
    pub skipped: usize,
    /// Frames where tracking was lost.
    pub lost: usize,
}

/// A frame where tracking was lost, and why.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LostFrame {
    /// Frame index.
    pub index: usize,
    /// The tracker's reason.
    pub reason: String,
}

/// The map part of [`RunStats`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MapStats {
    /// Registered map name.
    pub kind: String,
    /// Map elements.
    pub points: usize,
    /// Embedding dimension.
    pub dim: usize,
    /// Host memory of the map's storage, in bytes (its in-memory size: index, buffers, spare
    /// capacity; not the size of its map file).
    pub memory_bytes: usize,
    /// Device memory of the map's storage (`[map] device = "cuda"`), 0 for a map on the host.
    pub device_bytes: usize,
    /// The size of the map file the run saved (`map.vlem`), where it saved one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub file_bytes: Option<u64>,
}

impl MapStats {
    /// The size of `map`.
    pub fn of(map: &dyn EmbeddingMap) -> Self {
        Self {
            kind: map.name().into(),
            points: map.len(),
            dim: map.dim(),
            memory_bytes: map.memory_bytes(),
            device_bytes: map.device_memory_bytes(),
            file_bytes: None,
        }
    }
}

/// What a run writes as `stats.json`: counters, lost frames, mean stage times, the map's size.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RunStats {
    /// Frame counters.
    pub frames: FrameCounts,
    /// Every frame where tracking was lost.
    pub lost_frames: Vec<LostFrame>,
    /// Offline or real-time.
    pub mode: Mode,
    /// Mean milliseconds per stage.
    pub mean_ms: BTreeMap<&'static str, f64>,
    /// How the embedding stages shared threads (`overlapped` or `serial`).
    pub stages: StageLayout,
    /// Per embedding stage: calls, busy milliseconds (total and mean) and its worker's waits for
    /// input and for room downstream.
    pub stage_load: BTreeMap<&'static str, StageLoad>,
    /// Wall time of the run in seconds.
    pub wall_seconds: f64,
    /// Whether the run was stopped early ([`StopHandle`]).
    pub stopped: bool,
    /// What the config and the source warned about (an unused section, missing frames, …);
    /// empty when nothing.
    pub warnings: Vec<String>,
    /// The map after the run, when there is one.
    pub map: Option<MapStats>,
    /// Peak resident memory of the process, where the platform reports it.
    pub peak_resident_bytes: Option<u64>,
    /// Peak device memory in use during the run, as the driver reports it for the GPUs the
    /// config names (`None` when it names none); the front-end that samples it sets it.
    pub peak_device_bytes: Option<u64>,
}

impl RunReport {
    /// The run's statistics in `stats.json` form.
    pub fn stats(
        &self,
        mode: Mode,
        map: Option<&dyn EmbeddingMap>,
        peak_resident_bytes: Option<u64>,
    ) -> RunStats {
        RunStats {
            frames: FrameCounts {
                total: self.frames_total,
                tracked: self.frames_tracked,
                processed: self.frames_processed,
                skipped: self.frames_skipped,
                lost: self.frames_lost,
            },
            lost_frames: self
                .trajectory
                .iter()
                .filter_map(|e| {
                    e.lost.as_ref().map(|reason| LostFrame {
                        index: e.index,
                        reason: reason.clone(),
                    })
                })
                .collect(),
            mode,
            mean_ms: self.stage_ms.iter().map(|(k, t)| (*k, t.mean_ms)).collect(),
            stages: self.stages,
            stage_load: self.stage_load.clone(),
            wall_seconds: self.wall_seconds,
            stopped: self.stopped,
            warnings: self.warnings.clone(),
            map: map.map(MapStats::of),
            peak_resident_bytes,
            peak_device_bytes: None,
        }
    }

    /// The estimated trajectory as `(timestamp, pose)` pairs, for a trajectory file.
    pub fn poses(&self) -> Vec<(f64, Pose)> {
        self.trajectory
            .iter()
            .map(|e| (e.timestamp, e.pose))
            .collect()
    }

    /// The dataset's own poses of the tracked frames, when the dataset has one for each.
    pub fn reference_poses(&self) -> Option<Vec<(f64, Pose)>> {
        let poses: Option<Vec<_>> = self
            .trajectory
            .iter()
            .map(|e| e.reference.map(|pose| (e.timestamp, pose)))
            .collect();
        poses.filter(|p| !p.is_empty())
    }
}

#[derive(Default)]
struct TrackingOutcome {
    trajectory: Vec<TrajectoryEntry>,
    stopped: bool,
    lost: usize,
    skipped: usize,
    load: StageTiming,
    track: StageTiming,
}

impl Pipeline {
    /// Builds every stage the config names, through the registry.
    ///
    /// # Errors
    /// Unknown implementation names, invalid parameters (an unknown key located on its line where
    /// the config knows its text: [`Config::locate`]), an encoder that needs regions without a
    /// `[proposer]`, or an encoder and map that disagree on the embedding dimension.
    pub fn from_config(config: &Config, ctx: &BuildContext) -> Result<Self> {
        Self::build_from_config(config, ctx).map_err(|e| config.locate(e))
    }

    fn build_from_config(config: &Config, ctx: &BuildContext) -> Result<Self> {
        let registry = Registry::global()?;
        let tracker = registry.build_tracker(&config.tracker, ctx)?;
        let encoder = config
            .encoder
            .as_ref()
            .map(|stage| registry.build_encoder(stage, ctx))
            .transpose()?;
        // A proposer only runs for encoders that embed regions; `Pipeline::new` reports a missing
        // one, and an unused one is a warning (a shared config may name one for other encoders).
        let mut warnings = Vec::new();
        let proposer = match (&encoder, &config.proposer) {
            (Some(e), Some(stage)) if e.needs_regions() => {
                Some(registry.build_proposer(stage, ctx)?)
            }
            (encoder, Some(stage)) => {
                warnings.push(format!(
                    "[proposer] kind = \"{}\" is not used: {}",
                    stage.kind,
                    encoder.as_ref().map_or_else(
                        || "there is no [encoder]".to_owned(),
                        |e| format!(
                            "the encoder `{}` embeds the whole frame, not regions",
                            e.name()
                        )
                    )
                ));
                None
            }
            _ => None,
        };
        let map_ctx = BuildContext {
            embedding_dim: encoder.as_ref().map(|e| e.dim()),
            ..ctx.clone()
        };
        let map = config
            .map
            .as_ref()
            .map(|stage| registry.build_map(stage, &map_ctx))
            .transpose()?;
        let mut pipeline = Self::new(tracker, proposer, encoder, map, config.pipeline.clone())?;
        pipeline.warnings = warnings;
        // What a map file saved from this pipeline needs to rebuild its text encoder.
        pipeline.live.set_metadata(MapMetadata {
            encoder: config.encoder.clone(),
            config_dir: Some(ctx.config_dir.clone()),
            ..pipeline.live.metadata()
        });
        Ok(pipeline)
    }

    /// Assembles a pipeline from stages built elsewhere.
    ///
    /// # Errors
    /// [`CoreError::EmbeddingDimensionMismatch`] when the encoder's and the map's dimensions differ
    /// (a map without an encoder must have dimension 0), [`CoreError::MissingStage`] for an encoder
    /// that needs regions without a proposer, or a zero queue capacity.
    pub fn new(
        tracker: Box<dyn Tracker>,
        proposer: Option<Box<dyn RegionProposer>>,
        encoder: Option<Box<dyn Encoder>>,
        map: Option<Box<dyn EmbeddingMap>>,
        config: PipelineConfig,
    ) -> Result<Self> {
        if let Some(map) = &map {
            let (encoder_name, encoder_dim) = match &encoder {
                Some(e) => (e.name().to_owned(), e.dim()),
                None => ("(none)".to_owned(), 0),
            };
            if map.dim() != encoder_dim {
                return Err(CoreError::EmbeddingDimensionMismatch {
                    encoder: encoder_name,
                    encoder_dim,
                    map: map.name().to_owned(),
                    map_dim: map.dim(),
                });
            }
        }
        if let Some(e) = &encoder
            && e.needs_regions()
            && proposer.is_none()
        {
            return Err(CoreError::MissingStage {
                message: format!(
                    "the encoder `{}` embeds image regions: add a [proposer] section to the config",
                    e.name()
                ),
            });
        }
        config.validate()?;
        let encoder: Option<Arc<dyn Encoder>> = encoder.map(Arc::from);
        let live = LiveMap::new(map, encoder.clone());
        Ok(Self {
            tracker,
            proposer,
            encoder,
            live,
            config,
            stop: StopHandle::default(),
            warnings: Vec::new(),
        })
    }

    /// What the config asked for that this pipeline does not use (a `[proposer]` beside an
    /// encoder that embeds whole frames): front-ends print them, and each run's report lists them
    /// first among its [`RunReport::warnings`].
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// A handle that stops a run of this pipeline from another thread.
    pub fn stop_handle(&self) -> StopHandle {
        self.stop.clone()
    }

    /// The map, if the config has one, read-locked: hold it briefly while a run is in progress on
    /// another thread (integration waits for it). Other threads use [`Pipeline::live`].
    pub fn map(&self) -> Option<MapRead<'_>> {
        self.live.map_read()
    }

    /// A handle on the map, its encoder and the run's progress that other threads can hold while
    /// [`Pipeline::run`] integrates: queries, snapshots and saves never see a half-integrated
    /// frame.
    pub fn live(&self) -> LiveMap {
        self.live.clone()
    }

    /// The encoder, if the config has one.
    pub fn encoder(&self) -> Option<&dyn Encoder> {
        self.encoder.as_deref()
    }

    /// The tracker.
    pub fn tracker(&self) -> &dyn Tracker {
        self.tracker.as_ref()
    }

    /// Runs the pipeline over the first `frames` frames of `source` (all of them for `None`).
    ///
    /// # Errors
    /// The first error of any stage; the run stops there. A tracker that reads dataset poses on a
    /// source without poses fails before the first frame.
    pub fn run(
        &mut self,
        source: &mut dyn FrameSource,
        frames: Option<usize>,
        progress: &(dyn Fn(Progress) + Sync),
    ) -> Result<RunReport> {
        self.run_observed(source, frames, progress, &NoObserver)
    }

    /// [`Pipeline::run`], showing every frame to `observer` as it is tracked and integrated.
    ///
    /// # Errors
    /// As [`Pipeline::run`].
    pub fn run_observed(
        &mut self,
        source: &mut dyn FrameSource,
        frames: Option<usize>,
        progress: &(dyn Fn(Progress) + Sync),
        observer: &dyn RunObserver,
    ) -> Result<RunReport> {
        if self.tracker.needs_dataset_poses() && !source.has_poses() {
            return Err(CoreError::MissingStage {
                message: format!(
                    "the tracker `{}` reads poses from the dataset, but {} has no trajectory; \
                     add one or configure a tracker that estimates poses",
                    self.tracker.name(),
                    source.describe()
                ),
            });
        }
        // A live source's length is unknown: it is read until it ends (or `frames` are read).
        let live_source = source.is_live();
        let total = match (live_source, frames) {
            (true, limit) => limit.unwrap_or(usize::MAX),
            (false, limit) => limit.map_or(source.len(), |n| n.min(source.len())),
        };
        let mut warnings = self.warnings.clone();
        warnings.extend(source.warnings());
        let start = Instant::now();
        let (sender, receiver) = sync_channel::<Work>(self.config.queue_capacity);
        let config = self.config.clone();
        let integrate = self.live.has_map();
        let tracker = &mut self.tracker;
        let proposer = self.proposer.as_deref();
        let encoder = self.encoder.as_deref();
        let live = &self.live;
        let stop = &self.stop;
        stop.clear();
        live.update_status(|status| {
            status.state = RunState::Running;
            status.frames_total = if live_source { 0 } else { total };
            status.frames_tracked = 0;
            status.frames_lost = 0;
            status.frames_skipped = 0;
            status.frames_integrated = 0;
        });
        let watchers = Watchers {
            progress,
            observer,
            live,
            stop,
        };
        let stages = if integrate {
            embedding_stages(proposer, encoder, watchers)
        } else {
            Vec::new()
        };
        let groups = stages::layout(stages, config.stages);
        let (tracking, embedding) = std::thread::scope(|scope| {
            let tracking = scope.spawn(move || {
                track_frames(
                    tracker.as_mut(),
                    source,
                    total,
                    &config,
                    integrate,
                    sender,
                    watchers,
                )
            });
            let embedding = stages::run_workers(
                scope,
                groups,
                receiver,
                self.config.stage_queue_capacity,
                stop,
            );
            let tracking = tracking.join().map_err(|_| CoreError::Worker {
                reason: "the tracking thread panicked".into(),
            });
            (tracking, embedding)
        });
        // An embedding error makes the tracking thread stop early; report the cause, not that.
        let outcome = match (embedding, tracking) {
            (Err(e), _) | (Ok(_), Err(e) | Ok(Err(e))) => Err(e),
            (Ok(embedding), Ok(Ok(tracking))) => Ok((embedding, tracking)),
        };
        let finished = self.live.finished_state();
        self.live.update_status(|status| {
            status.state = match &outcome {
                Ok(_) => finished,
                Err(e) => RunState::Failed(message_chain(e)),
            }
        });
        let (embedding, tracking) = outcome?;
        let mut stage_ms = BTreeMap::new();
        stage_ms.insert("load", tracking.load);
        stage_ms.insert("track", tracking.track);
        for (name, load) in &embedding {
            stage_ms.insert(*name, load.busy);
        }
        stage_ms.retain(|_, t| t.count > 0);
        let processed = embedding
            .iter()
            .find(|(name, _)| *name == INTEGRATE)
            .map_or(0, |(_, load)| load.busy.count);
        Ok(RunReport {
            frames_total: if live_source {
                tracking.trajectory.len()
            } else {
                total
            },
            frames_tracked: tracking.trajectory.len(),
            frames_lost: tracking.lost,
            frames_processed: processed,
            frames_skipped: tracking.skipped,
            stage_ms,
            stage_load: embedding.into_iter().collect(),
            stages: self.config.stages,
            wall_seconds: start.elapsed().as_secs_f64(),
            stopped: tracking.stopped,
            warnings,
            trajectory: tracking.trajectory,
        })
    }
}

/// Who hears about each frame (the progress callback, the observer and the live map's status)
/// and who may end the run early (the stop handle).
#[derive(Clone, Copy)]
struct Watchers<'a> {
    progress: &'a (dyn Fn(Progress) + Sync),
    observer: &'a dyn RunObserver,
    live: &'a LiveMap,
    stop: &'a StopHandle,
}

fn track_frames(
    tracker: &mut dyn Tracker,
    source: &mut dyn FrameSource,
    total: usize,
    config: &PipelineConfig,
    integrate: bool,
    sender: SyncSender<Work>,
    Watchers {
        progress,
        observer,
        live,
        stop,
    }: Watchers<'_>,
) -> Result<TrackingOutcome> {
    let mut out = TrackingOutcome::default();
    let started = Instant::now();
    let frame_period = config.frame_period();
    let live_source = source.is_live();
    let paced = config.mode == Mode::RealTime && !live_source;
    for index in 0..total {
        if stop.requested() {
            out.stopped = true;
            break;
        }
        if paced {
            // Frames "arrive" at the sensor rate; never faster.
            let due = frame_period.saturating_mul(index as u32);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        let t = Instant::now();
        let Some(frame) = source.next_frame(index)? else {
            break; // The end of a live stream.
        };
        if !live_source {
            // A live source's "load" is the wait for the sensor, not work.
            out.load.add(t);
        }
        let t = Instant::now();
        let tracked = tracker.track(&frame)?;
        out.track.add(t);
        observer.frame_tracked(&frame, &tracked);
        let lost_reason = match tracked.state {
            TrackingState::Lost { reason } => Some(reason),
            TrackingState::Tracking => None,
        };
        let lost = lost_reason.is_some();
        live.update_status(|status| {
            status.frames_tracked += 1;
            status.frames_lost += usize::from(lost);
            status.latest_pose = Some(PoseStamp {
                index: frame.index,
                timestamp: frame.timestamp,
                pose: tracked.pose,
                lost,
            });
        });
        out.trajectory.push(TrajectoryEntry {
            index: frame.index,
            timestamp: frame.timestamp,
            pose: tracked.pose,
            lost: lost_reason,
            reference: frame.pose,
        });
        progress(Progress::Tracked { index: frame.index });
        if lost {
            out.lost += 1;
            continue;
        }
        if !integrate {
            continue;
        }
        let item = Work {
            frame,
            pose: tracked.pose,
            regions: Vec::new(),
            embeddings: None,
        };
        match config.mode {
            Mode::Offline => {
                if sender.send(item).is_err() {
                    break; // The embedding stage stopped with an error; it reports it.
                }
            }
            Mode::RealTime => match sender.try_send(item) {
                Ok(()) => {}
                Err(TrySendError::Full(item)) => {
                    out.skipped += 1;
                    live.update_status(|status| status.frames_skipped += 1);
                    progress(Progress::Skipped {
                        index: item.frame.index,
                    });
                }
                Err(TrySendError::Disconnected(_)) => break,
            },
        }
    }
    Ok(out)
}

/// The stage that integrates into the map: the one whose calls count the processed frames.
const INTEGRATE: &str = "integrate";

/// The embedding stages of a pipeline with a map, in order: propose (with a proposer), encode (with
/// an encoder), integrate.
fn embedding_stages<'a>(
    proposer: Option<&'a dyn RegionProposer>,
    encoder: Option<&'a dyn Encoder>,
    Watchers {
        progress,
        observer,
        live,
        ..
    }: Watchers<'a>,
) -> Vec<Stage<'a>> {
    let mut stages = Vec::with_capacity(3);
    if let Some(proposer) = proposer {
        stages.push(Stage {
            name: "propose",
            run: Box::new(move |work: &mut Work| {
                work.regions = proposer.propose(&work.frame.colour)?;
                Ok(())
            }) as StageFn<'a>,
        });
    }
    if let Some(encoder) = encoder {
        stages.push(Stage {
            name: "encode",
            run: Box::new(move |work: &mut Work| {
                if encoder.needs_labels() && work.frame.labels.is_none() {
                    return Err(CoreError::MissingLabels {
                        encoder: encoder.name().to_owned(),
                        frame: work.frame.index,
                    });
                }
                work.embeddings = Some(encoder.encode_frame(&work.frame, &work.regions)?);
                Ok(())
            }),
        });
    }
    stages.push(Stage {
        name: INTEGRATE,
        run: Box::new(move |work: &mut Work| {
            let Work {
                frame,
                pose,
                regions,
                embeddings,
            } = work;
            // The write lock covers exactly one integration: readers see whole frames only.
            live.write(|state| -> Result<_> {
                let _: IntegrationStats = state.map.integrate(&Observation {
                    frame,
                    pose,
                    embeddings: embeddings.as_ref(),
                })?;
                state.frames_integrated += 1;
                state.last_frame = Some(frame.index);
                Ok(())
            })??;
            // The write refreshed the map's summary; only this stage writes, so it is this frame's.
            let summary = live.summary().unwrap_or_default();
            let map_len = summary.points;
            live.update_status(|status| {
                status.frames_integrated += 1;
                status.map_len = map_len;
                status.map_host_bytes = summary.host_bytes;
                status.map_device_bytes = summary.device_bytes;
            });
            // Only this stage writes, so the map read now is the one just integrated.
            if let Some(map) = live.map_read() {
                observer.frame_integrated(frame, pose, regions, &*map);
            }
            progress(Progress::Integrated {
                index: frame.index,
                map_len,
            });
            Ok(())
        }),
    });
    stages
}
