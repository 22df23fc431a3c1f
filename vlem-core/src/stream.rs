//! A push-based frame source: frames that arrive from outside (a live camera, a robot's topics, a
//! Python caller) instead of being read from a dataset.
//!
//! Why it exists: the pipeline pulls frames from a [`FrameSource`], and a dataset folder can hand
//! out any frame on demand. A live source cannot: frames come when the sensor sends them. Every
//! live front-end (the Python package's frame feeding, the ROS 2 node, a future camera driver)
//! shares this one source instead of writing its own queue: a bounded channel from any number of
//! [`FrameSender`]s to the [`FrameStream`] the pipeline runs on, timestamps from the sender, and a
//! clear end of stream (every sender finished or dropped).
//!
//! The tracking thread reads every frame in order (a tracker needs every frame); in
//! [`crate::config::Mode::RealTime`] the pipeline does not pace a live source (its frames arrive at
//! their own rate) and skips embedding frames that arrive while the embedding stage is busy, as for
//! a dataset. When tracking falls behind, the channel fills: [`FrameSender::send`] waits for room,
//! [`FrameSender::try_send`] hands the frame back so the caller can drop and count it.

use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex, PoisonError};

use crate::error::{CoreError, Result};
use crate::traits::frame_source::FrameSource;
use crate::types::{Frame, Intrinsics};

/// What a stream is: its camera and whether its frames carry poses.
#[derive(Clone, Debug)]
pub struct StreamSpec {
    /// A short description for logs (e.g. "the ROS 2 topics /camera/color/image_raw, ...").
    pub description: String,
    /// The camera every frame must have.
    pub intrinsics: Intrinsics,
    /// Whether every frame carries a pose (from the robot's odometry, tf or the caller); a
    /// ground-truth tracker needs it, an estimating tracker keeps such poses as the reference.
    pub has_poses: bool,
    /// Frames that may wait between the senders and the tracking thread (1 to
    /// [`crate::config::MAX_QUEUE_CAPACITY`]).
    pub capacity: usize,
    /// The largest forward jump of a frame's timestamp past the previous frame's that the stream
    /// takes at once, in seconds ([`DEFAULT_MAX_STAMP_JUMP`]). A frame beyond it is refused without
    /// becoming the stream's time, so one frame stamped in the far future cannot lock out every
    /// later one; [`JUMP_CONFIRMATIONS`] frames in a row after such a jump, each within the bound
    /// of the one before (a camera that was paused), make it the stream's new time.
    pub max_stamp_jump: f64,
}

/// [`StreamSpec::max_stamp_jump`] by default: 10 s.
pub const DEFAULT_MAX_STAMP_JUMP: f64 = 10.0;

/// Frames in a row that confirm a timestamp jump (see [`StreamSpec::max_stamp_jump`]).
pub const JUMP_CONFIRMATIONS: usize = 3;

/// Creates a stream: the senders a live source pushes frames into, and the [`FrameSource`] a
/// pipeline runs on.
///
/// # Errors
/// [`CoreError::InvalidIntrinsics`] for an impossible camera, [`CoreError::InvalidParams`] for a
/// capacity outside 1 to [`crate::config::MAX_QUEUE_CAPACITY`] (its slots are allocated up front).
pub fn frame_stream(spec: StreamSpec) -> Result<(FrameSender, FrameStream)> {
    spec.intrinsics.validate()?;
    if !(spec.max_stamp_jump.is_finite() && spec.max_stamp_jump > 0.0) {
        return Err(CoreError::InvalidParams {
            section: "stream".into(),
            name: spec.description.clone(),
            message: format!(
                "max_stamp_jump must be a positive number of seconds, got {}",
                spec.max_stamp_jump
            ),
        });
    }
    let max = crate::config::MAX_QUEUE_CAPACITY;
    if !(1..=max).contains(&spec.capacity) {
        return Err(CoreError::InvalidParams {
            section: "stream".into(),
            name: spec.description.clone(),
            message: format!(
                "capacity must be at least 1 frame and at most {max}, got {}",
                spec.capacity
            ),
        });
    }
    let (sender, receiver) = sync_channel(spec.capacity);
    let shared = Arc::new(Mutex::new(Sequence::default()));
    Ok((
        FrameSender {
            sender,
            spec: Arc::new(spec.clone()),
            sequence: shared,
        },
        FrameStream { receiver, spec },
    ))
}

/// Where the senders are in the stream: the next index and the last timestamp, and the refused
/// frames after a timestamp jump (the last one's stamp and how many in a row).
#[derive(Default)]
struct Sequence {
    next_index: usize,
    last_timestamp: Option<f64>,
    jumped: Option<(f64, usize)>,
}

/// The pushing end of a stream; clone it for several producers. The stream ends when every sender
/// is finished or dropped.
#[derive(Clone)]
pub struct FrameSender {
    sender: SyncSender<Frame>,
    spec: Arc<StreamSpec>,
    sequence: Arc<Mutex<Sequence>>,
}

impl FrameSender {
    /// The stream's description.
    pub fn spec(&self) -> &StreamSpec {
        &self.spec
    }

    /// Pushes a frame, waiting while the stream is full. The frame's index is replaced by its
    /// position in the stream.
    ///
    /// # Errors
    /// [`CoreError::FrameRefused`] for a frame that does not fit the stream (the stream goes on),
    /// [`CoreError::StreamClosed`] once the pipeline has stopped reading.
    pub fn send(&self, frame: Frame) -> Result<usize> {
        // Held while waiting for room, so concurrent senders keep their order.
        let mut sequence = self.sequence.lock().unwrap_or_else(PoisonError::into_inner);
        let timestamp = frame.timestamp;
        let frame = self.admit(&mut sequence, frame)?;
        let index = frame.index;
        self.sender
            .send(frame)
            .map_err(|_| CoreError::StreamClosed)?;
        sequence.next_index += 1;
        sequence.last_timestamp = Some(timestamp);
        sequence.jumped = None;
        Ok(index)
    }

    /// Pushes a frame if there is room: `Ok(Some(index))` when it was queued, `Ok(None)` when the
    /// stream is full (the frame is dropped; count it).
    ///
    /// # Errors
    /// As [`FrameSender::send`].
    pub fn try_send(&self, frame: Frame) -> Result<Option<usize>> {
        let mut sequence = self.sequence.lock().unwrap_or_else(PoisonError::into_inner);
        let timestamp = frame.timestamp;
        let frame = self.admit(&mut sequence, frame)?;
        let index = frame.index;
        match self.sender.try_send(frame) {
            Ok(()) => {
                sequence.next_index += 1;
                sequence.last_timestamp = Some(timestamp);
                sequence.jumped = None;
                Ok(Some(index))
            }
            Err(TrySendError::Full(_)) => Ok(None),
            Err(TrySendError::Disconnected(_)) => Err(CoreError::StreamClosed),
        }
    }

    /// Ends this sender's part of the stream (as dropping it does); the pipeline's run ends after
    /// the frames already queued once every sender has finished.
    pub fn finish(self) {}

    /// Checks a frame against the stream and gives it its index.
    fn admit(&self, sequence: &mut Sequence, mut frame: Frame) -> Result<Frame> {
        let refuse = |reason: String| Err(CoreError::FrameRefused { reason });
        if !frame.timestamp.is_finite() {
            return refuse(format!("its timestamp {} is not finite", frame.timestamp));
        }
        if let Some(previous) = sequence.last_timestamp {
            let stamp = frame.timestamp;
            if stamp <= previous {
                return refuse(format!(
                    "its timestamp {stamp} s is not after the previous frame's ({previous} s)"
                ));
            }
            let max = self.spec.max_stamp_jump;
            if stamp - previous > max {
                let run = match sequence.jumped {
                    Some((last, n)) if stamp > last && stamp - last <= max => n + 1,
                    _ => 1,
                };
                if run < JUMP_CONFIRMATIONS {
                    sequence.jumped = Some((stamp, run));
                    return refuse(format!(
                        "its timestamp {stamp} s jumps {:.3} s past the previous frame's \
                         ({previous} s), more than the stream's max_stamp_jump of {max} s; it \
                         becomes the stream's time if {} more frames follow it",
                        stamp - previous,
                        JUMP_CONFIRMATIONS - run
                    ));
                }
            }
        }
        let (expected, actual) = (&self.spec.intrinsics, &frame.intrinsics);
        if actual != expected {
            return refuse(format!(
                "its camera ({}x{}, fx {} fy {} cx {} cy {}) is not the stream's ({}x{}, fx {} fy \
                 {} cx {} cy {}); start a new stream for another camera",
                actual.width,
                actual.height,
                actual.fx,
                actual.fy,
                actual.cx,
                actual.cy,
                expected.width,
                expected.height,
                expected.fx,
                expected.fy,
                expected.cx,
                expected.cy
            ));
        }
        if self.spec.has_poses && frame.pose.is_none() {
            return refuse(
                "it has no pose, but this stream's frames carry poses (the tracker reads them)"
                    .into(),
            );
        }
        frame.index = sequence.next_index;
        Ok(frame)
    }
}

/// The pipeline's end of a stream: a [`FrameSource`] whose frames are read in order as they
/// arrive, until every sender has finished.
pub struct FrameStream {
    receiver: Receiver<Frame>,
    spec: StreamSpec,
}

impl FrameSource for FrameStream {
    fn describe(&self) -> String {
        self.spec.description.clone()
    }

    /// Unknown for a live source: 0.
    fn len(&self) -> usize {
        0
    }

    fn intrinsics(&self) -> Intrinsics {
        self.spec.intrinsics
    }

    fn has_poses(&self) -> bool {
        self.spec.has_poses
    }

    fn is_live(&self) -> bool {
        true
    }

    fn frame(&mut self, index: usize) -> Result<Frame> {
        Err(CoreError::Dataset {
            source: format!(
                "{} is a live stream: frames are read in order as they arrive, not by index \
                 (asked for frame {index})",
                self.spec.description
            )
            .into(),
        })
    }

    /// Waits for the next frame; `None` once every sender has finished and the queue is empty.
    fn next_frame(&mut self, _index: usize) -> Result<Option<Frame>> {
        Ok(self.receiver.recv().ok())
    }
}
