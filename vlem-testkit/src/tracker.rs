//! The conformance suite for [`Tracker`] implementations:
//! [`tracker_conformance!`](crate::tracker_conformance).
//!
//! The suite runs on frames the invoking crate supplies ([`TrackerFrames`]: at least
//! [`MIN_FRAMES`] valid frames of one sequence in order, a small motion apart, with dataset poses),
//! so that each tracker is checked on data it can track. What every tracker must do:
//! - [`Tracker::name`] is a name registered for the tracker stage in the registry;
//! - every pose it returns is finite with a unit rotation ([`pose_is_finite`]), whatever the
//!   frame: a frame without any valid depth (all zero, all NaN), a frame whose depth is littered
//!   with NaN, infinite, negative and zero values, and a frame from elsewhere (the next frame turned
//!   upside down, a jump no tracker follows) included;
//! - the supplied sequence is tracked: every frame is [`TrackingState::Tracking`];
//! - a frame without any valid depth is reported [`TrackingState::Lost`] with a reason (also as the
//!   first frame);
//! - the same frame twice in a row gives (close to) the identity motion between the two poses;
//! - after a lost frame, the next good frame is tracked again, at (close to) the pose it gets in
//!   a run without the lost frame;
//! - a tracker that does not read dataset poses tracks frames that have none; one that does
//!   ([`Tracker::needs_dataset_poses`]) refuses such a frame with an error, not a panic.
//!
//! A tracker that returns the dataset's poses ([`TrackerContract::DatasetPoses`], e.g.
//! `ground-truth`) cannot lose a frame: the pose of a frame without depth is still known. For it the
//! lost-frame checks instead require the frame's own dataset pose, reported as tracking, and the
//! repeated-frame and recovery checks require exact dataset poses.
//!
//! The checks report failures by panicking, like `assert!`, with the tracker and frame in the
//! message.
#![allow(
    clippy::panic,
    reason = "a test kit reports failed checks by panicking, exactly as assert! does"
)]

use vlem_core::types::pose_is_finite;
use vlem_core::{
    DepthImage, Frame, Pose, Registry, StageKind, TrackedPose, Tracker, TrackingState,
};

/// How the suite gets a tracker: a function (or non-capturing closure) building a fresh one.
pub type BuildTracker = fn() -> Box<dyn Tracker>;

/// How the suite gets its frames: at least [`MIN_FRAMES`] valid frames of one sequence, in order,
/// consecutive frames a small motion apart (a few centimetres and degrees), each with its dataset
/// pose.
pub type TrackerFrames = fn() -> Vec<Frame>;

/// The fewest frames a [`TrackerFrames`] function must supply.
pub const MIN_FRAMES: usize = 4;

/// How far (metres) the motion between two poses of one repeated frame may be from the identity.
pub const REPEATED_FRAME_TRANSLATION: f64 = 2e-3;

/// How far (degrees) the motion between two poses of one repeated frame may be from the identity.
pub const REPEATED_FRAME_ROTATION_DEGREES: f64 = 0.2;

/// How far (metres) the pose of the first frame after a lost one may be from its pose in a run
/// without the lost frame.
pub const RECOVERY_TRANSLATION: f64 = 1e-2;

/// How far (degrees) the pose of the first frame after a lost one may be from its pose in a run
/// without the lost frame.
pub const RECOVERY_ROTATION_DEGREES: f64 = 1.0;

/// What a tracker promises about lost frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackerContract {
    /// It estimates poses from the images: a frame without valid depth is lost.
    Estimates,
    /// It returns each frame's dataset pose (`ground-truth`): no frame is lost, since the pose of a
    /// frame without depth is still known, and every pose is exactly the dataset's.
    DatasetPoses,
}

/// Runs the tracker conformance suite as `#[test]` functions in a module `tracker_conformance`.
///
/// `$build` is an expression of type [`BuildTracker`] (`fn() -> Box<dyn Tracker>`) and `$frames`
/// one of type [`TrackerFrames`] (`fn() -> Vec<Frame>`): function paths or closures that capture
/// nothing. Each test builds its own tracker and frames. An optional third argument, a
/// [`TrackerContract`], says what the tracker promises about lost frames; the default is
/// [`TrackerContract::Estimates`]. The crate that registers the tracker must be linked into the
/// test binary (building the tracker through it is enough).
///
/// Invoke it once per module (it declares `mod tracker_conformance`). `$build` and `$frames` are
/// expanded inside that module, which imports the invoking module's items with `use super::*`:
/// plain names and `crate::` paths work, `super::` paths do not.
///
/// ```
/// use vlem_core::{DepthImage, Frame, Intrinsics, Pose, Result, RgbImage};
/// use vlem_core::{TrackedPose, Tracker, TrackingState};
///
/// /// Stays where it started; loses frames without depth.
/// struct Still;
///
/// impl Tracker for Still {
///     fn name(&self) -> &'static str {
///         "still"
///     }
///     fn track(&mut self, frame: &Frame) -> Result<TrackedPose> {
///         let valid = frame.depth.as_raw().iter().any(|d| d.is_finite() && *d > 0.0);
///         let state = if valid {
///             TrackingState::Tracking
///         } else {
///             TrackingState::Lost { reason: "no valid depth".into() }
///         };
///         Ok(TrackedPose { pose: Pose::identity(), state })
///     }
/// }
///
/// fn frames() -> Vec<Frame> {
///     let k = Intrinsics::new(8, 6, 8.0, 8.0, 3.5, 2.5).unwrap();
///     (0..4)
///         .map(|i| {
///             let colour = RgbImage::filled(8, 6, [100, 100, 100]);
///             let depth = DepthImage::new(8, 6, vec![1.0; 48]).unwrap();
///             Frame::new(i, i as f64, colour, depth, k, Some(Pose::identity())).unwrap()
///         })
///         .collect()
/// }
///
/// // A real tracker also registers itself (`vlem_core::register_tracker!("still", ...)`),
/// // which the suite's `name_is_registered` checks.
/// vlem_testkit::tracker_conformance!(|| Box::new(Still), frames);
/// # fn main() {}
/// ```
#[macro_export]
macro_rules! tracker_conformance {
    ($build:expr, $frames:expr $(,)?) => {
        $crate::tracker_conformance!($build, $frames, $crate::tracker::TrackerContract::Estimates);
    };
    ($build:expr, $frames:expr, $contract:expr $(,)?) => {
        /// The vlem-testkit tracker conformance suite.
        mod tracker_conformance {
            #[allow(
                unused_imports,
                reason = "`$build` and `$frames` may name items of the invoking module"
            )]
            use super::*;

            #[test]
            fn name_is_registered() {
                $crate::tracker::check_registered($build);
            }

            #[test]
            fn the_sequence_is_tracked_with_finite_poses() {
                $crate::tracker::check_sequence($build, $frames, $contract);
            }

            #[test]
            fn a_frame_without_depth_is_lost_with_a_reason() {
                $crate::tracker::check_lost_frame($build, $frames, $contract);
            }

            #[test]
            fn bad_depth_and_jumps_give_finite_poses() {
                $crate::tracker::check_finite_poses($build, $frames);
            }

            #[test]
            fn a_repeated_frame_gives_the_identity_motion() {
                $crate::tracker::check_repeated_frame($build, $frames, $contract);
            }

            #[test]
            fn tracking_recovers_after_a_lost_frame() {
                $crate::tracker::check_recovery($build, $frames, $contract);
            }

            #[test]
            fn dataset_poses_are_used_only_when_needed() {
                $crate::tracker::check_dataset_poses($build, $frames);
            }
        }
    };
}

/// Checks that the tracker's name is registered for the tracker stage.
#[track_caller]
pub fn check_registered(build: BuildTracker) {
    let tracker = build();
    let name = tracker.name();
    let registry = match Registry::global() {
        Ok(r) => r,
        Err(e) => panic!("the registry cannot be built: {e}"),
    };
    if let Err(e) = registry.get(StageKind::Tracker, name) {
        panic!("tracker `{name}` is not registered: {e}");
    }
}

/// Checks that every supplied frame is tracked, with a finite pose (the dataset's exactly, for
/// [`TrackerContract::DatasetPoses`]).
#[track_caller]
pub fn check_sequence(build: BuildTracker, frames: TrackerFrames, contract: TrackerContract) {
    let frames = supplied(frames);
    let mut tracker = build();
    for frame in &frames {
        let tracked = track(tracker.as_mut(), frame, "frame of the sequence");
        assert_tracking(tracker.as_ref(), frame, &tracked, "frame of the sequence");
        if contract == TrackerContract::DatasetPoses {
            assert_dataset_pose(tracker.as_ref(), frame, &tracked);
        }
    }
}

/// Checks that a frame without any valid depth (all zero, all NaN) is lost with a non-empty
/// reason and a finite pose, after two tracked frames and as the very first frame. For
/// [`TrackerContract::DatasetPoses`] it is tracked at its dataset pose instead.
#[track_caller]
pub fn check_lost_frame(build: BuildTracker, frames: TrackerFrames, contract: TrackerContract) {
    let frames = supplied(frames);
    for (what, value) in [("zero depth", 0.0), ("NaN depth", f32::NAN)] {
        let mut tracker = build();
        for frame in &frames[..2] {
            let tracked = track(tracker.as_mut(), frame, "frame of the sequence");
            assert_tracking(tracker.as_ref(), frame, &tracked, "frame of the sequence");
        }
        let blank = with_depth(&frames[2], |_, _| value);
        let what_frame = format!("frame with {what}");
        let tracked = track(tracker.as_mut(), &blank, &what_frame);
        assert_lost_or_dataset_pose(tracker.as_ref(), &blank, &tracked, contract, &what_frame);

        let mut fresh = build();
        let first = with_depth(&frames[0], |_, _| value);
        let what_first = format!("first frame, with {what}");
        let tracked = track(fresh.as_mut(), &first, &what_first);
        assert_lost_or_dataset_pose(fresh.as_ref(), &first, &tracked, contract, &what_first);
    }
}

/// Checks that poses stay finite through frames whose depth is littered with NaN, infinite,
/// negative and zero values, and through a jump to a view no tracker follows (the next frame turned
/// upside down), and that a good frame after them still gets a finite pose.
#[track_caller]
pub fn check_finite_poses(build: BuildTracker, frames: TrackerFrames) {
    let frames = supplied(frames);
    let specials = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, 0.0];
    let littered = with_depth(&frames[1], |i, d| {
        if i % 3 == 0 {
            specials[i / 3 % specials.len()]
        } else {
            d
        }
    });
    let flipped = upside_down(&frames[2]);
    let mut tracker = build();
    let sequence = [
        (&frames[0], "first frame"),
        (
            &littered,
            "frame with NaN, infinite, negative and zero depth",
        ),
        (&flipped, "frame turned upside down (a jump)"),
        (&frames[3], "good frame after the jump"),
    ];
    for (frame, what) in sequence {
        // `track` checks that the pose is finite.
        let _ = track(tracker.as_mut(), frame, what);
    }
}

/// Checks that tracking the same frame twice in a row gives two poses whose relative motion is
/// within [`REPEATED_FRAME_TRANSLATION`] and [`REPEATED_FRAME_ROTATION_DEGREES`] of the identity
/// (exactly the identity, at the dataset pose, for [`TrackerContract::DatasetPoses`]).
#[track_caller]
pub fn check_repeated_frame(build: BuildTracker, frames: TrackerFrames, contract: TrackerContract) {
    let frames = supplied(frames);
    let mut tracker = build();
    let first = track(tracker.as_mut(), &frames[0], "frame 0");
    assert_tracking(tracker.as_ref(), &frames[0], &first, "frame 0");
    let once = track(tracker.as_mut(), &frames[1], "frame 1");
    assert_tracking(tracker.as_ref(), &frames[1], &once, "frame 1");
    let twice = track(tracker.as_mut(), &frames[1], "frame 1 again");
    assert_tracking(tracker.as_ref(), &frames[1], &twice, "frame 1 again");
    let (translation, degrees) = difference(&once.pose, &twice.pose);
    let (max_translation, max_degrees) = match contract {
        TrackerContract::Estimates => (REPEATED_FRAME_TRANSLATION, REPEATED_FRAME_ROTATION_DEGREES),
        TrackerContract::DatasetPoses => {
            assert_dataset_pose(tracker.as_ref(), &frames[1], &twice);
            // Equal poses; the composition `a⁻¹ b` still rounds.
            (1e-9, 1e-6)
        }
    };
    assert!(
        translation <= max_translation && degrees <= max_degrees,
        "tracker `{}`: the same frame twice moved the camera by {translation:.2e} m and \
         {degrees:.3}° (at most {max_translation:.1e} m and {max_degrees}°)",
        tracker.name()
    );
}

/// Checks that after a frame without depth the next good frame is tracked, at a pose within
/// [`RECOVERY_TRANSLATION`] and [`RECOVERY_ROTATION_DEGREES`] of the pose it gets in a run
/// without the lost frame (exactly its dataset pose for [`TrackerContract::DatasetPoses`]).
#[track_caller]
pub fn check_recovery(build: BuildTracker, frames: TrackerFrames, contract: TrackerContract) {
    let frames = supplied(frames);
    let mut uninterrupted = build();
    let mut reference = Pose::identity();
    for frame in &frames[..4] {
        let tracked = track(uninterrupted.as_mut(), frame, "frame of the sequence");
        assert_tracking(
            uninterrupted.as_ref(),
            frame,
            &tracked,
            "frame of the sequence",
        );
        reference = tracked.pose;
    }

    let mut tracker = build();
    for frame in &frames[..2] {
        let tracked = track(tracker.as_mut(), frame, "frame of the sequence");
        assert_tracking(tracker.as_ref(), frame, &tracked, "frame of the sequence");
    }
    let blank = with_depth(&frames[2], |_, _| 0.0);
    let tracked = track(tracker.as_mut(), &blank, "frame with zero depth");
    assert_lost_or_dataset_pose(
        tracker.as_ref(),
        &blank,
        &tracked,
        contract,
        "frame with zero depth",
    );
    let what = "first good frame after the lost one";
    let recovered = track(tracker.as_mut(), &frames[3], what);
    assert_tracking(tracker.as_ref(), &frames[3], &recovered, what);
    let (max_translation, max_degrees) = match contract {
        TrackerContract::Estimates => (RECOVERY_TRANSLATION, RECOVERY_ROTATION_DEGREES),
        TrackerContract::DatasetPoses => {
            assert_dataset_pose(tracker.as_ref(), &frames[3], &recovered);
            // Equal poses; the composition `a⁻¹ b` still rounds.
            (1e-9, 1e-6)
        }
    };
    let (translation, degrees) = difference(&reference, &recovered.pose);
    assert!(
        translation <= max_translation && degrees <= max_degrees,
        "tracker `{}`: frame {} after a lost frame is {translation:.2e} m and {degrees:.3}° from \
         its pose in a run without the loss (at most {max_translation:.1e} m and {max_degrees}°)",
        tracker.name(),
        frames[3].index
    );
}

/// Checks that a tracker that does not read dataset poses tracks frames without them, and that one
/// that does ([`Tracker::needs_dataset_poses`]) refuses a frame without a pose with an error.
#[track_caller]
pub fn check_dataset_poses(build: BuildTracker, frames: TrackerFrames) {
    let frames = supplied(frames);
    let mut tracker = build();
    if tracker.needs_dataset_poses() {
        let mut frame = frames[0].clone();
        frame.pose = None;
        assert!(
            tracker.track(&frame).is_err(),
            "tracker `{}` needs dataset poses but tracked a frame without one",
            tracker.name()
        );
    } else {
        for frame in &frames {
            let mut frame = frame.clone();
            frame.pose = None;
            let tracked = track(tracker.as_mut(), &frame, "frame without a dataset pose");
            assert_tracking(
                tracker.as_ref(),
                &frame,
                &tracked,
                "frame without a dataset pose",
            );
        }
    }
}

/// `frame` with depth `f(pixel index, depth)` (labels dropped).
pub fn with_depth(frame: &Frame, f: impl Fn(usize, f32) -> f32) -> Frame {
    let (w, h) = (frame.depth.width(), frame.depth.height());
    let depth: Vec<f32> = frame
        .depth
        .as_raw()
        .iter()
        .enumerate()
        .map(|(i, &d)| f(i, d))
        .collect();
    let depth = DepthImage::new(w, h, depth).unwrap_or_else(|e| panic!("depth of {w}x{h}: {e}"));
    rebuilt(frame, frame.colour.clone(), depth)
}

/// `frame` turned upside down (rotated 180° about the optical axis; labels dropped).
pub fn upside_down(frame: &Frame) -> Frame {
    let (w, h) = (frame.depth.width(), frame.depth.height());
    let mut depth = frame.depth.as_raw().to_vec();
    depth.reverse();
    let colour: Vec<u8> = frame
        .colour
        .as_raw()
        .chunks_exact(3)
        .rev()
        .flatten()
        .copied()
        .collect();
    let depth = DepthImage::new(w, h, depth).unwrap_or_else(|e| panic!("depth of {w}x{h}: {e}"));
    let colour =
        vlem_core::RgbImage::new(w, h, colour).unwrap_or_else(|e| panic!("colour of {w}x{h}: {e}"));
    rebuilt(frame, colour, depth)
}

fn rebuilt(frame: &Frame, colour: vlem_core::RgbImage, depth: DepthImage) -> Frame {
    Frame::new(
        frame.index,
        frame.timestamp,
        colour,
        depth,
        frame.intrinsics,
        frame.pose,
    )
    .unwrap_or_else(|e| panic!("frame {} rebuilt with other images: {e}", frame.index))
}

/// Translation (metres) and rotation angle (degrees) of the motion from `a` to `b`.
pub fn difference(a: &Pose, b: &Pose) -> (f64, f64) {
    let motion = a.inverse() * b;
    (
        motion.translation.vector.norm(),
        motion.rotation.angle().to_degrees(),
    )
}

/// The supplied frames, checked to be enough.
#[track_caller]
fn supplied(frames: TrackerFrames) -> Vec<Frame> {
    let frames = frames();
    assert!(
        frames.len() >= MIN_FRAMES,
        "the tracker suite needs at least {MIN_FRAMES} frames, got {}",
        frames.len()
    );
    assert!(
        frames.iter().all(|f| f.pose.is_some()),
        "the tracker suite needs frames with dataset poses"
    );
    frames
}

/// Tracks `frame`, panicking on an error or a non-finite pose.
#[track_caller]
fn track(tracker: &mut dyn Tracker, frame: &Frame, what: &str) -> TrackedPose {
    let tracked = tracker.track(frame).unwrap_or_else(|e| {
        panic!(
            "tracker `{}`, {what} {}: error {e}",
            tracker.name(),
            frame.index
        )
    });
    assert!(
        pose_is_finite(&tracked.pose),
        "tracker `{}`, {what} {}: non-finite pose {:?}",
        tracker.name(),
        frame.index,
        tracked.pose
    );
    tracked
}

#[track_caller]
fn assert_tracking(tracker: &dyn Tracker, frame: &Frame, tracked: &TrackedPose, what: &str) {
    assert!(
        tracked.state == TrackingState::Tracking,
        "tracker `{}`, {what} {}: {:?}",
        tracker.name(),
        frame.index,
        tracked.state
    );
}

#[track_caller]
fn assert_dataset_pose(tracker: &dyn Tracker, frame: &Frame, tracked: &TrackedPose) {
    assert!(
        Some(tracked.pose) == frame.pose,
        "tracker `{}`, frame {}: pose {:?} is not the dataset's {:?}",
        tracker.name(),
        frame.index,
        tracked.pose,
        frame.pose
    );
}

#[track_caller]
fn assert_lost_or_dataset_pose(
    tracker: &dyn Tracker,
    frame: &Frame,
    tracked: &TrackedPose,
    contract: TrackerContract,
    what: &str,
) {
    match contract {
        TrackerContract::Estimates => match &tracked.state {
            TrackingState::Lost { reason } => assert!(
                !reason.trim().is_empty(),
                "tracker `{}`, {what} {}: lost without a reason",
                tracker.name(),
                frame.index
            ),
            TrackingState::Tracking => panic!(
                "tracker `{}`, {what} {}: reported as tracking, not lost",
                tracker.name(),
                frame.index
            ),
        },
        TrackerContract::DatasetPoses => {
            assert_tracking(tracker, frame, tracked, what);
            assert_dataset_pose(tracker, frame, tracked);
        }
    }
}
