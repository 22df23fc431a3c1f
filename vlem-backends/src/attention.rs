//! The one multi-head attention layer of the candle models: CLIP's towers, the ViTs of dinov3 and
//! NARADIO (NACLIP's key-key attention as an option), and SAM's image encoders (relative
//! positions, TinyViT's bias table) and mask decoder (separate query, key and value inputs).
//!
//! Why it exists: each model had its own `Attention` with its own copy of the same projection,
//! head split, scaled product, softmax and merge. Written once, the models differ only in what
//! they declare (how the input is projected, what is added to the scores), and the step that
//! matters for speed, [`scaled_dot_product`], is one function: where a fused kernel for a device
//! goes, tested against this plain version.
//!
//! On the CPU, f32 attention runs in blocks of queries whose scores stay in cache
//! ([`crate::cpu_attention`], every kind of [`Scores`]). Elsewhere (other devices, half
//! precision without the fused kernel, a batch broadcast against another) the plain version
//! computes the scores of at most [`MAX_SCORES`] values at a time (chunks of the batch × head
//! dimension), which bounds the memory of global attention over large grids (SAM's 64 × 64
//! tokens) and leaves smaller inputs as one product.

use candle_core::{Result, Tensor};

use crate::cpu_attention::Sizes;
use crate::kernels::softmax_last_dim;
use crate::profile;

/// Attention scores computed at once at most (floats): 128 MiB.
pub(crate) const MAX_SCORES: usize = 1 << 25;

/// A linear layer over the last dimension of its input, whatever the leading dimensions.
pub(crate) trait Project {
    /// `x · Wᵀ + b`.
    fn project(&self, x: &Tensor) -> Result<Tensor>;
}

impl Project for candle_nn::Linear {
    fn project(&self, x: &Tensor) -> Result<Tensor> {
        use candle_core::Module;

        // candle's `Linear` wants rank 2 to 4 with a matching batch layout: flatten the leading
        // dimensions into one matrix product.
        let dims = x.dims().to_vec();
        let last = dims.len().saturating_sub(1);
        let rows: usize = dims[..last].iter().product();
        let inputs = dims.get(last).copied().unwrap_or(0);
        let out = self.forward(&x.reshape((rows, inputs))?)?;
        let mut out_dims = dims;
        if let Some(d) = out_dims.last_mut() {
            *d = out.dim(1)?;
        }
        out.reshape(out_dims)
    }
}

/// A rotation of queries and keys by their positions (RoPE), applied before the product.
pub(crate) trait Rotate {
    /// `x`: `(batch, heads, tokens, head_dim)`.
    fn rotate(&self, x: &Tensor) -> Result<Tensor>;
}

/// How the queries, keys and values are projected from the input.
#[derive(Clone, Debug)]
pub(crate) enum Inputs<L> {
    /// One product; output channels `[q | k | v]`, each `heads × head_dim` (CLIP, ViT, SAM ViT).
    Fused(L),
    /// One product; output channels per head `[q k v]`, each `head_dim` (TinyViT).
    FusedPerHead(L),
    /// Three products of three inputs (SAM's decoder, whose queries and keys differ).
    Separate {
        /// Query projection.
        q: L,
        /// Key projection.
        k: L,
        /// Value projection.
        v: L,
    },
}

/// What the attention weights are made of, beyond `softmax(q·kᵀ / √head_dim)`.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Scores<'a> {
    /// The plain scaled product.
    Plain,
    /// Plus a bias broadcast to `(batch, heads, queries, keys)`: a causal mask `(len, len)`,
    /// TinyViT's per-head table `(heads, n, n)`.
    Bias(&'a Tensor),
    /// NACLIP: keys against keys (the query is not used), plus the `(tokens, tokens)` prior.
    KeyKey {
        /// The Gaussian neighbourhood prior.
        prior: &'a Tensor,
    },
    /// SAM's decomposed relative positions on an `h × w` token grid: per query, the dot products
    /// of the (unscaled) query with the rows of `table_h` `(h, h, head_dim)` and `table_w`
    /// `(w, w, head_dim)` added along the key's row and column.
    Relative {
        /// Grid rows and columns (`h · w` tokens).
        grid: (usize, usize),
        /// Relative position rows by (query row, key row).
        table_h: &'a Tensor,
        /// Relative position rows by (query column, key column).
        table_w: &'a Tensor,
    },
}

/// Multi-head attention: input projections, the scaled product with its score options, the
/// output projection.
#[derive(Clone, Debug)]
pub(crate) struct Attention<L> {
    inputs: Inputs<L>,
    out: L,
    heads: usize,
}

impl<L: Project> Attention<L> {
    /// An attention layer with `heads` heads.
    pub(crate) fn new(inputs: Inputs<L>, out: L, heads: usize) -> Self {
        Self {
            inputs,
            out,
            heads: heads.max(1),
        }
    }

    /// The query, key and value projections of a layer with [`Inputs::Separate`] (SAM's fused
    /// decoder step applies them itself).
    pub(crate) fn separate_inputs(&self) -> Option<[&L; 3]> {
        match &self.inputs {
            Inputs::Separate { q, k, v } => Some([q, k, v]),
            Inputs::Fused(_) | Inputs::FusedPerHead(_) => None,
        }
    }

    /// The output projection.
    pub(crate) fn out(&self) -> &L {
        &self.out
    }

    /// Self-attention over `x` `(batch, tokens, width)`, queries and keys rotated by `rope`.
    pub(crate) fn forward(
        &self,
        x: &Tensor,
        rope: Option<&dyn Rotate>,
        scores: Scores<'_>,
    ) -> Result<Tensor> {
        self.attend(x, x, x, rope, scores)
    }

    /// Attention of queries from `q` over keys from `k` and values from `v` (each
    /// `(batch, tokens, width)`; a batch of 1 on either side broadcasts against the other).
    pub(crate) fn forward_qkv(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        scores: Scores<'_>,
    ) -> Result<Tensor> {
        self.attend(q, k, v, None, scores)
    }

    fn attend(
        &self,
        q_in: &Tensor,
        k_in: &Tensor,
        v_in: &Tensor,
        rope: Option<&dyn Rotate>,
        scores: Scores<'_>,
    ) -> Result<Tensor> {
        let device = q_in.device();
        let (mut q, mut k, v) = profile::timed("attention: q, k, v projections", device, || {
            self.project_inputs(q_in, k_in, v_in)
        })?;
        if let Some(rope) = rope {
            (q, k) = profile::timed("attention: RoPE", device, || {
                Ok((rope.rotate(&q)?, rope.rotate(&k)?))
            })?;
        }
        let head_dim = q.dim(3)?;
        // The step a fused kernel replaces: its share of a frame is what such a kernel can win.
        let mixed = profile::timed("attention: scores, softmax, mix", device, || {
            scaled_dot_product(&q, &k, &v, (head_dim as f64).powf(-0.5), scores)
        })?;
        // A batch of 1 on either side broadcasts: the batch is the product's.
        let (batch, heads, tokens, _) = mixed.dims4()?;
        let mixed = mixed
            .transpose(1, 2)?
            .reshape((batch, tokens, heads * head_dim))?;
        profile::timed("attention: output projection", device, || {
            self.out.project(&mixed)
        })
    }

    /// Queries, keys and values as `(batch, heads, tokens, head_dim)`, contiguous.
    fn project_inputs(
        &self,
        q_in: &Tensor,
        k_in: &Tensor,
        v_in: &Tensor,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let heads = self.heads;
        match &self.inputs {
            Inputs::Fused(qkv) => {
                let (batch, tokens, _) = q_in.dims3()?;
                let y = qkv.project(q_in)?;
                let head_dim = y.dim(2)? / (3 * heads);
                let y = y
                    .reshape((batch, tokens, 3, heads, head_dim))?
                    .permute((2, 0, 3, 1, 4))?; // (3, batch, heads, tokens, head_dim)
                Ok((
                    y.get(0)?.contiguous()?,
                    y.get(1)?.contiguous()?,
                    y.get(2)?.contiguous()?,
                ))
            }
            Inputs::FusedPerHead(qkv) => {
                let (batch, tokens, _) = q_in.dims3()?;
                let y = qkv.project(q_in)?;
                let head_dim = y.dim(2)? / (3 * heads);
                let y = y
                    .reshape((batch, tokens, heads, 3 * head_dim))?
                    .permute((0, 2, 1, 3))?;
                Ok((
                    y.narrow(3, 0, head_dim)?.contiguous()?,
                    y.narrow(3, head_dim, head_dim)?.contiguous()?,
                    y.narrow(3, 2 * head_dim, head_dim)?.contiguous()?,
                ))
            }
            Inputs::Separate { q, k, v } => {
                let split = |layer: &L, x: &Tensor| -> Result<Tensor> {
                    let (batch, tokens, _) = x.dims3()?;
                    let y = layer.project(x)?;
                    let head_dim = y.dim(2)? / heads;
                    y.reshape((batch, tokens, heads, head_dim))?
                        .transpose(1, 2)?
                        .contiguous()
                };
                Ok((split(q, q_in)?, split(k, k_in)?, split(v, v_in)?))
            }
        }
    }
}

/// `softmax(q·kᵀ·scale + bias)·v` with the options of [`Scores`]: `q` `(batch, heads, queries,
/// head_dim)`, `k` and `v` `(batch or 1, heads, keys, head_dim)`. With
/// [`crate::fused_attention::enabled`], plain scores in half precision go through the fused
/// kernel (on the CPU its twin); f32 on the CPU through the blocked product of
/// [`crate::cpu_attention`]; everything else through [`plain_scaled_dot_product`]: the scores
/// are materialised, [`MAX_SCORES`] at a time over the batch × head dimension. A batch of 1 on
/// either side broadcasts against the other (in one product).
pub(crate) fn scaled_dot_product(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    scores: Scores<'_>,
) -> Result<Tensor> {
    // The fused kernel where it is turned on and takes the inputs (half precision, plain scores):
    // CLIP's image tower, the ViTs of dinov3 and NARADIO.
    if matches!(scores, Scores::Plain)
        && crate::fused_attention::enabled()
        && crate::fused_attention::supports(q, k, v)
    {
        return crate::fused_attention::scaled_dot_product(q, k, v, scale);
    }
    if let Some(out) = blocked_on_cpu(q, k, v, scale, scores)? {
        return Ok(out);
    }
    plain_scaled_dot_product(q, k, v, scale, scores)
}

/// [`plain_scaled_dot_product`] on the CPU in cache-sized blocks of queries
/// ([`crate::cpu_attention`]): f32 tensors with the same batch on both sides and every kind of
/// [`Scores`]. `None` where it does not apply (another device or dtype, a broadcast batch, a
/// bias that does not broadcast as `(batch, heads, queries, keys)`): the caller then runs the
/// plain product.
fn blocked_on_cpu(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    scores: Scores<'_>,
) -> Result<Option<Tensor>> {
    use crate::cpu_attention::{Terms, attend};
    use candle_core::DType;

    let f32_on_cpu = |t: &Tensor| t.device().is_cpu() && t.dtype() == DType::F32;
    if !(f32_on_cpu(q) && f32_on_cpu(k) && f32_on_cpu(v)) {
        return Ok(None);
    }
    let (batch, heads, _, head_dim) = q.dims4()?;
    let (k_batch, k_heads, keys, k_dim) = k.dims4()?;
    if (k_batch, k_heads, k_dim) != (batch, heads, head_dim)
        || v.dims4()? != (batch, heads, keys, head_dim)
    {
        return Ok(None);
    }
    // NACLIP's key-key scores: the keys are the queries.
    let q = match scores {
        Scores::KeyKey { .. } => k,
        _ => q,
    };
    let queries = q.dim(2)?;
    let sizes = Sizes {
        batch,
        heads,
        queries,
        keys,
        head_dim,
    };
    // The added terms as contiguous f32, with how they are laid out.
    let bias = match scores {
        Scores::Bias(bias) | Scores::KeyKey { prior: bias } => {
            match bias_strides(bias.dims(), sizes) {
                Some(strides) => Some((bias.to_dtype(DType::F32)?.contiguous()?, strides)),
                None => return Ok(None),
            }
        }
        _ => None,
    };
    let relative = match scores {
        Scores::Relative {
            grid,
            table_h,
            table_w,
        } => {
            if grid.0 * grid.1 != queries || queries != keys {
                return Ok(None);
            }
            let q3 = q.reshape((batch * heads, queries, head_dim))?;
            Some((grid, relative_positions(&q3, grid, table_h, table_w)?))
        }
        _ => None,
    };

    let (q, k, v) = (q.contiguous()?, k.contiguous()?, v.contiguous()?);
    let (q_storage, q_layout) = q.storage_and_layout();
    let (k_storage, k_layout) = k.storage_and_layout();
    let (v_storage, v_layout) = v.storage_and_layout();
    let inputs = (
        f32_slice(&q_storage, q_layout)?,
        f32_slice(&k_storage, k_layout)?,
        f32_slice(&v_storage, v_layout)?,
    );
    let mut out = vec![0f32; batch * heads * queries * head_dim];
    match (&bias, &relative) {
        (Some((bias, (batch_stride, head_stride))), _) => {
            let (storage, layout) = bias.storage_and_layout();
            let terms = Terms::Bias {
                data: f32_slice(&storage, layout)?,
                batch_stride: *batch_stride,
                head_stride: *head_stride,
            };
            attend(inputs, sizes, scale as f32, terms, &mut out);
        }
        (None, Some((grid, (rel_h, rel_w)))) => {
            let (h_storage, h_layout) = rel_h.storage_and_layout();
            let (w_storage, w_layout) = rel_w.storage_and_layout();
            let terms = Terms::Relative {
                grid: *grid,
                rel_h: f32_slice(&h_storage, h_layout)?,
                rel_w: f32_slice(&w_storage, w_layout)?,
            };
            attend(inputs, sizes, scale as f32, terms, &mut out);
        }
        (None, None) => attend(inputs, sizes, scale as f32, Terms::None, &mut out),
    }
    Ok(Some(Tensor::from_vec(
        out,
        (batch, heads, queries, head_dim),
        q.device(),
    )?))
}

/// The offsets between the `(queries × keys)` matrices of a bias of shape `dims` for successive
/// batch entries and heads (0 where it broadcasts), or `None` where it does not broadcast as
/// `(batch, heads, queries, keys)`.
fn bias_strides(dims: &[usize], sizes: Sizes) -> Option<(usize, usize)> {
    let matrix = sizes.queries * sizes.keys;
    let (lead, last) = dims.split_at(dims.len().checked_sub(2)?);
    if last != [sizes.queries, sizes.keys] || lead.len() > 2 {
        return None;
    }
    let mut padded = [1usize; 2];
    padded[2 - lead.len()..].copy_from_slice(lead);
    let [b, h] = padded;
    let head_stride = match h {
        1 => 0,
        h if h == sizes.heads => matrix,
        _ => return None,
    };
    let batch_stride = match b {
        1 => 0,
        b if b == sizes.batch => h * matrix,
        _ => return None,
    };
    Some((batch_stride, head_stride))
}

/// The values of a contiguous f32 CPU tensor's storage.
fn f32_slice<'a>(
    storage: &'a candle_core::Storage,
    layout: &candle_core::Layout,
) -> Result<&'a [f32]> {
    match (storage, layout.contiguous_offsets()) {
        (candle_core::Storage::Cpu(candle_core::CpuStorage::F32(values)), Some((start, end))) => {
            Ok(&values[start..end])
        }
        _ => Err(candle_core::Error::Msg(
            "blocked attention: expected a contiguous f32 CPU tensor".into(),
        )),
    }
}

/// [`scaled_dot_product`] without the fused kernel: the scores materialised, [`MAX_SCORES`] at a
/// time.
pub(crate) fn plain_scaled_dot_product(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    scores: Scores<'_>,
) -> Result<Tensor> {
    let (batch, heads, queries, head_dim) = q.dims4()?;
    let keys = k.dim(2)?;
    // SAM's decoder: one image's keys against a batch of prompts' queries, or the reverse.
    if k.dim(0)? != batch {
        let logits = (q * scale)?.broadcast_matmul(&k.t()?)?;
        let logits = match scores {
            Scores::Bias(bias) => logits.broadcast_add(bias)?,
            _ => logits,
        };
        return softmax_last_dim(&logits)?.broadcast_matmul(v);
    }
    let rows = batch * heads;
    let chunk = (MAX_SCORES / (queries * keys).max(1)).max(1);
    if rows <= chunk && !matches!(scores, Scores::Relative { .. }) {
        // One product over the (batch, heads, …) tensors as they are: the op sequence each
        // model ran before this layer was shared.
        let logits = match scores {
            Scores::KeyKey { .. } => (k * scale)?.matmul(&k.t()?)?,
            _ => (q * scale)?.matmul(&k.t()?)?,
        };
        let logits = match scores {
            Scores::Bias(bias) => logits.broadcast_add(&bias.to_dtype(logits.dtype())?)?,
            Scores::KeyKey { prior } => logits.broadcast_add(&prior.to_dtype(logits.dtype())?)?,
            Scores::Plain | Scores::Relative { .. } => logits,
        };
        return softmax_last_dim(&logits)?.matmul(v);
    }
    let flat = |t: &Tensor| -> Result<Tensor> {
        let (_, _, n, d) = t.dims4()?;
        t.reshape((rows, n, d))
    };
    let (q3, k3, v3) = (flat(q)?, flat(k)?, flat(v)?);
    let relative = match scores {
        Scores::Relative {
            grid,
            table_h,
            table_w,
        } => Some(relative_positions(&q3, grid, table_h, table_w)?),
        _ => None,
    };
    let mut outs = Vec::with_capacity(rows.div_ceil(chunk));
    let mut start = 0;
    while start < rows {
        let len = chunk.min(rows - start);
        let k = k3.narrow(0, start, len)?;
        let logits = match scores {
            Scores::KeyKey { .. } => (&k * scale)?.matmul(&k.t()?)?,
            _ => (q3.narrow(0, start, len)? * scale)?.matmul(&k.t()?)?,
        };
        let logits = match scores {
            Scores::Plain => logits,
            Scores::Bias(bias) => add_per_row(&logits, bias, (batch, heads), start)?,
            Scores::KeyKey { prior } => logits.broadcast_add(&prior.to_dtype(logits.dtype())?)?,
            Scores::Relative { grid, .. } => match &relative {
                Some((rel_h, rel_w)) => {
                    let (h, w) = grid;
                    let rel = rel_h
                        .narrow(0, start, len)?
                        .unsqueeze(4)?
                        .broadcast_add(&rel_w.narrow(0, start, len)?.unsqueeze(3)?)?
                        .reshape((len, h * w, h * w))?;
                    logits.add(&rel)?
                }
                None => logits,
            },
        };
        outs.push(softmax_last_dim(&logits)?.matmul(&v3.narrow(0, start, len)?)?);
        start += len;
    }
    let out = match outs.len() {
        1 => outs.swap_remove(0),
        _ => Tensor::cat(&outs, 0)?,
    };
    out.reshape((batch, heads, queries, head_dim))
}

/// `bias` broadcast to `(batch, heads, queries, keys)`, the rows `start..start + len` of its
/// `batch × heads` flattening, added to `logits` `(len, queries, keys)`.
fn add_per_row(
    logits: &Tensor,
    bias: &Tensor,
    (batch, heads): (usize, usize),
    start: usize,
) -> Result<Tensor> {
    let (len, queries, keys) = logits.dims3()?;
    let bias = bias.to_dtype(logits.dtype())?;
    if start == 0 && len == batch * heads {
        // All rows at once (every model but SAM's global attention): the bias broadcasts as it
        // is, nothing materialised.
        return logits
            .reshape((batch, heads, queries, keys))?
            .broadcast_add(&bias)?
            .reshape((len, queries, keys));
    }
    let bias = bias.broadcast_as((batch, heads, queries, keys))?.reshape((
        batch * heads,
        queries,
        keys,
    ))?;
    logits.add(&bias.narrow(0, start, len)?)
}

/// SAM's decomposed relative position terms of queries `q` `(rows, h·w, head_dim)` on an
/// `h × w` grid: `rel_h[r, y, x, ky] = q[r, y, x] · table_h[y, ky]` and `rel_w[r, y, x, kx] =
/// q[r, y, x] · table_w[x, kx]`, as `(rows, h, w, h)` and `(rows, h, w, w)`.
fn relative_positions(
    q: &Tensor,
    (h, w): (usize, usize),
    table_h: &Tensor,
    table_w: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let (rows, _, head_dim) = q.dims3()?;
    let grid = q.reshape((rows, h, w, head_dim))?;
    let rel_h = grid
        .permute((1, 0, 2, 3))?
        .reshape((h, rows * w, head_dim))?
        .contiguous()?
        .matmul(&table_h.transpose(1, 2)?.contiguous()?)?
        .reshape((h, rows, w, h))?
        .permute((1, 0, 2, 3))?
        .contiguous()?;
    let rel_w = grid
        .permute((2, 0, 1, 3))?
        .reshape((w, rows * h, head_dim))?
        .contiguous()?
        .matmul(&table_w.transpose(1, 2)?.contiguous()?)?
        .reshape((w, rows, h, w))?
        .permute((1, 2, 0, 3))?
        .contiguous()?;
    Ok((rel_h, rel_w))
}

/// The scores and weights in `f32` whatever the tensors' dtype: the plain reference the tests
/// compare [`scaled_dot_product`] with (no chunks, no options but a bias).
#[cfg(test)]
fn reference(q: &Tensor, k: &Tensor, v: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    use candle_core::DType;

    let d = q.dim(3)?;
    let logits = (q
        .to_dtype(DType::F32)?
        .matmul(&k.to_dtype(DType::F32)?.t()?)?
        * (d as f64).powf(-0.5))?;
    let logits = match bias {
        Some(b) => logits.broadcast_add(b)?,
        None => logits,
    };
    candle_nn::ops::softmax_last_dim(&logits)?.matmul(&v.to_dtype(DType::F32)?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    fn random(shape: (usize, usize, usize, usize), seed: u64) -> Tensor {
        let n = shape.0 * shape.1 * shape.2 * shape.3;
        let mut state = seed;
        let values: Vec<f32> = (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1);
                ((state >> 33) as f32 / (1u64 << 31) as f32) - 0.5
            })
            .collect();
        Tensor::from_vec(values, shape, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        let a = a.flatten_all().and_then(|t| t.to_vec1::<f32>());
        let b = b.flatten_all().and_then(|t| t.to_vec1::<f32>());
        match (a, b) {
            (Ok(a), Ok(b)) => a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max),
            _ => f32::INFINITY,
        }
    }

    #[test]
    fn the_chunked_product_matches_the_plain_one() -> Result<()> {
        let (q, k, v) = (
            random((2, 3, 40, 8), 1),
            random((2, 3, 40, 8), 2),
            random((2, 3, 40, 8), 3),
        );
        let scale = 8f64.powf(-0.5);
        let expected = reference(&q, &k, &v, None)?;
        assert!(
            max_diff(
                &scaled_dot_product(&q, &k, &v, scale, Scores::Plain)?,
                &expected
            ) < 1e-6
        );
        // A causal mask, and a per-head bias.
        let mask: Vec<f32> = (0..40 * 40)
            .map(|i| {
                if i % 40 > i / 40 {
                    f32::NEG_INFINITY
                } else {
                    0.0
                }
            })
            .collect();
        let mask = Tensor::from_vec(mask, (40, 40), &Device::Cpu)?;
        let expected = reference(&q, &k, &v, Some(&mask))?;
        let got = scaled_dot_product(&q, &k, &v, scale, Scores::Bias(&mask))?;
        assert!(max_diff(&got, &expected) < 1e-6);
        let per_head = random((1, 3, 40, 40), 4).squeeze(0)?;
        let expected = reference(&q, &k, &v, Some(&per_head))?;
        let got = scaled_dot_product(&q, &k, &v, scale, Scores::Bias(&per_head))?;
        assert!(max_diff(&got, &expected) < 1e-6);
        // Keys against keys: the reference with the keys as queries, plus the prior.
        let prior = random((1, 1, 40, 40), 5).reshape((40, 40))?;
        let expected = reference(&k, &k, &v, Some(&prior))?;
        let got = scaled_dot_product(&q, &k, &v, scale, Scores::KeyKey { prior: &prior })?;
        assert!(max_diff(&got, &expected) < 1e-6);
        Ok(())
    }

    #[test]
    fn relative_positions_are_the_decomposed_bias() -> Result<()> {
        // A 4 × 5 grid: the bias of query (y, x) and key (ky, kx) is q·Th[y, ky] + q·Tw[x, kx].
        let (h, w, d) = (4, 5, 6);
        let q = random((1, 2, h * w, d), 6);
        let k = random((1, 2, h * w, d), 7);
        let v = random((1, 2, h * w, d), 8);
        let table_h = random((1, h, h, d), 9).squeeze(0)?;
        let table_w = random((1, w, w, d), 10).squeeze(0)?;
        let qv = q.flatten_all()?.to_vec1::<f32>()?;
        let th = table_h.flatten_all()?.to_vec1::<f32>()?;
        let tw = table_w.flatten_all()?.to_vec1::<f32>()?;
        let n = h * w;
        let mut bias = vec![0f32; 2 * n * n];
        for head in 0..2 {
            for (qi, (y, x)) in (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).enumerate() {
                let row = &qv[(head * n + qi) * d..(head * n + qi + 1) * d];
                for (ki, (ky, kx)) in (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).enumerate() {
                    let dot = |t: &[f32], a: usize, b: usize, size: usize| -> f32 {
                        let r = &t[(a * size + b) * d..(a * size + b + 1) * d];
                        row.iter().zip(r).map(|(p, q)| p * q).sum()
                    };
                    bias[(head * n + qi) * n + ki] = dot(&th, y, ky, h) + dot(&tw, x, kx, w);
                }
            }
        }
        let bias = Tensor::from_vec(bias, (2, n, n), &Device::Cpu)?;
        let expected = reference(&q, &k, &v, Some(&bias))?;
        let got = scaled_dot_product(
            &q,
            &k,
            &v,
            (d as f64).powf(-0.5),
            Scores::Relative {
                grid: (h, w),
                table_h: &table_h,
                table_w: &table_w,
            },
        )?;
        assert!(max_diff(&got, &expected) < 1e-5);
        Ok(())
    }

    #[test]
    fn the_blocked_product_is_the_plain_one_for_every_bias_layout() -> Result<()> {
        let (q, k, v) = (
            random((2, 3, 6, 4), 21),
            random((2, 3, 9, 4), 22),
            random((2, 3, 9, 4), 23),
        );
        let layouts: [&[usize]; 5] = [
            &[6, 9],
            &[3, 6, 9],
            &[2, 1, 6, 9],
            &[1, 3, 6, 9],
            &[2, 3, 6, 9],
        ];
        for (seed, dims) in (24..).zip(layouts) {
            let bias = random((1, 1, 1, dims.iter().product()), seed).reshape(dims)?;
            let scores = Scores::Bias(&bias);
            let plain = plain_scaled_dot_product(&q, &k, &v, 0.5, scores)?;
            let Some(blocked) = blocked_on_cpu(&q, &k, &v, 0.5, scores)? else {
                panic!("no blocked product for a bias of {dims:?}");
            };
            assert!(max_diff(&blocked, &plain) < 1e-6, "bias of {dims:?}");
        }
        // What does not broadcast as (batch, heads, queries, keys), another dtype, and a batch
        // of one against two go to the plain product.
        let sizes = Sizes {
            batch: 2,
            heads: 3,
            queries: 6,
            keys: 9,
            head_dim: 4,
        };
        for dims in [
            &[4, 6, 9][..],
            &[9, 6],
            &[3, 2, 6, 9],
            &[1, 1, 1, 6, 9],
            &[9],
        ] {
            assert_eq!(bias_strides(dims, sizes), None, "{dims:?}");
        }
        let half = q.to_dtype(candle_core::DType::F16)?;
        assert!(blocked_on_cpu(&half, &half, &half, 0.5, Scores::Plain)?.is_none());
        let one = q.narrow(0, 0, 1)?;
        assert!(blocked_on_cpu(&one, &k, &v, 0.5, Scores::Plain)?.is_none());
        Ok(())
    }

    #[test]
    fn a_batch_of_one_broadcasts_on_either_side() -> Result<()> {
        let q = random((3, 2, 5, 4), 11);
        let (k, v) = (random((1, 2, 7, 4), 12), random((1, 2, 7, 4), 13));
        let got = scaled_dot_product(&q, &k, &v, 0.5, Scores::Plain)?;
        for b in 0..3 {
            let expected = reference(&q.narrow(0, b, 1)?, &k, &v, None)?;
            assert!(max_diff(&got.narrow(0, b, 1)?, &expected) < 1e-6);
        }
        // And one query set against a batch of keys (the image attending to each prompt).
        let q = random((1, 2, 5, 4), 14);
        let (k, v) = (random((3, 2, 7, 4), 15), random((3, 2, 7, 4), 16));
        let got = scaled_dot_product(&q, &k, &v, 0.5, Scores::Plain)?;
        assert_eq!(got.dims(), &[3, 2, 5, 4]);
        for b in 0..3 {
            let expected = reference(&q, &k.narrow(0, b, 1)?, &v.narrow(0, b, 1)?, None)?;
            assert!(max_diff(&got.narrow(0, b, 1)?, &expected) < 1e-6);
        }
        Ok(())
    }
}
