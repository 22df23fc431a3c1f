//! Decoding colour and depth images into the core types.

use std::path::Path;

use image::imageops::FilterType;
use image::{DynamicImage, ImageReader};
use vlem_core::{DepthImage, RgbImage};

use crate::error::{DatasetError, Result};

/// Opens an image file, trusting its content over its extension (datasets do mislabel files).
fn open(path: &Path) -> Result<ImageReader<std::io::BufReader<std::fs::File>>> {
    ImageReader::open(path)
        .map_err(|e| DatasetError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))
}

fn decode(path: &Path) -> Result<DynamicImage> {
    open(path)?
        .decode()
        .map_err(|source| DatasetError::UnreadableImage {
            path: path.to_path_buf(),
            source,
        })
}

/// Reads a colour image as 8-bit RGB; grayscale, alpha and 16-bit inputs are converted.
pub(crate) fn read_colour(path: &Path) -> Result<RgbImage> {
    rgb_from(decode(path)?, path)
}

/// Reads a colour image and resamples it (bilinear) to `width` x `height`, for layouts whose colour
/// camera has a higher resolution than the depth camera it is registered to (ScanNet).
pub(crate) fn read_colour_resized(path: &Path, width: u32, height: u32) -> Result<RgbImage> {
    let image = decode(path)?;
    let image = if (image.width(), image.height()) == (width, height) {
        image
    } else {
        image.resize_exact(width, height, FilterType::Triangle)
    };
    rgb_from(image, path)
}

fn rgb_from(image: DynamicImage, path: &Path) -> Result<RgbImage> {
    let rgb = image.into_rgb8();
    let (width, height) = rgb.dimensions();
    RgbImage::new(width, height, rgb.into_raw()).map_err(|source| DatasetError::Core {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads a 16-bit single-channel depth image and converts it to metres with `scale` raw units per
/// metre (0 stays "no measurement").
///
/// Anything else is refused rather than converted: an 8-bit or colour "depth" image is almost
/// always a visualisation, whose values are not distances.
pub(crate) fn read_depth(path: &Path, scale: f32) -> Result<DepthImage> {
    match decode(path)? {
        DynamicImage::ImageLuma16(raw) => {
            let (width, height) = raw.dimensions();
            DepthImage::from_raw_u16(width, height, raw.as_raw(), scale).map_err(|source| {
                DatasetError::Core {
                    path: path.to_path_buf(),
                    source,
                }
            })
        }
        other => Err(DatasetError::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!(
                "depth must be a 16-bit single-channel image, this one is {:?} ({} bits per pixel)",
                other.color(),
                other.color().bits_per_pixel()
            ),
        }),
    }
}

/// The width and height of an image, read from its header only.
pub(crate) fn dimensions(path: &Path) -> Result<(u32, u32)> {
    open(path)?
        .into_dimensions()
        .map_err(|source| DatasetError::UnreadableImage {
            path: path.to_path_buf(),
            source,
        })
}
