//! Decoding colour and depth images into the core types.
//!
//! The path functions read the whole file and hand its bytes to the `*_from_bytes` functions,
//! which do the decoding; those are public so that callers (and the fuzz targets) can decode
//! images held in memory.

use std::io::Cursor;
use std::path::Path;

use image::imageops::FilterType;
use image::{DynamicImage, ImageReader};
use vlem_core::{DepthImage, LabelImage, LabelNames, RgbImage};

use crate::error::{DatasetError, Result};

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| DatasetError::io(path, e))
}

/// The largest image decoded, in bytes of decoded pixels: 256 MiB (an 8K colour frame is 100 MB,
/// an 8K 16-bit depth frame 66 MB). The decoder checks the size the header declares against it
/// before allocating, so a compressed bomb (13000 × 13000 RGB in 490 KB of PNG) is refused
/// without the memory it would take.
pub(crate) const MAX_DECODED_BYTES: u64 = 256 << 20;

/// The widest or tallest image decoded, in pixels.
pub(crate) const MAX_IMAGE_SIDE: u32 = 16_384;

/// Decodes `bytes`, trusting their content over the file's extension (datasets do mislabel files),
/// within [`MAX_DECODED_BYTES`] and [`MAX_IMAGE_SIDE`].
fn decode(bytes: &[u8], origin: &Path) -> Result<DynamicImage> {
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_DECODED_BYTES);
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    let mut reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| DatasetError::io(origin, e))?;
    reader.limits(limits);
    if reader.format() == Some(image::ImageFormat::Jpeg) && !jpeg_is_complete(bytes) {
        return Err(DatasetError::UnsupportedImage {
            path: origin.to_path_buf(),
            reason: format!(
                "cannot decode image: the JPEG data ({} bytes) ends inside its last scan, before \
                 the end-of-image marker: the file is truncated (an interrupted copy or \
                 recording?); the decoder would fill the missing rows with grey",
                bytes.len()
            ),
        });
    }
    reader
        .decode()
        .map_err(|source| DatasetError::UnreadableImage {
            path: origin.to_path_buf(),
            source,
        })
}

/// Whether a JPEG stream has an end-of-image marker (`FF D9`) after its last start-of-scan
/// (`FF DA`). The decoder accepts a file cut inside its entropy-coded data and fills the missing
/// rows with grey, which would put a grey band into the map's colours and embeddings without a
/// word. Inside entropy-coded data `FF` is always followed by `00` or a restart marker, so these
/// two byte pairs there are real markers; an EXIF thumbnail's own markers come before the main
/// image's scans, and bytes after the end marker (padding some cameras add) are allowed.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    const START_OF_SCAN: [u8; 2] = [0xFF, 0xDA];
    const END_OF_IMAGE: [u8; 2] = [0xFF, 0xD9];
    let Some(last_scan) = bytes.windows(2).rposition(|pair| pair == START_OF_SCAN) else {
        // No scan at all: the decoder's own error says what is wrong.
        return true;
    };
    bytes[last_scan..]
        .windows(2)
        .any(|pair| pair == END_OF_IMAGE)
}

/// Reads a colour image as 8-bit RGB; grayscale, alpha and 16-bit inputs are converted.
pub(crate) fn read_colour(path: &Path) -> Result<RgbImage> {
    colour_from_bytes(&read_bytes(path)?, path)
}

/// Decodes a colour image (PNG, JPEG or PNM, recognised by content) held in memory as 8-bit RGB;
/// grayscale, alpha and 16-bit inputs are converted. `origin` is the file the bytes came from, as
/// errors name it.
///
/// # Errors
/// [`DatasetError::UnreadableImage`] when the bytes are not an image the decoder can read (or one
/// beyond its memory limits), [`DatasetError::Core`] when the decoded size is inconsistent.
pub fn colour_from_bytes(bytes: &[u8], origin: &Path) -> Result<RgbImage> {
    rgb_from(decode(bytes, origin)?, origin)
}

/// Reads a colour image and resamples it (bilinear) to `width` x `height`, for layouts whose colour
/// camera has a higher resolution than the depth camera it is registered to (ScanNet).
pub(crate) fn read_colour_resized(path: &Path, width: u32, height: u32) -> Result<RgbImage> {
    colour_resized_from_bytes(&read_bytes(path)?, width, height, path)
}

/// [`colour_from_bytes`], then resampled (bilinear) to `width` x `height` when the image has
/// another size, as the ScanNet reader registers colour to the depth camera.
///
/// # Errors
/// Those of [`colour_from_bytes`].
pub fn colour_resized_from_bytes(
    bytes: &[u8],
    width: u32,
    height: u32,
    origin: &Path,
) -> Result<RgbImage> {
    let image = decode(bytes, origin)?;
    let image = if (image.width(), image.height()) == (width, height) {
        image
    } else {
        image.resize_exact(width, height, FilterType::Triangle)
    };
    rgb_from(image, origin)
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
pub(crate) fn read_depth(path: &Path, scale: f32) -> Result<DepthImage> {
    depth_from_bytes(&read_bytes(path)?, scale, path)
}

/// Decodes a 16-bit single-channel depth image (a 16-bit grayscale PNG, as every supported layout
/// stores depth) held in memory, and converts it to metres with `scale` raw units per metre
/// (0 stays "no measurement"). `origin` is the file the bytes came from, as errors name it.
///
/// Anything else is refused rather than converted: an 8-bit or colour "depth" image is almost
/// always a visualisation, whose values are not distances.
///
/// # Errors
/// [`DatasetError::UnreadableImage`] when the bytes are not an image the decoder can read (or one
/// beyond its memory limits), [`DatasetError::UnsupportedImage`] for an image that is not 16-bit
/// single-channel, [`DatasetError::Core`] when the decoded size is inconsistent.
pub fn depth_from_bytes(bytes: &[u8], scale: f32, origin: &Path) -> Result<DepthImage> {
    match decode(bytes, origin)? {
        DynamicImage::ImageLuma16(raw) => {
            let (width, height) = raw.dimensions();
            DepthImage::from_raw_u16(width, height, raw.as_raw(), scale).map_err(|source| {
                DatasetError::Core {
                    path: origin.to_path_buf(),
                    source,
                }
            })
        }
        other => Err(DatasetError::UnsupportedImage {
            path: origin.to_path_buf(),
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
    ImageReader::open(path)
        .map_err(|e| DatasetError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))?
        .into_dimensions()
        .map_err(|source| DatasetError::UnreadableImage {
            path: path.to_path_buf(),
            source,
        })
}

/// Reads a label image: one class id per pixel (16-bit or 8-bit single channel, 0 = unlabelled).
pub(crate) fn read_labels(path: &Path, names: &std::sync::Arc<LabelNames>) -> Result<LabelImage> {
    labels_from_bytes(&read_bytes(path)?, names, path)
}

/// Decodes a label image held in memory: 16-bit or 8-bit single channel, one class id per pixel
/// (0 = unlabelled), named by `names`. `origin` is the file the bytes came from, as errors name it.
///
/// # Errors
/// [`DatasetError::UnreadableImage`] when the bytes are not an image the decoder can read,
/// [`DatasetError::UnsupportedImage`] for a colour image (ids are not colours).
pub fn labels_from_bytes(
    bytes: &[u8],
    names: &std::sync::Arc<LabelNames>,
    origin: &Path,
) -> Result<LabelImage> {
    let (width, height, ids) = match decode(bytes, origin)? {
        DynamicImage::ImageLuma16(raw) => {
            let (w, h) = raw.dimensions();
            (w, h, raw.into_raw())
        }
        DynamicImage::ImageLuma8(raw) => {
            let (w, h) = raw.dimensions();
            (w, h, raw.into_raw().into_iter().map(u16::from).collect())
        }
        other => {
            return Err(DatasetError::UnsupportedImage {
                path: origin.to_path_buf(),
                reason: format!(
                    "labels must be a single-channel image of class ids, this one is {:?}",
                    other.color()
                ),
            });
        }
    };
    LabelImage::new(width, height, ids, names.clone()).map_err(|source| DatasetError::Core {
        path: origin.to_path_buf(),
        source,
    })
}
