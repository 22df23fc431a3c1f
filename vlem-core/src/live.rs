//! The live map: a handle through which other threads read the map while a pipeline builds it.
//!
//! Why it exists: the paper's map "can be accessed at any point in time" and is "queried in
//! real-time as well" while frames keep arriving. The pipeline's embedding thread owns integration;
//! everything else (a query server, a Python caller, a robot node, a viewer) holds a cloneable
//! [`LiveMap`] and reads through it.
//!
//! How it stays consistent and fast:
//! - The map sits behind one `RwLock` together with the count of integrated frames. The embedding
//!   thread takes the write lock only around [`EmbeddingMap::integrate`] (never while proposing or
//!   encoding), so a reader sees the map either before or after a whole frame, never half of one.
//! - Readers hold the read lock only for a pass over the map ([`LiveMap::read`]); callers do their
//!   slow work (text encoding, segmentation, file writing) outside it. std's `RwLock` lets a
//!   waiting writer in before new readers, so integration waits at most for the readers already
//!   inside.
//! - Run progress and the tracker's latest pose live in a separate small mutex that the tracking
//!   thread updates per frame: reading the pose never waits for integration.
//! - The map's size (kind, points, bytes) is copied into another small mutex at the end of every
//!   write, so a status request ([`LiveMap::summary`]) never waits behind a long query's read
//!   lock and the writer queued after it.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock, RwLockReadGuard};

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::mapfile::{MapMetadata, MapSnapshot, write_map_file};
use crate::traits::embedding_map::EmbeddingMap;
use crate::traits::encoder::Encoder;
use crate::types::Pose;

/// A cloneable, `Send + Sync` handle on a pipeline's map, its text encoder and its run status.
///
/// Obtain it from [`crate::pipeline::Pipeline::live`] before a run; it stays valid during and after
/// the run (the map outlives the run as long as one handle or the pipeline exists).
#[derive(Clone)]
pub struct LiveMap {
    shared: Arc<Shared>,
}

struct Shared {
    map: Option<RwLock<MapState>>,
    encoder: Option<Arc<dyn Encoder>>,
    metadata: Mutex<MapMetadata>,
    status: Mutex<RunStatus>,
    /// The map's size as of the last write (`None` without a map).
    summary: Mutex<Option<MapSummary>>,
    /// Whether the owner writes outputs after a run ([`LiveMap::announce_outputs`]).
    outputs_follow: AtomicBool,
}

/// The map and how many frames it holds, changed together under the write lock.
pub(crate) struct MapState {
    pub(crate) map: Box<dyn EmbeddingMap>,
    /// Frames integrated by this pipeline (across runs).
    pub(crate) frames_integrated: usize,
    /// Index of the last integrated frame.
    pub(crate) last_frame: Option<usize>,
}

/// A read-locked view of the map: the map and the integrated-frame count it corresponds to.
#[derive(Clone, Copy)]
pub struct MapView<'a> {
    /// The map, as it is after [`MapView::frames_integrated`] whole frames.
    pub map: &'a dyn EmbeddingMap,
    /// Frames integrated so far.
    pub frames_integrated: usize,
    /// Index (in the source) of the last integrated frame.
    pub last_frame: Option<usize>,
}

/// Where a run is.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    /// No run has started.
    #[default]
    Idle,
    /// Frames are being tracked and integrated.
    Running,
    /// The run's frames are all mapped and its owner is writing its outputs (map file,
    /// trajectory, statistics); `Finished` follows once they are complete. Only owners that
    /// announce outputs ([`LiveMap::announce_outputs`], as `vlem run` does) pass through it.
    Saving,
    /// The last run ended normally (and its outputs, where announced, are written).
    Finished,
    /// The last run stopped with an error (its message).
    Failed(String),
}

/// The tracker's latest pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseStamp {
    /// Frame index in the source.
    pub index: usize,
    /// Frame timestamp (seconds, or the frame index where the dataset has none).
    pub timestamp: f64,
    /// Camera-to-world pose; serialised as `{"position": [x, y, z], "orientation": [x, y, z, w]}`
    /// (a unit quaternion in ROS order).
    #[serde(with = "pose_wire")]
    pub pose: Pose,
    /// Whether tracking was lost at this frame (the pose is then the tracker's best guess).
    pub lost: bool,
}

/// Counters of a run and the latest pose, as the run goes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunStatus {
    /// Where the run is.
    pub state: RunState,
    /// Frames the source offers for this run.
    pub frames_total: usize,
    /// Frames tracked (lost ones included).
    pub frames_tracked: usize,
    /// Frames where tracking was lost.
    pub frames_lost: usize,
    /// Frames integrated into the map.
    pub frames_integrated: usize,
    /// Frames skipped in real-time mode because the embedding stage was busy.
    pub frames_skipped: usize,
    /// Map elements after the last integration.
    pub map_len: usize,
    /// Host bytes of the map after the last integration.
    #[serde(default)]
    pub map_host_bytes: usize,
    /// Device bytes of the map (its embedding table with `[map] device = "cuda"`), 0 on the host.
    #[serde(default)]
    pub map_device_bytes: usize,
    /// The tracker's latest pose.
    pub latest_pose: Option<PoseStamp>,
}

/// The map's kind and size as of its last change, read without the map's lock.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapSummary {
    /// Registered map name.
    pub kind: String,
    /// Map elements.
    pub points: usize,
    /// Embedding dimension.
    pub dim: usize,
    /// Host bytes of map storage.
    pub host_bytes: usize,
    /// Device bytes of map storage (`[map] device = "cuda"`), 0 for a map on the host.
    pub device_bytes: usize,
    /// Frames integrated by this pipeline (across runs).
    pub frames_integrated: usize,
}

impl MapSummary {
    fn of(state: &MapState) -> Self {
        Self {
            kind: state.map.name().to_owned(),
            points: state.map.len(),
            dim: state.map.dim(),
            host_bytes: state.map.memory_bytes(),
            device_bytes: state.map.device_memory_bytes(),
            frames_integrated: state.frames_integrated,
        }
    }
}

impl LiveMap {
    pub(crate) fn new(
        map: Option<Box<dyn EmbeddingMap>>,
        encoder: Option<Arc<dyn Encoder>>,
    ) -> Self {
        let map_len = map.as_ref().map_or(0, |m| m.len());
        let map_host_bytes = map.as_ref().map_or(0, |m| m.memory_bytes());
        let map_device_bytes = map.as_ref().map_or(0, |m| m.device_memory_bytes());
        let state = map.map(|map| MapState {
            map,
            frames_integrated: 0,
            last_frame: None,
        });
        let summary = state.as_ref().map(MapSummary::of);
        Self {
            shared: Arc::new(Shared {
                map: state.map(RwLock::new),
                encoder,
                metadata: Mutex::new(MapMetadata {
                    vlem_version: env!("CARGO_PKG_VERSION").into(),
                    ..MapMetadata::default()
                }),
                status: Mutex::new(RunStatus {
                    map_len,
                    map_host_bytes,
                    map_device_bytes,
                    ..RunStatus::default()
                }),
                summary: Mutex::new(summary),
                outputs_follow: AtomicBool::new(false),
            }),
        }
    }

    /// Whether the pipeline has a map at all (a tracking-only config has none).
    pub fn has_map(&self) -> bool {
        self.shared.map.is_some()
    }

    /// The encoder that made the map's embeddings, for embedding query texts the same way; `None`
    /// for a geometry-only pipeline.
    pub fn encoder(&self) -> Option<&Arc<dyn Encoder>> {
        self.shared.encoder.as_ref()
    }

    /// Runs `read` on the map as it is after a whole number of integrated frames, holding the read
    /// lock meanwhile: keep `read` to one pass over the map and do slow work outside.
    ///
    /// # Errors
    /// [`CoreError::MissingStage`] for a pipeline without a map; [`CoreError::Worker`] when an
    /// integration panicked and left the map unusable.
    pub fn read<R>(&self, read: impl FnOnce(MapView<'_>) -> R) -> Result<R> {
        let guard = self.read_guard()?;
        Ok(read(MapView {
            map: guard.map.as_ref(),
            frames_integrated: guard.frames_integrated,
            last_frame: guard.last_frame,
        }))
    }

    pub(crate) fn read_guard(&self) -> Result<RwLockReadGuard<'_, MapState>> {
        let lock = self.shared.map.as_ref().ok_or_else(no_map)?;
        lock.read().map_err(|_| poisoned())
    }

    /// The map read-locked, for the pipeline's owner; `None` without a map (or after a panic in
    /// integration, which the run reports).
    pub(crate) fn map_read(&self) -> Option<MapRead<'_>> {
        self.read_guard().ok().map(MapRead)
    }

    /// Applies `change` to the map under the write lock (the embedding thread's integration).
    pub(crate) fn write<R>(&self, change: impl FnOnce(&mut MapState) -> R) -> Result<R> {
        let map = self.shared.map.as_ref().ok_or_else(no_map)?;
        let mut state = map.write().map_err(|_| poisoned())?;
        let changed = change(&mut state);
        *lock(&self.shared.summary) = Some(MapSummary::of(&state));
        Ok(changed)
    }

    /// The map's kind and size as of its last change, without waiting for the map's lock (a
    /// status line stays prompt while long queries read the map); `None` without a map.
    pub fn summary(&self) -> Option<MapSummary> {
        lock(&self.shared.summary).clone()
    }

    /// Says that outputs are written after the next run: it then ends in [`RunState::Saving`]
    /// rather than `Finished`, until [`LiveMap::outputs_written`]. A client polling for
    /// `finished` (over HTTP, say) then finds the map file and the rest complete.
    pub fn announce_outputs(&self) {
        self.shared.outputs_follow.store(true, Ordering::Relaxed);
    }

    /// Ends [`RunState::Saving`]: the outputs announced are written.
    pub fn outputs_written(&self) {
        self.shared.outputs_follow.store(false, Ordering::Relaxed);
        self.update_status(|status| {
            if status.state == RunState::Saving {
                status.state = RunState::Finished;
            }
        });
    }

    /// The state a run that ended well reports: `Saving` while announced outputs are pending.
    pub(crate) fn finished_state(&self) -> RunState {
        if self.shared.outputs_follow.load(Ordering::Relaxed) {
            RunState::Saving
        } else {
            RunState::Finished
        }
    }

    /// Every element as point, colour and embedding, with the metadata a map file needs; its
    /// `metadata.frames_integrated` is the frame count the content belongs to.
    ///
    /// # Errors
    /// As [`LiveMap::read`].
    pub fn snapshot(&self) -> Result<MapSnapshot> {
        let metadata = self.metadata();
        let mut snapshot = self.read(|view| {
            let mut snapshot = view.map.snapshot()?;
            // Maps count their frames themselves (restored ones included); one that does not
            // gets this pipeline's count.
            snapshot.metadata.frames_integrated = snapshot
                .metadata
                .frames_integrated
                .max(view.frames_integrated);
            Ok(snapshot)
        })??;
        snapshot.metadata = MapMetadata {
            frames_integrated: snapshot.metadata.frames_integrated,
            ..metadata
        };
        Ok(snapshot)
    }

    /// Writes a consistent snapshot to a map file (atomically: a temporary file, then a rename),
    /// while mapping goes on; returns the snapshot's point count and frame count.
    ///
    /// # Errors
    /// As [`LiveMap::snapshot`], and I/O errors of writing the file.
    pub fn save(&self, path: &Path) -> Result<SavedMap> {
        let snapshot = self.snapshot()?;
        let bytes = write_map_file(path, &snapshot)?;
        Ok(SavedMap {
            points: snapshot.len(),
            frames_integrated: snapshot.metadata.frames_integrated,
            bytes,
        })
    }

    /// The provenance a saved map carries (encoder config, config folder, version).
    pub fn metadata(&self) -> MapMetadata {
        lock(&self.shared.metadata).clone()
    }

    /// Sets the provenance saved maps carry; `frames_integrated` is always taken from the map.
    pub fn set_metadata(&self, metadata: MapMetadata) {
        *lock(&self.shared.metadata) = metadata;
    }

    /// The run's counters and the tracker's latest pose.
    pub fn status(&self) -> RunStatus {
        lock(&self.shared.status).clone()
    }

    /// The tracker's latest pose, if a frame was tracked.
    pub fn latest_pose(&self) -> Option<PoseStamp> {
        lock(&self.shared.status).latest_pose
    }

    pub(crate) fn update_status(&self, change: impl FnOnce(&mut RunStatus)) {
        change(&mut lock(&self.shared.status));
    }
}

impl std::fmt::Debug for LiveMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveMap")
            .field("has_map", &self.has_map())
            .field("status", &self.status())
            .finish_non_exhaustive()
    }
}

/// The map behind a read lock, as [`crate::pipeline::Pipeline::map`] returns it: it derefs to the
/// map; integration waits while it is held.
pub struct MapRead<'a>(RwLockReadGuard<'a, MapState>);

impl MapRead<'_> {
    /// Frames integrated into the map.
    pub fn frames_integrated(&self) -> usize {
        self.0.frames_integrated
    }
}

impl std::ops::Deref for MapRead<'_> {
    type Target = dyn EmbeddingMap;

    fn deref(&self) -> &Self::Target {
        self.0.map.as_ref()
    }
}

/// What [`LiveMap::save`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SavedMap {
    /// Map elements in the file.
    pub points: usize,
    /// Frames integrated into the saved content.
    pub frames_integrated: usize,
    /// File size in bytes.
    pub bytes: u64,
}

/// A mutex of plain counters: a panic elsewhere cannot leave them half-updated, so a poisoned lock
/// is still read.
fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

fn no_map() -> CoreError {
    CoreError::MissingStage {
        message: "the pipeline has no [map]: there is nothing to query or save".into(),
    }
}

fn poisoned() -> CoreError {
    CoreError::Worker {
        reason: "the map was left unusable by a panic during integration".into(),
    }
}

/// A pose on the wire: position and unit quaternion `[x, y, z, w]`, the order ROS messages use.
mod pose_wire {
    use nalgebra::{Quaternion, Translation3, UnitQuaternion};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use crate::types::Pose;

    #[derive(Serialize, Deserialize)]
    struct Wire {
        position: [f64; 3],
        orientation: [f64; 4],
    }

    pub(super) fn serialize<S: Serializer>(pose: &Pose, serializer: S) -> Result<S::Ok, S::Error> {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        Wire {
            position: [t.x, t.y, t.z],
            orientation: [q.i, q.j, q.k, q.w],
        }
        .serialize(serializer)
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(
        deserializer: D,
    ) -> Result<Pose, D::Error> {
        let Wire {
            position: [x, y, z],
            orientation: [i, j, k, w],
        } = Wire::deserialize(deserializer)?;
        Ok(Pose::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_quaternion(Quaternion::new(w, i, j, k)),
        ))
    }
}
