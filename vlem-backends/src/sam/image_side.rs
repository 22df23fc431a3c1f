//! The image side of SAM's two-way transformer on the CPU, fused: the cross attentions between a
//! prompt's few tokens and its 4096 image tokens, and the image tokens' residual update.
//!
//! Why it exists: after the first image update every prompt has its own image tokens, so the
//! decoder's three later cross attentions project `4096 × 256` tokens per prompt, and as candle
//! ops each step writes a fresh 2-4 MB intermediate per prompt. With only `T` (7) tokens on the
//! other side, both attentions can instead move the projections to the token side (exact
//! algebra, different rounding):
//! - token to image: the score of token `t` and image token `i` in head `h` is
//!   `q_th · (W_kh x_i + b_kh)` = `x_i · (W_khᵀ q_th) + b_kh · q_th`, with `x_i` the image token
//!   plus its positional encoding; so one `(4096 × 256) · (256 × 8T)` product gives every score,
//!   and the values' projection moves after the weighted sum: `Σ_i a_i (W_vh k_i + b_vh)` =
//!   `W_vh (Σ_i a_i k_i) + b_vh`.
//! - image to token: the same for the query projection, and the output projection moves before
//!   the weighted sum of the token values: `W_o (Σ_t a_t v_t)` = `Σ_t a_t (W_o v_t)`.
//!
//! That is 2 × 58 M multiply-adds per attention and prompt instead of 2-4 × 134 M, in bands of
//! image rows that stay in the cache, prompts in parallel. The candle ops of `MaskDecoder`
//! remain the path of other devices and the reference the tests compare this with.

use candle_core::{Result, Tensor};
use candle_nn::{LayerNorm, Linear};
use rayon::prelude::*;

use super::image::{EMBED_DIM, GRID};
use crate::kernels::{layer_norm_in_place, matmul, softmax_runs};

/// Attention heads of the decoder's attentions.
const HEADS: usize = 8;
/// Image tokens.
const TOKENS: usize = GRID * GRID;
/// Image rows per band of the image-to-token update.
const BAND: usize = 128;

/// A PyTorch linear layer's weight `(out, in)` and bias, as row-major values.
#[derive(Debug)]
struct Projection {
    weight: Vec<f32>,
    bias: Vec<f32>,
    out: usize,
}

impl Projection {
    fn new(linear: &Linear) -> Result<Self> {
        let (out, _) = linear.weight().dims2()?;
        let bias = match linear.bias() {
            Some(b) => b.to_vec1::<f32>()?,
            None => vec![0.0; out],
        };
        Ok(Self {
            weight: linear.weight().flatten_all()?.to_vec1::<f32>()?,
            bias,
            out,
        })
    }
}

/// Per-thread buffers of one prompt's attention.
#[derive(Default)]
struct Scratch {
    /// `(256, 8T)`: the token side moved through the image-side projection.
    moved: Vec<f32>,
    /// `(8T, 256)`: the same, transposed.
    moved_rows: Vec<f32>,
    /// `8T` score offsets from the projection's bias.
    offsets: Vec<f32>,
    /// Image tokens plus positional encoding of a band, `(rows, 256)`.
    x: Vec<f32>,
    /// Scores, `(rows, 8T)`.
    scores: Vec<f32>,
    /// Scores transposed, `(8T, 4096)`.
    transposed: Vec<f32>,
    /// `(8T, 256)`: weighted sums of image tokens, or the token values through `W_o`.
    sums: Vec<f32>,
    /// A band's attention output, `(rows, 256)`.
    update: Vec<f32>,
}

impl Scratch {
    /// Fills `moved` and `offsets` with `proj` moved onto the `t` projected tokens `side` (see
    /// [`move_projection`], scaled by the attention's `1/√head_dim`); returns their column count
    /// `8T`.
    fn move_onto(&mut self, proj: &Projection, side: &[f32], t: usize) -> usize {
        let cols = HEADS * t;
        let scale = 1.0 / ((proj.out / HEADS) as f32).sqrt();
        let moved = sized(&mut self.moved, EMBED_DIM * cols);
        let offsets = sized(&mut self.offsets, cols);
        let rows = sized(&mut self.moved_rows, cols * EMBED_DIM);
        move_projection(proj, side, t, scale, (moved, rows, offsets));
        cols
    }
}

/// Resizes a buffer (values are overwritten by the caller).
fn sized(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    buf.resize(len, 0.0);
    &mut buf[..len]
}

/// `moved[c, h·T + t] = scale · Σ_d W[h·hd + d, c] · side[t, h·hd + d]` and
/// `offsets[h·T + t] = scale · Σ_d b[h·hd + d] · side[t, h·hd + d]`: an image-side projection
/// (`W`: `(internal, 256)`) moved onto the `T` projected tokens `side` (`(T, internal)`).
/// `rows` is a `(8T, 256)` buffer for the transpose of `moved`.
fn move_projection(
    proj: &Projection,
    side: &[f32],
    t: usize,
    scale: f32,
    (moved, rows, offsets): (&mut [f32], &mut [f32], &mut [f32]),
) {
    let internal = proj.out;
    let hd = internal / HEADS;
    let cols = HEADS * t;
    rows.fill(0.0);
    for h in 0..HEADS {
        for j in 0..t {
            let col = h * t + j;
            let acc = &mut rows[col * EMBED_DIM..(col + 1) * EMBED_DIM];
            let mut offset = 0.0f32;
            for d in 0..hd {
                let r = h * hd + d;
                let s = side[j * internal + r] * scale;
                offset += proj.bias[r] * s;
                let weights = &proj.weight[r * EMBED_DIM..(r + 1) * EMBED_DIM];
                for (a, w) in acc.iter_mut().zip(weights) {
                    *a += w * s;
                }
            }
            offsets[col] = offset;
        }
    }
    for (col, row) in rows.chunks_exact(EMBED_DIM).enumerate() {
        for (c, v) in row.iter().enumerate() {
            moved[c * cols + col] = *v;
        }
    }
}

/// The weights of a token-to-image attention (`cross_attn_token_to_image`,
/// `final_attn_token_to_image`): the image side's key and value projections.
#[derive(Debug)]
pub(crate) struct TokenToImage {
    k: Projection,
    v: Projection,
}

impl TokenToImage {
    pub(crate) fn new(k: &Linear, v: &Linear) -> Result<Self> {
        Ok(Self {
            k: Projection::new(k)?,
            v: Projection::new(v)?,
        })
    }

    /// One prompt's attention output before the output projection, `(T, internal)`, for its
    /// projected token queries `q` (`(T, internal)`), image tokens `keys` and the positional
    /// encoding `pe` (both `(4096, 256)`).
    fn attend(&self, keys: &[f32], pe: &[f32], q: &[f32], t: usize, s: &mut Scratch) -> Vec<f32> {
        let internal = self.k.out;
        let hd = internal / HEADS;
        let cols = s.move_onto(&self.k, q, t);
        let (moved, offsets) = (&s.moved[..], &s.offsets[..]);
        let x = sized(&mut s.x, TOKENS * EMBED_DIM);
        for ((x, k), p) in x.iter_mut().zip(keys).zip(pe) {
            *x = k + p;
        }
        let scores = sized(&mut s.scores, TOKENS * cols);
        matmul(x, moved, scores, (TOKENS, EMBED_DIM, cols));
        // Softmax over the image tokens, per column: transposed, each column is a run.
        let transposed = sized(&mut s.transposed, cols * TOKENS);
        for (i, row) in scores.chunks_exact(cols).enumerate() {
            for (col, v) in row.iter().enumerate() {
                transposed[col * TOKENS + i] = v + offsets[col];
            }
        }
        softmax_runs(transposed, TOKENS);
        let sums = sized(&mut s.sums, cols * EMBED_DIM);
        matmul(transposed, keys, sums, (cols, TOKENS, EMBED_DIM));
        // The value projection of the weighted sums (the weights sum to 1, so the bias once).
        let mut out = vec![0.0f32; t * internal];
        for h in 0..HEADS {
            for j in 0..t {
                let sum = &sums[(h * t + j) * EMBED_DIM..][..EMBED_DIM];
                for d in 0..hd {
                    let r = h * hd + d;
                    let row = &self.v.weight[r * EMBED_DIM..(r + 1) * EMBED_DIM];
                    let dot: f32 = row.iter().zip(sum).map(|(a, b)| a * b).sum();
                    out[j * internal + r] = dot + self.v.bias[r];
                }
            }
        }
        out
    }
}

/// The weights of an image-to-token attention and the norm after it
/// (`cross_attn_image_to_token` and `norm4` of a two-way block).
#[derive(Debug)]
pub(crate) struct ImageToToken {
    q: Projection,
    /// The output projection's weight transposed, `(internal, 256)`, and its bias.
    o_columns: Vec<f32>,
    o_bias: Vec<f32>,
    norm_weight: Vec<f32>,
    norm_bias: Vec<f32>,
    eps: f32,
}

impl ImageToToken {
    pub(crate) fn new(q: &Linear, o: &Linear, norm: &LayerNorm) -> Result<Self> {
        let vec = |t: &Tensor| t.to_vec1::<f32>();
        Ok(Self {
            q: Projection::new(q)?,
            o_columns: o.weight().t()?.flatten_all()?.to_vec1::<f32>()?,
            o_bias: Projection::new(o)?.bias,
            norm_weight: vec(norm.weight())?,
            norm_bias: match norm.bias() {
                Some(b) => vec(b)?,
                None => vec![0.0; EMBED_DIM],
            },
            eps: norm.eps() as f32,
        })
    }

    /// Updates one prompt's image tokens `keys` (`(4096, 256)`) in place:
    /// `keys ← norm(keys + attention)`, the image tokens (plus `pe`) attending to the prompt's
    /// projected token keys `k` and values `v` (both `(T, internal)`).
    fn update(
        &self,
        keys: &mut [f32],
        pe: &[f32],
        k: &[f32],
        v: &[f32],
        t: usize,
        s: &mut Scratch,
    ) {
        let internal = self.q.out;
        let hd = internal / HEADS;
        let cols = s.move_onto(&self.q, k, t);
        let (moved, offsets) = (&s.moved[..], &s.offsets[..]);
        // Each (head, token) value through its head's columns of the output projection.
        let through = sized(&mut s.sums, cols * EMBED_DIM);
        through.fill(0.0);
        for h in 0..HEADS {
            for j in 0..t {
                let row = &mut through[(h * t + j) * EMBED_DIM..][..EMBED_DIM];
                for d in 0..hd {
                    let r = h * hd + d;
                    let value = v[j * internal + r];
                    let column = &self.o_columns[r * EMBED_DIM..(r + 1) * EMBED_DIM];
                    for (acc, w) in row.iter_mut().zip(column) {
                        *acc += w * value;
                    }
                }
            }
        }
        let x = sized(&mut s.x, BAND * EMBED_DIM);
        let scores = sized(&mut s.scores, BAND * cols);
        let update = sized(&mut s.update, BAND * EMBED_DIM);
        for (band, pe) in keys
            .chunks_exact_mut(BAND * EMBED_DIM)
            .zip(pe.chunks_exact(BAND * EMBED_DIM))
        {
            for ((x, k), p) in x.iter_mut().zip(band.iter()).zip(pe) {
                *x = k + p;
            }
            matmul(x, moved, scores, (BAND, EMBED_DIM, cols));
            for row in scores.chunks_exact_mut(cols) {
                for (v, o) in row.iter_mut().zip(offsets.iter()) {
                    *v += o;
                }
            }
            // Softmax over the tokens within each head: runs of `t`.
            softmax_runs(scores, t);
            matmul(scores, through, update, (BAND, cols, EMBED_DIM));
            for (row, upd) in band
                .chunks_exact_mut(EMBED_DIM)
                .zip(update.chunks_exact(EMBED_DIM))
            {
                for ((k, u), b) in row.iter_mut().zip(upd).zip(&self.o_bias) {
                    *k += u + b;
                }
                layer_norm_in_place(row, &self.norm_weight, &self.norm_bias, self.eps);
            }
        }
    }
}

/// The values of a tensor on the CPU, row-major.
fn values(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

/// [`TokenToImage::attend`] for a batch of prompts in parallel: `keys` holds `B` prompts' image
/// tokens, `q` is `(B, T, internal)`; returns `(B, T, internal)`.
pub(crate) fn token_to_image(
    attention: &TokenToImage,
    keys: &[f32],
    pe: &[f32],
    q: &Tensor,
) -> Result<Tensor> {
    let (b, t, internal) = q.dims3()?;
    let q_values = values(q)?;
    let outs: Vec<Vec<f32>> = keys
        .par_chunks(TOKENS * EMBED_DIM)
        .zip(q_values.par_chunks(t * internal))
        .map_init(Scratch::default, |s, (keys, q)| {
            attention.attend(keys, pe, q, t, s)
        })
        .collect();
    Tensor::from_vec(outs.concat(), (b, t, internal), q.device())
}

/// [`ImageToToken::update`] for a batch of prompts in parallel: `k` and `v` are
/// `(B, T, internal)`.
pub(crate) fn image_to_token(
    attention: &ImageToToken,
    keys: &mut [f32],
    pe: &[f32],
    k: &Tensor,
    v: &Tensor,
) -> Result<()> {
    let (_, t, internal) = k.dims3()?;
    let (k_values, v_values) = (values(k)?, values(v)?);
    keys.par_chunks_mut(TOKENS * EMBED_DIM)
        .zip(k_values.par_chunks(t * internal))
        .zip(v_values.par_chunks(t * internal))
        .for_each_init(Scratch::default, |s, ((keys, k), v)| {
            attention.update(keys, pe, k, v, t, s);
        });
    Ok(())
}
