//! MobileSAM's TinyViT image encoder (`tiny_vit_sam.py` of MobileSAM): a convolutional stem and
//! MBConv stage, then three stages of windowed attention with learned attention biases and
//! depthwise "local" convolutions, and SAM's neck down to 256 channels.
//!
//! Why it exists: MobileSAM's `mobile_sam.pt` loads into it under its original tensor names
//! (batch norms are folded at load time); see the [`layers`](super::layers) module for why
//! candle-transformers' copy is not used.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

use super::image::{EMBED_DIM, GRID};
use super::layers::{LayerNorm2d, apply_linear, conv2d_bn, gelu, layer_norm, linear};
use super::vit::{window_partition, window_unpartition};
use crate::attention::{Attention, Inputs, Scores};

/// The shape of a TinyViT encoder (four stages; the first is convolutional).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TinyVitConfig {
    /// Channels of each stage.
    pub embed_dims: [usize; 4],
    /// Blocks of each stage.
    pub depths: [usize; 4],
    /// Attention heads of each stage (the first stage has none).
    pub num_heads: [usize; 4],
    /// Attention window of each stage.
    pub window_sizes: [usize; 4],
}

impl TinyVitConfig {
    /// MobileSAM's encoder (TinyViT-5M at 1024 x 1024).
    pub fn mobile_sam() -> Self {
        Self {
            embed_dims: [64, 128, 160, 320],
            depths: [2, 2, 6, 2],
            num_heads: [2, 4, 5, 10],
            window_sizes: [7, 7, 14, 7],
        }
    }
}

const MLP_RATIO: usize = 4;
const MBCONV_EXPAND: usize = 4;
const OUT_CHANS: usize = EMBED_DIM;

fn conv_cfg(stride: usize, padding: usize, groups: usize) -> Conv2dConfig {
    Conv2dConfig {
        stride,
        padding,
        groups,
        ..Default::default()
    }
}

#[derive(Debug)]
struct MbConv {
    conv1: Conv2d,
    conv2: Conv2d,
    conv3: Conv2d,
}

impl MbConv {
    fn new(vb: VarBuilder, dim: usize) -> Result<Self> {
        let hidden = dim * MBCONV_EXPAND;
        Ok(Self {
            conv1: conv2d_bn(vb.pp("conv1"), dim, hidden, 1, conv_cfg(1, 0, 1))?,
            conv2: conv2d_bn(vb.pp("conv2"), hidden, hidden, 3, conv_cfg(1, 1, hidden))?,
            conv3: conv2d_bn(vb.pp("conv3"), hidden, dim, 1, conv_cfg(1, 0, 1))?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let x = gelu(&self.conv1.forward(xs)?)?;
        let x = gelu(&self.conv2.forward(&x)?)?;
        let x = self.conv3.forward(&x)?;
        gelu(&(x + xs)?)
    }
}

/// Downsampling between stages; MobileSAM keeps the resolution (stride 1) when the output width
/// is 320, 448 or 576, so that the last stage runs at 64 x 64.
#[derive(Debug)]
struct PatchMerging {
    conv1: Conv2d,
    conv2: Conv2d,
    conv3: Conv2d,
}

impl PatchMerging {
    fn new(vb: VarBuilder, dim: usize, out_dim: usize) -> Result<Self> {
        let stride = if matches!(out_dim, 320 | 448 | 576) {
            1
        } else {
            2
        };
        Ok(Self {
            conv1: conv2d_bn(vb.pp("conv1"), dim, out_dim, 1, conv_cfg(1, 0, 1))?,
            conv2: conv2d_bn(
                vb.pp("conv2"),
                out_dim,
                out_dim,
                3,
                conv_cfg(stride, 1, out_dim),
            )?,
            conv3: conv2d_bn(vb.pp("conv3"), out_dim, out_dim, 1, conv_cfg(1, 0, 1))?,
        })
    }

    /// `(B, C, H, W)` to `(B, L, C')` tokens.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let x = gelu(&self.conv1.forward(xs)?)?;
        let x = gelu(&self.conv2.forward(&x)?)?;
        let x = self.conv3.forward(&x)?;
        x.flatten_from(2)?.transpose(1, 2)
    }
}

/// TinyViT's attention module: a norm, then the shared attention (per head `[q k v]` channels)
/// with a learned per-head bias of the offsets within a window.
#[derive(Debug)]
struct WindowAttention {
    norm: LayerNorm,
    attention: Attention<Linear>,
    /// `(heads, N, N)` attention biases, gathered from the learned table.
    bias: Tensor,
}

/// The reference's attention bias index: offsets `(|dy|, |dx|)` numbered in order of first
/// appearance over all point pairs of a `res x res` window.
fn attention_bias_index(res: usize) -> (Vec<u32>, usize) {
    let points: Vec<(usize, usize)> = (0..res)
        .flat_map(|y| (0..res).map(move |x| (y, x)))
        .collect();
    let mut seen: std::collections::HashMap<(usize, usize), u32> = std::collections::HashMap::new();
    let mut idx = Vec::with_capacity(points.len() * points.len());
    for p1 in &points {
        for p2 in &points {
            let off = (p1.0.abs_diff(p2.0), p1.1.abs_diff(p2.1));
            let next = seen.len() as u32;
            idx.push(*seen.entry(off).or_insert(next));
        }
    }
    (idx, seen.len())
}

impl WindowAttention {
    fn new(vb: VarBuilder, dim: usize, num_heads: usize, window: usize) -> Result<Self> {
        let n = window * window;
        let (idx, offsets) = attention_bias_index(window);
        let table = vb.get((num_heads, offsets), "attention_biases")?;
        let idx = Tensor::from_vec(idx, n * n, table.device())?;
        let bias = table.index_select(&idx, 1)?.reshape((num_heads, n, n))?;
        Ok(Self {
            norm: layer_norm(vb.pp("norm"), dim, 1e-5)?,
            attention: Attention::new(
                Inputs::FusedPerHead(linear(vb.pp("qkv"), dim, 3 * dim)?),
                linear(vb.pp("proj"), dim, dim)?,
                num_heads,
            ),
            bias,
        })
    }

    /// `(B, N, C)` tokens of windows of `N` pixels.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.attention
            .forward(&self.norm.forward(xs)?, None, Scores::Bias(&self.bias))
    }
}

#[derive(Debug)]
struct TinyVitBlock {
    attn: WindowAttention,
    mlp_norm: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    local_conv: Conv2d,
    window: usize,
    res: usize,
}

impl TinyVitBlock {
    fn new(vb: VarBuilder, dim: usize, heads: usize, window: usize, res: usize) -> Result<Self> {
        let mlp = vb.pp("mlp");
        Ok(Self {
            attn: WindowAttention::new(vb.pp("attn"), dim, heads, window)?,
            mlp_norm: layer_norm(mlp.pp("norm"), dim, 1e-5)?,
            fc1: linear(mlp.pp("fc1"), dim, dim * MLP_RATIO)?,
            fc2: linear(mlp.pp("fc2"), dim * MLP_RATIO, dim)?,
            local_conv: conv2d_bn(vb.pp("local_conv"), dim, dim, 3, conv_cfg(1, 1, dim))?,
            window,
            res,
        })
    }

    /// `(B, L, C)` tokens of a `res x res` map.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, l, c) = xs.dims3()?;
        let (h, w, win) = (self.res, self.res, self.window);
        let x = if h == win && w == win {
            self.attn.forward(xs)?
        } else {
            // Zero padding before the attention's norm, as the reference pads.
            let (windows, hp, wp) = window_partition(&xs.reshape((b, h, w, c))?, win)?;
            let nw = windows.dim(0)?;
            let out = self
                .attn
                .forward(&windows.reshape((nw, win * win, c))?)?
                .reshape((nw, win, win, c))?;
            window_unpartition(&out, win, (b, hp, wp, c))?
                .narrow(1, 0, h)?
                .narrow(2, 0, w)?
                .reshape((b, l, c))?
        };
        let x = (xs + x)?;
        let x = x.transpose(1, 2)?.reshape((b, c, h, w))?;
        let x = self
            .local_conv
            .forward(&x)?
            .reshape((b, c, l))?
            .transpose(1, 2)?;
        let mlp = apply_linear(
            &self.fc2,
            &gelu(&apply_linear(&self.fc1, &self.mlp_norm.forward(&x)?)?)?,
        )?;
        x + mlp
    }
}

/// MobileSAM's TinyViT image encoder; see the [module documentation](self).
#[derive(Debug)]
pub struct TinyVit {
    stem1: Conv2d,
    stem2: Conv2d,
    conv_blocks: Vec<MbConv>,
    merges: Vec<PatchMerging>,
    /// Blocks of stages 1-3 with their stage's resolution.
    stages: Vec<Vec<TinyVitBlock>>,
    stage_res: Vec<usize>,
    neck_conv1: Conv2d,
    neck_ln1: LayerNorm2d,
    neck_conv2: Conv2d,
    neck_ln2: LayerNorm2d,
}

impl TinyVit {
    /// Loads the encoder from `vb` (the checkpoint's `image_encoder.` prefix). The classifier
    /// head of TinyViT (`norm_head`, `head`), unused by SAM, is not read.
    pub fn new(vb: VarBuilder, cfg: &TinyVitConfig) -> Result<Self> {
        let e = cfg.embed_dims;
        let seq = vb.pp("patch_embed").pp("seq");
        let stem1 = conv2d_bn(seq.pp("0"), 3, e[0] / 2, 3, conv_cfg(2, 1, 1))?;
        let stem2 = conv2d_bn(seq.pp("2"), e[0] / 2, e[0], 3, conv_cfg(2, 1, 1))?;
        let layers = vb.pp("layers");
        let conv_blocks = (0..cfg.depths[0])
            .map(|i| MbConv::new(layers.pp("0").pp("blocks").pp(i), e[0]))
            .collect::<Result<Vec<_>>>()?;
        let merges = e
            .windows(2)
            .enumerate()
            .map(|(i, pair)| PatchMerging::new(layers.pp(i).pp("downsample"), pair[0], pair[1]))
            .collect::<Result<Vec<_>>>()?;
        // The reference's stage resolutions: 256 / 2^i, except that the last stage repeats the
        // third's (its downsampling keeps the size).
        let patches = 1024 / 4;
        let mut stages = Vec::with_capacity(3);
        let mut stage_res = Vec::with_capacity(3);
        let per_stage = e
            .iter()
            .zip(&cfg.depths)
            .zip(&cfg.num_heads)
            .zip(&cfg.window_sizes)
            .enumerate()
            .skip(1);
        for (i, (((&dim, &depth), &heads), &window)) in per_stage {
            let exp = if i == 3 { i - 1 } else { i };
            let res = patches >> exp;
            let blocks = (0..depth)
                .map(|j| {
                    TinyVitBlock::new(layers.pp(i).pp("blocks").pp(j), dim, heads, window, res)
                })
                .collect::<Result<Vec<_>>>()?;
            stages.push(blocks);
            stage_res.push(res);
        }
        let neck = vb.pp("neck");
        Ok(Self {
            stem1,
            stem2,
            conv_blocks,
            merges,
            stages,
            stage_res,
            neck_conv1: candle_nn::conv2d_no_bias(
                e[3],
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
                conv_cfg(1, 1, 1),
                neck.pp("2"),
            )?,
            neck_ln2: LayerNorm2d::new(neck.pp("3"), OUT_CHANS, 1e-6)?,
        })
    }
}

impl Module for TinyVit {
    /// `(1, 3, 1024, 1024)` normalised input to `(1, 256, 64, 64)` image embeddings.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let mut x = self.stem2.forward(&gelu(&self.stem1.forward(xs)?)?)?;
        for block in &self.conv_blocks {
            x = block.forward(&x)?;
        }
        // Stage 0's output is a map; later stages work on tokens.
        let mut tokens = match self.merges.first() {
            Some(m) => m.forward(&x)?,
            None => x.flatten_from(2)?.transpose(1, 2)?,
        };
        for (i, (blocks, &res)) in self.stages.iter().zip(&self.stage_res).enumerate() {
            for block in blocks {
                tokens = block.forward(&tokens)?;
            }
            if let Some(merge) = self.merges.get(i + 1) {
                let (b, _, c) = tokens.dims3()?;
                let map = tokens.transpose(1, 2)?.reshape((b, c, res, res))?;
                tokens = merge.forward(&map)?;
            }
        }
        let (b, _, c) = tokens.dims3()?;
        tokens
            .reshape((b, GRID, GRID, c))?
            .permute((0, 3, 1, 2))?
            .contiguous()?
            .apply(&self.neck_conv1)?
            .apply(&self.neck_ln1)?
            .apply(&self.neck_conv2)?
            .apply(&self.neck_ln2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attention_bias_index_numbers_offsets_in_first_appearance_order() {
        // 2 x 2 window: points (0,0) (0,1) (1,0) (1,1); offsets from (0,0): (0,0)=0, (0,1)=1,
        // (1,0)=2, (1,1)=3.
        let (idx, n) = attention_bias_index(2);
        assert_eq!(n, 4);
        assert_eq!(&idx[0..4], &[0, 1, 2, 3]);
        // From (0,1): (0,1) (0,0) (1,1) (1,0).
        assert_eq!(&idx[4..8], &[1, 0, 3, 2]);
        let (_, n7) = attention_bias_index(7);
        assert_eq!(n7, 49);
    }
}
