//! SAM's image preprocessing and mask postprocessing, bit-compatible with the reference.
//!
//! Why it exists: SAM sees the image resized so that its longest side is 1024 pixels (the
//! reference resizes with Pillow's bilinear filter on 8-bit data), normalised with the ImageNet
//! pixel mean and deviation, and zero-padded to 1024 x 1024; its 256 x 256 mask logits go back to
//! the image by two bilinear resizes (to 1024 x 1024, cropped to the resized image, then to the
//! original size). Thresholds (the stability score, the mask itself) act on those upsampled
//! logits, so both directions must follow the reference closely: this module owns them.
//!
//! The image resize reproduces Pillow's fixed-point two-pass resampling (coefficients rounded to
//! 22 fractional bits, horizontal pass first, each pass rounded to 8 bits), so the same bytes come
//! out. The mask resize composes the two bilinear steps into one linear map per axis (bilinear
//! resizing is separable and linear), evaluated only where needed.

/// SAM's input side length.
pub const INPUT_SIZE: usize = 1024;

/// Side length of SAM's low-resolution mask logits.
pub const LOW_RES: usize = 256;

/// Channels of the image encoder's embeddings and of the decoder's prompt tokens (every variant).
pub const EMBED_DIM: usize = 256;

/// Side of the image embedding grid: `INPUT_SIZE / 16` (every variant).
pub const GRID: usize = 64;

/// SAM's pixel mean (RGB, 0-255).
pub const PIXEL_MEAN: [f32; 3] = [123.675, 116.28, 103.53];

/// SAM's pixel standard deviation (RGB, 0-255).
pub const PIXEL_STD: [f32; 3] = [58.395, 57.12, 57.375];

/// The reference's `ResizeLongestSide.get_preprocess_shape`: `(height, width)` scaled so that the
/// longer side is `target`, each rounded half up.
pub fn preprocess_shape(height: usize, width: usize, target: usize) -> (usize, usize) {
    let scale = target as f64 / height.max(width).max(1) as f64;
    let round = |v: usize| (v as f64 * scale + 0.5) as usize;
    (round(height), round(width))
}

/// Fractional bits of Pillow's 8-bit resampling coefficients.
const PRECISION_BITS: u32 = 32 - 8 - 2;

/// Pillow's resampling coefficients for one axis: for each output index, the first input index
/// and the fixed-point weights of the consecutive inputs from there.
struct PilTaps {
    first: Vec<usize>,
    weights: Vec<Vec<i32>>,
}

/// Pillow's `precompute_coeffs` with the bilinear (triangle) filter, then
/// `normalize_coeffs_8bpc`.
fn pil_taps(in_size: usize, out_size: usize) -> PilTaps {
    let scale = in_size as f64 / out_size as f64;
    let filter_scale = scale.max(1.0);
    let support = filter_scale; // The triangle filter's support is 1.
    let mut first = Vec::with_capacity(out_size);
    let mut weights = Vec::with_capacity(out_size);
    for xx in 0..out_size {
        let center = (xx as f64 + 0.5) * scale;
        // C's `(int)` truncates toward zero; negative starts clamp to 0 either way.
        let xmin = ((center - support + 0.5) as i64).max(0) as usize;
        let xmax = ((center + support + 0.5) as i64).clamp(0, in_size as i64) as usize;
        let count = xmax.saturating_sub(xmin);
        let mut w: Vec<f64> = (0..count)
            .map(|x| {
                let t = ((x + xmin) as f64 - center + 0.5) / filter_scale;
                (1.0 - t.abs()).max(0.0)
            })
            .collect();
        let total: f64 = w.iter().sum();
        if total != 0.0 {
            w.iter_mut().for_each(|v| *v /= total);
        }
        let one = f64::from(1u32 << PRECISION_BITS);
        let fixed = w
            .iter()
            .map(|&v| {
                if v < 0.0 {
                    (-0.5 + v * one) as i32
                } else {
                    (0.5 + v * one) as i32
                }
            })
            .collect();
        first.push(xmin);
        weights.push(fixed);
    }
    PilTaps { first, weights }
}

/// Pillow's `clip8`: a fixed-point sum back to a byte.
fn clip8(v: i64) -> u8 {
    if v >= (1i64 << PRECISION_BITS) << 8 {
        255
    } else if v <= 0 {
        0
    } else {
        (v >> PRECISION_BITS) as u8
    }
}

/// Resizes an interleaved RGB image like Pillow's `Image.resize(size, Image.BILINEAR)` (which
/// the reference calls through torchvision): returns `out_w * out_h * 3` bytes.
pub fn resize_rgb_like_pillow(
    rgb: &[u8],
    width: usize,
    height: usize,
    out_w: usize,
    out_h: usize,
) -> Vec<u8> {
    // Horizontal pass (skipped when the width stays, as in Pillow).
    let horizontal: Vec<u8> = if out_w == width {
        rgb.to_vec()
    } else {
        let taps = pil_taps(width, out_w);
        let mut out = vec![0u8; out_w * height * 3];
        for y in 0..height {
            let row = &rgb[y * width * 3..(y + 1) * width * 3];
            for (xx, (first, w)) in taps.first.iter().zip(&taps.weights).enumerate() {
                for c in 0..3 {
                    let mut ss = 1i64 << (PRECISION_BITS - 1);
                    for (k, &wk) in w.iter().enumerate() {
                        ss += i64::from(row[(first + k) * 3 + c]) * i64::from(wk);
                    }
                    out[(y * out_w + xx) * 3 + c] = clip8(ss);
                }
            }
        }
        out
    };
    if out_h == height {
        return horizontal;
    }
    let taps = pil_taps(height, out_h);
    let mut out = vec![0u8; out_w * out_h * 3];
    for (yy, (first, w)) in taps.first.iter().zip(&taps.weights).enumerate() {
        for x in 0..out_w * 3 {
            let mut ss = 1i64 << (PRECISION_BITS - 1);
            for (k, &wk) in w.iter().enumerate() {
                ss += i64::from(horizontal[(first + k) * out_w * 3 + x]) * i64::from(wk);
            }
            out[yy * out_w * 3 + x] = clip8(ss);
        }
    }
    out
}

/// SAM's model input: the resized image normalised and zero-padded to `1024 x 1024`, channel
/// planes (CHW, f32). `resized` is `width * height * 3` interleaved bytes with both sides at
/// most 1024.
pub fn normalise_and_pad(resized: &[u8], width: usize, height: usize) -> Vec<f32> {
    let plane = INPUT_SIZE * INPUT_SIZE;
    let mut out = vec![0f32; 3 * plane];
    for y in 0..height.min(INPUT_SIZE) {
        for x in 0..width.min(INPUT_SIZE) {
            for c in 0..3 {
                let v = f32::from(resized[(y * width + x) * 3 + c]);
                out[c * plane + y * INPUT_SIZE + x] = (v - PIXEL_MEAN[c]) / PIXEL_STD[c];
            }
        }
    }
    out
}

/// One axis of PyTorch's `interpolate(mode="bilinear", align_corners=False)` from `in_size` to
/// `out_size`: for each output index, two input indices and their weights (computed in f32, as
/// PyTorch does for f32 tensors).
fn torch_bilinear_axis(in_size: usize, out_size: usize) -> Vec<[(usize, f32); 2]> {
    let scale = in_size as f32 / out_size as f32;
    (0..out_size)
        .map(|o| {
            let real = (scale * (o as f32 + 0.5) - 0.5).max(0.0);
            let i0 = (real as usize).min(in_size.saturating_sub(1));
            let i1 = if i0 + 1 < in_size { i0 + 1 } else { i0 };
            let l1 = real - i0 as f32;
            [(i0, 1.0 - l1), (i1, l1)]
        })
        .collect()
}

/// One axis of the reference's mask postprocessing (low-res -> 1024, keep the first
/// `input_len`, -> `out_len`) as one linear map: for each output index, the low-res indices and
/// weights (at most four).
#[derive(Clone, Debug)]
pub struct AxisMap {
    taps: Vec<Vec<(usize, f32)>>,
}

impl AxisMap {
    /// The map for an image axis of `out_len` pixels that was resized to `input_len` (<= 1024).
    pub fn new(input_len: usize, out_len: usize) -> Self {
        let up = torch_bilinear_axis(LOW_RES, INPUT_SIZE);
        let down = torch_bilinear_axis(input_len.clamp(1, INPUT_SIZE), out_len);
        let taps = down
            .iter()
            .map(|pair| {
                let mut taps: Vec<(usize, f32)> = Vec::with_capacity(4);
                for &(mid, w_mid) in pair {
                    for &(low, w_low) in &up[mid.min(INPUT_SIZE - 1)] {
                        let w = w_mid * w_low;
                        match taps.iter_mut().find(|(i, _)| *i == low) {
                            Some(t) => t.1 += w,
                            None => taps.push((low, w)),
                        }
                    }
                }
                taps
            })
            .collect();
        Self { taps }
    }

    /// Output length.
    pub fn len(&self) -> usize {
        self.taps.len()
    }

    /// Whether the output is empty.
    pub fn is_empty(&self) -> bool {
        self.taps.is_empty()
    }

    /// The map as a dense `len × 256` row-major matrix (each row's few taps, zeros elsewhere):
    /// the form a device applies as one matrix product.
    pub fn matrix(&self) -> Vec<f32> {
        let mut m = vec![0f32; self.taps.len() * LOW_RES];
        for (row, taps) in m.chunks_exact_mut(LOW_RES).zip(&self.taps) {
            for &(i, w) in taps {
                row[i] += w;
            }
        }
        m
    }
}

/// Upsamples one `256 x 256` logit map to the original image (`xs.len()` wide, `ys.len()` high),
/// row-major: columns first into a `256 x width` buffer, then rows.
pub fn upsample_logits(low: &[f32], xs: &AxisMap, ys: &AxisMap) -> Vec<f32> {
    let width = xs.len();
    let mut rows = vec![0f32; LOW_RES * width];
    for (r, row) in low.chunks_exact(LOW_RES).enumerate().take(LOW_RES) {
        let out = &mut rows[r * width..(r + 1) * width];
        for (o, taps) in out.iter_mut().zip(&xs.taps) {
            *o = taps.iter().map(|&(i, w)| row[i] * w).sum();
        }
    }
    let mut out = vec![0f32; ys.len() * width];
    for (y, taps) in ys.taps.iter().enumerate() {
        let dst = &mut out[y * width..(y + 1) * width];
        for &(i, w) in taps {
            let src = &rows[i * width..(i + 1) * width];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += s * w;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preprocess_shape_rounds_like_the_reference() {
        assert_eq!(preprocess_shape(480, 640, 1024), (768, 1024));
        assert_eq!(preprocess_shape(968, 1296, 1024), (765, 1024));
        assert_eq!(preprocess_shape(1024, 10, 1024), (1024, 10));
        assert_eq!(preprocess_shape(3, 1, 1024), (1024, 341));
    }

    #[test]
    fn pillow_resize_doubles_by_hand() {
        // 2 -> 4 pixels in one row: centres at 0.25, 0.75, 1.25, 1.75 of the input, so the
        // weights are (1, 0), (0.75, 0.25), (0.25, 0.75), (0, 1) after Pillow's edge clamping.
        let row = [0u8, 0, 0, 100, 200, 40];
        let out = resize_rgb_like_pillow(&row, 2, 1, 4, 1);
        assert_eq!(&out[0..3], &[0, 0, 0]);
        assert_eq!(&out[3..6], &[25, 50, 10]);
        assert_eq!(&out[6..9], &[75, 150, 30]);
        assert_eq!(&out[9..12], &[100, 200, 40]);
        // Same size: the bytes stay.
        assert_eq!(resize_rgb_like_pillow(&row, 2, 1, 2, 1), row.to_vec());
    }

    #[test]
    fn normalisation_pads_with_zeros_after_normalising() {
        let resized = [124u8, 116, 104];
        let input = normalise_and_pad(&resized, 1, 1);
        assert!((input[0] - (124.0 - 123.675) / 58.395).abs() < 1e-7);
        assert!((input[INPUT_SIZE * INPUT_SIZE] - (116.0 - 116.28) / 57.12).abs() < 1e-7);
        assert_eq!(input[1], 0.0);
        assert_eq!(input[INPUT_SIZE], 0.0);
    }

    #[test]
    fn torch_bilinear_axis_clamps_and_interpolates() {
        // 2 -> 4: sources -0.25 (clamped to 0), 0.25, 0.75, 1.25 (i1 stays at the last index).
        let taps = torch_bilinear_axis(2, 4);
        assert_eq!(taps[0], [(0, 1.0), (1, 0.0)]);
        assert_eq!(taps[1], [(0, 0.75), (1, 0.25)]);
        assert_eq!(taps[2], [(0, 0.25), (1, 0.75)]);
        assert_eq!(taps[3], [(1, 0.75), (1, 0.25)]);
    }

    #[test]
    fn upsampling_a_constant_or_a_ramp_is_exact() {
        let xs = AxisMap::new(1024, 640);
        let ys = AxisMap::new(768, 480);
        let constant = vec![2.5f32; LOW_RES * LOW_RES];
        let up = upsample_logits(&constant, &xs, &ys);
        assert_eq!(up.len(), 640 * 480);
        assert!(up.iter().all(|v| (v - 2.5).abs() < 1e-5));
        // Weights of each output sum to one.
        for taps in xs.taps.iter().chain(&ys.taps) {
            let s: f32 = taps.iter().map(|t| t.1).sum();
            assert!((s - 1.0).abs() < 1e-6);
        }
    }
}
