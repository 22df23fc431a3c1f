//! What the node counted: every message it could not use, every frame it dropped, and why.
//!
//! Why: a live node must never die on a bad message, so everything wrong is skipped; the counts
//! (and a rate-limited log line per kind) are how a user sees that it happened.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

/// What the node counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(usize)]
pub enum Counter {
    /// Colour images received.
    Colour,
    /// Depth images received.
    Depth,
    /// Frames handed to the pipeline.
    FramesQueued,
    /// Frames dropped because the tracker was behind (the queue was full).
    DroppedBusy,
    /// Frames the stream refused (stamp not after the previous one, another camera).
    Refused,
    /// Images that found no partner within the tolerance.
    Unpaired,
    /// Frames without a pose near their stamp (pose topic configured).
    NoPose,
    /// Frames made before any camera info arrived.
    NoCameraInfo,
    /// Colour and depth of different sizes, or images not of the camera info's size.
    SizeMismatch,
    /// Messages that could not be decoded or converted.
    BadMessage,
    /// Camera info that changed.
    CameraChanged,
    /// Camera info with distortion.
    Distorted,
    /// Times the images stopped arriving for longer than `stall_seconds`.
    Stalls,
    /// Queries answered.
    Queries,
    /// Queries that failed (e.g. an empty map).
    QueryErrors,
    /// Queries dropped because [`QUERY_QUEUE`](crate::node::QUERY_QUEUE) queries were waiting.
    QueriesDropped,
    /// Maps published.
    MapsPublished,
}

const COUNTERS: usize = Counter::MapsPublished as usize + 1;

/// The node's counters, shared between its threads.
#[derive(Debug)]
pub struct Status {
    counts: [AtomicU64; COUNTERS],
    last_log: Mutex<[Option<Instant>; COUNTERS]>,
}

impl Default for Status {
    fn default() -> Self {
        Self {
            counts: std::array::from_fn(|_| AtomicU64::new(0)),
            last_log: Mutex::new([None; COUNTERS]),
        }
    }
}

/// A log line per kind at most this often.
const LOG_EVERY: Duration = Duration::from_secs(2);

impl Status {
    /// Adds one.
    pub fn count(&self, counter: Counter) {
        self.counts[counter as usize].fetch_add(1, Ordering::Relaxed);
    }

    /// Adds one and logs `message` (with the count), at most every 2 s per kind.
    pub fn warn(&self, counter: Counter, message: &str) {
        self.count(counter);
        let mut last = self
            .last_log
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let slot = &mut last[counter as usize];
        if slot.is_none_or(|t| t.elapsed() >= LOG_EVERY) {
            *slot = Some(Instant::now());
            eprintln!(
                "vlem ros2: {message} ({:?}: {} so far)",
                counter,
                self.get(counter)
            );
        }
    }

    /// The count of `counter`.
    pub fn get(&self, counter: Counter) -> u64 {
        self.counts[counter as usize].load(Ordering::Relaxed)
    }

    /// Every count, for the node's report.
    pub fn report(&self) -> StatusReport {
        StatusReport {
            colour_images: self.get(Counter::Colour),
            depth_images: self.get(Counter::Depth),
            frames_queued: self.get(Counter::FramesQueued),
            dropped_busy: self.get(Counter::DroppedBusy),
            refused: self.get(Counter::Refused),
            unpaired_images: self.get(Counter::Unpaired),
            no_pose: self.get(Counter::NoPose),
            no_camera_info: self.get(Counter::NoCameraInfo),
            size_mismatch: self.get(Counter::SizeMismatch),
            bad_messages: self.get(Counter::BadMessage),
            camera_changes: self.get(Counter::CameraChanged),
            stalls: self.get(Counter::Stalls),
            queries: self.get(Counter::Queries),
            query_errors: self.get(Counter::QueryErrors),
            queries_dropped: self.get(Counter::QueriesDropped),
            maps_published: self.get(Counter::MapsPublished),
        }
    }
}

/// The counts at one moment (what `vlem ros2` prints and writes).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct StatusReport {
    /// Colour images received.
    pub colour_images: u64,
    /// Depth images received.
    pub depth_images: u64,
    /// Frames handed to the pipeline.
    pub frames_queued: u64,
    /// Frames dropped because tracking was behind.
    pub dropped_busy: u64,
    /// Frames the stream refused (out-of-order stamp, another camera).
    pub refused: u64,
    /// Images without a partner.
    pub unpaired_images: u64,
    /// Frames without a pose.
    pub no_pose: u64,
    /// Frames before camera info.
    pub no_camera_info: u64,
    /// Size mismatches.
    pub size_mismatch: u64,
    /// Undecodable messages.
    pub bad_messages: u64,
    /// Camera info changes.
    pub camera_changes: u64,
    /// Input stalls.
    pub stalls: u64,
    /// Queries answered.
    pub queries: u64,
    /// Queries that failed.
    pub query_errors: u64,
    /// Queries dropped because the query queue was full.
    #[serde(default)]
    pub queries_dropped: u64,
    /// Maps published.
    pub maps_published: u64,
}
