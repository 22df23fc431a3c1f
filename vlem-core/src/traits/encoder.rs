//! `Encoder`: vision-language embeddings for pixels and for text.
//!
//! Why it exists: the paper compares VLM backends (CLIP on regions, DINOv3 dino.txt and NARADIO on
//! patches) under one pipeline; researchers add new ones. An encoder owns its model weights and
//! produces [`PixelEmbeddings`] in whichever layout it computes natively (regions or patch grid),
//! never a dense per-pixel tensor. The text side is a capability: an image-only encoder returns
//! [`CoreError::Unsupported`] from [`Encoder::encode_text`].

use crate::embeddings::PixelEmbeddings;
use crate::error::{CoreError, Result};
use crate::types::{Frame, Region, RgbImage};

/// The text that describes anything: the baseline that the `argmax` and `cluster` segmenters
/// compare every query against unless one is configured. An encoder that cannot embed it names
/// its own in [`Encoder::generic_text`], which queries then use in its place.
pub const GENERIC_TEXT: &str = "object";

/// Maps images (and, where supported, text) into one embedding space of dimension [`Encoder::dim`].
pub trait Encoder: Send + Sync {
    /// The registered name.
    fn name(&self) -> &'static str;

    /// Embedding dimension of both sides.
    fn dim(&self) -> usize;

    /// Whether [`Encoder::encode_image`] needs regions from a [`crate::RegionProposer`].
    fn needs_regions(&self) -> bool {
        false
    }

    /// Whether the encoder reads the frame's ground-truth labels ([`Frame::labels`]), as
    /// label-driven upper-bound encoders do; the pipeline refuses frames without labels for it.
    fn needs_labels(&self) -> bool {
        false
    }

    /// Embeds a frame: what the pipeline calls. The default embeds the colour image with
    /// [`Encoder::encode_image`]; encoders that read more of the frame (its labels) override it.
    ///
    /// # Errors
    /// As [`Encoder::encode_image`].
    fn encode_frame(&self, frame: &Frame, regions: &[Region]) -> Result<PixelEmbeddings> {
        self.encode_image(&frame.colour, regions)
    }

    /// Embeds an image. `regions` is empty unless [`Encoder::needs_regions`] is true.
    ///
    /// # Errors
    /// Model failures, or inconsistent inputs.
    fn encode_image(&self, image: &RgbImage, regions: &[Region]) -> Result<PixelEmbeddings>;

    /// Embeds a text query into a unit-norm vector of length [`Encoder::dim`].
    ///
    /// # Errors
    /// [`CoreError::Unsupported`] for encoders without a text side (the default), or a message
    /// saying why this text cannot be embedded.
    fn encode_text(&self, text: &str) -> Result<Vec<f32>> {
        let _ = text;
        Err(CoreError::Unsupported {
            implementation: format!("encoder `{}`", self.name()),
            capability: "text encoding",
        })
    }

    /// This encoder's text for [`GENERIC_TEXT`] (the default baseline): one it can embed that
    /// describes anything. The default is [`GENERIC_TEXT`] itself; an encoder whose vocabulary
    /// lacks "object" (the colour-names encoder knows colour words only) names its own.
    fn generic_text(&self) -> &str {
        GENERIC_TEXT
    }
}
