//! The dino.txt vision head and text tower (Meta's `dinov3_vitl16_dinotxt_tet1280d20h24l`) on
//! candle, read from the released checkpoint file.
//!
//! Why it exists: dino.txt is what makes DINOv3 patch tokens comparable with text. Meta ships
//! it as one PyTorch file, `dinov3_vitl16_dinotxt_vision_head_and_text_encoder-*.pth` (a plain
//! state dict without the backbone), to be used on top of the ViT-L/16 backbone; there is no
//! Hugging Face port. This module owns reading that file ([`DinoTxtHeads::load_pth`]) and both
//! forward passes, as `dinov3/eval/text/` computes them (checked to 1e-4 against Meta's own code
//! on a tiny random model, `vlem-backends/goldens/dinov3/`):
//!
//! - vision head ([`DinoTxtHeads::vision`]): the backbone's normalised tokens `[CLS, registers,
//!   patches]` go through pre-norm blocks (fused qkv without bias, no RoPE, no mask, layer
//!   scales, SwiGLU MLP `w3(silu(w1 x) ⊙ w2 x)`) and a final layer norm. The image embedding is
//!   `[head CLS, mean of head patches]`; the per-patch embeddings are the head's patch tokens,
//!   which the reference pairs with the second half of the text embedding.
//! - text tower ([`DinoTxtHeads::text`]): token plus position embeddings, causal pre-norm blocks
//!   (fused qkv without bias, exact-GELU MLP, no layer scale), a final layer norm, a linear
//!   projection without bias, pooled at the end-of-text token (the largest id).
//!
//! Tokenising text is [`super::clip_bpe`]'s job; the encoder joins the parts ([`super::encoder`]).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{LayerNorm, Module};

use super::model::BackboneOutput;
use crate::ModelDtype;
use crate::error::BackendError;
use crate::vit::{Activation, Block, Linear, Mlp, Weights, fused_attention};

/// The checkpoint's name in messages.
pub const MODEL: &str = "dino.txt";

/// Channels per text attention head of the released text tower (1280 wide, 20 heads): the
/// checkpoint does not record the head count, so it is derived from the width with this.
pub const TEXT_HEAD_DIM: usize = 64;

/// What the vision head gives for a batch of images.
#[derive(Clone, Debug)]
pub struct VisionOutput {
    /// `(batch, 2·width)`: the head's CLS token, then the mean of its patch tokens; not
    /// normalised.
    pub image_embedding: Tensor,
    /// `(batch, grid_height, grid_width, width)`: the head's patch tokens; not normalised.
    pub patch_grid: Tensor,
}

/// The dino.txt text tower.
#[derive(Clone, Debug)]
struct TextTower {
    token_embedding: Tensor,
    positions: Tensor,
    blocks: Vec<Block>,
    norm: LayerNorm,
    projection: Linear,
}

/// The dino.txt vision head and text tower, ready to run. Thread-safe: every method takes `&self`.
#[derive(Clone, Debug)]
pub struct DinoTxtHeads {
    vision_blocks: Vec<Block>,
    vision_norm: LayerNorm,
    width: usize,
    text: TextTower,
    end_token: u32,
}

/// How many `{prefix}.{i}.{suffix}` tensors there are, counting from 0.
fn count_blocks(w: &Weights, prefix: &str, suffix: &str) -> usize {
    (0..)
        .take_while(|i| w.contains(&format!("{prefix}.{i}.{suffix}")))
        .count()
}

fn dims_of(w: &Weights, name: &str) -> Result<Vec<usize>, String> {
    w.dims(name)
        .ok_or_else(|| format!("tensor {name} is missing"))
}

impl DinoTxtHeads {
    /// Reads the released checkpoint (a `torch.save`d state dict, `.pth`) for a backbone with
    /// `vision_heads` attention heads (16 for ViT-L/16), onto `device` in `dtype`. The text
    /// tower's head count is its width over [`TEXT_HEAD_DIM`] unless `text_heads` says otherwise.
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] for a file that cannot be read as a PyTorch state dict
    /// or lacks or misshapes a tensor of the heads (the message names it).
    pub fn load_pth(
        path: &Path,
        vision_heads: usize,
        text_heads: Option<usize>,
        device: &Device,
        dtype: ModelDtype,
    ) -> Result<Self, BackendError> {
        let invalid = |reason: String| BackendError::InvalidModelFile {
            path: path.to_path_buf(),
            reason,
        };
        let tensors = candle_core::pickle::read_all(path)
            .map_err(|e| invalid(format!("cannot read it as a PyTorch state dict: {e}")))?;
        let tensors: HashMap<String, Tensor> = tensors.into_iter().collect();
        let weights = Weights::new(tensors, device, dtype.candle());
        Self::from_weights(&weights, vision_heads, text_heads).map_err(invalid)
    }

    /// The heads from tensors named as in the released checkpoint, on `device` in `dtype`, for
    /// benchmarks that fill the full-size architecture with random weights.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] naming a missing or misshapen tensor.
    #[doc(hidden)]
    pub fn from_tensors(
        tensors: HashMap<String, Tensor>,
        vision_heads: usize,
        text_heads: Option<usize>,
        device: &Device,
        dtype: ModelDtype,
    ) -> Result<Self, BackendError> {
        let weights = Weights::new(tensors, device, dtype.candle());
        Self::from_weights(&weights, vision_heads, text_heads).map_err(BackendError::InvalidParams)
    }

    /// Builds the heads from tensors named as in Meta's `DINOTxt` state dict.
    pub(crate) fn from_weights(
        w: &Weights,
        vision_heads: usize,
        text_heads: Option<usize>,
    ) -> Result<Self, String> {
        // Vision head: shapes come from the tensors themselves.
        let vh = "visual_model.head";
        let width = match dims_of(w, &format!("{vh}.ln_final.weight"))?.as_slice() {
            [c] => *c,
            other => return Err(format!("{vh}.ln_final.weight has shape {other:?}")),
        };
        if vision_heads == 0 || !width.is_multiple_of(vision_heads) {
            return Err(format!(
                "the vision head is {width} wide, which {vision_heads} attention heads do not divide"
            ));
        }
        let eps = 1e-5; // nn.LayerNorm's default, which every dino.txt norm uses.
        let blocks = count_blocks(w, &format!("{vh}.blocks"), "norm1.weight");
        let vision_blocks = (0..blocks)
            .map(|i| {
                let p = format!("{vh}.blocks.{i}");
                let hidden = match dims_of(w, &format!("{p}.mlp.w1.weight"))?.as_slice() {
                    [h, _] => *h,
                    other => return Err(format!("{p}.mlp.w1.weight has shape {other:?}")),
                };
                Ok(Block {
                    norm1: w.layer_norm(&format!("{p}.norm1"), width, eps)?,
                    attention: fused_attention(
                        w.linear(&format!("{p}.attn.qkv"), width, 3 * width, false)?,
                        w.linear(&format!("{p}.attn.proj"), width, width, true)?,
                        vision_heads,
                    ),
                    scale1: Some(w.get(&format!("{p}.ls1.gamma"), &[width])?),
                    norm2: w.layer_norm(&format!("{p}.norm2"), width, eps)?,
                    mlp: Mlp::Gated {
                        gate: w.linear(&format!("{p}.mlp.w1"), width, hidden, true)?,
                        up: w.linear(&format!("{p}.mlp.w2"), width, hidden, true)?,
                        down: w.linear(&format!("{p}.mlp.w3"), hidden, width, true)?,
                        act: Activation::Silu,
                    },
                    scale2: Some(w.get(&format!("{p}.ls2.gamma"), &[width])?),
                })
            })
            .collect::<Result<Vec<_>, String>>()?;
        let vision_norm = w.layer_norm(&format!("{vh}.ln_final"), width, eps)?;

        // Text tower.
        let tb = "text_model.backbone";
        let (vocab, dim) = match dims_of(w, &format!("{tb}.token_embedding.weight"))?.as_slice() {
            [v, d] => (*v, *d),
            other => return Err(format!("{tb}.token_embedding.weight has shape {other:?}")),
        };
        let context = match dims_of(w, &format!("{tb}.positional_embedding"))?.as_slice() {
            [n, d] if *d == dim => *n,
            other => return Err(format!("{tb}.positional_embedding has shape {other:?}")),
        };
        let heads = text_heads.unwrap_or(dim / TEXT_HEAD_DIM);
        if heads == 0 || !dim.is_multiple_of(heads) || vocab == 0 || context < 2 {
            return Err(format!(
                "text tower of width {dim}, {heads} heads, {vocab} tokens, {context} positions \
                 is not a supported shape"
            ));
        }
        let layers = count_blocks(w, &format!("{tb}.blocks"), "attention_norm.weight");
        let text_blocks = (0..layers)
            .map(|i| {
                let p = format!("{tb}.blocks.{i}");
                let hidden = match dims_of(w, &format!("{p}.feed_forward.fc1.weight"))?.as_slice() {
                    [h, _] => *h,
                    other => {
                        return Err(format!("{p}.feed_forward.fc1.weight has shape {other:?}"));
                    }
                };
                Ok(Block {
                    norm1: w.layer_norm(&format!("{p}.attention_norm"), dim, eps)?,
                    attention: fused_attention(
                        w.linear(&format!("{p}.attention.qkv"), dim, 3 * dim, false)?,
                        w.linear(&format!("{p}.attention.proj"), dim, dim, true)?,
                        heads,
                    ),
                    scale1: None,
                    norm2: w.layer_norm(&format!("{p}.ffn_norm"), dim, eps)?,
                    mlp: Mlp::Plain {
                        up: w.linear(&format!("{p}.feed_forward.fc1"), dim, hidden, true)?,
                        down: w.linear(&format!("{p}.feed_forward.fc2"), hidden, dim, true)?,
                        act: Activation::Gelu,
                    },
                    scale2: None,
                })
            })
            .collect::<Result<Vec<_>, String>>()?;
        let embed = match dims_of(w, "text_model.head.linear_projection.weight")?.as_slice() {
            [e, d] if *d == dim => *e,
            other => {
                return Err(format!(
                    "text_model.head.linear_projection.weight has shape {other:?}"
                ));
            }
        };
        if embed != 2 * width {
            return Err(format!(
                "the text embedding is {embed}-d but the image embedding [CLS, mean patch] is \
                 {}-d",
                2 * width
            ));
        }
        let text = TextTower {
            token_embedding: w.get(&format!("{tb}.token_embedding.weight"), &[vocab, dim])?,
            positions: w.get(&format!("{tb}.positional_embedding"), &[context, dim])?,
            blocks: text_blocks,
            norm: w.layer_norm(&format!("{tb}.ln_final"), dim, eps)?,
            projection: w.linear("text_model.head.linear_projection", dim, embed, false)?,
        };
        let end_token = u32::try_from(vocab - 1).map_err(|e| e.to_string())?;
        Ok(Self {
            vision_blocks,
            vision_norm,
            width,
            text,
            end_token,
        })
    }

    /// Width of the vision head = dimension of a per-patch embedding (1024 for ViT-L/16).
    pub fn patch_dim(&self) -> usize {
        self.width
    }

    /// Dimension of the image and text embeddings (`2 × patch_dim`).
    pub fn embed_dim(&self) -> usize {
        2 * self.width
    }

    /// Text positions (77 for the released model), start and end tokens included.
    pub fn context_length(&self) -> usize {
        self.text.positions.dim(0).unwrap_or(0)
    }

    /// Entries of the text tower's token embedding (49408 for the released model).
    pub fn vocab_size(&self) -> usize {
        self.text.token_embedding.dim(0).unwrap_or(0)
    }

    /// The type the heads compute in.
    pub fn dtype(&self) -> DType {
        self.text.token_embedding.dtype()
    }

    /// Vision head blocks.
    pub fn vision_blocks(&self) -> usize {
        self.vision_blocks.len()
    }

    /// The vision head over the backbone's output (converted to the heads' type, which the
    /// output is in).
    ///
    /// # Errors
    /// A candle error if the backbone is not as wide as the head.
    pub fn vision(&self, backbone: &BackboneOutput) -> candle_core::Result<VisionOutput> {
        let (batch, _, hidden) = backbone.tokens.dims3()?;
        if hidden != self.width {
            return Err(candle_core::Error::Msg(format!(
                "the backbone gives {hidden}-d tokens, the dino.txt head takes {}-d",
                self.width
            )));
        }
        let mut x = backbone.tokens.to_dtype(self.dtype())?;
        for block in &self.vision_blocks {
            x = block.forward(&x, None, None)?;
        }
        let x = self.vision_norm.forward(&x)?;
        let (gh, gw) = (backbone.grid_height, backbone.grid_width);
        let patches = x.narrow(1, 1 + backbone.num_register_tokens, gh * gw)?;
        let cls = x.narrow(1, 0, 1)?.squeeze(1)?;
        let image_embedding = Tensor::cat(&[&cls, &patches.mean(1)?], D::Minus1)?;
        Ok(VisionOutput {
            image_embedding,
            patch_grid: patches.reshape((batch, gh, gw, hidden))?,
        })
    }

    /// The text embedding (`embed_dim`, not normalised) of one token sequence, start and end
    /// tokens included, as the reference computes it on the zero-padded sequence: pooled at the
    /// first position of the largest id. Sequences longer than the context are cut as Meta's
    /// tokenizer cuts them (the last kept token becomes the end token). The causal mask makes
    /// the padding irrelevant, so it is not run.
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for an empty sequence or an id outside the vocabulary;
    /// [`BackendError::Inference`] if the model fails.
    pub fn text(&self, ids: &[u32]) -> Result<Vec<f32>, BackendError> {
        let vocab = self.text.token_embedding.dim(0).unwrap_or(0);
        if ids.is_empty() {
            return Err(BackendError::InvalidInput(
                "dino.txt: an empty token sequence".to_owned(),
            ));
        }
        if let Some(bad) = ids.iter().find(|&&id| id as usize >= vocab) {
            return Err(BackendError::InvalidInput(format!(
                "dino.txt: token id {bad} is outside the vocabulary of {vocab}"
            )));
        }
        let mut ids = ids.to_vec();
        let context = self.context_length();
        if ids.len() > context {
            ids.truncate(context);
            if let Some(last) = ids.last_mut() {
                *last = self.end_token;
            }
        }
        // The first position of the largest id (torch.argmax); padding zeros never win over a
        // non-empty sequence's ids, and an all-zero one pools at 0 either way.
        let max = ids.iter().copied().max().unwrap_or(0);
        let pooled = ids.iter().position(|&id| id == max).unwrap_or(0);
        let run = || -> candle_core::Result<Vec<f32>> {
            let t = &self.text;
            let len = pooled + 1;
            let device = t.token_embedding.device();
            let idx = Tensor::from_vec(ids[..len].to_vec(), len, device)?;
            let x = t
                .token_embedding
                .index_select(&idx, 0)?
                .add(&t.positions.narrow(0, 0, len)?)?
                .unsqueeze(0)?;
            let mask: Vec<f32> = (0..len)
                .flat_map(|i| (0..len).map(move |j| if j > i { f32::NEG_INFINITY } else { 0.0 }))
                .collect();
            let mask = Tensor::from_vec(mask, (len, len), device)?.to_dtype(x.dtype())?;
            let mut x = x;
            for block in &t.blocks {
                x = block.forward(&x, None, Some(&mask))?;
            }
            let last = t.norm.forward(&x.narrow(1, pooled, 1)?)?;
            t.projection
                .forward(&last)?
                .flatten_all()?
                .to_dtype(DType::F32)?
                .to_vec1()
        };
        run().map_err(|e| BackendError::Inference {
            what: "dino.txt text tower".to_owned(),
            source: Box::new(e),
        })
    }
}
