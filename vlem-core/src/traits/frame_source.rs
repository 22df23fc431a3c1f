//! `FrameSource`: where RGB-D frames come from.
//!
//! Why it exists: the pipeline must not care whether frames come from a dataset folder, a synthetic
//! scene or a live camera. A source owns decoding and unit conversion (depth to metres, poses to
//! camera-to-world), so every stage downstream sees the conventions of [`crate::types`].

use crate::error::Result;
use crate::types::{Frame, Intrinsics};

/// A finite, random-access sequence of frames.
pub trait FrameSource: Send {
    /// A short description for logs (e.g. "ICL-NUIM folder data/living-room").
    fn describe(&self) -> String;

    /// Number of frames.
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
}
