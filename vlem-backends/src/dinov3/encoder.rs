//! The `dinov3` patch encoder (`[encoder] kind = "dinov3"`): DINOv3 ViT-L/16 with the dino.txt
//! heads, one embedding per 16×16 patch of the whole frame.
//!
//! Why it exists: it is the paper's DINO backend ("ViT-Patch-Embeddings"): no region proposer,
//! every pixel gets the bilinear interpolation of the patch grid around it. This module owns
//! finding the three downloads it needs, the frame's input size and normalisation, and the
//! text side with prompt ensembling.
//!
//! Image side: the frame resized (aspect ratio kept, bicubic) so that its shorter side is
//! `short_side` pixels and both sides are multiples of 16, normalised with ImageNet's mean and
//! standard deviation; the backbone's normalised tokens go through the dino.txt vision head; its
//! patch tokens, each L2-normalised as Meta's segmentation notebook does before it compares them
//! with text, form the patch grid ([`PixelEmbeddings::from_patch_grid`]: interpolated bilinearly
//! and normalised again where a pixel is looked up).
//!
//! Text side: each template with the query put in, tokenised ([`super::clip_bpe`]), through the
//! text tower; of the 2048-d text embedding, the second half is the one that pairs with patch
//! tokens (the first pairs with the head's CLS token). Each prompt's half is normalised, the mean
//! over templates normalised again.
//!
//! ```toml
//! [encoder]
//! kind = "dinov3"
//! model_dir = "models/dinov3-vitl16"   # else $VLEM_DINOV3_DIR: config.json, model.safetensors,
//!                                      # dinov3_vitl16_dinotxt_vision_head_and_text_encoder-*.pth,
//!                                      # bpe_simple_vocab_16e6.txt.gz
//! # dinotxt_weights = "other/place/dinotxt.pth"   # instead of the one in model_dir
//! # bpe_vocab = "other/place/bpe_simple_vocab_16e6.txt.gz"   # else model_dir, else open_clip's
//! # short_side = 448                  # input's shorter side in pixels, a multiple of 16
//! # templates = ["a photo of a {}."]
//! # device = "cpu"                   # "cuda", "cuda:N" with feature `cuda`
//! # dtype = "f32"                     # "f16", "bf16": backbone and heads in half precision
//! # tf32 = true                       # on a GPU, f32 matrix products in TF32 (off by default)
//! ```

use std::path::{Path, PathBuf};

use candle_core::{DType, Tensor};
use serde::Deserialize;
use vlem_core::{BuildContext, Encoder, PixelEmbeddings, Region, RgbImage, StageKind};

use super::clip_bpe::{self, ClipBpe};
use super::dinotxt::DinoTxtHeads;
use super::model::{self, Dinov3Backbone};
use crate::error::BackendError;
use crate::patch_input::{IMAGENET_MEAN, IMAGENET_STD, normalised_planes, patch_aligned_size};

/// The name this encoder is registered under.
pub const NAME: &str = "dinov3";

/// The encoder's model in messages.
pub const MODEL: &str = "DINOv3 ViT-L/16 with dino.txt";

/// Environment variable naming the model folder when the config does not.
pub const MODEL_DIR_ENV: &str = "VLEM_DINOV3_DIR";

/// The released dino.txt checkpoint's name up to its hash (`-a442d8f5.pth`).
pub const DINOTXT_FILE_PREFIX: &str = "dinov3_vitl16_dinotxt_vision_head_and_text_encoder";

/// How the dino.txt checkpoint is named in messages.
pub const DINOTXT_FILE: &str = "dinov3_vitl16_dinotxt_vision_head_and_text_encoder-*.pth";

/// The default input's shorter side: 28 patches (a 640×480 frame becomes 592×448, 37×28).
pub const DEFAULT_SHORT_SIDE: u32 = 448;

/// How to get the dino.txt files, for the messages that say they are missing.
pub const DINOTXT_INSTALL_HINT: &str = "dino.txt is not on Hugging Face: request the DINOv3 \
     downloads from Meta (https://ai.meta.com/resources/models-and-libraries/dinov3-downloads/), \
     put dinov3_vitl16_dinotxt_vision_head_and_text_encoder-a442d8f5.pth into the model folder \
     (or name it with dinotxt_weights), and bpe_simple_vocab_16e6.txt.gz too (from the same \
     downloads, or `python3 -m pip install --no-deps open_clip_torch`, which ships it and is \
     found without configuration); the backbone: DINOv3 weights are gated: accept the licence \
     of facebook/dinov3-vitl16-pretrain-lvd1689m on Hugging Face, then on a connected machine \
     `hf download facebook/dinov3-vitl16-pretrain-lvd1689m config.json model.safetensors \
     --local-dir DIR`";

/// Parameters of the encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Dinov3EncoderConfig {
    /// The folder with the ViT-L/16 backbone in the Hugging Face layout (`config.json`,
    /// `model.safetensors`), usually also holding the dino.txt checkpoint and the BPE
    /// vocabulary; relative to the config file's folder. Unset: [`MODEL_DIR_ENV`].
    pub model_dir: Option<PathBuf>,
    /// The dino.txt checkpoint. Unset: the one file in `model_dir` named
    /// [`DINOTXT_FILE`].
    pub dinotxt_weights: Option<PathBuf>,
    /// CLIP's BPE vocabulary. Unset: `model_dir`'s `bpe_simple_vocab_16e6.txt.gz`, else the copy
    /// in the Python package `open_clip`.
    pub bpe_vocab: Option<PathBuf>,
    /// The input's shorter side in pixels, a multiple of 16 (the longer side follows the
    /// frame's aspect ratio). Default [`DEFAULT_SHORT_SIDE`].
    pub short_side: u32,
    /// Prompt templates, each with one `{}` that the query replaces. Default `["{}"]`.
    pub templates: Vec<String>,
    /// Attention heads of the text tower, which the checkpoint does not record. Unset: its
    /// width over 64 (the released tower: 1280 wide, 20 heads). Only other tower shapes need it.
    pub text_heads: Option<usize>,
    /// Where the model runs: `"cpu"` (default), `"cuda"` or `"cuda:N"` (feature `cuda`).
    pub device: crate::ComputeDevice,
    /// What the backbone and both heads compute in: `"f32"` (default), `"f16"` or `"bf16"` (for
    /// a GPU; on the CPU half precision runs through candle's plain ops, slower than f32's).
    pub dtype: crate::ModelDtype,
    /// `true`: on a GPU, f32 matrix products run on TF32 tensor cores (faster, 10-bit mantissa
    /// inputs); `false`: they do not; unset (default): left as it is, off unless a model asked.
    /// One setting per process (see [`crate::ComputeDevice::open_for`]).
    pub tf32: Option<bool>,
}

impl Default for Dinov3EncoderConfig {
    fn default() -> Self {
        Self {
            model_dir: None,
            dinotxt_weights: None,
            bpe_vocab: None,
            short_side: DEFAULT_SHORT_SIDE,
            templates: crate::prompts::default_templates(),
            text_heads: None,
            device: crate::ComputeDevice::Cpu,
            dtype: crate::ModelDtype::F32,
            tf32: None,
        }
    }
}

/// Where the three parts were found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dinov3Files {
    /// The backbone folder.
    pub model_dir: PathBuf,
    /// The dino.txt checkpoint.
    pub dinotxt_weights: PathBuf,
    /// The BPE vocabulary.
    pub bpe_vocab: PathBuf,
}

/// The one dino.txt checkpoint in `dir`, if there is exactly one.
fn find_dinotxt(dir: &Path) -> Option<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| {
            path.is_file()
                && path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|name| {
                        name.starts_with(DINOTXT_FILE_PREFIX) && name.ends_with(".pth")
                    })
        })
        .collect();
    found.sort();
    (found.len() == 1).then(|| found.remove(0))
}

/// Finds the files: see [`Dinov3EncoderConfig`]. `model_dir`, `dinotxt_weights` and `bpe_vocab`
/// are already resolved against the config's folder.
///
/// # Errors
/// [`BackendError::ModelNotFound`] when no folder is configured;
/// [`BackendError::MissingModelFiles`] naming every missing file of the folder;
/// [`BackendError::MissingWeights`] for a configured file that does not exist. Each says how to
/// get the files.
pub fn locate_files(
    model_dir: Option<&Path>,
    dinotxt_weights: Option<&Path>,
    bpe_vocab: Option<&Path>,
) -> Result<Dinov3Files, BackendError> {
    let (dir, origin) = match model_dir {
        Some(dir) => (dir.to_path_buf(), "[encoder] model_dir".to_owned()),
        None => match std::env::var_os(MODEL_DIR_ENV) {
            Some(dir) if !dir.is_empty() => (
                PathBuf::from(dir),
                format!("the environment variable {MODEL_DIR_ENV}"),
            ),
            _ => {
                return Err(BackendError::ModelNotFound {
                    model: MODEL,
                    searched: vec![
                        "[encoder] model_dir: not set".to_owned(),
                        format!("{MODEL_DIR_ENV}: not set"),
                    ],
                    hint: DINOTXT_INSTALL_HINT,
                });
            }
        },
    };
    let configured = |path: Option<&Path>| -> Result<Option<PathBuf>, BackendError> {
        match path {
            Some(p) if p.is_file() => Ok(Some(p.to_path_buf())),
            Some(p) => Err(BackendError::MissingWeights {
                model: MODEL,
                path: p.to_path_buf(),
                hint: DINOTXT_INSTALL_HINT.to_owned(),
            }),
            None => Ok(None),
        }
    };
    let mut missing = crate::model_files::missing_files(&dir, &model::REQUIRED_FILES);
    let dinotxt = configured(dinotxt_weights)?.or_else(|| find_dinotxt(&dir));
    if dinotxt.is_none() {
        missing.push(DINOTXT_FILE);
    }
    let vocab = configured(bpe_vocab)?
        .or_else(|| Some(dir.join(clip_bpe::VOCAB_FILE)).filter(|p| p.is_file()))
        .or_else(|| {
            crate::model_files::python_package_dir("open_clip")
                .ok()
                .map(|d| d.join(clip_bpe::VOCAB_FILE))
                .filter(|p| p.is_file())
        });
    if vocab.is_none() {
        missing.push(clip_bpe::VOCAB_FILE);
    }
    match (dinotxt, vocab) {
        (Some(dinotxt_weights), Some(bpe_vocab)) if missing.is_empty() => Ok(Dinov3Files {
            model_dir: dir,
            dinotxt_weights,
            bpe_vocab,
        }),
        _ => Err(BackendError::MissingModelFiles {
            model: MODEL,
            dir,
            origin,
            missing,
            hint: DINOTXT_INSTALL_HINT,
        }),
    }
}

/// The DINOv3 + dino.txt patch encoder. See the [module documentation](self).
#[derive(Debug)]
pub struct Dinov3Encoder {
    backbone: Dinov3Backbone,
    heads: DinoTxtHeads,
    tokenizer: ClipBpe,
    short_side: u32,
    templates: Vec<String>,
}

impl Dinov3Encoder {
    /// An encoder over loaded parts.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for a short side that is not a positive multiple of the
    /// patch size, no template or a template without `{}`, or a backbone whose width is not the
    /// head's (dino.txt exists for ViT-L/16 only).
    pub fn new(
        backbone: Dinov3Backbone,
        heads: DinoTxtHeads,
        tokenizer: ClipBpe,
        short_side: u32,
        templates: Vec<String>,
    ) -> Result<Self, BackendError> {
        crate::patch_input::check_short_side(
            short_side,
            backbone.config().patch_size,
            DEFAULT_SHORT_SIDE,
        )?;
        crate::prompts::check_templates(&templates, "[encoder]")?;
        if backbone.config().hidden_size != heads.patch_dim() {
            return Err(BackendError::InvalidParams(format!(
                "the backbone in {} is {}-d but the dino.txt head takes {}-d tokens: dino.txt \
                 belongs to the ViT-L/16 backbone (facebook/dinov3-vitl16-pretrain-lvd1689m)",
                backbone.dir().display(),
                backbone.config().hidden_size,
                heads.patch_dim()
            )));
        }
        Ok(Self {
            backbone,
            heads,
            tokenizer,
            short_side,
            templates,
        })
    }

    /// Loads the encoder from its parameters.
    ///
    /// # Errors
    /// As [`crate::ComputeDevice::open`], [`locate_files`], [`Dinov3Backbone::load`],
    /// [`DinoTxtHeads::load_pth`],
    /// [`ClipBpe::load`] and [`Dinov3Encoder::new`].
    pub fn from_config(
        config: Dinov3EncoderConfig,
        ctx: &BuildContext,
    ) -> Result<Self, BackendError> {
        let resolve = |p: &Option<PathBuf>| p.as_deref().map(|p| ctx.resolve(p));
        let files = locate_files(
            resolve(&config.model_dir).as_deref(),
            resolve(&config.dinotxt_weights).as_deref(),
            resolve(&config.bpe_vocab).as_deref(),
        )?;
        let device = config.device.open_for(config.dtype, config.tf32)?;
        let backbone = Dinov3Backbone::load(&files.model_dir, &device, config.dtype)?;
        let heads = DinoTxtHeads::load_pth(
            &files.dinotxt_weights,
            backbone.config().num_attention_heads,
            config.text_heads,
            &device,
            config.dtype,
        )?;
        let tokenizer = ClipBpe::load(&files.bpe_vocab)?;
        if tokenizer.vocab_size() > heads.vocab_size() {
            return Err(BackendError::InvalidModelFile {
                path: files.bpe_vocab,
                reason: format!(
                    "its vocabulary has {} entries, the dino.txt text tower {}",
                    tokenizer.vocab_size(),
                    heads.vocab_size()
                ),
            });
        }
        Self::new(
            backbone,
            heads,
            tokenizer,
            config.short_side,
            config.templates,
        )
    }

    /// The input size, `(width, height)`, for a `width × height` frame.
    pub fn input_size(&self, width: u32, height: u32) -> (u32, u32) {
        let patch = u32::try_from(self.backbone.config().patch_size).unwrap_or(16);
        patch_aligned_size(width, height, self.short_side, patch)
    }

    /// The tokenizer.
    pub fn tokenizer(&self) -> &ClipBpe {
        &self.tokenizer
    }

    /// The patch grid of one frame: `(grid_width, grid_height, values)`, each patch's
    /// embedding L2-normalised, row-major.
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for an empty image; [`BackendError::Inference`].
    pub fn patch_grid(&self, image: &RgbImage) -> Result<(u32, u32, Vec<f32>), BackendError> {
        let (width, height) = self.input_size(image.width(), image.height());
        let planes = normalised_planes(image, width, height, IMAGENET_MEAN, IMAGENET_STD)?;
        let run = || -> candle_core::Result<(usize, usize, Vec<f32>)> {
            let pixels = Tensor::from_vec(
                planes,
                (1, 3, height as usize, width as usize),
                self.backbone.device(),
            )?;
            let tokens = self.backbone.forward(&pixels)?;
            // Normalised in f32 whatever the model's type.
            let grid = self
                .heads
                .vision(&tokens)?
                .patch_grid
                .to_dtype(DType::F32)?;
            let norms = grid.sqr()?.sum_keepdim(3)?.sqrt()?;
            let grid = grid.broadcast_div(&norms)?;
            Ok((
                tokens.grid_width,
                tokens.grid_height,
                grid.flatten_all()?.to_vec1()?,
            ))
        };
        let (gw, gh, data) = run().map_err(|e| BackendError::Inference {
            what: format!("dino.txt patch embeddings of a {width}x{height} input"),
            source: Box::new(e),
        })?;
        let to_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        Ok((to_u32(gw), to_u32(gh), data))
    }

    /// The unit-norm patch-space embedding of `text`, averaged over the templates.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when the text tower fails or an embedding is zero.
    pub fn embed_text(&self, text: &str) -> Result<Vec<f32>, BackendError> {
        let dim = self.heads.patch_dim();
        let context = self.heads.context_length();
        let bad = || BackendError::Inference {
            what: format!("dino.txt embedding of {text:?}"),
            source: "the text embedding is zero or not finite".into(),
        };
        let halves = crate::prompts::fill(&self.templates, &[text])
            .iter()
            .map(|prompt| {
                let full = self.heads.text(&self.tokenizer.tokenize(prompt, context))?;
                full.get(dim..).map(<[f32]>::to_vec).ok_or_else(bad)
            })
            .collect::<Result<Vec<_>, _>>()?;
        crate::prompts::mean_of_unit(&halves, dim).ok_or_else(bad)
    }
}

impl Encoder for Dinov3Encoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.heads.patch_dim()
    }

    fn encode_image(
        &self,
        image: &RgbImage,
        _regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        let (gw, gh, data) = self.patch_grid(image).map_err(|e| e.into_core(NAME))?;
        PixelEmbeddings::from_patch_grid(image.width(), image.height(), self.dim(), gw, gh, data)
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        self.embed_text(text).map_err(|e| e.into_core(NAME))
    }
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`vlem_core::CoreError::InvalidParams`] for unknown keys or bad values; a
/// [`vlem_core::CoreError::Stage`] naming the missing files and how to get them.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: Dinov3EncoderConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let encoder = Dinov3Encoder::from_config(config, ctx).map_err(|e| e.into_core(NAME))?;
    Ok(Box::new(encoder))
}

vlem_core::register_encoder!(
    NAME,
    "DINOv3 ViT-L/16 with dino.txt (candle CPU): patch embeddings of the whole frame, no \
     proposer; needs the backbone folder, the dino.txt checkpoint and CLIP's BPE vocabulary \
     (model_dir)",
    build
);
