//! The DINOv3 ViT backbone on candle, read from a Hugging Face `DINOv3ViTModel` folder.
//!
//! Why it exists: candle-transformers has DINOv2 but not DINOv3, whose ViTs differ in every
//! block: register tokens, rotary position encoding (RoPE) on the patch tokens instead of a
//! learnt position table, no key bias, layer scale, and a gated SiLU MLP in the "plus" sizes.
//! This module owns the whole backbone: parsing `config.json` ([`Dinov3Config`]), loading
//! `model.safetensors` in the tensor layout of the checkpoints on the Hugging Face hub
//! (`facebook/dinov3-vits16-pretrain-lvd1689m`, `-vitb16-`, `-vitl16-`, and the `plus` sizes),
//! and computing what `transformers`' `DINOv3ViTModel` computes (its `last_hidden_state`), to
//! 1e-4 (checked by the goldens in `vlem-backends/goldens/dinov3/`).
//!
//! The forward pass, as `transformers` defines it:
//! - patch embedding: a 16×16 stride-16 convolution (here a reshape and one matrix product);
//!   tokens are `[CLS, registers..., patches (row-major)]`; no position table is added.
//! - every layer: `x += ls1 ⊙ attn(norm1(x))`, `x += ls2 ⊙ mlp(norm2(x))`, with pre-norm layer
//!   norms, per-channel layer scales `ls1`, `ls2`, attention scaled by `head_dim^-½`.
//! - RoPE, applied to queries and keys of the patch tokens only (CLS and registers pass
//!   unrotated): patch centres `((i + ½) / h, (j + ½) / w)` mapped to `[-1, 1]`, each axis by its
//!   own patch count; `head_dim / 4` frequencies `θ^(-4k / head_dim)`; angles `2π · coord · freq`,
//!   laid out `[y freqs, x freqs, y freqs, x freqs]`; rotation by "rotate half"
//!   (`x·cos + [-x₂, x₁]·sin`).
//! - the final layer norm, applied to every token.
//!
//! Training-only parts are left out: the mask token (read, never used at inference), drop path,
//! the random shift / jitter / rescale of RoPE coordinates.

use std::path::{Path, PathBuf};

use crate::hf_config::{HfConfigError, Section};
use candle_core::{DType, Device, Tensor};
use candle_nn::{LayerNorm, Module};

use crate::ModelDtype;
use crate::error::BackendError;
pub use crate::vit::{Activation, rope_angles};
use crate::vit::{Block, Linear, Mlp, Rope, Weights, fused_attention};

/// The model's name in messages.
pub const MODEL: &str = "DINOv3 ViT";

/// The files [`Dinov3Backbone::load`] needs in the model folder.
pub const REQUIRED_FILES: [&str; 2] = ["config.json", "model.safetensors"];

/// How to get a DINOv3 backbone folder, for the messages that say it is missing.
pub const DINOV3_INSTALL_HINT: &str = "DINOv3 weights are gated: accept the licence of \
     facebook/dinov3-vitl16-pretrain-lvd1689m (or -vits16-, -vitb16-) on Hugging Face, then on a \
     connected machine `hf download facebook/dinov3-vitl16-pretrain-lvd1689m config.json \
     model.safetensors --local-dir DIR` (older huggingface_hub: `huggingface-cli download` with \
     the same arguments), copy DIR here and name it in the config";

/// A `DINOv3ViTModel` `config.json`: what the forward pass needs of it.
#[derive(Clone, Debug, PartialEq)]
pub struct Dinov3Config {
    /// Side of a square patch in pixels (16 in every released checkpoint).
    pub patch_size: usize,
    /// Width of the transformer (384 ViT-S, 768 ViT-B, 1024 ViT-L, 1280 ViT-H+).
    pub hidden_size: usize,
    /// Width of the MLP.
    pub intermediate_size: usize,
    /// Transformer layers.
    pub num_hidden_layers: usize,
    /// Attention heads per layer; `hidden_size / num_attention_heads` must be a multiple of 4
    /// (RoPE gives each image axis half of each rotated pair).
    pub num_attention_heads: usize,
    /// Register tokens between CLS and the patches (4 in every released checkpoint).
    pub num_register_tokens: usize,
    /// Input channels (3).
    pub num_channels: usize,
    /// MLP activation.
    pub hidden_act: Activation,
    /// Epsilon of every layer norm.
    pub layer_norm_eps: f64,
    /// RoPE base period θ.
    pub rope_theta: f64,
    /// Whether the query projection has a bias.
    pub query_bias: bool,
    /// Whether the key projection has a bias (false in every released checkpoint).
    pub key_bias: bool,
    /// Whether the value projection has a bias.
    pub value_bias: bool,
    /// Whether the attention output projection has a bias.
    pub proj_bias: bool,
    /// Whether the MLP projections have biases.
    pub mlp_bias: bool,
    /// Gated MLP (`down(act(gate(x)) ⊙ up(x))`) instead of `down(act(up(x)))`.
    pub use_gated_mlp: bool,
}

impl Default for Dinov3Config {
    /// `transformers`' defaults: the ViT-S/16 shape.
    fn default() -> Self {
        Self {
            patch_size: 16,
            hidden_size: 384,
            intermediate_size: 1536,
            num_hidden_layers: 12,
            num_attention_heads: 6,
            num_register_tokens: 0,
            num_channels: 3,
            hidden_act: Activation::Gelu,
            layer_norm_eps: 1e-5,
            rope_theta: 100.0,
            query_bias: true,
            key_bias: false,
            value_bias: true,
            proj_bias: true,
            mlp_bias: true,
            use_gated_mlp: false,
        }
    }
}

impl Dinov3Config {
    /// Parses the text of a `DINOv3ViTModel` `config.json`, with `transformers`' defaults for
    /// absent keys. Keys the forward pass does not use (`image_size`, the training-time RoPE
    /// augmentations, backbone outputs) are ignored: real files carry them.
    ///
    /// # Errors
    /// [`HfConfigError`] naming the key that is malformed or describes an unsupported model.
    pub fn from_json(text: &str) -> Result<Self, HfConfigError> {
        let m = Section::parse(text)?;
        m.expect_model_type(
            "dinov3_vit",
            "this backbone reads DINOv3ViTModel folders (model_type \"dinov3_vit\"; the ConvNeXt \
             DINOv3 models are not supported)",
        )?;
        let d = Self::default();
        let act_name = m.string("hidden_act", "gelu")?;
        let hidden_act =
            Activation::from_hf_name(&act_name).ok_or_else(|| HfConfigError::Unsupported {
                key: m.name("hidden_act"),
                found: format!("{act_name:?}"),
                reason: "supported: gelu, gelu_pytorch_tanh, silu".to_owned(),
            })?;
        let config = Self {
            patch_size: m.square("patch_size", d.patch_size)?,
            hidden_size: m.usize("hidden_size", d.hidden_size)?,
            intermediate_size: m.usize("intermediate_size", d.intermediate_size)?,
            num_hidden_layers: m.usize("num_hidden_layers", d.num_hidden_layers)?,
            num_attention_heads: m.usize("num_attention_heads", d.num_attention_heads)?,
            num_register_tokens: m.usize("num_register_tokens", d.num_register_tokens)?,
            num_channels: m.usize("num_channels", d.num_channels)?,
            hidden_act,
            layer_norm_eps: m.positive("layer_norm_eps", d.layer_norm_eps)?,
            rope_theta: m.positive("rope_theta", d.rope_theta)?,
            query_bias: m.bool("query_bias", d.query_bias)?,
            key_bias: m.bool("key_bias", d.key_bias)?,
            value_bias: m.bool("value_bias", d.value_bias)?,
            proj_bias: m.bool("proj_bias", d.proj_bias)?,
            mlp_bias: m.bool("mlp_bias", d.mlp_bias)?,
            use_gated_mlp: m.bool("use_gated_mlp", d.use_gated_mlp)?,
        };
        config.validate()?;
        Ok(config)
    }

    /// Checks the relations between values that the forward pass relies on.
    pub fn validate(&self) -> Result<(), HfConfigError> {
        let positive = [
            ("patch_size", self.patch_size),
            ("hidden_size", self.hidden_size),
            ("intermediate_size", self.intermediate_size),
            ("num_attention_heads", self.num_attention_heads),
            ("num_channels", self.num_channels),
        ];
        if let Some((key, _)) = positive.iter().find(|(_, n)| *n == 0) {
            return Err(HfConfigError::Inconsistent(format!("{key} is 0")));
        }
        if !self.hidden_size.is_multiple_of(self.num_attention_heads) {
            return Err(HfConfigError::Inconsistent(format!(
                "hidden_size {} is not a multiple of num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            )));
        }
        if !self.head_dim().is_multiple_of(4) {
            return Err(HfConfigError::Inconsistent(format!(
                "the head dimension hidden_size / num_attention_heads = {} is not a multiple of \
                 4, which 2-D RoPE needs",
                self.head_dim()
            )));
        }
        Ok(())
    }

    /// Channels per attention head.
    pub fn head_dim(&self) -> usize {
        self.hidden_size / self.num_attention_heads.max(1)
    }

    /// Tokens before the patches: CLS and the registers.
    pub fn prefix_tokens(&self) -> usize {
        1 + self.num_register_tokens
    }
}

/// What the backbone gives for a batch of images: every token after the final layer norm
/// (`transformers`' `last_hidden_state`), and the patch grid's shape.
#[derive(Clone, Debug)]
pub struct BackboneOutput {
    /// `(batch, 1 + registers + grid_height·grid_width, hidden)`: CLS, registers, patches.
    pub tokens: Tensor,
    /// Register tokens per image.
    pub num_register_tokens: usize,
    /// Patch rows.
    pub grid_height: usize,
    /// Patches per row.
    pub grid_width: usize,
}

impl BackboneOutput {
    /// The CLS tokens, `(batch, hidden)`.
    ///
    /// # Errors
    /// Only if the tensor is not the shape this type describes.
    pub fn cls(&self) -> candle_core::Result<Tensor> {
        self.tokens.narrow(1, 0, 1)?.squeeze(1)
    }

    /// The register tokens, `(batch, registers, hidden)`.
    ///
    /// # Errors
    /// Only if the tensor is not the shape this type describes.
    pub fn registers(&self) -> candle_core::Result<Tensor> {
        self.tokens.narrow(1, 1, self.num_register_tokens)
    }

    /// The patch tokens as a grid, `(batch, grid_height, grid_width, hidden)`, row-major as the
    /// image.
    ///
    /// # Errors
    /// Only if the tensor is not the shape this type describes.
    pub fn patch_grid(&self) -> candle_core::Result<Tensor> {
        let (batch, _, hidden) = self.tokens.dims3()?;
        self.tokens
            .narrow(
                1,
                1 + self.num_register_tokens,
                self.grid_height * self.grid_width,
            )?
            .reshape((batch, self.grid_height, self.grid_width, hidden))
    }
}

/// The DINOv3 ViT backbone, ready to run. Thread-safe: every method takes `&self`.
#[derive(Clone)]
pub struct Dinov3Backbone {
    config: Dinov3Config,
    /// `(channels·patch·patch, hidden)`: the patch convolution as a matrix.
    patch_weight_t: Tensor,
    patch_bias: Tensor,
    /// `(1, 1 + registers, hidden)`: CLS then the registers.
    prefix: Tensor,
    layers: Vec<Block>,
    norm: LayerNorm,
    device: Device,
    /// What the backbone computes in; its input is converted on the way in.
    dtype: DType,
    dir: PathBuf,
}

impl std::fmt::Debug for Dinov3Backbone {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dinov3Backbone")
            .field("dir", &self.dir)
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

/// `dir` if it holds every file of [`REQUIRED_FILES`]; `origin` says where the folder came from.
///
/// # Errors
/// [`BackendError::MissingModelFiles`] naming the missing files and how to get them.
pub fn check_model_dir(dir: &Path, origin: String) -> Result<PathBuf, BackendError> {
    crate::model_files::require_files(dir, &REQUIRED_FILES, MODEL, origin, DINOV3_INSTALL_HINT)
}

impl Dinov3Backbone {
    /// Loads the backbone in `dir` (`config.json`, `model.safetensors`) onto `device`, its
    /// weights converted to `dtype`, the type it computes in. Reads the tensor names of the hub
    /// checkpoints (`layer.N.…`) and those `transformers` ≥ 5 uses in memory
    /// (`model.layer.N.…`).
    ///
    /// # Errors
    /// [`BackendError::MissingModelFiles`] when a file is missing,
    /// [`BackendError::InvalidModelFile`] when one cannot be read or does not describe a DINOv3
    /// ViT (wrong `model_type`, tensor names or shapes that disagree with `config.json`).
    pub fn load(dir: &Path, device: &Device, dtype: ModelDtype) -> Result<Self, BackendError> {
        let dir = check_model_dir(dir, "the caller".to_owned())?;
        let config_path = dir.join("config.json");
        let text = crate::model_files::read_text(&config_path)?;
        let config =
            Dinov3Config::from_json(&text).map_err(|source| BackendError::InvalidModelConfig {
                path: config_path.clone(),
                source,
            })?;
        let weights_path = dir.join("model.safetensors");
        let tensors = candle_core::safetensors::load(&weights_path, device).map_err(|e| {
            BackendError::InvalidModelFile {
                path: weights_path.clone(),
                reason: format!("cannot read the weights: {e}"),
            }
        })?;
        let weights = Weights::new(tensors, device, dtype.candle());
        let mut backbone = Self::from_weights(&config, &weights, "").map_err(|reason| {
            BackendError::InvalidModelFile {
                path: weights_path.clone(),
                reason: format!("the weights do not match config.json: {reason}"),
            }
        })?;
        backbone.dir = dir;
        Ok(backbone)
    }

    /// The backbone from tensors named as in a hub `model.safetensors`, on `device` in `dtype`,
    /// for benchmarks that fill a full-size architecture with random weights.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] naming a missing or misshapen tensor.
    #[doc(hidden)]
    pub fn from_tensors(
        config: &Dinov3Config,
        tensors: std::collections::HashMap<String, Tensor>,
        device: &Device,
        dtype: ModelDtype,
    ) -> Result<Self, BackendError> {
        Self::from_weights(config, &Weights::new(tensors, device, dtype.candle()), "")
            .map_err(BackendError::InvalidParams)
    }

    /// Builds the backbone from tensors named as in a `DINOv3ViTModel` state dict, each name
    /// preceded by `prefix` (empty for a backbone file of its own).
    pub(crate) fn from_weights(
        config: &Dinov3Config,
        w: &Weights,
        prefix: &str,
    ) -> Result<Self, String> {
        config.validate().map_err(|e| e.to_string())?;
        let c = config;
        let hidden = c.hidden_size;
        let p = c.patch_size;
        let e = format!("{prefix}embeddings");
        let patch = w.get(
            &format!("{e}.patch_embeddings.weight"),
            &[hidden, c.num_channels, p, p],
        )?;
        let patch_weight_t = patch
            .reshape((hidden, c.num_channels * p * p))
            .and_then(|t| t.t())
            .and_then(|t| t.contiguous())
            .map_err(|e| e.to_string())?;
        let patch_bias = w.get(&format!("{e}.patch_embeddings.bias"), &[hidden])?;
        let cls = w.get(&format!("{e}.cls_token"), &[1, 1, hidden])?;
        let prefix_tokens = if c.num_register_tokens > 0 {
            let registers = w.get(
                &format!("{e}.register_tokens"),
                &[1, c.num_register_tokens, hidden],
            )?;
            Tensor::cat(&[&cls, &registers], 1).map_err(|e| e.to_string())?
        } else {
            cls
        };
        // Hub files say `layer.N`; transformers ≥ 5 keeps `model.layer.N` in memory.
        let layer_root = if w.contains(&format!("{prefix}model.layer.0.norm1.weight")) {
            format!("{prefix}model.layer")
        } else {
            format!("{prefix}layer")
        };
        let layers = (0..c.num_hidden_layers)
            .map(|i| load_hf_layer(w, &format!("{layer_root}.{i}"), c))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            config: config.clone(),
            patch_weight_t,
            patch_bias,
            prefix: prefix_tokens,
            layers,
            norm: w.layer_norm(&format!("{prefix}norm"), hidden, c.layer_norm_eps)?,
            device: w.device().clone(),
            dtype: w.dtype(),
            dir: PathBuf::new(),
        })
    }

    /// The parsed `config.json`.
    pub fn config(&self) -> &Dinov3Config {
        &self.config
    }

    /// The model folder (empty when built from tensors in memory).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The type the backbone computes in, and its output's.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Runs the backbone on `pixels`, `(batch, channels, height, width)`, normalised (ImageNet
    /// mean and std for the released checkpoints), in any float type (converted to the
    /// backbone's); `height` and `width` must be multiples of the patch size, and may differ.
    /// The output is in the backbone's [`dtype`](Self::dtype).
    ///
    /// # Errors
    /// A candle error for a tensor of the wrong rank or channel count, or a side that is not a
    /// positive multiple of the patch size.
    pub fn forward(&self, pixels: &Tensor) -> candle_core::Result<BackboneOutput> {
        let c = &self.config;
        let (batch, channels, height, width) = pixels.dims4()?;
        let p = c.patch_size;
        if channels != c.num_channels
            || height == 0
            || width == 0
            || !height.is_multiple_of(p)
            || !width.is_multiple_of(p)
        {
            return Err(candle_core::Error::Msg(format!(
                "the backbone takes {} channels and sides that are positive multiples of {p}; \
                 got {channels} channels, {height}x{width}",
                c.num_channels
            )));
        }
        let (gh, gw) = (height / p, width / p);
        // (b, c, gh, p, gw, p) -> (b, gh, gw, c, p, p): each patch's pixels in the order of the
        // convolution weight, so that the convolution is one matrix product.
        let patches = pixels
            .to_dtype(self.dtype)?
            .reshape((batch, channels, gh, p, gw, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((batch * gh * gw, channels * p * p))?;
        let patches = patches
            .matmul(&self.patch_weight_t)?
            .broadcast_add(&self.patch_bias)?
            .reshape((batch, gh * gw, c.hidden_size))?;
        let prefix = self
            .prefix
            .broadcast_as((batch, c.prefix_tokens(), c.hidden_size))?;
        let mut x = Tensor::cat(&[&prefix, &patches], 1)?;
        let rope = Rope::new(
            (gh, gw),
            c.head_dim(),
            c.rope_theta,
            &self.device,
            self.dtype,
        )?;
        for layer in &self.layers {
            x = layer.forward(&x, Some(&rope), None)?;
        }
        Ok(BackboneOutput {
            tokens: self.norm.forward(&x)?,
            num_register_tokens: c.num_register_tokens,
            grid_height: gh,
            grid_width: gw,
        })
    }
}

/// One `DINOv3ViTLayer` from its state-dict names under `prefix`.
fn load_hf_layer(w: &Weights, prefix: &str, c: &Dinov3Config) -> Result<Block, String> {
    let h = c.hidden_size;
    let a = format!("{prefix}.attention");
    let part = |name: &str, bias: bool| -> Result<(Tensor, Tensor), String> {
        let weight = w.get(&format!("{a}.{name}.weight"), &[h, h])?;
        let bias = if bias {
            w.get(&format!("{a}.{name}.bias"), &[h])?
        } else {
            Tensor::zeros(h, w.dtype(), w.device()).map_err(|e| e.to_string())?
        };
        Ok((weight, bias))
    };
    let (qw, qb) = part("q_proj", c.query_bias)?;
    let (kw, kb) = part("k_proj", c.key_bias)?;
    let (vw, vb) = part("v_proj", c.value_bias)?;
    let fused = |ts: [&Tensor; 3]| Tensor::cat(&ts, 0).map_err(|e| e.to_string());
    let qkv = Linear::new(&fused([&qw, &kw, &vw])?, Some(fused([&qb, &kb, &vb])?))
        .map_err(|e| e.to_string())?;
    let attention = fused_attention(
        qkv,
        w.linear(&format!("{a}.o_proj"), h, h, c.proj_bias)?,
        c.num_attention_heads,
    );
    let m = format!("{prefix}.mlp");
    let i = c.intermediate_size;
    let mlp = if c.use_gated_mlp {
        Mlp::Gated {
            gate: w.linear(&format!("{m}.gate_proj"), h, i, c.mlp_bias)?,
            up: w.linear(&format!("{m}.up_proj"), h, i, c.mlp_bias)?,
            down: w.linear(&format!("{m}.down_proj"), i, h, c.mlp_bias)?,
            act: c.hidden_act,
        }
    } else {
        Mlp::Plain {
            up: w.linear(&format!("{m}.up_proj"), h, i, c.mlp_bias)?,
            down: w.linear(&format!("{m}.down_proj"), i, h, c.mlp_bias)?,
            act: c.hidden_act,
        }
    };
    Ok(Block {
        norm1: w.layer_norm(&format!("{prefix}.norm1"), h, c.layer_norm_eps)?,
        attention,
        scale1: Some(w.get(&format!("{prefix}.layer_scale1.lambda1"), &[h])?),
        norm2: w.layer_norm(&format!("{prefix}.norm2"), h, c.layer_norm_eps)?,
        mlp,
        scale2: Some(w.get(&format!("{prefix}.layer_scale2.lambda1"), &[h])?),
    })
}

#[cfg(test)]
mod tests {
    #![allow(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        reason = "tests"
    )]

    use super::*;

    #[test]
    fn config_defaults_are_transformers_defaults() {
        let c = Dinov3Config::from_json("{}").unwrap();
        assert_eq!(c, Dinov3Config::default());
        assert_eq!(c.head_dim(), 64);
        assert_eq!(c.prefix_tokens(), 1);
    }

    #[test]
    fn bad_configs_name_the_key() {
        let e = Dinov3Config::from_json(r#"{"model_type": "dinov2"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("dinov2"), "{e}");
        let e = Dinov3Config::from_json(r#"{"hidden_act": "relu"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("relu"), "{e}");
        let e = Dinov3Config::from_json(r#"{"hidden_size": 40, "num_attention_heads": 4}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("multiple of 4"), "{e}");
        let e = Dinov3Config::from_json(r#"{"patch_size": [16, 8]}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("patch_size"), "{e}");
        assert_eq!(
            Dinov3Config::from_json(r#"{"patch_size": [14, 14]}"#)
                .unwrap()
                .patch_size,
            14
        );
    }

    #[test]
    fn rope_angles_follow_the_centre_coordinates() {
        // A 1x2 grid, head_dim 8: two frequencies, theta^0 = 1 and theta^(-4/8) = 0.1.
        let a = rope_angles(1, 2, 8, 100.0);
        assert_eq!(a.len(), 2 * 8);
        let tau = 2.0 * std::f32::consts::PI;
        // Patch (0, 0): y = 0 (one row), x = -0.5; layout [y f0, y f1, x f0, x f1].
        let expected0 = [0.0, 0.0, -0.5 * tau, -0.5 * tau * 0.1];
        for (got, want) in a[..4].iter().zip(expected0) {
            assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        }
        assert_eq!(a[..4], a[4..8], "the second half repeats the first");
        // Patch (0, 1): x = +0.5.
        assert!((a[8 + 2] - 0.5 * tau).abs() < 1e-6);
    }
}
