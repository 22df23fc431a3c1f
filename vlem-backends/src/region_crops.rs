//! Region crops and region embeddings: the preprocessing of the paper's segment-embedding path
//! (section "Segment-Embeddings"; vlem says *region* for what the paper calls a segment), shared
//! by every encoder that embeds one crop per region (`clip`, `onnx`).
//!
//! Why it exists: cropping, background replacement, resampling and normalisation decide what a
//! region encoder sees, and the paper ablates exactly these choices; written once here, every
//! encoder makes them the same way and the ablation is a config switch. The module owns two steps:
//!
//! - [`crop_batch`]: region crops → an `N × 3 × size × size` batch for a vision tower;
//! - [`region_embeddings`]: one embedding per region → [`PixelEmbeddings`] in the region
//!   layout, resolving overlaps in favour of the smaller region.
//!
//! Crop pipeline, per region `k` (in the paper's notation `C_k` is the crop, `M_k` its mask):
//! 1. cut the region's bounding box out of the image, in `[0, 1]` units (bytes / 255);
//! 2. replace the pixels outside the mask (`M_k = 0`) by the [`Background`] strategy;
//! 3. resample the crop to `size × size` with the `image` crate's Catmull-Rom filter
//!    ([`image::imageops::FilterType::CatmullRom`]): the cubic convolution with `a = -0.5`, the
//!    paper's "bicubic" and the kernel of PIL's `BICUBIC` that CLIP's own preprocessing uses; the
//!    kernel widens when shrinking (antialiasing, as PIL does), the aspect ratio is not kept (the
//!    paper resamples every region "to the same resolution"), and results are clamped to `[0, 1]`;
//! 4. normalise each channel, `(x - mean) / std`.

use image::imageops::{self, FilterType};
use image::{ImageBuffer, Rgb};
use vlem_core::{NO_REGION, PixelEmbeddings, Region, RgbImage};

use crate::error::BackendError;

/// Per-channel mean of OpenAI CLIP's image preprocessing, in `[0, 1]` units.
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];

/// Per-channel standard deviation of OpenAI CLIP's image preprocessing, in `[0, 1]` units.
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_6, 0.275_777_1];

/// The colour `v` that replaces the crop pixels outside the region's mask (the paper's ablation
/// near "the background is replaced by random data").
///
/// In config files the variants are spelt `"none"`, `"random"`, `"static"`, `"mean-image"` and
/// `"mean-segment"`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Background {
    /// Keep the image under the mask's background: the plain bounding-box crop. The default,
    /// following the paper's 2D ablation, where no replacement did better.
    #[default]
    None,
    /// A uniformly random colour per pixel, each channel uniform in `[0, 1)`, drawn from a
    /// generator seeded by [`CropSpec::seed`] and the region's index, so a batch is reproducible.
    /// The paper's best 3D setting.
    Random,
    /// The static colour `v = (1, 0, 1)`: magenta.
    Static,
    /// The mean colour of the whole image, `v = mean(C_i)`.
    MeanImage,
    /// The mean colour of the region's foreground pixels, `v = mean(C_k | M_k = 1)`.
    ///
    /// The paper's formula writes `M_k(u, v) = 0`, which read literally is the mean of exactly
    /// the pixels being replaced, i.e. a blurred form of [`Background::None`]; its name, "mean
    /// segment foreground", says foreground. We follow the name: the background takes the
    /// region's own average colour, which hides the neighbours without adding a foreign colour.
    MeanSegment,
}

/// How [`crop_batch`] turns regions into encoder input.
#[derive(Clone, Debug, PartialEq)]
pub struct CropSpec {
    /// Side of the square crops in pixels (e.g. 224 for CLIP ViT-B); positive.
    pub size: u32,
    /// Per-channel mean subtracted after scaling to `[0, 1]`.
    pub mean: [f32; 3],
    /// Per-channel standard deviation divided by; finite and non-zero.
    pub std: [f32; 3],
    /// What replaces the crop pixels outside the mask.
    pub background: Background,
    /// Seed of [`Background::Random`]; other strategies ignore it.
    pub seed: u64,
}

impl Default for CropSpec {
    /// 224 × 224 crops with CLIP's mean and standard deviation and no background replacement.
    fn default() -> Self {
        Self {
            size: 224,
            mean: CLIP_MEAN,
            std: CLIP_STD,
            background: Background::None,
            seed: 0,
        }
    }
}

/// A crop in `[0, 1]` units, the form the `image` crate resamples.
type CropImage = ImageBuffer<Rgb<f32>, Vec<f32>>;

/// The crops of `regions`, as one `N × 3 × size × size` batch of `f32` (N = `regions.len()`),
/// each crop channel-major (CHW, channels R, G, B), values `(x / 255 - mean) / std`. See the
/// [module documentation](self) for the steps.
///
/// # Errors
/// [`BackendError::InvalidParams`] for a zero `size`, a non-finite mean or a zero or non-finite
/// std; [`BackendError::InvalidInput`] for a region that is empty, lies (partly) outside the
/// image, has a mask of the wrong length or no foreground pixel.
pub fn crop_batch(
    image: &RgbImage,
    regions: &[Region],
    spec: &CropSpec,
) -> Result<Vec<f32>, BackendError> {
    check_spec(spec)?;
    for (k, region) in regions.iter().enumerate() {
        check_region(k, region, image.width(), image.height())?;
        if !region.mask.contains(&true) {
            return Err(BackendError::InvalidInput(format!(
                "region {k} has no foreground pixel, so it has no crop to embed"
            )));
        }
    }
    let plane = spec.size as usize * spec.size as usize;
    let total = regions.len().checked_mul(3 * plane).ok_or_else(|| {
        BackendError::InvalidParams(format!("crop size {} is too large", spec.size))
    })?;
    let mean_image = match spec.background {
        Background::MeanImage => mean_colour(image.as_raw().chunks_exact(3)),
        _ => [0.0; 3],
    };
    let mut out = Vec::with_capacity(total);
    for (k, region) in regions.iter().enumerate() {
        let crop = masked_crop(image, region, spec, k, mean_image)?;
        let resized: CropImage =
            imageops::resize(&crop, spec.size, spec.size, FilterType::CatmullRom);
        for c in 0..3 {
            let (mean, inv_std) = (spec.mean[c], 1.0 / spec.std[c]);
            out.extend(resized.pixels().map(|p| (p.0[c] - mean) * inv_std));
        }
    }
    Ok(out)
}

/// Per-pixel region assignment and embedding table, as [`PixelEmbeddings`] in the region
/// layout for a `width × height` image.
///
/// `embeddings` is `regions.len() × dim`, row `k` the embedding of `regions[k]`; rows are
/// L2-normalised by [`PixelEmbeddings::from_regions`]. Each pixel gets the index of the region
/// of smallest area (foreground pixel count) among those whose mask covers it, ties going to the
/// lower index: a small object lying on a larger surface keeps its own embedding. Pixels in no
/// mask get [`NO_REGION`], i.e. no embedding. A region that wins no pixel keeps its row (unused).
///
/// # Errors
/// [`BackendError::InvalidInput`] when `dim` is 0, `embeddings` does not hold
/// `regions.len() × dim` values, a region does not fit the image or its mask has the wrong
/// length, or a row is zero or non-finite.
pub fn region_embeddings(
    width: u32,
    height: u32,
    regions: &[Region],
    dim: usize,
    embeddings: Vec<f32>,
) -> Result<PixelEmbeddings, BackendError> {
    if dim == 0 {
        return Err(BackendError::InvalidInput(
            "region embeddings of dimension 0".to_owned(),
        ));
    }
    if regions.len().checked_mul(dim) != Some(embeddings.len()) {
        return Err(BackendError::InvalidInput(format!(
            "{} embedding values for {} regions of dimension {dim} (expected {} × {dim})",
            embeddings.len(),
            regions.len(),
            regions.len()
        )));
    }
    for (k, region) in regions.iter().enumerate() {
        check_region(k, region, width, height)?;
    }
    // Indices 0..len must stay below NO_REGION (u32::MAX), the "no region" marker.
    if u32::try_from(regions.len()).map_or(true, |n| n == NO_REGION) {
        return Err(BackendError::InvalidInput(format!(
            "{} regions do not fit a u32 region index",
            regions.len()
        )));
    }
    // Smallest first, and a pixel keeps the first region that claims it: that is "smallest
    // wins" without comparing areas per pixel. The sort is stable, so ties keep index order.
    let areas: Vec<usize> = regions.iter().map(Region::area).collect();
    let mut order: Vec<usize> = (0..regions.len()).collect();
    order.sort_by_key(|&k| areas.get(k).copied().unwrap_or(usize::MAX));
    let mut index = vec![NO_REGION; width as usize * height as usize];
    for k in order {
        let Some(region) = regions.get(k) else {
            continue;
        };
        // Fits: checked above that the count is below NO_REGION.
        let label = k as u32;
        let b = region.bbox;
        for (row, mask_row) in region.mask.chunks_exact(b.width as usize).enumerate() {
            let start = (b.y as usize + row) * width as usize + b.x as usize;
            let Some(pixels) = index.get_mut(start..start + b.width as usize) else {
                continue;
            };
            for (pixel, &inside) in pixels.iter_mut().zip(mask_row) {
                if inside && *pixel == NO_REGION {
                    *pixel = label;
                }
            }
        }
    }
    PixelEmbeddings::from_regions(width, height, dim, index, embeddings)
        .map_err(|e| BackendError::InvalidInput(e.to_string()))
}

/// Refuses crop specifications that would give meaningless or non-finite values.
fn check_spec(spec: &CropSpec) -> Result<(), BackendError> {
    if spec.size == 0 {
        return Err(BackendError::InvalidParams(
            "crop size must be positive".to_owned(),
        ));
    }
    if spec.mean.iter().any(|m| !m.is_finite()) {
        return Err(BackendError::InvalidParams(format!(
            "crop mean {:?} must be finite",
            spec.mean
        )));
    }
    if spec.std.iter().any(|s| !s.is_finite() || *s == 0.0) {
        return Err(BackendError::InvalidParams(format!(
            "crop std {:?} must be finite and non-zero",
            spec.std
        )));
    }
    Ok(())
}

/// Checks that region `k` is non-empty, lies inside a `width × height` image and has a mask of
/// `bbox.width × bbox.height` entries: what makes the indexing of this module safe.
fn check_region(k: usize, region: &Region, width: u32, height: u32) -> Result<(), BackendError> {
    let b = region.bbox;
    if b.width == 0 || b.height == 0 {
        return Err(BackendError::InvalidInput(format!(
            "region {k} has an empty bounding box ({}x{})",
            b.width, b.height
        )));
    }
    let right = u64::from(b.x) + u64::from(b.width);
    let bottom = u64::from(b.y) + u64::from(b.height);
    if right > u64::from(width) || bottom > u64::from(height) {
        return Err(BackendError::InvalidInput(format!(
            "region {k}'s bounding box {}x{} at ({}, {}) reaches outside the {width}x{height} image",
            b.width, b.height, b.x, b.y
        )));
    }
    let expected = b.width as usize * b.height as usize;
    if region.mask.len() != expected {
        return Err(BackendError::InvalidInput(format!(
            "region {k}'s mask has {} entries for a {}x{} bounding box (expected {expected})",
            region.mask.len(),
            b.width,
            b.height
        )));
    }
    Ok(())
}

/// The bounding-box crop of `region` (index `k`) in `[0, 1]` units, background replaced.
fn masked_crop(
    image: &RgbImage,
    region: &Region,
    spec: &CropSpec,
    k: usize,
    mean_image: [f32; 3],
) -> Result<CropImage, BackendError> {
    let b = region.bbox;
    let (bw, bh) = (b.width as usize, b.height as usize);
    let stride = image.width() as usize * 3;
    let mut rows = Vec::with_capacity(bh);
    for row in 0..bh {
        let start = (b.y as usize + row) * stride + b.x as usize * 3;
        let bytes = image.as_raw().get(start..start + bw * 3).ok_or_else(|| {
            BackendError::InvalidInput(format!("region {k} reaches outside the image"))
        })?;
        rows.push(bytes);
    }
    let foreground = || {
        rows.iter()
            .zip(region.mask.chunks_exact(bw))
            .flat_map(|(bytes, mask)| bytes.chunks_exact(3).zip(mask))
            .filter(|(_, inside)| **inside)
            .map(|(rgb, _)| rgb)
    };
    let mut fill = match spec.background {
        Background::None => Fill::Keep,
        Background::Random => Fill::Noise(SplitMix64::for_crop(spec.seed, k)),
        Background::Static => Fill::Colour([1.0, 0.0, 1.0]),
        Background::MeanImage => Fill::Colour(mean_image),
        Background::MeanSegment => Fill::Colour(mean_colour(foreground())),
    };
    let mut data = Vec::with_capacity(bw * bh * 3);
    for (bytes, mask) in rows.iter().zip(region.mask.chunks_exact(bw)) {
        for (rgb, &inside) in bytes.chunks_exact(3).zip(mask) {
            match &mut fill {
                Fill::Colour(v) if !inside => data.extend(*v),
                Fill::Noise(rng) if !inside => data.extend([rng.unit(), rng.unit(), rng.unit()]),
                _ => data.extend(rgb.iter().map(|&c| f32::from(c) / 255.0)),
            }
        }
    }
    CropImage::from_raw(b.width, b.height, data)
        .ok_or_else(|| BackendError::InvalidInput(format!("region {k}'s crop has the wrong size")))
}

/// What a crop pixel outside the mask becomes.
enum Fill {
    /// The image's own pixel.
    Keep,
    /// One colour, in `[0, 1]` units.
    Colour([f32; 3]),
    /// Fresh noise per pixel.
    Noise(SplitMix64),
}

/// The mean colour of some RGB byte triples, in `[0, 1]` units; black for none.
fn mean_colour<'a>(pixels: impl Iterator<Item = &'a [u8]>) -> [f32; 3] {
    // u64 sums: exact for any image that fits in memory.
    let mut sum = [0u64; 3];
    let mut n = 0u64;
    for rgb in pixels {
        for (s, &c) in sum.iter_mut().zip(rgb) {
            *s += u64::from(c);
        }
        n += 1;
    }
    if n == 0 {
        return [0.0; 3];
    }
    sum.map(|s| (s as f64 / (n as f64 * 255.0)) as f32)
}

/// SplitMix64 (Steele, Lea, Flood 2014): a tiny, well-mixed generator, enough for background
/// noise, and no dependency on `rand` whose streams may change between versions.
struct SplitMix64(u64);

impl SplitMix64 {
    const GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;

    /// The generator of crop `k` under `seed`: crops get distinct streams, and a crop's noise does
    /// not depend on how many other regions the frame has.
    fn for_crop(seed: u64, k: usize) -> Self {
        let mut g = Self(seed ^ (k as u64).wrapping_mul(Self::GAMMA).rotate_left(29));
        let start = g.next_u64();
        Self(start)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(Self::GAMMA);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` with 24 bits, exactly representable in `f32`.
    fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}
