//! RADIOv2.5 on candle: the CPE ViT trunk, RayFronts' NACLIP last block and the adaptor MLP.
//!
//! Why it exists: NARADIO is RADIO's trunk with its last attention replaced (RayFronts'
//! `GaussKernelAttn`), read out through the `siglip` adaptor's summary MLP; this module is that
//! forward pass, kept numerically identical to NVlabs/RADIO + RayFronts (see
//! `docs/notes/naradio.md` and the goldens of `goldens/naradio/make_goldens.py`). It owns the model
//! folder's `config.json` + `radio.safetensors` (written by `goldens/naradio/convert_radio.py`),
//! the cropped position embeddings and the Gaussian spatial prior.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{LayerNorm, Module};
use serde::Deserialize;

use crate::ModelDtype;
use crate::attention::Scores;
use crate::error::BackendError;
use crate::vit::{Activation, Attention, Block, Linear, Mlp, Weights, fused_attention};

/// The model name in error messages.
pub const MODEL: &str = "NARADIO (RADIOv2.5 + SigLIP)";

/// The files of a NARADIO model folder.
pub const REQUIRED_FILES: [&str; 5] = [
    "config.json",
    "radio.safetensors",
    "text/config.json",
    "text/model.safetensors",
    "text/tokenizer.json",
];

/// How a user gets a NARADIO model folder.
pub const NARADIO_INSTALL_HINT: &str = "make one with vlem-backends/goldens/naradio/convert_radio.py \
     --version radio_v2.5-l --out DIR (or radio_v2.5-b); it needs Python with torch, timm, einops, \
     open_clip_torch and safetensors and the network once: it loads RADIO through torch.hub exactly \
     as RayFronts does, which downloads radio-v2.5-l_half.pth.tar from huggingface.co/nvidia/RADIO \
     and the SigLIP text tower timm/ViT-SO400M-14-SigLIP-384; then set [encoder] model_dir = DIR \
     or VLEM_NARADIO_DIR";

/// The model folder's `config.json`, as `convert_radio.py` writes it.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct RadioConfig {
    /// `vlem-naradio-1`.
    pub format: String,
    /// Patch side in pixels (16).
    pub patch_size: usize,
    /// Token width (768 for B/16, 1024 for L/16).
    pub embed_dim: usize,
    /// Number of blocks.
    pub depth: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Hidden width of the block MLPs.
    pub mlp_hidden: usize,
    /// Whether the fused qkv projection has a bias.
    pub qkv_bias: bool,
    /// Whether the blocks have layer scales (`ls1.gamma`, `ls2.gamma`).
    pub layer_scale: bool,
    /// LayerNorm epsilon of the blocks and the final norm.
    pub layer_norm_eps: f64,
    /// Whether the trunk ends with its LayerNorm (`args.model_norm`).
    pub final_norm: bool,
    /// `(rows, cols)` of the learnt position-embedding table.
    pub pos_grid: [usize; 2],
    /// Summary (cls) tokens, one per teacher.
    pub num_cls_tokens: usize,
    /// Register tokens after the cls tokens.
    pub num_registers: usize,
    /// The cls tokens that make up the summary, in order.
    pub summary_idxs: Vec<usize>,
    /// The adaptor's name (`siglip`).
    pub adaptor: String,
    /// The adaptor's token slot: which chunk of the summary it reads.
    pub adaptor_token_slot: usize,
    /// `v1` (`MLP`) or `v2` (`MLP2`).
    pub adaptor_mlp: String,
    /// LayerNorm epsilon of the adaptor MLP.
    pub adaptor_layer_norm_eps: f64,
    /// Whether `radio.safetensors` holds a feature normaliser.
    pub feature_normalizer: bool,
    /// RADIO's input conditioner: channel mean of `[0, 1]` RGB.
    pub input_mean: [f32; 3],
    /// RADIO's input conditioner: channel standard deviation.
    pub input_std: [f32; 3],
}

/// How the Gaussian prior of the NACLIP block lays the patch tokens out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GaussianGrid {
    /// As RayFronts' `GaussKernelAttn` builds it: for an `h × w` patch grid the prior is the one
    /// of a `w`-row, `h`-column grid (it passes `(W/16, H/16)` where NACLIP passes `(H/16, W/16)`).
    /// The same as `image` for square inputs.
    #[default]
    Rayfronts,
    /// NACLIP's: the true image neighbourhood of every patch.
    Image,
}

/// The last block of the trunk.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LastBlock {
    /// RADIO's own block (plain self-attention).
    Plain,
    /// RayFronts' NACLIP change: attention logits `k·kᵀ/√d + prior`, the prior a Gaussian of
    /// standard deviation `std` patches over the grid laid out as `grid` says (zero for the
    /// prefix tokens). `reduced`: NACLIP's own "reduced" block (the attention output alone, no
    /// residual, no MLP); RayFronts keeps the residual and the MLP (`reduced = false`).
    Naclip {
        /// Standard deviation of the Gaussian, in patches (RayFronts: 7).
        std: f64,
        /// Token layout of the prior.
        grid: GaussianGrid,
        /// Drop the residual and the MLP after the attention.
        reduced: bool,
    },
}

/// The Gaussian prior added to the attention logits of the NACLIP block: `(prefix + h·w)²`
/// values, row-major; zero on the `prefix` rows and columns, and between patches `s`, `t` at
/// grid offset `(Δ₁, Δ₂)` `exp(-(Δ₁² + Δ₂²) / (2 std²))`, the grid being `rows × cols` for
/// [`GaussianGrid::Image`] and `cols × rows` (the tokens still row-major) for
/// [`GaussianGrid::Rayfronts`].
pub fn gaussian_prior(
    rows: usize,
    cols: usize,
    std: f64,
    grid: GaussianGrid,
    prefix: usize,
) -> Vec<f32> {
    // The grid the prior sees: d1 rows of d2 tokens.
    let d2 = match grid {
        GaussianGrid::Image => cols,
        GaussianGrid::Rayfronts => rows,
    }
    .max(1);
    let n = rows * cols;
    let total = prefix + n;
    let scale = 1.0 / (2.0 * std * std);
    let mut out = vec![0.0f32; total * total];
    for s in 0..n {
        let (a1, a2) = ((s / d2) as f64, (s % d2) as f64);
        let row = &mut out[(prefix + s) * total + prefix..(prefix + s + 1) * total];
        for (t, v) in row.iter_mut().enumerate() {
            let (b1, b2) = ((t / d2) as f64, (t % d2) as f64);
            *v = (-((a1 - b1).powi(2) + (a2 - b2).powi(2)) * scale).exp() as f32;
        }
    }
    out
}

/// The `out × input` matrix of PyTorch's bilinear resize (`align_corners=False`, no antialias)
/// along one axis, first `keep` rows only (RADIO crops the top-left of the resized table).
fn resize_matrix(input: usize, out: usize, keep: usize) -> Vec<f32> {
    let mut m = vec![0.0f32; keep * input];
    let scale = input as f64 / out as f64;
    for (i, row) in m.chunks_exact_mut(input.max(1)).enumerate() {
        let src = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(input - 1);
        let i1 = (i0 + 1).min(input - 1);
        let l = (src - i0 as f64) as f32;
        row[i0] += 1.0 - l;
        row[i1] += l;
    }
    m
}

/// The adaptor's summary MLP (`head_mlp`), which maps RADIO features into the teacher's space.
#[derive(Clone, Debug)]
enum AdaptorMlp {
    /// `MLP2`: `fc1`, residual `[LN, GELU, Linear]` blocks, then `[LN, GELU, Linear]`.
    V2 {
        fc1: Linear,
        blocks: Vec<(LayerNorm, Linear)>,
        final_norm: LayerNorm,
        final_linear: Linear,
    },
    /// `MLP`: `fc1, LN, ReLU`, `[Linear, LN, ReLU]*`, `fc2`.
    V1 {
        fc1: Linear,
        norm: LayerNorm,
        inner: Vec<(Linear, LayerNorm)>,
        fc2: Linear,
    },
}

impl AdaptorMlp {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Self::V2 {
                fc1,
                blocks,
                final_norm,
                final_linear,
            } => {
                let mut x = fc1.forward(x)?;
                for (norm, linear) in blocks {
                    let y = linear.forward(&crate::kernels::gelu_erf(&norm.forward(&x)?)?)?;
                    x = (x + y)?;
                }
                final_linear.forward(&crate::kernels::gelu_erf(&final_norm.forward(&x)?)?)
            }
            Self::V1 {
                fc1,
                norm,
                inner,
                fc2,
            } => {
                let mut x = norm.forward(&fc1.forward(x)?)?.relu()?;
                for (linear, norm) in inner {
                    x = norm.forward(&linear.forward(&x)?)?.relu()?;
                }
                fc2.forward(&x)
            }
        }
    }

    fn output_dim(&self) -> candle_core::Result<usize> {
        match self {
            Self::V2 { final_linear, .. } => final_linear.outputs(),
            Self::V1 { fc2, .. } => fc2.outputs(),
        }
    }
}

/// What the trunk returns for a batch.
#[derive(Clone, Debug)]
pub struct RadioOutput {
    /// `(batch, summary_idxs.len() · embed_dim)`: the summary tokens, concatenated.
    pub summary: Tensor,
    /// `(batch, rows · cols, embed_dim)`: the patch tokens, row-major.
    pub features: Tensor,
}

type Cache = Arc<Mutex<HashMap<(usize, usize), Tensor>>>;
/// Priors by grid rows, cols, the bits of the std, and whether the layout is the image's.
type PriorCache = Arc<Mutex<HashMap<(usize, usize, u64, bool), Tensor>>>;

/// RADIOv2.5 with its adaptor summary MLP, ready to run on the CPU in f32. Thread-safe.
#[derive(Clone)]
pub struct RadioModel {
    config: RadioConfig,
    /// `(3·p·p, embed_dim)`.
    patch_weight_t: Tensor,
    /// `(pos rows, pos cols · embed_dim)`.
    pos_table: Tensor,
    /// `(1, cls + registers, embed_dim)`.
    prefix: Tensor,
    blocks: Vec<Block>,
    norm: Option<LayerNorm>,
    normalizer: Option<(Tensor, Tensor)>,
    adaptor: AdaptorMlp,
    pos_cache: Cache,
    prior_cache: PriorCache,
    device: Device,
    /// What the trunk and adaptor compute in; inputs are converted on the way in.
    dtype: DType,
    dir: PathBuf,
}

impl std::fmt::Debug for RadioModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RadioModel")
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
    crate::model_files::require_files(dir, &REQUIRED_FILES, MODEL, origin, NARADIO_INSTALL_HINT)
}

fn invalid(path: &Path, reason: impl Into<String>) -> BackendError {
    BackendError::InvalidModelFile {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn inference(what: &str, e: candle_core::Error) -> BackendError {
    BackendError::Inference {
        what: what.to_owned(),
        source: Box::new(e),
    }
}

impl RadioModel {
    /// Loads `config.json` and `radio.safetensors` of the NARADIO folder `dir` onto `device`, the
    /// weights converted to `dtype`, the type the trunk and adaptor compute in.
    ///
    /// # Errors
    /// [`BackendError::MissingModelFiles`] when a file of the folder is missing;
    /// [`BackendError::InvalidModelFile`] when one cannot be read or disagrees with the config.
    pub fn load(dir: &Path, device: &Device, dtype: ModelDtype) -> Result<Self, BackendError> {
        let dir = check_model_dir(dir, "the caller".to_owned())?;
        let config_path = dir.join("config.json");
        let text = crate::model_files::read_text(&config_path)?;
        let config: RadioConfig =
            serde_json::from_str(&text).map_err(|e| invalid(&config_path, e.to_string()))?;
        if config.format != "vlem-naradio-1" {
            return Err(invalid(
                &config_path,
                format!("format {:?}, expected \"vlem-naradio-1\"", config.format),
            ));
        }
        let c = &config;
        let bad_shape = c.embed_dim == 0
            || c.num_heads == 0
            || !c.embed_dim.is_multiple_of(c.num_heads)
            || c.patch_size == 0
            || c.pos_grid.contains(&0)
            || c.summary_idxs.iter().any(|&i| i >= c.num_cls_tokens)
            || c.adaptor_token_slot >= c.summary_idxs.len()
            || c.input_std.contains(&0.0);
        if bad_shape {
            return Err(invalid(&config_path, "inconsistent model shape"));
        }
        let weights_path = dir.join("radio.safetensors");
        let tensors = candle_core::safetensors::load(&weights_path, device)
            .map_err(|e| invalid(&weights_path, format!("cannot read it: {e}")))?;
        let w = Weights::new(tensors, device, dtype.candle());
        Self::from_weights(config, &w, dir.clone()).map_err(|reason| invalid(&weights_path, reason))
    }

    fn from_weights(config: RadioConfig, w: &Weights, dir: PathBuf) -> Result<Self, String> {
        let device = w.device().clone();
        let c = &config;
        let e = c.embed_dim;
        let p = c.patch_size;
        fn ce(what: &'static str) -> impl Fn(candle_core::Error) -> String {
            move |err| format!("{what}: {err}")
        }
        let patch = w.get("patch_generator.embedder.weight", &[e, 3 * p * p])?;
        let patch_weight_t = patch
            .t()
            .and_then(|t| t.contiguous())
            .map_err(ce("patch"))?;
        let [gr, gc] = c.pos_grid;
        let pos_table = w
            .get("patch_generator.pos_embed", &[1, gr * gc, e])?
            .reshape((gr, gc * e))
            .map_err(ce("pos_embed"))?;
        let prefix_n = c.num_cls_tokens + c.num_registers;
        let prefix = w
            .get("patch_generator.cls_token.token", &[prefix_n, e])?
            .unsqueeze(0)
            .map_err(ce("cls tokens"))?;
        let eps = c.layer_norm_eps;
        let mut blocks = Vec::with_capacity(c.depth);
        for i in 0..c.depth {
            let b = format!("blocks.{i}");
            let scale = |n: &str| -> Result<Option<Tensor>, String> {
                if c.layer_scale {
                    Ok(Some(w.get(&format!("{b}.{n}.gamma"), &[e])?))
                } else {
                    Ok(None)
                }
            };
            blocks.push(Block {
                norm1: w.layer_norm(&format!("{b}.norm1"), e, eps)?,
                attention: fused_attention(
                    w.linear(&format!("{b}.attn.qkv"), e, 3 * e, c.qkv_bias)?,
                    w.linear(&format!("{b}.attn.proj"), e, e, true)?,
                    c.num_heads,
                ),
                scale1: scale("ls1")?,
                norm2: w.layer_norm(&format!("{b}.norm2"), e, eps)?,
                mlp: Mlp::Plain {
                    up: w.linear(&format!("{b}.mlp.fc1"), e, c.mlp_hidden, true)?,
                    down: w.linear(&format!("{b}.mlp.fc2"), c.mlp_hidden, e, true)?,
                    act: Activation::Gelu,
                },
                scale2: scale("ls2")?,
            });
        }
        let norm = if c.final_norm {
            Some(w.layer_norm("norm", e, eps)?)
        } else {
            None
        };
        let normalizer = if c.feature_normalizer {
            let tx = w.get("feature_normalizer.tx", &[e, e])?;
            Some((
                w.get("feature_normalizer.mean", &[e])?,
                tx.t().and_then(|t| t.contiguous()).map_err(ce("tx"))?,
            ))
        } else {
            None
        };
        let adaptor = load_adaptor(c, w)?;
        Ok(Self {
            config,
            patch_weight_t,
            pos_table,
            prefix,
            blocks,
            norm,
            normalizer,
            adaptor,
            pos_cache: Arc::default(),
            prior_cache: Arc::default(),
            device,
            dtype: w.dtype(),
            dir,
        })
    }

    /// A model of the shape `config` with random weights and a `v2` adaptor of `adaptor_hidden`
    /// → `adaptor_out` with one inner block, on `device` in `dtype`: for speed measurements only.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for an inconsistent shape.
    #[doc(hidden)]
    pub fn random(
        config: RadioConfig,
        adaptor_hidden: usize,
        adaptor_out: usize,
        device: &Device,
        dtype: ModelDtype,
    ) -> Result<Self, BackendError> {
        let c = &config;
        let (e, p, h) = (c.embed_dim, c.patch_size, c.mlp_hidden);
        let mut shapes: Vec<(String, Vec<usize>)> = vec![
            ("patch_generator.embedder.weight".into(), vec![e, 3 * p * p]),
            (
                "patch_generator.pos_embed".into(),
                vec![1, c.pos_grid[0] * c.pos_grid[1], e],
            ),
            (
                "patch_generator.cls_token.token".into(),
                vec![c.num_cls_tokens + c.num_registers, e],
            ),
            ("norm.weight".into(), vec![e]),
            ("norm.bias".into(), vec![e]),
        ];
        for i in 0..c.depth {
            let b = format!("blocks.{i}");
            for (n, s) in [
                ("norm1.weight", vec![e]),
                ("norm1.bias", vec![e]),
                ("attn.qkv.weight", vec![3 * e, e]),
                ("attn.qkv.bias", vec![3 * e]),
                ("attn.proj.weight", vec![e, e]),
                ("attn.proj.bias", vec![e]),
                ("norm2.weight", vec![e]),
                ("norm2.bias", vec![e]),
                ("mlp.fc1.weight", vec![h, e]),
                ("mlp.fc1.bias", vec![h]),
                ("mlp.fc2.weight", vec![e, h]),
                ("mlp.fc2.bias", vec![e]),
                ("ls1.gamma", vec![e]),
                ("ls2.gamma", vec![e]),
            ] {
                shapes.push((format!("{b}.{n}"), s));
            }
        }
        let (ah, ao) = (adaptor_hidden, adaptor_out);
        for (n, s) in [
            ("fc1.weight", vec![ah, e]),
            ("fc1.bias", vec![ah]),
            ("blocks.0.0.weight", vec![ah]),
            ("blocks.0.0.bias", vec![ah]),
            ("blocks.0.2.weight", vec![ah, ah]),
            ("blocks.0.2.bias", vec![ah]),
            ("final.0.weight", vec![ah]),
            ("final.0.bias", vec![ah]),
            ("final.2.weight", vec![ao, ah]),
            ("final.2.bias", vec![ao]),
        ] {
            shapes.push((format!("adaptor.{n}"), s));
        }
        let mut tensors = HashMap::new();
        for (name, shape) in shapes {
            let fan_in = if shape.len() == 2 { shape[1] } else { 1 };
            let std = (1.0 / fan_in as f64).sqrt() as f32;
            let t = Tensor::randn(0f32, std, shape, device)
                .map_err(|e| BackendError::InvalidParams(e.to_string()))?;
            tensors.insert(name, t);
        }
        let config = RadioConfig {
            adaptor_mlp: "v2".into(),
            ..config
        };
        let weights = Weights::new(tensors, device, dtype.candle());
        Self::from_weights(config, &weights, PathBuf::new()).map_err(BackendError::InvalidParams)
    }

    /// The folder's `config.json`.
    pub fn config(&self) -> &RadioConfig {
        &self.config
    }

    /// The width of the adaptor's output (the text space; 1152 for SigLIP SO400M).
    ///
    /// # Errors
    /// Never in practice (the width is read off a loaded tensor).
    pub fn adaptor_dim(&self) -> Result<usize, BackendError> {
        self.adaptor
            .output_dim()
            .map_err(|e| inference("the adaptor width", e))
    }

    /// The device the model runs on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The type the model computes in, and its outputs'.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// RADIO's input conditioning of `[0, 1]` RGB `(batch, 3, h, w)`: `(x - mean) / std`, in
    /// `x`'s type.
    ///
    /// # Errors
    /// [`BackendError::Inference`] for a tensor of another shape.
    pub fn condition(&self, x: &Tensor) -> Result<Tensor, BackendError> {
        let run = || -> candle_core::Result<Tensor> {
            let channels = |v: &[f32; 3]| {
                Tensor::new(v, &self.device)?
                    .reshape((1, 3, 1, 1))?
                    .to_dtype(x.dtype())
            };
            let (mean, std) = (
                channels(&self.config.input_mean)?,
                channels(&self.config.input_std)?,
            );
            x.broadcast_sub(&mean)?.broadcast_div(&std)
        };
        run().map_err(|e| inference("conditioning the input", e))
    }

    /// The position embeddings of an `rows × cols` grid, `(rows·cols, embed_dim)`: the table
    /// resized bilinearly to `m × m`, `m = max(rows, cols)`, and its top-left `rows × cols` kept.
    fn pos_embed(&self, rows: usize, cols: usize) -> candle_core::Result<Tensor> {
        if let Ok(cache) = self.pos_cache.lock()
            && let Some(t) = cache.get(&(rows, cols))
        {
            return Ok(t.clone());
        }
        let [gr, gc] = self.config.pos_grid;
        let e = self.config.embed_dim;
        let t = if (rows, cols) == (gr, gc) {
            self.pos_table.reshape((rows * cols, e))?
        } else {
            let m = rows.max(cols);
            let ry = Tensor::from_vec(resize_matrix(gr, m, rows), (rows, gr), &self.device)?
                .to_dtype(self.dtype)?;
            let rx = Tensor::from_vec(resize_matrix(gc, m, cols), (1, cols, gc), &self.device)?
                .to_dtype(self.dtype)?;
            // (rows, gc·e) -> (rows, gc, e), then each row through the column resize.
            let y = ry.matmul(&self.pos_table)?.reshape((rows, gc, e))?;
            rx.broadcast_as((rows, cols, gc))?
                .contiguous()?
                .matmul(&y)?
                .reshape((rows * cols, e))?
        };
        if let Ok(mut cache) = self.pos_cache.lock() {
            cache.insert((rows, cols), t.clone());
        }
        Ok(t)
    }

    fn prior(
        &self,
        rows: usize,
        cols: usize,
        std: f64,
        grid: GaussianGrid,
    ) -> candle_core::Result<Tensor> {
        let key = (rows, cols, std.to_bits(), grid == GaussianGrid::Image);
        if let Ok(cache) = self.prior_cache.lock()
            && let Some(t) = cache.get(&key)
        {
            return Ok(t.clone());
        }
        let prefix = self.config.num_cls_tokens + self.config.num_registers;
        let n = prefix + rows * cols;
        let t = Tensor::from_vec(
            gaussian_prior(rows, cols, std, grid, prefix),
            (n, n),
            &self.device,
        )?
        .to_dtype(self.dtype)?;
        if let Ok(mut cache) = self.prior_cache.lock() {
            cache.insert(key, t.clone());
        }
        Ok(t)
    }

    /// The trunk on conditioned pixels `(batch, 3, h, w)` (h, w multiples of the patch size; any
    /// float type, converted to the model's), with `last` as its last block. The outputs are in
    /// the model's [`dtype`](Self::dtype).
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for a wrong shape; [`BackendError::Inference`].
    pub fn forward(&self, x: &Tensor, last: LastBlock) -> Result<RadioOutput, BackendError> {
        let (batch, channels, h, w) = x
            .dims4()
            .map_err(|e| BackendError::InvalidInput(format!("pixels: {e}")))?;
        let p = self.config.patch_size;
        if channels != 3 || !h.is_multiple_of(p) || !w.is_multiple_of(p) || h == 0 || w == 0 {
            return Err(BackendError::InvalidInput(format!(
                "pixels of shape {:?}: need (batch, 3, h, w), h and w positive multiples of {p}",
                x.dims()
            )));
        }
        self.forward_inner(x, batch, h / p, w / p, last)
            .map_err(|e| inference("the RADIO trunk", e))
    }

    fn forward_inner(
        &self,
        x: &Tensor,
        batch: usize,
        rows: usize,
        cols: usize,
        last: LastBlock,
    ) -> candle_core::Result<RadioOutput> {
        let c = &self.config;
        let (p, e) = (c.patch_size, c.embed_dim);
        // b c (rows p) (cols p) -> b (rows cols) (c p p)
        let patches = x
            .to_dtype(self.dtype)?
            .reshape((batch, 3, rows, p, cols, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((batch * rows * cols, 3 * p * p))?
            .matmul(&self.patch_weight_t)?
            .reshape((batch, rows * cols, e))?;
        let patches = patches.broadcast_add(&self.pos_embed(rows, cols)?)?;
        let prefix = self.prefix.broadcast_as((batch, self.prefix.dim(1)?, e))?;
        let mut y = Tensor::cat(&[&prefix, &patches], 1)?;
        let n_blocks = self.blocks.len();
        for (i, block) in self.blocks.iter().enumerate() {
            y = match last {
                LastBlock::Naclip { std, grid, reduced } if i + 1 == n_blocks => {
                    let prior = self.prior(rows, cols, std, grid)?;
                    naclip_block(block, &y, &prior, reduced)?
                }
                _ => block.forward(&y, None, None)?,
            };
        }
        if let Some(norm) = &self.norm {
            y = norm.forward(&y)?;
        }
        let skip = c.num_cls_tokens + c.num_registers;
        let mut features = y.narrow(1, skip, rows * cols)?;
        if let Some((mean, tx_t)) = &self.normalizer {
            let f = features.broadcast_sub(mean)?;
            features = f
                .reshape((batch * rows * cols, e))?
                .matmul(tx_t)?
                .reshape((batch, rows * cols, e))?;
        }
        let idx: Vec<u32> = c.summary_idxs.iter().map(|&i| i as u32).collect();
        let idx = Tensor::new(idx.as_slice(), &self.device)?;
        let summary = y
            .narrow(1, 0, c.num_cls_tokens)?
            .index_select(&idx, 1)?
            .reshape((batch, c.summary_idxs.len() * e))?;
        Ok(RadioOutput { summary, features })
    }

    /// The adaptor's summary MLP over the last dimension of `x` (patch tokens or summary
    /// chunks, converted to the model's type): RADIO features into the text space.
    ///
    /// # Errors
    /// [`BackendError::Inference`] for a wrong width.
    pub fn adapt(&self, x: &Tensor) -> Result<Tensor, BackendError> {
        x.to_dtype(self.dtype)
            .and_then(|x| self.adaptor.forward(&x))
            .map_err(|e| inference("the adaptor MLP", e))
    }

    /// The adaptor's chunk of a summary `(batch, summary_idxs.len() · embed_dim)`: what
    /// RayFronts' `encode_image_to_vector` reads (`summary[:, C·slot : C·(slot+1)]`).
    ///
    /// # Errors
    /// [`BackendError::Inference`] for a summary of another width.
    pub fn adaptor_summary(&self, summary: &Tensor) -> Result<Tensor, BackendError> {
        let e = self.config.embed_dim;
        summary
            .narrow(D::Minus1, self.config.adaptor_token_slot * e, e)
            .map_err(|err| inference("the adaptor's summary chunk", err))
    }
}

fn load_adaptor(c: &RadioConfig, w: &Weights) -> Result<AdaptorMlp, String> {
    let dims = |name: &str| {
        w.dims(name)
            .filter(|d| d.len() == 2)
            .ok_or_else(|| format!("tensor {name} is missing or not a matrix"))
    };
    let eps = c.adaptor_layer_norm_eps;
    let fc1 = dims("adaptor.fc1.weight")?;
    let (hidden, input) = (fc1[0], fc1[1]);
    if input != c.embed_dim {
        return Err(format!(
            "adaptor.fc1 takes {input} inputs, the trunk gives {}",
            c.embed_dim
        ));
    }
    match c.adaptor_mlp.as_str() {
        "v2" => {
            let mut blocks = Vec::new();
            while w.contains(&format!("adaptor.blocks.{}.0.weight", blocks.len())) {
                let i = blocks.len();
                blocks.push((
                    w.layer_norm(&format!("adaptor.blocks.{i}.0"), hidden, eps)?,
                    w.linear(&format!("adaptor.blocks.{i}.2"), hidden, hidden, true)?,
                ));
            }
            let out = dims("adaptor.final.2.weight")?[0];
            Ok(AdaptorMlp::V2 {
                fc1: w.linear("adaptor.fc1", input, hidden, true)?,
                blocks,
                final_norm: w.layer_norm("adaptor.final.0", hidden, eps)?,
                final_linear: w.linear("adaptor.final.2", hidden, out, true)?,
            })
        }
        "v1" => {
            let mut inner = Vec::new();
            while w.contains(&format!("adaptor.inner.{}.weight", 3 * inner.len())) {
                let i = 3 * inner.len();
                inner.push((
                    w.linear(&format!("adaptor.inner.{i}"), hidden, hidden, true)?,
                    w.layer_norm(&format!("adaptor.inner.{}", i + 1), hidden, eps)?,
                ));
            }
            let out = dims("adaptor.fc2.weight")?[0];
            Ok(AdaptorMlp::V1 {
                fc1: w.linear("adaptor.fc1", input, hidden, true)?,
                norm: w.layer_norm("adaptor.norm", hidden, eps)?,
                inner,
                fc2: w.linear("adaptor.fc2", hidden, out, true)?,
            })
        }
        other => Err(format!(
            "adaptor_mlp {other:?}: only \"v1\" and \"v2\" are supported"
        )),
    }
}

/// RayFronts' last block: `a = proj(softmax(k·kᵀ/√d + prior) · v)` on `norm1 x`, then (unless
/// `reduced`) `x + ls1·a`, `+ ls2·mlp(norm2 ·)` as the timm block it replaces the attention of.
fn naclip_block(
    block: &Block,
    x: &Tensor,
    prior: &Tensor,
    reduced: bool,
) -> candle_core::Result<Tensor> {
    let a = naclip_attention(&block.attention, &block.norm1.forward(x)?, prior)?;
    if reduced {
        return Ok(a);
    }
    let scaled = |y: Tensor, s: &Option<Tensor>| match s {
        Some(s) => y.broadcast_mul(s),
        None => Ok(y),
    };
    let x = (x + scaled(a, &block.scale1)?)?;
    let m = block.mlp.forward(&block.norm2.forward(&x)?)?;
    x + scaled(m, &block.scale2)?
}

/// NACLIP's attention (RayFronts' `GaussKernelAttn.custom_attn`) on `x` `(batch, tokens,
/// width)`: key-key similarity plus the `(tokens, tokens)` `prior`; the query is not used.
pub(crate) fn naclip_attention(
    attention: &Attention,
    x: &Tensor,
    prior: &Tensor,
) -> candle_core::Result<Tensor> {
    attention.forward(x, None, Scores::KeyKey { prior })
}

/// [`naclip_attention`] on one image of `tokens × width` values `x` with a given fused qkv
/// projection (`3·width × width` weight, `3·width` bias) and an identity output projection:
/// for hand-computed tests. Inconsistent shapes give NaNs.
#[doc(hidden)]
pub fn naclip_attention_for_test(
    qkv_weight: &[f32],
    qkv_bias: &[f32],
    x: &[f32],
    width: usize,
    heads: usize,
    prior: &[f32],
) -> Vec<f32> {
    let run = || -> candle_core::Result<Vec<f32>> {
        let device = Device::Cpu;
        let tokens = x.len() / width.max(1);
        let w = Tensor::from_slice(qkv_weight, (3 * width, width), &device)?;
        let b = Tensor::from_slice(qkv_bias, 3 * width, &device)?;
        let attention = fused_attention(
            Linear::new(&w, Some(b))?,
            Linear::new(&Tensor::eye(width, DType::F32, &device)?, None)?,
            heads,
        );
        let x = Tensor::from_slice(x, (1, tokens, width), &device)?;
        let prior = Tensor::from_slice(prior, (tokens, tokens), &device)?;
        naclip_attention(&attention, &x, &prior)?
            .flatten_all()?
            .to_vec1::<f32>()
    };
    run().unwrap_or_else(|_| vec![f32::NAN; x.len()])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resize_matrix_matches_pytorch_bilinear() {
        // F.interpolate(arange(4), size=2, bilinear, align_corners=False) = [0.5, 2.5]:
        // src = (i + 0.5)·2 - 0.5 = 0.5, 2.5.
        let m = resize_matrix(4, 2, 2);
        assert_eq!(m, vec![0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]);
        // Upsampling 2 -> 4: src = -0.25 (clamped to 0), 0.25, 0.75, 1.25 (clamped index).
        let m = resize_matrix(2, 4, 4);
        assert_eq!(m, vec![1.0, 0.0, 0.75, 0.25, 0.25, 0.75, 0.0, 1.0]);
        // Only the kept rows.
        assert_eq!(resize_matrix(2, 4, 1), vec![1.0, 0.0]);
    }
}
