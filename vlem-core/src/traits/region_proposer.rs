//! `RegionProposer`: image regions for region encoders.
//!
//! Why it exists: the paper's segment embeddings (section "Segment-Embeddings") encode one crop per
//! region. Where the regions come from (SAM with fill-in refinement, a weight-free graph
//! segmentation, ...) is independent of how they are encoded, so it is its own stage. A proposer owns
//! only the 2D segmentation of one colour image.

use crate::error::Result;
use crate::types::{Region, RgbImage};

/// Proposes regions (bounding box + mask) in a colour image.
pub trait RegionProposer: Send + Sync {
    /// The registered name.
    fn name(&self) -> &'static str;

    /// The regions of `image`; may be empty.
    ///
    /// # Errors
    /// Failures of the underlying model.
    fn propose(&self, image: &RgbImage) -> Result<Vec<Region>>;
}
