//! The CLIP ViT image and text towers on candle, read from a Hugging Face `CLIPModel` folder.
//!
//! Why it exists: candle-transformers' `clip` module fixes the ViT-B/32 shape, hard-codes
//! quick-GELU and a layer-norm epsilon, reads no `config.json` and pools the text tower by the
//! largest token id only. Users have Hugging Face folders of every ViT size (B/32, B/16, L/14,
//! H/14, ...), some with exact GELU and some with the corrected `eos_token_id`, so this module
//! owns the whole model: parsing `config.json` ([`ClipConfig`]), loading `model.safetensors` in
//! the `CLIPModel` tensor layout, tokenising with `tokenizer.json`, and computing what
//! `transformers`' `get_image_features` and `get_text_features` compute, to 1e-4 (checked by the
//! goldens in `vlem-backends/goldens/clip/`).
//!
//! The forward passes are written here, on candle tensors, with two choices made for CPU speed
//! that do not change the result beyond float rounding: the query, key and value projections are
//! one matrix product (their weights concatenated at load time), and the patch embedding is a
//! reshape and a matrix product instead of a strided convolution.

use std::path::{Path, PathBuf};

use candle_core::{D, DType, Device, IndexOp, Module, Tensor};
use candle_nn::{Embedding, LayerNorm, VarBuilder};
use tokenizers::{Tokenizer, TruncationParams};

use crate::ModelDtype;
use crate::attention::Scores;
use crate::error::BackendError;
use crate::hf_config::{HfConfigError, Section};
use crate::profile;

/// The model's name in messages.
pub const MODEL: &str = "CLIP";

/// The files [`ClipModel::load`] needs in the model folder.
pub const REQUIRED_FILES: [&str; 3] = ["config.json", "model.safetensors", "tokenizer.json"];

/// How to get a CLIP model folder, for the messages that say it is missing.
pub const CLIP_INSTALL_HINT: &str = "download a CLIP model in the Hugging Face layout on a \
     connected machine, e.g. `huggingface-cli download openai/clip-vit-base-patch16 config.json \
     model.safetensors tokenizer.json preprocessor_config.json --local-dir DIR` (newer \
     huggingface_hub: `hf download` with the same arguments), copy DIR here and set \
     `[encoder] model_dir = \"DIR\"` (or the environment variable VLEM_CLIP_DIR)";

/// How to turn an older Hugging Face folder (`pytorch_model.bin`, `vocab.json` + `merges.txt`)
/// into the files this module reads.
pub const CLIP_CONVERT_HINT: &str = "the folder has the older files (pytorch_model.bin, or \
     vocab.json and merges.txt): convert them once with transformers, `python3 -c \"import sys; \
     from transformers import CLIPModel, CLIPTokenizer; d = sys.argv[1]; \
     CLIPModel.from_pretrained(d).save_pretrained(d); \
     CLIPTokenizer.from_pretrained(d).save_pretrained(d)\" DIR`, which writes model.safetensors \
     and tokenizer.json";

/// The legacy `eos_token_id` of the first Hugging Face CLIP configs: with it, `transformers`
/// pools the text tower at the largest token id of each sequence (the end token has the largest
/// id in CLIP's vocabulary); with any other value, at the first position of that id.
pub const LEGACY_EOS_TOKEN_ID: i64 = 2;

/// The largest MLP activation, in bytes, of one image-tower call (see
/// [`ClipModel::image_features`]): one image at a time for ViT-B/16 (2.4 MB) and larger, six for
/// B/32, the whole batch for tiny models. Measured on ViT-B/16, a batch of 16 embedded six images
/// per call ran at 1.1-1.45 images/s and one per call at 1.85-2.2 images/s (1 thread).
const GROUP_BYTES: usize = 4 << 20;

/// A transformer MLP activation, from `hidden_act` in `config.json`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// `quick_gelu`: `x * sigmoid(1.702 x)`, the activation of OpenAI's CLIP models.
    QuickGelu,
    /// `gelu`: the exact GELU, `x * Φ(x)` (erf).
    Gelu,
    /// `gelu_new`, `gelu_pytorch_tanh`, `gelu_fast`: the tanh approximation of GELU.
    GeluTanh,
}

impl Activation {
    /// The activation named `name` in `transformers`' `ACT2FN`, where it is one of these.
    pub fn from_hf_name(name: &str) -> Option<Self> {
        match name {
            "quick_gelu" => Some(Self::QuickGelu),
            "gelu" => Some(Self::Gelu),
            "gelu_new" | "gelu_pytorch_tanh" | "gelu_fast" => Some(Self::GeluTanh),
            _ => None,
        }
    }

    fn apply(self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Self::QuickGelu => crate::kernels::quick_gelu(x),
            Self::Gelu => crate::kernels::gelu_erf(x),
            Self::GeluTanh => x.gelu(),
        }
    }
}

/// `text_config` of a `CLIPModel` `config.json`.
#[derive(Clone, Debug, PartialEq)]
pub struct TextConfig {
    /// Token vocabulary size.
    pub vocab_size: usize,
    /// Width of the transformer.
    pub hidden_size: usize,
    /// Width of the MLP.
    pub intermediate_size: usize,
    /// Transformer layers.
    pub num_hidden_layers: usize,
    /// Attention heads per layer.
    pub num_attention_heads: usize,
    /// Tokens per text at most (start and end tokens included); longer texts are truncated.
    pub max_position_embeddings: usize,
    /// MLP activation.
    pub hidden_act: Activation,
    /// Epsilon of every layer norm.
    pub layer_norm_eps: f64,
    /// The end token's id, or [`LEGACY_EOS_TOKEN_ID`]; decides the pooling rule.
    pub eos_token_id: i64,
}

/// `vision_config` of a `CLIPModel` `config.json`.
#[derive(Clone, Debug, PartialEq)]
pub struct VisionConfig {
    /// Width of the transformer.
    pub hidden_size: usize,
    /// Width of the MLP.
    pub intermediate_size: usize,
    /// Transformer layers.
    pub num_hidden_layers: usize,
    /// Attention heads per layer.
    pub num_attention_heads: usize,
    /// Input channels (3).
    pub num_channels: usize,
    /// Side of the square input image in pixels.
    pub image_size: usize,
    /// Side of a square patch in pixels.
    pub patch_size: usize,
    /// MLP activation.
    pub hidden_act: Activation,
    /// Epsilon of every layer norm.
    pub layer_norm_eps: f64,
}

/// A `CLIPModel` `config.json`: the two towers and the shared embedding size.
#[derive(Clone, Debug, PartialEq)]
pub struct ClipConfig {
    /// The text tower.
    pub text: TextConfig,
    /// The image tower.
    pub vision: VisionConfig,
    /// Dimension of the joint embedding space (both projections).
    pub projection_dim: usize,
}

impl ClipConfig {
    /// Parses the text of a `CLIPModel` `config.json`, with `transformers`' defaults for absent
    /// keys. Keys this model does not use are ignored: real files carry many. The legacy
    /// `text_config_dict` / `vision_config_dict`, where present, override `text_config` /
    /// `vision_config` as they do in `transformers`.
    ///
    /// # Errors
    /// [`HfConfigError`] naming the key that is malformed or describes an unsupported model.
    pub fn from_json(text: &str) -> Result<Self, HfConfigError> {
        let root = Section::parse(text)?;
        root.expect_model_type(
            "clip",
            "this encoder reads CLIPModel folders (model_type \"clip\")",
        )?;
        let text = root.section("text_config")?;
        let vision = root.section("vision_config")?;
        let text = TextConfig {
            vocab_size: text.usize("vocab_size", 49408)?,
            hidden_size: text.usize("hidden_size", 512)?,
            intermediate_size: text.usize("intermediate_size", 2048)?,
            num_hidden_layers: text.usize("num_hidden_layers", 12)?,
            num_attention_heads: text.usize("num_attention_heads", 8)?,
            max_position_embeddings: text.usize("max_position_embeddings", 77)?,
            hidden_act: activation(&text, "quick_gelu")?,
            layer_norm_eps: text.positive("layer_norm_eps", 1e-5)?,
            eos_token_id: text.integer("eos_token_id", 49407)?,
        };
        let vision = VisionConfig {
            hidden_size: vision.usize("hidden_size", 768)?,
            intermediate_size: vision.usize("intermediate_size", 3072)?,
            num_hidden_layers: vision.usize("num_hidden_layers", 12)?,
            num_attention_heads: vision.usize("num_attention_heads", 12)?,
            num_channels: vision.usize("num_channels", 3)?,
            image_size: vision.square("image_size", 224)?,
            patch_size: vision.square("patch_size", 32)?,
            hidden_act: activation(&vision, "quick_gelu")?,
            layer_norm_eps: vision.positive("layer_norm_eps", 1e-5)?,
        };
        let config = Self {
            text,
            vision,
            projection_dim: root.usize("projection_dim", 512)?,
        };
        config.validate()?;
        Ok(config)
    }

    /// Checks the relations between values that the forward pass relies on.
    fn validate(&self) -> Result<(), HfConfigError> {
        let (t, v) = (&self.text, &self.vision);
        let positive = [
            ("projection_dim", self.projection_dim),
            ("text_config.vocab_size", t.vocab_size),
            ("text_config.hidden_size", t.hidden_size),
            ("text_config.intermediate_size", t.intermediate_size),
            ("text_config.num_attention_heads", t.num_attention_heads),
            (
                "text_config.max_position_embeddings",
                t.max_position_embeddings,
            ),
            ("vision_config.hidden_size", v.hidden_size),
            ("vision_config.intermediate_size", v.intermediate_size),
            ("vision_config.num_attention_heads", v.num_attention_heads),
            ("vision_config.num_channels", v.num_channels),
            ("vision_config.image_size", v.image_size),
            ("vision_config.patch_size", v.patch_size),
        ];
        if let Some((key, _)) = positive.iter().find(|(_, n)| *n == 0) {
            return Err(HfConfigError::Inconsistent(format!("{key} is 0")));
        }
        if !t.hidden_size.is_multiple_of(t.num_attention_heads) {
            return Err(HfConfigError::Inconsistent(format!(
                "text_config.hidden_size {} is not a multiple of num_attention_heads {}",
                t.hidden_size, t.num_attention_heads
            )));
        }
        if !v.hidden_size.is_multiple_of(v.num_attention_heads) {
            return Err(HfConfigError::Inconsistent(format!(
                "vision_config.hidden_size {} is not a multiple of num_attention_heads {}",
                v.hidden_size, v.num_attention_heads
            )));
        }
        if !v.image_size.is_multiple_of(v.patch_size) {
            return Err(HfConfigError::Inconsistent(format!(
                "vision_config.image_size {} is not a multiple of patch_size {}",
                v.image_size, v.patch_size
            )));
        }
        if t.max_position_embeddings < 2 {
            return Err(HfConfigError::Inconsistent(
                "text_config.max_position_embeddings is below 2 (start and end tokens)".into(),
            ));
        }
        Ok(())
    }

    /// Patches per image side.
    pub fn grid(&self) -> usize {
        self.vision.image_size / self.vision.patch_size
    }
}

/// The section's `hidden_act`.
fn activation(section: &Section, default: &str) -> Result<Activation, HfConfigError> {
    let name = section.string("hidden_act", default)?;
    Activation::from_hf_name(&name).ok_or_else(|| HfConfigError::Unsupported {
        key: section.name("hidden_act"),
        found: format!("{name:?}"),
        reason: "supported: \"quick_gelu\", \"gelu\", \"gelu_new\", \"gelu_pytorch_tanh\", \
                 \"gelu_fast\""
            .to_owned(),
    })
}

/// A linear layer whose weight is stored transposed, `(in, out)`, so that the product with a
/// `(rows, in)` input is one plain matrix product.
#[derive(Clone, Debug)]
struct Linear {
    weight_t: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    fn load(
        vb: &VarBuilder,
        inputs: usize,
        outputs: usize,
        bias: bool,
    ) -> candle_core::Result<Self> {
        let weight = vb.get((outputs, inputs), "weight")?;
        let bias = if bias {
            Some(vb.get(outputs, "bias")?)
        } else {
            None
        };
        Self::from_parts(&weight, bias)
    }

    fn from_parts(weight: &Tensor, bias: Option<Tensor>) -> candle_core::Result<Self> {
        Ok(Self {
            weight_t: weight.t()?.contiguous()?,
            bias,
        })
    }

    /// `x · Wᵀ + b` over the last dimension of `x`, whatever its leading dimensions.
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let dims = x.dims().to_vec();
        let inputs = x.dim(D::Minus1)?;
        let rows = x.elem_count() / inputs.max(1);
        let y = x.reshape((rows, inputs))?.matmul(&self.weight_t)?;
        let y = match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        };
        let mut out_dims = dims;
        if let Some(last) = out_dims.last_mut() {
            *last = self.weight_t.dim(1)?;
        }
        y.reshape(out_dims)
    }
}

impl crate::attention::Project for Linear {
    fn project(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        self.forward(x)
    }
}

/// CLIP's multi-head self-attention: the shared layer, its three input projections fused into one.
type Attention = crate::attention::Attention<Linear>;

fn load_attention(vb: &VarBuilder, width: usize, heads: usize) -> candle_core::Result<Attention> {
    let part = |name: &str| -> candle_core::Result<(Tensor, Tensor)> {
        let p = vb.pp(name);
        Ok((p.get((width, width), "weight")?, p.get(width, "bias")?))
    };
    let (qw, qb) = part("q_proj")?;
    let (kw, kb) = part("k_proj")?;
    let (vw, vbias) = part("v_proj")?;
    let weight = Tensor::cat(&[&qw, &kw, &vw], 0)?;
    let bias = Tensor::cat(&[&qb, &kb, &vbias], 0)?;
    Ok(Attention::new(
        crate::attention::Inputs::Fused(Linear::from_parts(&weight, Some(bias))?),
        Linear::load(&vb.pp("out_proj"), width, width, true)?,
        heads,
    ))
}

/// One pre-norm transformer layer (`CLIPEncoderLayer`).
#[derive(Clone, Debug)]
struct Layer {
    norm1: LayerNorm,
    attention: Attention,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    act: Activation,
}

impl Layer {
    fn load(
        vb: &VarBuilder,
        width: usize,
        mlp: usize,
        heads: usize,
        act: Activation,
        eps: f64,
    ) -> candle_core::Result<Self> {
        Ok(Self {
            norm1: candle_nn::layer_norm(width, eps, vb.pp("layer_norm1"))?,
            attention: load_attention(&vb.pp("self_attn"), width, heads)?,
            norm2: candle_nn::layer_norm(width, eps, vb.pp("layer_norm2"))?,
            fc1: Linear::load(&vb.pp("mlp").pp("fc1"), width, mlp, true)?,
            fc2: Linear::load(&vb.pp("mlp").pp("fc2"), mlp, width, true)?,
            act,
        })
    }

    fn forward(&self, x: &Tensor, mask: Option<&Tensor>) -> candle_core::Result<Tensor> {
        let scores = mask.map_or(Scores::Plain, Scores::Bias);
        let device = x.device();
        let normed = profile::timed("norm", device, || self.norm1.forward(x))?;
        let x = (x + self.attention.forward(&normed, None, scores)?)?;
        let normed = profile::timed("norm", device, || self.norm2.forward(&x))?;
        let h = profile::timed("mlp", device, || {
            self.fc2
                .forward(&self.act.apply(&self.fc1.forward(&normed)?)?)
        })?;
        x + h
    }
}

fn load_layers(
    vb: &VarBuilder,
    count: usize,
    width: usize,
    mlp: usize,
    heads: usize,
    act: Activation,
    eps: f64,
) -> candle_core::Result<Vec<Layer>> {
    let vb = vb.pp("encoder").pp("layers");
    (0..count)
        .map(|i| Layer::load(&vb.pp(i.to_string()), width, mlp, heads, act, eps))
        .collect()
}

/// The ViT image tower with its projection (`vision_model` + `visual_projection`).
#[derive(Clone, Debug)]
struct VisionTower {
    /// `(channels * patch * patch, width)`: the patch convolution as a matrix.
    patch_weight_t: Tensor,
    class_embedding: Tensor,
    positions: Tensor,
    pre_norm: LayerNorm,
    layers: Vec<Layer>,
    post_norm: LayerNorm,
    projection: Linear,
    config: VisionConfig,
}

impl VisionTower {
    fn load(vb: &VarBuilder, c: &VisionConfig, projection_dim: usize) -> candle_core::Result<Self> {
        let m = vb.pp("vision_model");
        let e = m.pp("embeddings");
        let w = c.hidden_size;
        let patch = e
            .pp("patch_embedding")
            .get((w, c.num_channels, c.patch_size, c.patch_size), "weight")?;
        let grid = c.image_size / c.patch_size;
        Ok(Self {
            patch_weight_t: patch
                .reshape((w, c.num_channels * c.patch_size * c.patch_size))?
                .t()?
                .contiguous()?,
            class_embedding: e.get(w, "class_embedding")?,
            positions: e
                .pp("position_embedding")
                .get((grid * grid + 1, w), "weight")?,
            pre_norm: candle_nn::layer_norm(w, c.layer_norm_eps, m.pp("pre_layrnorm"))?,
            layers: load_layers(
                &m,
                c.num_hidden_layers,
                w,
                c.intermediate_size,
                c.num_attention_heads,
                c.hidden_act,
                c.layer_norm_eps,
            )?,
            post_norm: candle_nn::layer_norm(w, c.layer_norm_eps, m.pp("post_layernorm"))?,
            projection: Linear::load(&vb.pp("visual_projection"), w, projection_dim, false)?,
            config: c.clone(),
        })
    }

    /// `pixels`: `(batch, channels, size, size)`, normalised; returns `(batch, projection_dim)`.
    fn forward(&self, pixels: &Tensor) -> candle_core::Result<Tensor> {
        let c = &self.config;
        let (batch, channels, _, _) = pixels.dims4()?;
        let (p, g, w) = (c.patch_size, c.image_size / c.patch_size, c.hidden_size);
        // Cut into patches, each flattened channel-major like the convolution kernel.
        let patches = pixels
            .reshape((batch, channels, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .reshape((batch * g * g, channels * p * p))?;
        let tokens = patches
            .matmul(&self.patch_weight_t)?
            .reshape((batch, g * g, w))?;
        let class = self
            .class_embedding
            .reshape((1, 1, w))?
            .repeat((batch, 1, 1))?;
        let x = Tensor::cat(&[&class, &tokens], 1)?.broadcast_add(&self.positions)?;
        let mut x = self.pre_norm.forward(&x)?;
        for layer in &self.layers {
            x = layer.forward(&x, None)?;
        }
        let pooled = x.i((.., 0, ..))?.contiguous()?;
        self.projection.forward(&self.post_norm.forward(&pooled)?)
    }
}

/// The causal text transformer with its projection (`text_model` + `text_projection`).
#[derive(Clone, Debug)]
struct TextTower {
    tokens: Embedding,
    positions: Tensor,
    layers: Vec<Layer>,
    final_norm: LayerNorm,
    projection: Linear,
    config: TextConfig,
}

impl TextTower {
    fn load(vb: &VarBuilder, c: &TextConfig, projection_dim: usize) -> candle_core::Result<Self> {
        let m = vb.pp("text_model");
        let e = m.pp("embeddings");
        let w = c.hidden_size;
        Ok(Self {
            tokens: candle_nn::embedding(c.vocab_size, w, e.pp("token_embedding"))?,
            positions: e
                .pp("position_embedding")
                .get((c.max_position_embeddings, w), "weight")?,
            layers: load_layers(
                &m,
                c.num_hidden_layers,
                w,
                c.intermediate_size,
                c.num_attention_heads,
                c.hidden_act,
                c.layer_norm_eps,
            )?,
            final_norm: candle_nn::layer_norm(w, c.layer_norm_eps, m.pp("final_layer_norm"))?,
            projection: Linear::load(&vb.pp("text_projection"), w, projection_dim, false)?,
            config: c.clone(),
        })
    }

    /// `ids`: `(batch, len)` u32, right-padded; `pooled[b]`: the position whose state is the
    /// text's embedding. Returns `(batch, projection_dim)`.
    fn forward(&self, ids: &Tensor, pooled: &[usize]) -> candle_core::Result<Tensor> {
        let len = ids.dim(1)?;
        let x = self
            .tokens
            .forward(ids)?
            .broadcast_add(&self.positions.narrow(0, 0, len)?)?;
        // Causal mask: position i sees positions 0..=i. Padding comes after the pooled token,
        // so it never reaches it and needs no mask of its own.
        let mask: Vec<f32> = (0..len)
            .flat_map(|i| (0..len).map(move |j| if j > i { f32::NEG_INFINITY } else { 0.0 }))
            .collect();
        let mask = Tensor::from_vec(mask, (len, len), ids.device())?.to_dtype(x.dtype())?;
        let mut x = x;
        for layer in &self.layers {
            x = layer.forward(&x, Some(&mask))?;
        }
        // The layer norm works per token: normalising the pooled tokens alone is the same.
        let rows = pooled
            .iter()
            .enumerate()
            .map(|(b, &p)| x.i((b, p)))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let pooled = Tensor::stack(&rows, 0)?;
        self.projection.forward(&self.final_norm.forward(&pooled)?)
    }

    /// The position `transformers` pools for one tokenised text (see [`LEGACY_EOS_TOKEN_ID`]);
    /// 0 when the end token is absent, as `argmax` over all-false gives.
    fn pooled_position(&self, ids: &[u32]) -> usize {
        if self.config.eos_token_id == LEGACY_EOS_TOKEN_ID {
            // The first largest id, as torch's argmax.
            let mut best = 0;
            for (i, &id) in ids.iter().enumerate() {
                if ids.get(best).is_some_and(|&b| id > b) {
                    best = i;
                }
            }
            best
        } else {
            ids.iter()
                .position(|&id| i64::from(id) == self.config.eos_token_id)
                .unwrap_or(0)
        }
    }
}

/// A CLIP model loaded from a Hugging Face folder: both towers and the tokenizer. Thread-safe:
/// every method takes `&self`.
pub struct ClipModel {
    config: ClipConfig,
    vision: VisionTower,
    text: TextTower,
    tokenizer: Tokenizer,
    device: Device,
    /// What the towers compute in; their f32 inputs are converted on the way in.
    dtype: DType,
    dir: PathBuf,
}

impl std::fmt::Debug for ClipModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClipModel")
            .field("dir", &self.dir)
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

/// `dir` if it holds every file of [`REQUIRED_FILES`]; `origin` says where the folder came from.
/// The hint is [`CLIP_CONVERT_HINT`] when the older files that it converts are there instead,
/// else [`CLIP_INSTALL_HINT`].
///
/// # Errors
/// [`BackendError::MissingModelFiles`] naming the missing files.
pub fn check_model_dir(dir: &Path, origin: String) -> Result<PathBuf, BackendError> {
    let missing = crate::model_files::missing_files(dir, &REQUIRED_FILES);
    if missing.is_empty() {
        return Ok(dir.to_path_buf());
    }
    let convertible = (missing.contains(&"model.safetensors")
        && dir.join("pytorch_model.bin").is_file())
        || (missing.contains(&"tokenizer.json")
            && dir.join("vocab.json").is_file()
            && dir.join("merges.txt").is_file());
    Err(BackendError::MissingModelFiles {
        model: MODEL,
        dir: dir.to_path_buf(),
        origin,
        missing,
        hint: if convertible {
            CLIP_CONVERT_HINT
        } else {
            CLIP_INSTALL_HINT
        },
    })
}

impl ClipModel {
    /// Loads the model in `dir` (`config.json`, `model.safetensors`, `tokenizer.json`) onto
    /// `device` (see [`crate::ComputeDevice::open`]), its weights converted to `dtype`, the type
    /// both towers compute in (their inputs and outputs stay f32).
    ///
    /// # Errors
    /// [`BackendError::MissingModelFiles`] when a file is missing,
    /// [`BackendError::InvalidModelFile`] when one cannot be read or does not describe a CLIP
    /// model (wrong `model_type`, tensor names or shapes that disagree with `config.json`).
    pub fn load(dir: &Path, device: &Device, dtype: ModelDtype) -> Result<Self, BackendError> {
        let dir = check_model_dir(dir, "the caller".to_owned())?;
        let config_path = dir.join("config.json");
        let text = crate::model_files::read_text(&config_path)?;
        let config =
            ClipConfig::from_json(&text).map_err(|source| BackendError::InvalidModelConfig {
                path: config_path.clone(),
                source,
            })?;

        let tokenizer_path = dir.join("tokenizer.json");
        let bad_tokenizer = |reason: String| BackendError::InvalidModelFile {
            path: tokenizer_path.clone(),
            reason,
        };
        let mut tokenizer = Tokenizer::from_file(&tokenizer_path)
            .map_err(|e| bad_tokenizer(format!("cannot load the tokenizer: {e}")))?;
        // Truncated to the text positions, end token kept; padding is done per batch here.
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: config.text.max_position_embeddings,
                ..TruncationParams::default()
            }))
            .map_err(|e| bad_tokenizer(format!("cannot set truncation: {e}")))?;
        tokenizer.with_padding(None);
        let vocab = tokenizer.get_vocab_size(true);
        if vocab > config.text.vocab_size {
            return Err(bad_tokenizer(format!(
                "it has {vocab} tokens but config.json's text_config.vocab_size is {}",
                config.text.vocab_size
            )));
        }

        let device = device.clone();
        let weights_path = dir.join("model.safetensors");
        let weights = candle_core::safetensors::load(&weights_path, &device).map_err(|e| {
            BackendError::InvalidModelFile {
                path: weights_path.clone(),
                reason: format!("cannot read the weights: {e}"),
            }
        })?;
        let vb = VarBuilder::from_tensors(weights, dtype.candle(), &device);
        let mismatch = |e: candle_core::Error| BackendError::InvalidModelFile {
            path: weights_path.clone(),
            reason: format!("the weights do not match config.json: {e}"),
        };
        let vision =
            VisionTower::load(&vb, &config.vision, config.projection_dim).map_err(mismatch)?;
        let text = TextTower::load(&vb, &config.text, config.projection_dim).map_err(mismatch)?;
        Ok(Self {
            config,
            vision,
            text,
            tokenizer,
            device,
            dtype: dtype.candle(),
            dir,
        })
    }

    /// The parsed `config.json`.
    pub fn config(&self) -> &ClipConfig {
        &self.config
    }

    /// The model folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Dimension of the joint embedding space.
    pub fn projection_dim(&self) -> usize {
        self.config.projection_dim
    }

    /// Side of the square image the image tower takes, in pixels.
    pub fn image_size(&self) -> usize {
        self.config.vision.image_size
    }

    /// The token ids of `text`: start token, text, end token, truncated to
    /// `max_position_embeddings` tokens.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when the tokenizer fails or gives no token at all.
    pub fn tokenize(&self, text: &str) -> Result<Vec<u32>, BackendError> {
        let encoding = self
            .tokenizer
            .encode(text, true)
            .map_err(|e| inference(format!("tokenising {text:?}"), e.to_string()))?;
        let ids = encoding.get_ids().to_vec();
        if ids.is_empty() {
            return Err(inference(
                format!("tokenising {text:?}"),
                "the tokenizer gave no tokens (does tokenizer.json add the start and end tokens?)",
            ));
        }
        Ok(ids)
    }

    /// `get_image_features`: the projected, not normalised, embedding of each image of
    /// `pixels`, `batch x 3 x S x S` normalised values (S = [`ClipModel::image_size`]), row-major.
    ///
    /// # Errors
    /// [`BackendError::Inference`] for a length that is not `batch x 3 x S x S`, or a failing model.
    pub fn image_features(
        &self,
        pixels: &[f32],
        batch: usize,
    ) -> Result<Vec<Vec<f32>>, BackendError> {
        let c = &self.config.vision;
        let per_image = c.num_channels * c.image_size * c.image_size;
        let what = || format!("embedding {batch} image(s)");
        if batch == 0 {
            return Ok(Vec::new());
        }
        if pixels.len() != batch * per_image {
            return Err(inference(
                what(),
                format!(
                    "{} values for {batch} image(s) of {}x{}x{} ({} expected)",
                    pixels.len(),
                    c.num_channels,
                    c.image_size,
                    c.image_size,
                    batch * per_image
                ),
            ));
        }
        // Images go through the tower in groups whose largest activation (the MLP's) stays
        // under GROUP_BYTES: the element-wise passes (bias, activation, softmax, norms) then work
        // in cache, and the allocator reuses its buffers instead of mapping fresh pages each
        // call; that gains more than larger matrix products do.
        let tokens = self.config.grid() * self.config.grid() + 1;
        let widest = c.intermediate_size.max(3 * c.hidden_size);
        let group = if self.device.is_cpu() {
            (GROUP_BYTES / (tokens * widest * 4).max(1)).max(1)
        } else {
            // A GPU wants the whole batch in one call; its memory is bounded by `batch_size`.
            usize::MAX
        };
        self.image_features_in_groups(pixels, group)
            .map_err(|e| BackendError::Inference {
                what: what(),
                source: Box::new(e),
            })
    }

    /// [`ClipModel::image_features`] of checked input, `group` images per tower call.
    fn image_features_in_groups(
        &self,
        pixels: &[f32],
        group: usize,
    ) -> candle_core::Result<Vec<Vec<f32>>> {
        let c = &self.config.vision;
        let per_image = c.num_channels * c.image_size * c.image_size;
        let mut out = Vec::with_capacity(pixels.len() / per_image.max(1));
        for chunk in pixels.chunks(group.max(1) * per_image) {
            let x = Tensor::from_slice(
                chunk,
                (
                    chunk.len() / per_image,
                    c.num_channels,
                    c.image_size,
                    c.image_size,
                ),
                &self.device,
            )?
            .to_dtype(self.dtype)?;
            out.extend(
                self.vision
                    .forward(&x)?
                    .to_dtype(DType::F32)?
                    .to_vec2::<f32>()?,
            );
        }
        Ok(out)
    }

    /// `get_text_features` for already tokenised texts (see [`ClipModel::tokenize`]): the
    /// projected, not normalised, embeddings, computed as one right-padded batch.
    ///
    /// # Errors
    /// [`BackendError::Inference`] for an empty or too long sequence, an id outside the
    /// vocabulary, or a failing model.
    pub fn text_features_of_ids(&self, ids: &[Vec<u32>]) -> Result<Vec<Vec<f32>>, BackendError> {
        let what = || format!("embedding {} text(s)", ids.len());
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let t = &self.config.text;
        let len = ids.iter().map(Vec::len).max().unwrap_or(0);
        if len == 0 || len > t.max_position_embeddings {
            return Err(inference(
                what(),
                format!(
                    "token sequences must hold 1 to {} tokens, one has {len}",
                    t.max_position_embeddings
                ),
            ));
        }
        if ids.iter().any(|s| s.is_empty()) {
            return Err(inference(what(), "an empty token sequence"));
        }
        if let Some(bad) = ids
            .iter()
            .flatten()
            .find(|&&id| id as usize >= t.vocab_size)
        {
            return Err(inference(
                what(),
                format!(
                    "token id {bad} is outside the vocabulary of {}",
                    t.vocab_size
                ),
            ));
        }
        let pooled: Vec<usize> = ids.iter().map(|s| self.text.pooled_position(s)).collect();
        let mut flat = Vec::with_capacity(ids.len() * len);
        for s in ids {
            flat.extend_from_slice(s);
            // The pad value never matters: padding sits after the pooled token.
            flat.resize(flat.len() + len - s.len(), 0);
        }
        let run = || -> candle_core::Result<Vec<Vec<f32>>> {
            let x = Tensor::from_vec(flat, (ids.len(), len), &self.device)?;
            self.text
                .forward(&x, &pooled)?
                .to_dtype(DType::F32)?
                .to_vec2::<f32>()
        };
        run().map_err(|e| BackendError::Inference {
            what: what(),
            source: Box::new(e),
        })
    }

    /// `get_text_features` of `texts`: tokenised, then [`ClipModel::text_features_of_ids`].
    ///
    /// # Errors
    /// As [`ClipModel::tokenize`] and [`ClipModel::text_features_of_ids`].
    pub fn text_features(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        let ids = texts
            .iter()
            .map(|t| self.tokenize(t))
            .collect::<Result<Vec<_>, _>>()?;
        self.text_features_of_ids(&ids)
    }
}

fn inference(what: String, reason: impl Into<String>) -> BackendError {
    BackendError::Inference {
        what,
        source: reason.into().into(),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_are_transformers_defaults() {
        let c = ClipConfig::from_json("{}").unwrap();
        assert_eq!(c.projection_dim, 512);
        assert_eq!(c.text.vocab_size, 49408);
        assert_eq!(c.text.max_position_embeddings, 77);
        assert_eq!(c.text.eos_token_id, 49407);
        assert_eq!(c.vision.patch_size, 32);
        assert_eq!(c.vision.image_size, 224);
        assert_eq!(c.vision.hidden_act, Activation::QuickGelu);
        assert_eq!(c.grid(), 7);
    }

    #[test]
    fn legacy_config_dicts_override_and_sizes_may_be_pairs() {
        let c = ClipConfig::from_json(
            r#"{"model_type": "clip", "projection_dim": 768,
                "text_config": {"hidden_act": "quick_gelu", "eos_token_id": 2},
                "text_config_dict": {"hidden_act": "gelu", "hidden_size": 768, "num_attention_heads": 12},
                "vision_config": {"image_size": [336, 336], "patch_size": 14, "hidden_size": 1024,
                                  "num_attention_heads": 16, "hidden_act": "gelu_pytorch_tanh"}}"#,
        )
        .unwrap();
        assert_eq!(c.text.hidden_act, Activation::Gelu);
        assert_eq!(c.text.hidden_size, 768);
        assert_eq!(c.text.eos_token_id, LEGACY_EOS_TOKEN_ID);
        assert_eq!(c.vision.image_size, 336);
        assert_eq!(c.vision.hidden_act, Activation::GeluTanh);
        assert_eq!(c.grid(), 24);
    }

    #[test]
    fn bad_configs_name_the_key() {
        let err = |json: &str| ClipConfig::from_json(json).unwrap_err().to_string();
        assert!(err(r#"{"model_type": "siglip"}"#).contains("model_type is \"siglip\""));
        assert!(
            err(r#"{"vision_config": {"hidden_act": "relu"}}"#)
                .contains("vision_config.hidden_act is \"relu\"")
        );
        assert!(err(r#"{"vision_config": {"image_size": [224, 160]}}"#).contains("only square"));
        assert!(
            err(r#"{"vision_config": {"image_size": 100, "patch_size": 16}}"#)
                .contains("not a multiple of patch_size")
        );
        assert!(
            err(r#"{"text_config": {"hidden_size": 30}}"#)
                .contains("text_config.hidden_size 30 is not a multiple")
        );
        assert!(
            err(r#"{"text_config": {"eos_token_id": [2, 3]}}"#)
                .contains("text_config.eos_token_id")
        );
        assert!(err(r#"{"projection_dim": -1}"#).contains("projection_dim is -1"));
        assert!(err("[1]").contains("expected an object"));
    }

    #[test]
    fn grouping_images_does_not_change_their_features() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/clip/tiny-gelu");
        let model = ClipModel::load(&dir, &Device::Cpu, ModelDtype::F32).unwrap();
        let pixels: Vec<f32> = (0..5 * 3 * 32 * 32)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
        let all = model.image_features(&pixels, 5).unwrap();
        assert_eq!(all.len(), 5);
        for group in [1, 2, 3] {
            let grouped = model.image_features_in_groups(&pixels, group).unwrap();
            assert_eq!(grouped.len(), 5);
            for (a, b) in all.iter().zip(&grouped) {
                assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5));
            }
        }
        // Different images give different features (the check above could not pass vacuously).
        assert!(
            all[0]
                .iter()
                .zip(&all[1])
                .any(|(x, y)| (x - y).abs() > 1e-3)
        );
    }

    #[test]
    fn missing_files_name_themselves_and_the_way_to_get_them() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("config.json"), "{}").unwrap();
        let message = check_model_dir(dir.path(), "[encoder] model_dir".to_owned())
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("lacks model.safetensors, tokenizer.json;"),
            "{message}"
        );
        assert!(
            message.contains("huggingface-cli download openai/clip-vit-base-patch16"),
            "{message}"
        );

        // The older layout gets the conversion line instead.
        std::fs::write(dir.path().join("pytorch_model.bin"), "").unwrap();
        let message = check_model_dir(dir.path(), "[encoder] model_dir".to_owned())
            .unwrap_err()
            .to_string();
        assert!(message.contains("pytorch_model.bin"), "{message}");
        assert!(message.contains("save_pretrained"), "{message}");
    }
}
