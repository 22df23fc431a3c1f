//! `FrameSource`: where RGB-D frames come from.
//!
//! Why it exists: the pipeline must not care whether frames come from a dataset folder, a synthetic
//! scene or a live camera. A source owns decoding and unit conversion (depth to metres, poses to
//! camera-to-world), so every stage downstream sees the conventions of [`crate::types`].

use crate::error::Result;
use crate::types::{Frame, Intrinsics};

/// A sequence of frames: a finite, random-access one (a dataset), or a live one whose frames
/// arrive in order ([`crate::stream::FrameStream`]).
pub trait FrameSource: Send {
    /// A short description for logs (e.g. "ICL-NUIM folder data/living-room").
    fn describe(&self) -> String;

    /// Number of frames; 0 for a live source, whose length is not known in advance.
    fn len(&self) -> usize;

    /// Whether the source has no frames.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The camera (the same for every frame).
    fn intrinsics(&self) -> Intrinsics;

    /// Whether frames carry poses (ground truth or offline estimates).
    fn has_poses(&self) -> bool;

    /// Loads frame `index` (0-based, `< len()`).
    ///
    /// # Errors
    /// A typed error naming the file that is missing, unreadable or inconsistent.
    fn frame(&mut self, index: usize) -> Result<Frame>;

    /// What the reader noticed when it opened the source and a user should know before a run
    /// (frames it dropped and why, calibration it cannot apply, a frame convention it could not
    /// check); front-ends print each as a warning. Empty by default.
    fn warnings(&self) -> Vec<String> {
        Vec::new()
    }

    /// Whether frames arrive from outside at their own rate (a camera, a robot's topics) rather
    /// than being read on demand: the pipeline then reads with [`FrameSource::next_frame`] until
    /// it answers `None`, and does not pace the source in real-time mode.
    fn is_live(&self) -> bool {
        false
    }

    /// The frame at position `index` of the run, or `None` at the end: [`FrameSource::frame`]
    /// while `index < len()` for a finite source; a live source waits for its next frame.
    ///
    /// # Errors
    /// As [`FrameSource::frame`].
    fn next_frame(&mut self, index: usize) -> Result<Option<Frame>> {
        if index < self.len() {
            self.frame(index).map(Some)
        } else {
            Ok(None)
        }
    }
}
