//! The end of SAM's mask decoder on the CPU, fused: output upscaling (a 2×2 transposed
//! convolution, LayerNorm over channels, GELU, a second 2×2 transposed convolution, GELU) and the
//! hypernetwork product that turns 32 channels into each mask's logit.
//!
//! Why it exists: per prompt this stage turns the `64 × 64 × 256` image tokens into `128 × 128 ×
//! 64` and `256 × 256 × 32` intermediates (4 and 8 MB). As a chain of candle ops that is about
//! fifteen passes over fresh buffers per prompt, half the decoder's time on a CPU, most of it page
//! faults, copies and the scalar `erf`. Both convolutions have stride = kernel, so every grid cell
//! owns its output pixels: a band of grid rows can go through every step while it sits in the
//! cache, and prompts run in parallel. The candle chain (`MaskDecoder::upscale_with_ops`) stays
//! for other devices and is what the tests compare this with.

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::image::{EMBED_DIM, GRID};
use crate::kernels::{gelu_erf_in_place, layer_norm_in_place, matmul};

/// Channels after the first transposed convolution.
const MID: usize = EMBED_DIM / 4;
/// Channels after the second one (the hypernetworks' output size).
const OUT: usize = EMBED_DIM / 8;
/// Masks per prompt.
const MASKS: usize = 4;
/// Side of the output logits.
const SIDE: usize = GRID * 4;
/// Grid rows per band: two rows keep the band's three buffers (~0.5 MB) in the L2 cache.
const BAND_ROWS: usize = 2;
const BAND: usize = BAND_ROWS * GRID;

/// The upscaling weights in the fused loop's layout.
#[derive(Debug)]
pub(crate) struct FusedMaskHead {
    /// `(256, 4 · 64)`: input channel × (kernel position, output channel).
    w1: Vec<f32>,
    b1: Vec<f32>,
    ln_weight: Vec<f32>,
    ln_bias: Vec<f32>,
    ln_eps: f32,
    /// `(64, 4 · 32)`, the same layout.
    w2: Vec<f32>,
    b2: Vec<f32>,
}

/// A `ConvTranspose2d(c, o, 2, 2)` weight `(c, o, 2, 2)` as `(c, 4 · o)` with columns ordered by
/// kernel position, then output channel, so each position's channels are contiguous.
fn by_kernel_position(weight: &Tensor) -> Result<Vec<f32>> {
    let (c, o, kh, kw) = weight.dims4()?;
    weight
        .permute((0, 2, 3, 1))?
        .reshape((c, kh * kw * o))?
        .flatten_all()?
        .to_vec1::<f32>()
}

/// Each prompt's buffers for one band.
struct Band {
    /// `(BAND, 4 · MID)`: after the first convolution, then normalised and activated in place;
    /// read as `(BAND · 4, MID)`, one row per first-level output pixel.
    first: Vec<f32>,
    /// `(BAND · 4, 4 · OUT)`: after the second convolution and activation; read as
    /// `(BAND · 16, OUT)`, one row per output pixel.
    second: Vec<f32>,
    /// `(BAND · 16, MASKS)`: each output pixel's logits.
    logits: Vec<f32>,
    /// The prompt's hypernetwork outputs transposed, `(OUT, MASKS)`.
    hyper: Vec<f32>,
}

impl Band {
    fn new() -> Self {
        Self {
            first: vec![0.0; BAND * 4 * MID],
            second: vec![0.0; BAND * 16 * OUT],
            logits: vec![0.0; BAND * 16 * MASKS],
            hyper: vec![0.0; OUT * MASKS],
        }
    }
}

impl FusedMaskHead {
    /// The fused layout of the decoder's `output_upscaling` weights: the two transposed
    /// convolutions `(256, 64, 2, 2)` and `(64, 32, 2, 2)` with their biases, the channel norm's
    /// weight, bias and epsilon.
    pub(crate) fn new(
        up1: (&Tensor, &Tensor),
        norm: (&Tensor, &Tensor, f64),
        up2: (&Tensor, &Tensor),
    ) -> Result<Self> {
        let vec = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
        Ok(Self {
            w1: by_kernel_position(up1.0)?,
            b1: vec(up1.1)?,
            ln_weight: vec(norm.0)?,
            ln_bias: vec(norm.1)?,
            ln_eps: norm.2 as f32,
            w2: by_kernel_position(up2.0)?,
            b2: vec(up2.1)?,
        })
    }

    /// The `(B, 4, 256, 256)` mask logits of `(B, 4096, 256)` image tokens (row-major grid) and
    /// `(B, 4, 32)` hypernetwork outputs, both row-major, `B` = `hyper.len() / 128`.
    pub(crate) fn masks(&self, tokens: &[f32], hyper: &[f32]) -> Vec<f32> {
        let batch = hyper.len() / (MASKS * OUT);
        let plane = SIDE * SIDE;
        let mut out = vec![0.0f32; batch * MASKS * plane];
        out.par_chunks_mut(MASKS * plane)
            .zip(tokens.par_chunks(GRID * GRID * EMBED_DIM))
            .zip(hyper.par_chunks(MASKS * OUT))
            .for_each_init(Band::new, |band, ((out, tokens), hyper)| {
                for (m, h) in hyper.chunks_exact(OUT).enumerate() {
                    for (c, v) in h.iter().enumerate() {
                        band.hyper[c * MASKS + m] = *v;
                    }
                }
                for (b, rows) in tokens.chunks_exact(BAND * EMBED_DIM).enumerate() {
                    self.band(rows, b * BAND_ROWS, band, out);
                }
            });
        out
    }

    /// One band of one prompt: grid rows `row0..row0 + BAND_ROWS` (`rows` are their tokens) to
    /// output rows `4 · row0 .. 4 · (row0 + BAND_ROWS)` of each mask plane of `out`.
    fn band(&self, rows: &[f32], row0: usize, band: &mut Band, out: &mut [f32]) {
        let Band {
            first,
            second,
            logits,
            hyper,
        } = band;
        matmul(rows, &self.w1, first, (BAND, EMBED_DIM, 4 * MID));
        // LayerNorm2d over each first-level pixel's channels.
        for pixel in first.chunks_exact_mut(MID) {
            for (v, b) in pixel.iter_mut().zip(&self.b1) {
                *v += b;
            }
            layer_norm_in_place(pixel, &self.ln_weight, &self.ln_bias, self.ln_eps);
        }
        gelu_erf_in_place(first);
        matmul(first, &self.w2, second, (BAND * 4, MID, 4 * OUT));
        for channels in second.chunks_exact_mut(OUT) {
            for (v, b) in channels.iter_mut().zip(&self.b2) {
                *v += b;
            }
        }
        gelu_erf_in_place(second);
        matmul(second, hyper, logits, (BAND * 16, OUT, MASKS));
        // Row `r2 = (p · 4 + k1) · 4 + k2` of `logits` is output pixel
        // (2 · y1 + k2 / 2, 2 · x1 + k2 % 2) of first-level pixel (y1, x1) =
        // (2y + k1 / 2, 2x + k1 % 2) of grid cell p = (y, x).
        let plane = SIDE * SIDE;
        for (r2, pixel) in logits.chunks_exact(MASKS).enumerate() {
            let (p, k1, k2) = (r2 / 16, (r2 / 4) % 4, r2 % 4);
            let (y, x) = (row0 + p / GRID, p % GRID);
            let (y1, x1) = (2 * y + k1 / 2, 2 * x + k1 % 2);
            let at = (2 * y1 + k2 / 2) * SIDE + 2 * x1 + k2 % 2;
            for (m, &logit) in pixel.iter().enumerate() {
                out[m * plane + at] = logit;
            }
        }
    }
}
