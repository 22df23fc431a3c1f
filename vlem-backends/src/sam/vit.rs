//! SAM's ViT image encoder (`ImageEncoderViT` of the reference: ViT-B, -L, -H): 16 x 16 patches,
//! absolute position embedding, blocks with windowed or global attention and decomposed relative
//! position terms, and a convolutional neck down to 256 channels.
//!
//! Why it exists: the ViT-B/L/H checkpoints load into it under their original tensor names; see
//! the [`layers`](super::layers) module for why candle-transformers' copy is not used.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

use super::image::{EMBED_DIM, GRID, INPUT_SIZE};
use super::layers::{LayerNorm2d, apply_linear, gelu, layer_norm, linear};
use crate::attention::{Attention, Inputs, Scores};
use crate::profile;

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
const _: () = assert!(INPUT_SIZE / PATCH == GRID);
const WINDOW: usize = 14;
const OUT_CHANS: usize = EMBED_DIM;

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

#[derive(Debug)]
struct Block {
    norm1: LayerNorm,
    attn: Attention<Linear>,
    /// The relative position tables `(size, size, head_dim)` of rows and of columns, for the
    /// `size × size` token grid (a window, or the whole grid) the block attends over.
    rel_pos: (Tensor, Tensor),
    norm2: LayerNorm,
    lin1: Linear,
    lin2: Linear,
    window: usize,
}

impl Block {
    fn new(vb: VarBuilder, dim: usize, num_heads: usize, window: usize) -> Result<Self> {
        let size = if window == 0 { GRID } else { window };
        let head_dim = dim / num_heads;
        let a = vb.pp("attn");
        let table = |name: &str| rel_pos_table(size, &a.get((2 * size - 1, head_dim), name)?);
        Ok(Self {
            norm1: layer_norm(vb.pp("norm1"), dim, 1e-6)?,
            attn: Attention::new(
                Inputs::Fused(linear(a.pp("qkv"), dim, dim * 3)?),
                linear(a.pp("proj"), dim, dim)?,
                num_heads,
            ),
            rel_pos: (table("rel_pos_h")?, table("rel_pos_w")?),
            norm2: layer_norm(vb.pp("norm2"), dim, 1e-6)?,
            lin1: linear(vb.pp("mlp").pp("lin1"), dim, dim * 4)?,
            lin2: linear(vb.pp("mlp").pp("lin2"), dim * 4, dim)?,
            window,
        })
    }

    /// Attention over `(B, H, W, C)` tokens, `H == W` the size the tables were built for.
    fn attend(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, h, w, c) = xs.dims4()?;
        let scores = Scores::Relative {
            grid: (h, w),
            table_h: &self.rel_pos.0,
            table_w: &self.rel_pos.1,
        };
        self.attn
            .forward(&xs.reshape((b, h * w, c))?, None, scores)?
            .reshape((b, h, w, c))
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let shortcut = xs;
        let device = xs.device();
        let x = profile::timed("norm", device, || self.norm1.forward(xs))?;
        let x = if self.window > 0 {
            let (b, h, w, c) = x.dims4()?;
            let (windows, hp, wp) = window_partition(&x, self.window)?;
            let out = self.attend(&windows)?;
            window_unpartition(&out, self.window, (b, hp, wp, c))?
                .narrow(1, 0, h)?
                .narrow(2, 0, w)?
        } else {
            self.attend(&x)?
        };
        let x = (shortcut + x)?;
        let normed = profile::timed("norm", device, || self.norm2.forward(&x))?;
        let mlp = profile::timed("mlp", device, || {
            apply_linear(&self.lin2, &gelu(&apply_linear(&self.lin1, &normed)?)?)
        })?;
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
