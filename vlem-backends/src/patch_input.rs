//! Whole-frame input of the patch encoders: the input size, and the resampled, normalised pixels.
//!
//! Why it exists: every patch encoder (ONNX `patch-grid`, DINOv3 with dino.txt, NARADIO) feeds a
//! ViT the whole frame at a size that is a multiple of its patch size, and normalises it with
//! the model's mean and standard deviation; one implementation keeps their resampling identical.
//! It owns the choice of input size ([`patch_aligned_size`]) and the conversion to channel
//! planes ([`normalised_planes`]).

use image::imageops::{self, FilterType};
use image::{ImageBuffer, Rgb};
use vlem_core::RgbImage;

use crate::error::BackendError;

/// ImageNet's channel mean, the normalisation of DINOv3 (and of timm's ViTs).
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];

/// ImageNet's channel standard deviation.
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// The largest `short_side` a patch encoder accepts, in pixels. Attention (and NARADIO's
/// Gaussian prior) grow with the square of the token count: at 1536 px a 4:3 frame is 12,288
/// patches of 16 px and NARADIO's prior alone is 0.6 GB; beyond, one frame needs many GB.
pub const MAX_SHORT_SIDE: u32 = 1536;

/// Checks a configured `short_side`: a multiple of the model's `patch` size, at most
/// [`MAX_SHORT_SIDE`].
///
/// # Errors
/// [`BackendError::InvalidParams`] naming the value and what is accepted.
pub fn check_short_side(short_side: u32, patch: usize, example: u32) -> Result<(), BackendError> {
    let aligned = short_side > 0
        && usize::try_from(short_side).is_ok_and(|side| side.is_multiple_of(patch.max(1)));
    if !aligned || short_side > MAX_SHORT_SIDE {
        return Err(BackendError::InvalidParams(format!(
            "short_side must be a multiple of the patch size {patch} from {patch} to \
             {MAX_SHORT_SIDE} pixels (attention grows with the square of the patches), e.g. \
             {example}; got {short_side}"
        )));
    }
    Ok(())
}

/// The input size, `(width, height)`, for a `width × height` frame whose shorter side becomes
/// `short_side` and whose longer side keeps the aspect ratio, rounded to the nearest multiple
/// of `patch` (at least one patch). `short_side` is rounded to a multiple of `patch` likewise.
/// The small stretch the rounding makes (under half a patch per side) is what the reference
/// pipelines do too.
pub fn patch_aligned_size(width: u32, height: u32, short_side: u32, patch: u32) -> (u32, u32) {
    let patch = patch.max(1);
    let round = |x: f64| -> u32 {
        let patches = (x / f64::from(patch)).round().max(1.0);
        // A frame and a short side in u32 keep `patches * patch` far below u32::MAX.
        (patches as u32).saturating_mul(patch)
    };
    let (short, long) = if width <= height {
        (width, height)
    } else {
        (height, width)
    };
    let scale = f64::from(short_side) / f64::from(short.max(1));
    let new_short = round(f64::from(short_side));
    let new_long = round(f64::from(long) * scale);
    if width <= height {
        (new_short, new_long)
    } else {
        (new_long, new_short)
    }
}

/// `3 × height × width` values: `image` resampled to `width × height` if it has another size,
/// each channel normalised as `(x / 255 - mean) / std` (bicubic resampling, Catmull-Rom, the
/// values clamped to `[0, 1]` before normalising, as PIL's bicubic resize of 8-bit images does).
///
/// # Errors
/// [`BackendError::InvalidInput`] for an empty image.
pub fn normalised_planes(
    image: &RgbImage,
    width: u32,
    height: u32,
    mean: [f32; 3],
    std: [f32; 3],
) -> Result<Vec<f32>, BackendError> {
    if image.width() == 0 || image.height() == 0 {
        return Err(BackendError::InvalidInput(format!(
            "cannot embed an empty {}x{} image",
            image.width(),
            image.height()
        )));
    }
    // Pixels in [0, 1] units, interleaved RGB.
    let pixels: Vec<f32> = if image.width() == width && image.height() == height {
        image
            .as_raw()
            .iter()
            .map(|&b| f32::from(b) / 255.0)
            .collect()
    } else {
        let source: ImageBuffer<Rgb<f32>, Vec<f32>> = ImageBuffer::from_raw(
            image.width(),
            image.height(),
            image
                .as_raw()
                .iter()
                .map(|&b| f32::from(b) / 255.0)
                .collect(),
        )
        .ok_or_else(|| BackendError::InvalidInput("inconsistent image buffer".to_owned()))?;
        imageops::resize(&source, width, height, FilterType::CatmullRom)
            .into_raw()
            .into_iter()
            .map(|x| x.clamp(0.0, 1.0))
            .collect()
    };
    let mut out = Vec::with_capacity(pixels.len());
    for c in 0..3 {
        out.extend(pixels.chunks_exact(3).map(|p| (p[c] - mean[c]) / std[c]));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aligned_size_keeps_the_aspect_ratio_on_patch_multiples() {
        // 640x480 at short side 448: 597.3 wide -> 592 (37 patches), 448 high (28 patches).
        assert_eq!(patch_aligned_size(640, 480, 448, 16), (592, 448));
        // Portrait frames swap the roles.
        assert_eq!(patch_aligned_size(480, 640, 448, 16), (448, 592));
        // The frame's own size when it is already aligned.
        assert_eq!(patch_aligned_size(640, 480, 480, 16), (640, 480));
        // A short side off the grid is rounded too; never below one patch.
        assert_eq!(patch_aligned_size(640, 480, 500, 16), (672, 496));
        assert_eq!(patch_aligned_size(1000, 10, 4, 16), (400, 16));
    }

    #[test]
    fn planes_are_normalised_per_channel() {
        let image = RgbImage::new(2, 1, vec![255, 0, 51, 0, 255, 102]).unwrap();
        let planes = normalised_planes(&image, 2, 1, [0.5; 3], [0.5; 3]).unwrap();
        // Channel-major: R of both pixels, then G, then B; (x/255 - 0.5) / 0.5.
        let expected = [1.0, -1.0, -1.0, 1.0, -0.6, -0.2];
        for (a, b) in planes.iter().zip(expected) {
            assert!((a - b).abs() < 1e-6, "{planes:?}");
        }
        assert!(
            normalised_planes(&RgbImage::filled(0, 0, [0; 3]), 2, 1, [0.5; 3], [0.5; 3]).is_err()
        );
    }
}
