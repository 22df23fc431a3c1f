//! SAM's ViT image encoder (`ImageEncoderViT` of the reference: ViT-B, -L, -H): 16 x 16 patches,
//! absolute position embedding, blocks with windowed or global attention and decomposed relative
//! position terms, and a convolutional neck down to 256 channels.
//!
//! Why it exists: the ViT-B/L/H checkpoints load into it under their original tensor names; see
//! the [`layers`](super::layers) module for why candle-transformers' copy is not used.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

use super::layers::{LayerNorm2d, apply_linear, gelu, layer_norm, linear, softmax_last};

/// The shape of a SAM ViT image encoder.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VitConfig {
    /// Token width (768 for ViT-B).
    pub embed_dim: usize,
    /// Number of blocks (12 for ViT-B).
    pub depth: usize,
    /// Attention heads (12 for ViT-B).
    pub num_heads: usize,
    /// Blocks with global attention; the others attend within 14 x 14 windows.
    pub global_attn_indexes: Vec<usize>,
}

impl VitConfig {
    /// SAM ViT-B.
    pub fn vit_b() -> Self {
        Self {
            embed_dim: 768,
            depth: 12,
            num_heads: 12,
            global_attn_indexes: vec![2, 5, 8, 11],
        }
    }

    /// SAM ViT-L.
    pub fn vit_l() -> Self {
        Self {
            embed_dim: 1024,
            depth: 24,
            num_heads: 16,
            global_attn_indexes: vec![5, 11, 17, 23],
        }
    }

    /// SAM ViT-H.
    pub fn vit_h() -> Self {
        Self {
            embed_dim: 1280,
            depth: 32,
            num_heads: 16,
            global_attn_indexes: vec![7, 15, 23, 31],
        }
    }
}

const PATCH: usize = 16;
const GRID: usize = 1024 / PATCH;
const WINDOW: usize = 14;
const OUT_CHANS: usize = 256;
/// Attention scores computed at once at most (floats), to bound the memory of global attention.
const MAX_SCORES: usize = 1 << 25;

#[derive(Debug)]
struct Attention {
    qkv: Linear,
    proj: Linear,
    num_heads: usize,
    scale: f64,
    rel_pos_h: Tensor,
    rel_pos_w: Tensor,
}

/// The relative position table for query and key lengths `size`: `(size, size, head_dim)` rows
/// `q - k + size - 1` of `rel_pos` (the reference's `get_rel_pos` for equal sizes, where no
/// interpolation is needed).
fn rel_pos_table(size: usize, rel_pos: &Tensor) -> Result<Tensor> {
    let idx: Vec<u32> = (0..size)
        .flat_map(|q| (0..size).map(move |k| (q + size - 1 - k) as u32))
        .collect();
    let idx = Tensor::from_vec(idx, size * size, rel_pos.device())?;
    rel_pos.index_select(&idx, 0)?.reshape((size, size, ()))
}

impl Attention {
    fn new(vb: VarBuilder, dim: usize, num_heads: usize, size: usize) -> Result<Self> {
        let head_dim = dim / num_heads;
        Ok(Self {
            qkv: linear(vb.pp("qkv"), dim, dim * 3)?,
            proj: linear(vb.pp("proj"), dim, dim)?,
            num_heads,
            scale: 1.0 / (head_dim as f64).sqrt(),
            rel_pos_h: rel_pos_table(size, &vb.get((2 * size - 1, head_dim), "rel_pos_h")?)?,
            rel_pos_w: rel_pos_table(size, &vb.get((2 * size - 1, head_dim), "rel_pos_w")?)?,
        })
    }

    /// `xs`: `(B, H, W, C)` with `H == W` the size the tables were built for.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, h, w, c) = xs.dims4()?;
        let hd = c / self.num_heads;
        let bh = b * self.num_heads;
        let n = h * w;
        let qkv = apply_linear(&self.qkv, xs)?
            .reshape((b, n, 3, self.num_heads, hd))?
            .permute((2, 0, 3, 1, 4))?
            .reshape((3, bh, n, hd))?;
        let q = qkv.get(0)?.contiguous()?;
        let k = qkv.get(1)?.contiguous()?;
        let v = qkv.get(2)?.contiguous()?;

        // rel_h[b, y, x, ky] = q[b, y, x, :] . Rh[y, ky, :], rel_w likewise along x.
        let r_q = q.reshape((bh, h, w, hd))?;
        let rel_h = r_q
            .permute((1, 0, 2, 3))?
            .reshape((h, bh * w, hd))?
            .contiguous()?
            .matmul(&self.rel_pos_h.transpose(1, 2)?.contiguous()?)?
            .reshape((h, bh, w, h))?
            .permute((1, 0, 2, 3))?;
        let rel_w = r_q
            .permute((2, 0, 1, 3))?
            .reshape((w, bh * h, hd))?
            .contiguous()?
            .matmul(&self.rel_pos_w.transpose(1, 2)?.contiguous()?)?
            .reshape((w, bh, h, w))?
            .permute((1, 2, 0, 3))?;
        let rel_h = rel_h.contiguous()?;
        let rel_w = rel_w.contiguous()?;

        // Chunks over (batch x head) bound the score memory of global attention.
        let chunk = (MAX_SCORES / (n * n)).max(1);
        let mut outs = Vec::with_capacity(bh.div_ceil(chunk));
        let mut start = 0;
        while start < bh {
            let len = chunk.min(bh - start);
            // attn[(y, x), (ky, kx)] += rel_h[y, x, ky] + rel_w[y, x, kx].
            let rel = rel_h
                .narrow(0, start, len)?
                .unsqueeze(4)?
                .broadcast_add(&rel_w.narrow(0, start, len)?.unsqueeze(3)?)?
                .reshape((len, n, n))?;
            let scores = (q.narrow(0, start, len)? * self.scale)?
                .matmul(&k.narrow(0, start, len)?.t()?)?
                .add(&rel)?;
            outs.push(softmax_last(&scores)?.matmul(&v.narrow(0, start, len)?)?);
            start += len;
        }
        let out = Tensor::cat(&outs, 0)?
            .reshape((b, self.num_heads, h, w, hd))?
            .permute((0, 2, 3, 1, 4))?
            .reshape((b, h, w, c))?;
        apply_linear(&self.proj, &out)
    }
}

#[derive(Debug)]
struct Block {
    norm1: LayerNorm,
    attn: Attention,
    norm2: LayerNorm,
    lin1: Linear,
    lin2: Linear,
    window: usize,
}

impl Block {
    fn new(vb: VarBuilder, dim: usize, num_heads: usize, window: usize) -> Result<Self> {
        let size = if window == 0 { GRID } else { window };
        Ok(Self {
            norm1: layer_norm(vb.pp("norm1"), dim, 1e-6)?,
            attn: Attention::new(vb.pp("attn"), dim, num_heads, size)?,
            norm2: layer_norm(vb.pp("norm2"), dim, 1e-6)?,
            lin1: linear(vb.pp("mlp").pp("lin1"), dim, dim * 4)?,
            lin2: linear(vb.pp("mlp").pp("lin2"), dim * 4, dim)?,
            window,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let shortcut = xs;
        let x = self.norm1.forward(xs)?;
        let x = if self.window > 0 {
            let (b, h, w, c) = x.dims4()?;
            let (windows, hp, wp) = window_partition(&x, self.window)?;
            let out = self.attn.forward(&windows)?;
            window_unpartition(&out, self.window, (b, hp, wp, c))?
                .narrow(1, 0, h)?
                .narrow(2, 0, w)?
        } else {
            self.attn.forward(&x)?
        };
        let x = (shortcut + x)?;
        let mlp = apply_linear(
            &self.lin2,
            &gelu(&apply_linear(&self.lin1, &self.norm2.forward(&x)?)?)?,
        )?;
        x + mlp
    }
}

/// Pads `(B, H, W, C)` with zeros to multiples of `win` and splits it into `(B * nH * nW, win,
/// win, C)` windows (the reference pads after `norm1`, so the padding is zero tokens).
pub(crate) fn window_partition(xs: &Tensor, win: usize) -> Result<(Tensor, usize, usize)> {
    let (b, h, w, c) = xs.dims4()?;
    let (pad_h, pad_w) = ((win - h % win) % win, (win - w % win) % win);
    let xs = xs
        .pad_with_zeros(1, 0, pad_h)?
        .pad_with_zeros(2, 0, pad_w)?;
    let (hp, wp) = (h + pad_h, w + pad_w);
    let windows = xs
        .reshape((b, hp / win, win, wp / win, win, c))?
        .permute((0, 1, 3, 2, 4, 5))?
        .reshape((b * (hp / win) * (wp / win), win, win, c))?;
    Ok((windows, hp, wp))
}

/// The inverse of [`window_partition`], still padded: `(B, Hp, Wp, C)`.
pub(crate) fn window_unpartition(
    windows: &Tensor,
    win: usize,
    (b, hp, wp, c): (usize, usize, usize, usize),
) -> Result<Tensor> {
    windows
        .reshape((b, hp / win, wp / win, win, win, c))?
        .permute((0, 1, 3, 2, 4, 5))?
        .reshape((b, hp, wp, c))
}

/// SAM's ViT image encoder; see the [module documentation](self).
#[derive(Debug)]
pub struct ImageEncoderVit {
    patch_embed: Conv2d,
    pos_embed: Tensor,
    blocks: Vec<Block>,
    neck_conv1: Conv2d,
    neck_ln1: LayerNorm2d,
    neck_conv2: Conv2d,
    neck_ln2: LayerNorm2d,
}

impl ImageEncoderVit {
    /// Loads the encoder from `vb` (the checkpoint's `image_encoder.` prefix).
    pub fn new(vb: VarBuilder, cfg: &VitConfig) -> Result<Self> {
        let dim = cfg.embed_dim;
        let patch_embed = candle_nn::conv2d(
            3,
            dim,
            PATCH,
            Conv2dConfig {
                stride: PATCH,
                ..Default::default()
            },
            vb.pp("patch_embed").pp("proj"),
        )?;
        let pos_embed = vb.get((1, GRID, GRID, dim), "pos_embed")?;
        let blocks = (0..cfg.depth)
            .map(|i| {
                let window = if cfg.global_attn_indexes.contains(&i) {
                    0
                } else {
                    WINDOW
                };
                Block::new(vb.pp("blocks").pp(i), dim, cfg.num_heads, window)
            })
            .collect::<Result<Vec<_>>>()?;
        let neck = vb.pp("neck");
        Ok(Self {
            patch_embed,
            pos_embed,
            blocks,
            neck_conv1: candle_nn::conv2d_no_bias(
                dim,
                OUT_CHANS,
                1,
                Default::default(),
                neck.pp("0"),
            )?,
            neck_ln1: LayerNorm2d::new(neck.pp("1"), OUT_CHANS, 1e-6)?,
            neck_conv2: candle_nn::conv2d_no_bias(
                OUT_CHANS,
                OUT_CHANS,
                3,
                Conv2dConfig {
                    padding: 1,
                    ..Default::default()
                },
                neck.pp("2"),
            )?,
            neck_ln2: LayerNorm2d::new(neck.pp("3"), OUT_CHANS, 1e-6)?,
        })
    }
}

impl Module for ImageEncoderVit {
    /// `(1, 3, 1024, 1024)` normalised input to `(1, 256, 64, 64)` image embeddings.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let mut x = self
            .patch_embed
            .forward(xs)?
            .permute((0, 2, 3, 1))?
            .broadcast_add(&self.pos_embed)?;
        for block in &self.blocks {
            x = block.forward(&x)?;
        }
        x.permute((0, 3, 1, 2))?
            .contiguous()?
            .apply(&self.neck_conv1)?
            .apply(&self.neck_ln1)?
            .apply(&self.neck_conv2)?
            .apply(&self.neck_ln2)
    }
}
