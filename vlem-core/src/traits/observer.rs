//! `RunObserver`: a look at every frame as the pipeline processes it.
//!
//! Why it exists: people look at maps rather than read them. A visualiser (the binary's rerun
//! recorder), a debugger or a logger needs each frame's pose, its region proposals and the growing
//! map, none of which the pipeline otherwise hands out before the run ends. An observer owns only
//! what it does with that view; it cannot change the run. Both methods are called from the
//! pipeline's threads (tracking and embedding run concurrently), hence `Sync`, and both default to
//! doing nothing so an observer implements only what it shows.

use crate::traits::embedding_map::EmbeddingMap;
use crate::traits::tracker::TrackedPose;
use crate::types::{Frame, Pose, Region};

/// Receives each frame as it is tracked and as it is integrated.
pub trait RunObserver: Sync {
    /// Frame `frame` was tracked (lost or not); called on the tracking thread, in frame order.
    fn frame_tracked(&self, frame: &Frame, tracked: &TrackedPose) {
        let _ = (frame, tracked);
    }

    /// Frame `frame` was integrated into `map` at `pose`, with the region proposer's `regions`
    /// (empty without a proposer); called on the embedding thread, in frame order.
    fn frame_integrated(
        &self,
        frame: &Frame,
        pose: &Pose,
        regions: &[Region],
        map: &dyn EmbeddingMap,
    ) {
        let _ = (frame, pose, regions, map);
    }
}

/// The observer of a run nobody watches.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoObserver;

impl RunObserver for NoObserver {}
