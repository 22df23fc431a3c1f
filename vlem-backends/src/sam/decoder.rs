//! SAM's prompt encoder (point prompts) and mask decoder (two-way transformer, upscaling,
//! hypernetwork heads, IoU head), shared by every SAM variant.
//!
//! Why it exists: the automatic mask generator runs the decoder once per grid point, so this is
//! where most of the proposer's time goes on a CPU. It follows the reference module by module
//! (same tensor names), with one change of evaluation order that does not change the result:
//! the first transformer layer's image-side projections are computed once and broadcast over the
//! batch of prompts, since every prompt sees the same image embedding there. On the CPU the later
//! cross attentions' image side, the output upscaling and the hypernetwork product run fused, per
//! prompt (modules `image_side`, `mask_head`: same arithmetic, reassociated, so equal
//! within rounding); elsewhere every step is a candle op.

use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{LayerNorm, Linear, VarBuilder};

use super::image::{EMBED_DIM, GRID, INPUT_SIZE};
use super::image_side::{self, ImageToToken, TokenToImage};
use super::layers::{LayerNorm2d, apply_linear, cat_last, gelu, layer_norm, linear};
use super::mask_head::FusedMaskHead;
use crate::attention::{Attention, Inputs, Scores};

const NUM_MASK_TOKENS: usize = 4;
const HEADS: usize = 8;
const MLP_DIM: usize = 2048;

/// The prompt encoder, point prompts only (no boxes, no mask input).
#[derive(Debug)]
pub struct PromptEncoder {
    /// The random Fourier matrix, in f32 whatever the model's type: the features are sines of
    /// 2π times products of up to ~10, which half precision would shift by a good part of a
    /// period. They are converted to the model's type once made.
    gaussian: Tensor,
    point_embeddings: Vec<Tensor>,
    not_a_point: Tensor,
    no_mask: Tensor,
}

impl PromptEncoder {
    /// Loads from `vb` (the checkpoint's `prompt_encoder.` prefix); the mask-downscaling
    /// convolutions and the box-corner embeddings are not needed for point prompts.
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let point_embeddings = (0..2)
            .map(|i| {
                vb.pp("point_embeddings")
                    .pp(i)
                    .get((1, EMBED_DIM), "weight")
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            gaussian: vb
                .pp("pe_layer")
                .get((2, EMBED_DIM / 2), "positional_encoding_gaussian_matrix")?
                .to_dtype(DType::F32)?,
            point_embeddings,
            not_a_point: vb.pp("not_a_point_embed").get((1, EMBED_DIM), "weight")?,
            no_mask: vb.pp("no_mask_embed").get((1, EMBED_DIM), "weight")?,
        })
    }

    /// Random Fourier features of f32 coordinates in `[0, 1]` (last dimension 2), computed in
    /// f32 and given in the model's type.
    fn pe_encoding(&self, coords: &Tensor) -> Result<Tensor> {
        let c = coords.affine(2.0, -1.0)?.broadcast_matmul(&self.gaussian)?;
        let c = (c * (2.0 * std::f64::consts::PI))?;
        cat_last(&[&c.sin()?, &c.cos()?])?.to_dtype(self.no_mask.dtype())
    }

    /// The positional encoding of the embedding grid, `(1, 256, 64, 64)`.
    pub fn dense_pe(&self) -> Result<Tensor> {
        let dev = self.gaussian.device();
        let mut coords = Vec::with_capacity(GRID * GRID * 2);
        for y in 0..GRID {
            for x in 0..GRID {
                coords.push((x as f32 + 0.5) / GRID as f32);
                coords.push((y as f32 + 0.5) / GRID as f32);
            }
        }
        let coords = Tensor::from_vec(coords, (GRID, GRID, 2), dev)?;
        self.pe_encoding(&coords)?
            .permute((2, 0, 1))?
            .unsqueeze(0)?
            .contiguous()
    }

    /// Sparse embeddings `(B, 2, 256)` of one foreground point per prompt, `points` in input
    /// (1024-scale) pixel coordinates: the point, then the padding point the reference adds when
    /// no box is given.
    pub fn embed_points(&self, points: &[[f32; 2]]) -> Result<Tensor> {
        let dev = self.gaussian.device();
        let b = points.len();
        let coords: Vec<f32> = points
            .iter()
            .flat_map(|p| {
                [
                    (p[0] + 0.5) / INPUT_SIZE as f32,
                    (p[1] + 0.5) / INPUT_SIZE as f32,
                ]
            })
            .collect();
        let coords = Tensor::from_vec(coords, (b, 1, 2), dev)?;
        let point = self
            .pe_encoding(&coords)?
            .broadcast_add(&self.point_embeddings[1])?;
        let pad = self
            .not_a_point
            .unsqueeze(0)?
            .broadcast_as((b, 1, EMBED_DIM))?;
        Tensor::cat(&[&point, &pad], 1)
    }

    /// The dense embedding without a mask prompt, `(1, 256, 1, 1)` (broadcast over the grid).
    pub fn no_mask_dense(&self) -> Result<Tensor> {
        self.no_mask.reshape((1, EMBED_DIM, 1, 1))
    }
}

/// The decoder's attention: the shared layer with separate query, key and value inputs, its
/// internal width the token width over `downsample`.
fn decoder_attention(vb: VarBuilder, dim: usize, downsample: usize) -> Result<Attention<Linear>> {
    let internal = dim / downsample;
    Ok(Attention::new(
        Inputs::Separate {
            q: linear(vb.pp("q_proj"), dim, internal)?,
            k: linear(vb.pp("k_proj"), dim, internal)?,
            v: linear(vb.pp("v_proj"), dim, internal)?,
        },
        linear(vb.pp("out_proj"), internal, dim)?,
        HEADS,
    ))
}

/// One of a decoder attention's input projections: 0 the query's, 1 the key's, 2 the value's.
fn projection(attention: &Attention<Linear>, which: usize) -> Result<&Linear> {
    attention
        .separate_inputs()
        .and_then(|p| p.get(which).copied())
        .ok_or_else(|| {
            candle_core::Error::Msg("the decoder's attention has separate inputs".into())
        })
}

#[derive(Debug)]
struct TwoWayBlock {
    self_attn: Attention<Linear>,
    norm1: LayerNorm,
    cross_t2i: Attention<Linear>,
    norm2: LayerNorm,
    lin1: Linear,
    lin2: Linear,
    norm3: LayerNorm,
    norm4: LayerNorm,
    cross_i2t: Attention<Linear>,
    skip_first_pe: bool,
}

impl TwoWayBlock {
    fn new(vb: VarBuilder, skip_first_pe: bool) -> Result<Self> {
        let d = EMBED_DIM;
        Ok(Self {
            self_attn: decoder_attention(vb.pp("self_attn"), d, 1)?,
            norm1: layer_norm(vb.pp("norm1"), d, 1e-5)?,
            cross_t2i: decoder_attention(vb.pp("cross_attn_token_to_image"), d, 2)?,
            norm2: layer_norm(vb.pp("norm2"), d, 1e-5)?,
            lin1: linear(vb.pp("mlp").pp("lin1"), d, MLP_DIM)?,
            lin2: linear(vb.pp("mlp").pp("lin2"), MLP_DIM, d)?,
            norm3: layer_norm(vb.pp("norm3"), d, 1e-5)?,
            norm4: layer_norm(vb.pp("norm4"), d, 1e-5)?,
            cross_i2t: decoder_attention(vb.pp("cross_attn_image_to_token"), d, 2)?,
            skip_first_pe,
        })
    }

    /// The tokens' self-attention (with its residual unless first) and its norm.
    fn attend_self(&self, queries: &Tensor, query_pe: &Tensor) -> Result<Tensor> {
        let queries = if self.skip_first_pe {
            self.self_attn
                .forward_qkv(queries, queries, queries, Scores::Plain)?
        } else {
            let q = (queries + query_pe)?;
            (queries + self.self_attn.forward_qkv(&q, &q, queries, Scores::Plain)?)?
        };
        self.norm1.forward(&queries)
    }

    /// The token-to-image attention's residual and norm, then the tokens' MLP and its norm.
    fn after_token_to_image(&self, queries: &Tensor, attn: &Tensor) -> Result<Tensor> {
        let queries = self.norm2.forward(&(queries + attn)?)?;
        let mlp = apply_linear(&self.lin2, &apply_linear(&self.lin1, &queries)?.relu()?)?;
        self.norm3.forward(&(queries + mlp)?)
    }

    fn forward(
        &self,
        queries: &Tensor,
        keys: &Tensor,
        query_pe: &Tensor,
        key_pe: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let queries = self.attend_self(queries, query_pe)?;
        let q = (&queries + query_pe)?;
        let k = keys.broadcast_add(key_pe)?;
        let attn = self.cross_t2i.forward_qkv(&q, &k, keys, Scores::Plain)?;
        let queries = self.after_token_to_image(&queries, &attn)?;

        let q = (&queries + query_pe)?;
        let attn = self
            .cross_i2t
            .forward_qkv(&k, &q, &queries, Scores::Plain)?;
        let keys = self.norm4.forward(&keys.broadcast_add(&attn)?)?;
        Ok((queries, keys))
    }
}

#[derive(Debug)]
struct Mlp {
    layers: Vec<Linear>,
}

impl Mlp {
    fn new(vb: VarBuilder, input: usize, hidden: usize, output: usize, n: usize) -> Result<Self> {
        let layers = (0..n)
            .map(|i| {
                let i_dim = if i == 0 { input } else { hidden };
                let o_dim = if i + 1 == n { output } else { hidden };
                linear(vb.pp("layers").pp(i), i_dim, o_dim)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { layers })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let mut x = xs.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            x = apply_linear(layer, &x)?;
            if i + 1 < self.layers.len() {
                x = x.relu()?;
            }
        }
        Ok(x)
    }
}

/// SAM's mask decoder; see the [module documentation](self).
#[derive(Debug)]
pub struct MaskDecoder {
    output_tokens: Tensor,
    layers: Vec<TwoWayBlock>,
    final_t2i: Attention<Linear>,
    norm_final: LayerNorm,
    up1: UpConv2x2,
    up_ln: LayerNorm2d,
    up2: UpConv2x2,
    hypernets: Vec<Mlp>,
    iou_head: Mlp,
    /// The fused image side, on the CPU only.
    fused: Option<Fused>,
}

/// The CPU path's fused pieces ([`super::image_side`], [`super::mask_head`]).
#[derive(Debug)]
struct Fused {
    /// The token-to-image attentions of the layers after the first (the first sees one image
    /// for all prompts and stays a candle op), then the final one.
    token_to_image: Vec<TokenToImage>,
    /// Each layer's image-to-token attention and norm.
    image_to_token: Vec<ImageToToken>,
    head: FusedMaskHead,
}

impl MaskDecoder {
    /// Loads from `vb` (the checkpoint's `mask_decoder.` prefix).
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let d = EMBED_DIM;
        let iou_token = vb.pp("iou_token").get((1, d), "weight")?;
        let mask_tokens = vb.pp("mask_tokens").get((NUM_MASK_TOKENS, d), "weight")?;
        let t = vb.pp("transformer");
        let layers = (0..2)
            .map(|i| TwoWayBlock::new(t.pp("layers").pp(i), i == 0))
            .collect::<Result<Vec<_>>>()?;
        let up = vb.pp("output_upscaling");
        // The fused image side reads and writes f32 host buffers: the CPU in f32 only.
        let head = if vb.device().is_cpu() && vb.dtype() == DType::F32 {
            let (up1, norm, up2) = (up.pp("0"), up.pp("1"), up.pp("3"));
            Some(FusedMaskHead::new(
                (
                    &up1.get((d, d / 4, 2, 2), "weight")?,
                    &up1.get(d / 4, "bias")?,
                ),
                (&norm.get(d / 4, "weight")?, &norm.get(d / 4, "bias")?, 1e-6),
                (
                    &up2.get((d / 4, d / 8, 2, 2), "weight")?,
                    &up2.get(d / 8, "bias")?,
                ),
            )?)
        } else {
            None
        };
        let final_t2i = decoder_attention(t.pp("final_attn_token_to_image"), d, 2)?;
        let fused = match head {
            Some(head) => Some(Fused {
                token_to_image: layers
                    .iter()
                    .skip(1)
                    .map(|l| &l.cross_t2i)
                    .chain([&final_t2i])
                    .map(|a| TokenToImage::new(projection(a, 1)?, projection(a, 2)?))
                    .collect::<Result<Vec<_>>>()?,
                image_to_token: layers
                    .iter()
                    .map(|l| {
                        ImageToToken::new(projection(&l.cross_i2t, 0)?, l.cross_i2t.out(), &l.norm4)
                    })
                    .collect::<Result<Vec<_>>>()?,
                head,
            }),
            None => None,
        };
        Ok(Self {
            output_tokens: Tensor::cat(&[&iou_token, &mask_tokens], 0)?,
            layers,
            final_t2i,
            norm_final: layer_norm(t.pp("norm_final_attn"), d, 1e-5)?,
            up1: UpConv2x2::new(up.pp("0"), d, d / 4)?,
            up_ln: LayerNorm2d::new(up.pp("1"), d / 4, 1e-6)?,
            up2: UpConv2x2::new(up.pp("3"), d / 4, d / 8)?,
            hypernets: (0..NUM_MASK_TOKENS)
                .map(|i| Mlp::new(vb.pp("output_hypernetworks_mlps").pp(i), d, d, d / 8, 3))
                .collect::<Result<Vec<_>>>()?,
            iou_head: Mlp::new(vb.pp("iou_prediction_head"), d, 256, NUM_MASK_TOKENS, 3)?,
            fused,
        })
    }

    /// All four masks and IoU predictions of each prompt: `(B, 4, 256, 256)` logits and
    /// `(B, 4)`. `image` is `(1, 256, 64, 64)` image embeddings, `image_pe` the dense
    /// positional encoding, `dense` the no-mask embedding, `sparse` `(B, T, 256)` prompt tokens.
    pub fn forward(
        &self,
        image: &Tensor,
        image_pe: &Tensor,
        dense: &Tensor,
        sparse: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let tokens = self.tokens(sparse)?;
        // Every prompt has the same image embedding (plus the same no-mask embedding): keep a
        // batch of one until the first image update makes the keys differ.
        let src = image.broadcast_add(dense)?;
        let keys = src.flatten_from(2)?.transpose(1, 2)?.contiguous()?;
        let key_pe = image_pe.flatten_from(2)?.transpose(1, 2)?.contiguous()?;
        match &self.fused {
            Some(fused) => self.forward_fused(fused, &tokens, &keys, &key_pe),
            None => self.forward_with_ops(&tokens, &keys, &key_pe),
        }
    }

    /// The transformer and the heads as candle ops (any device): `tokens` `(B, T, 256)`, `keys`
    /// and `key_pe` `(1, 4096, 256)`.
    fn forward_with_ops(
        &self,
        tokens: &Tensor,
        keys: &Tensor,
        key_pe: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let mut queries = tokens.clone();
        let mut keys = keys.clone();
        for layer in &self.layers {
            (queries, keys) = layer.forward(&queries, &keys, tokens, key_pe)?;
        }
        let q = (&queries + tokens)?;
        let k = keys.broadcast_add(key_pe)?;
        let queries = self
            .norm_final
            .forward(&(&queries + self.final_t2i.forward_qkv(&q, &k, &keys, Scores::Plain)?)?)?;
        let (hyper, iou) = self.heads(&queries)?;
        Ok((self.upscale_with_ops(&keys, &hyper)?, iou))
    }

    /// [`Self::forward_with_ops`] with the image side fused on the CPU: the token side stays
    /// candle ops over the batch, each prompt's image tokens live in one buffer that the fused
    /// attentions read and update.
    fn forward_fused(
        &self,
        fused: &Fused,
        tokens: &Tensor,
        keys: &Tensor,
        key_pe: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let b = tokens.dim(0)?;
        let pe = key_pe.flatten_all()?.to_vec1::<f32>()?;
        let mut image = keys.flatten_all()?.to_vec1::<f32>()?.repeat(b);
        let mut queries = tokens.clone();
        for (l, (layer, image_to_token)) in
            self.layers.iter().zip(&fused.image_to_token).enumerate()
        {
            queries = layer.attend_self(&queries, tokens)?;
            let q = (&queries + tokens)?;
            // `token_to_image[l - 1]`: the first layer has none.
            let attn = match l.checked_sub(1).and_then(|i| fused.token_to_image.get(i)) {
                Some(t2i) => {
                    let q = apply_linear(projection(&layer.cross_t2i, 0)?, &q)?;
                    let out = image_side::token_to_image(t2i, &image, &pe, &q)?;
                    apply_linear(layer.cross_t2i.out(), &out)?
                }
                None => {
                    // The first layer: one image for every prompt.
                    let k = keys.broadcast_add(key_pe)?;
                    layer.cross_t2i.forward_qkv(&q, &k, keys, Scores::Plain)?
                }
            };
            queries = layer.after_token_to_image(&queries, &attn)?;
            let q = (&queries + tokens)?;
            let k = apply_linear(projection(&layer.cross_i2t, 1)?, &q)?;
            let v = apply_linear(projection(&layer.cross_i2t, 2)?, &queries)?;
            image_side::image_to_token(image_to_token, &mut image, &pe, &k, &v)?;
        }
        let final_t2i = fused
            .token_to_image
            .last()
            .ok_or_else(|| candle_core::Error::Msg("no final attention".to_owned()))?;
        let q = apply_linear(projection(&self.final_t2i, 0)?, &(&queries + tokens)?)?;
        let out = image_side::token_to_image(final_t2i, &image, &pe, &q)?;
        let attn = apply_linear(self.final_t2i.out(), &out)?;
        let queries = self.norm_final.forward(&(&queries + attn)?)?;
        let (hyper, iou) = self.heads(&queries)?;
        let masks = fused
            .head
            .masks(&image, &hyper.flatten_all()?.to_vec1::<f32>()?);
        let masks = Tensor::from_vec(
            masks,
            (b, NUM_MASK_TOKENS, GRID * 4, GRID * 4),
            tokens.device(),
        )?;
        Ok((masks, iou))
    }

    /// The decoder's output tokens (IoU, then the masks') followed by each prompt's sparse
    /// tokens: `(B, 5 + T, 256)`.
    fn tokens(&self, sparse: &Tensor) -> Result<Tensor> {
        let b = sparse.dim(0)?;
        Tensor::cat(
            &[
                &self
                    .output_tokens
                    .unsqueeze(0)?
                    .broadcast_as((b, NUM_MASK_TOKENS + 1, EMBED_DIM))?
                    .contiguous()?,
                sparse,
            ],
            1,
        )
    }

    /// The hypernetwork outputs `(B, 4, 32)` and the IoU predictions `(B, 4)` of the final
    /// tokens.
    fn heads(&self, queries: &Tensor) -> Result<(Tensor, Tensor)> {
        let iou_out = queries.narrow(1, 0, 1)?.squeeze(1)?;
        let mask_out = queries.narrow(1, 1, NUM_MASK_TOKENS)?;
        let hyper = self
            .hypernets
            .iter()
            .enumerate()
            .map(|(i, mlp)| mlp.forward(&mask_out.narrow(1, i, 1)?.squeeze(1)?))
            .collect::<Result<Vec<_>>>()?;
        Ok((Tensor::stack(&hyper, 1)?, self.iou_head.forward(&iou_out)?))
    }

    /// The mask logits `(B, 4, 256, 256)` of the final image tokens `(B or 1, 4096, 256)` and
    /// the hypernetwork outputs `(B, 4, 32)`, as candle ops (any device).
    fn upscale_with_ops(&self, keys: &Tensor, hyper: &Tensor) -> Result<Tensor> {
        let b = hyper.dim(0)?;
        let keys = keys.broadcast_as((b, GRID * GRID, EMBED_DIM))?;
        let src = keys.transpose(1, 2)?.reshape((b, EMBED_DIM, GRID, GRID))?;
        let up = gelu(&self.up_ln.forward(&self.up1.forward(&src)?)?)?;
        let up = gelu(&self.up2.forward(&up)?)?;
        let (_, c, h, w) = up.dims4()?;
        hyper
            .matmul(&up.reshape((b, c, h * w))?)?
            .reshape((b, NUM_MASK_TOKENS, h, w))
    }

    /// Both paths of [`Self::forward`], fused then candle ops, for the tests.
    #[cfg(test)]
    fn forward_both(
        &self,
        image: &Tensor,
        image_pe: &Tensor,
        dense: &Tensor,
        sparse: &Tensor,
    ) -> Result<[(Tensor, Tensor); 2]> {
        let fused = self
            .fused
            .as_ref()
            .ok_or_else(|| candle_core::Error::Msg("no fused path".to_owned()))?;
        let tokens = self.tokens(sparse)?;
        let keys = image
            .broadcast_add(dense)?
            .flatten_from(2)?
            .transpose(1, 2)?
            .contiguous()?;
        let key_pe = image_pe.flatten_from(2)?.transpose(1, 2)?.contiguous()?;
        Ok([
            self.forward_fused(fused, &tokens, &keys, &key_pe)?,
            self.forward_with_ops(&tokens, &keys, &key_pe)?,
        ])
    }
}

/// A transposed convolution with kernel 2 and stride 2 (`nn.ConvTranspose2d(c, o, 2, 2)`): the
/// output pixels of one input pixel do not overlap, so it is one matrix product per batch.
#[derive(Debug)]
struct UpConv2x2 {
    /// `(C, O * 4)`: the weight `(C, O, 2, 2)` flattened.
    weight: Tensor,
    /// `(O, 1, 1)`.
    bias: Tensor,
    out: usize,
}

impl UpConv2x2 {
    fn new(vb: VarBuilder, in_ch: usize, out_ch: usize) -> Result<Self> {
        Ok(Self {
            weight: vb
                .get((in_ch, out_ch, 2, 2), "weight")?
                .reshape((in_ch, out_ch * 4))?,
            bias: vb.get(out_ch, "bias")?.reshape((out_ch, 1, 1))?,
            out: out_ch,
        })
    }

    /// `(B, C, H, W)` to `(B, O, 2H, 2W)`.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let y = xs
            .reshape((b, c, h * w))?
            .transpose(1, 2)?
            .contiguous()?
            .broadcast_matmul(&self.weight)?;
        // (B, H, W, O, 2, 2) -> (B, O, H, 2, W, 2).
        y.reshape((b, h, w, self.out, 2, 2))?
            .permute((0, 3, 1, 4, 2, 5))?
            .reshape((b, self.out, 2 * h, 2 * w))?
            .broadcast_add(&self.bias)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::*;
    use crate::sam::synthetic::SyntheticWeights;

    /// Values in `[-1, 1)`, deterministic.
    fn spread(n: usize, seed: u64) -> Vec<f32> {
        (0..n as u64)
            .map(|i| {
                let z = crate::sam::amg::splitmix64_mix(i.wrapping_mul(31).wrapping_add(seed));
                (z >> 40) as f32 / 8_388_608.0 - 1.0
            })
            .collect()
    }

    fn max_abs(t: &Tensor) -> Result<f32> {
        t.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()
    }

    #[test]
    fn fused_upscaling_matches_the_candle_ops() -> Result<()> {
        let vb = SyntheticWeights::new().var_builder(&Device::Cpu);
        let decoder = MaskDecoder::new(vb.pp("mask_decoder"))?;
        let Some(fused) = &decoder.fused else {
            panic!("the CPU decoder has the fused path");
        };
        let b = 3;
        let keys = Tensor::from_vec(
            spread(b * GRID * GRID * EMBED_DIM, 1),
            (b, GRID * GRID, EMBED_DIM),
            &Device::Cpu,
        )?;
        let hyper = Tensor::from_vec(spread(b * 4 * 32, 2), (b, 4, 32), &Device::Cpu)?;
        let masks = fused.head.masks(
            &keys.flatten_all()?.to_vec1::<f32>()?,
            &hyper.flatten_all()?.to_vec1::<f32>()?,
        );
        let masks = Tensor::from_vec(masks, (b, 4, 256, 256), &Device::Cpu)?;
        let ops = decoder.upscale_with_ops(&keys, &hyper)?;
        assert!(max_abs(&ops)? > 0.1, "logits of a realistic size");
        let diff = max_abs(&(&masks - &ops)?)?;
        assert!(diff < 1e-4, "max difference {diff}");
        Ok(())
    }

    #[test]
    fn fused_decoder_matches_the_candle_ops() -> Result<()> {
        let vb = SyntheticWeights::new().var_builder(&Device::Cpu);
        let prompt = PromptEncoder::new(vb.pp("prompt_encoder"))?;
        let decoder = MaskDecoder::new(vb.pp("mask_decoder"))?;
        let image = Tensor::from_vec(
            spread(EMBED_DIM * GRID * GRID, 3),
            (1, EMBED_DIM, GRID, GRID),
            &Device::Cpu,
        )?;
        let points = [[100.0, 200.0], [512.5, 40.0], [1000.0, 900.0]];
        let sparse = prompt.embed_points(&points)?;
        let [(masks, iou), (masks_ops, iou_ops)] = decoder.forward_both(
            &image,
            &prompt.dense_pe()?,
            &prompt.no_mask_dense()?,
            &sparse,
        )?;
        assert_eq!(masks.dims(), &[3, 4, 256, 256]);
        assert!(max_abs(&masks_ops)? > 0.1, "logits of a realistic size");
        let diff = max_abs(&(&masks - &masks_ops)?)?;
        assert!(diff < 1e-4, "masks: max difference {diff}");
        let diff = max_abs(&(&iou - &iou_ops)?)?;
        assert!(diff < 1e-5, "IoU: max difference {diff}");
        Ok(())
    }
}
