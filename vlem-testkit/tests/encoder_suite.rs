//! The encoder suite passes conforming encoders and catches each way of breaking the contract.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::sync::atomic::{AtomicU32, Ordering};

use vlem_core::{CoreError, Encoder, NO_REGION, PixelEmbeddings, Region, Result, RgbImage};
use vlem_testkit::encoder::{
    check_dim, check_image_determinism, check_image_embeddings_unit_norm, check_image_shapes,
    check_text,
};

/// Embeds each pixel as the direction of its colour in RGB space. Configurable misbehaviour.
#[derive(Default)]
struct Rgb {
    /// Claims this dim instead of 3.
    claimed_dim: Option<usize>,
    /// Embeds only the pixels inside the regions, and refuses to run without regions.
    regions_only: bool,
    /// Returns embeddings for an image of half the size.
    half_size: bool,
    /// Shifts every encoding a little more than the last one.
    drifts: Option<AtomicU32>,
    /// Text side: `Some(scale)` embeds colour words as `scale` times a one-hot vector.
    text_scale: Option<f32>,
}

impl Encoder for Rgb {
    fn name(&self) -> &'static str {
        "test-rgb"
    }

    fn dim(&self) -> usize {
        self.claimed_dim.unwrap_or(3)
    }

    fn needs_regions(&self) -> bool {
        self.regions_only
    }

    fn encode_image(&self, image: &RgbImage, regions: &[Region]) -> Result<PixelEmbeddings> {
        if self.regions_only && regions.is_empty() {
            return Err(CoreError::InvalidEmbeddings {
                reason: "no regions".into(),
            });
        }
        let (w, h) = if self.half_size {
            (image.width() / 2, image.height() / 2)
        } else {
            (image.width(), image.height())
        };
        let drift = self
            .drifts
            .as_ref()
            .map_or(0, |d| d.fetch_add(1, Ordering::Relaxed)) as f32;
        let mut index = Vec::new();
        let mut table = Vec::new();
        for v in 0..h {
            for u in 0..w {
                if self.regions_only && !regions.iter().any(|r| r.contains(u, v)) {
                    index.push(NO_REGION);
                    continue;
                }
                index.push((table.len() / 3) as u32);
                let c = image.get(u, v).unwrap();
                table.extend(c.map(|c| f32::from(c) + 1.0 + drift));
            }
        }
        PixelEmbeddings::from_regions(w, h, 3, index, table)
    }

    fn encode_text(&self, text: &str) -> Result<Vec<f32>> {
        let Some(scale) = self.text_scale else {
            return Err(CoreError::Unsupported {
                implementation: "test-rgb".into(),
                capability: "text encoding",
            });
        };
        let k = ["red", "green", "blue"]
            .iter()
            .position(|w| *w == text)
            .ok_or_else(|| CoreError::InvalidEmbeddings {
                reason: format!("no colour in {text:?}"),
            })?;
        let mut v = vec![0.0; 3];
        v[k] = scale;
        Ok(v)
    }
}

fn conforming() -> Box<dyn Encoder> {
    Box::new(Rgb::default())
}

// An image-only encoder passes (its text side answers Unsupported).
vlem_testkit::encoder_conformance!(conforming);

mod with_text {
    // A closure, a text the encoder understands, and an encoder that needs regions.
    vlem_testkit::encoder_conformance!(
        || Box::new(crate::Rgb {
            regions_only: true,
            text_scale: Some(1.0),
            ..crate::Rgb::default()
        }),
        text = "green",
    );
}

#[test]
#[should_panic(expected = "has dim() = 0")]
fn zero_dim_is_caught() {
    check_dim(|| {
        Box::new(Rgb {
            claimed_dim: Some(0),
            ..Rgb::default()
        })
    });
}

#[test]
#[should_panic(expected = "embedding dim differs from Encoder::dim()")]
fn a_wrong_dim_is_caught() {
    check_image_shapes(|| {
        Box::new(Rgb {
            claimed_dim: Some(4),
            ..Rgb::default()
        })
    });
}

#[test]
#[should_panic(expected = "64x48 uniform grey: embeddings cover a different size than the image")]
fn a_wrong_size_is_caught() {
    check_image_shapes(|| {
        Box::new(Rgb {
            half_size: true,
            ..Rgb::default()
        })
    });
}

#[test]
#[should_panic(expected = "not deterministic")]
fn nondeterminism_is_caught() {
    check_image_determinism(|| {
        Box::new(Rgb {
            drifts: Some(AtomicU32::new(0)),
            ..Rgb::default()
        })
    });
}

#[test]
#[should_panic(expected = "no sampled pixel has an embedding")]
fn an_encoder_that_embeds_nothing_is_caught() {
    struct Empty;
    impl Encoder for Empty {
        fn name(&self) -> &'static str {
            "test-empty"
        }
        fn dim(&self) -> usize {
            3
        }
        fn encode_image(&self, image: &RgbImage, _: &[Region]) -> Result<PixelEmbeddings> {
            let n = image.width() as usize * image.height() as usize;
            PixelEmbeddings::from_regions(
                image.width(),
                image.height(),
                3,
                vec![NO_REGION; n],
                Vec::new(),
            )
        }
    }
    check_image_embeddings_unit_norm(|| Box::new(Empty));
}

#[test]
#[should_panic(expected = "has L2 norm 2, expected 1")]
fn a_text_embedding_that_is_not_unit_norm_is_caught() {
    check_text(
        || {
            Box::new(Rgb {
                text_scale: Some(2.0),
                ..Rgb::default()
            })
        },
        Some("red"),
    );
}

#[test]
#[should_panic(expected = "cannot embed the text \"red\"")]
fn a_named_text_must_be_supported() {
    check_text(conforming, Some("red"));
}

#[test]
#[should_panic(expected = "cannot embed the text \"a red chair next to a white wall\"")]
fn the_probe_text_may_only_fail_as_unsupported() {
    // Understands "red" alone, and fails on the probe with an error other than Unsupported.
    check_text(
        || {
            Box::new(Rgb {
                text_scale: Some(1.0),
                ..Rgb::default()
            })
        },
        None,
    );
}
