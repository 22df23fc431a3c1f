//! `naradio`: RayFronts' NARADIO encoder (`[encoder] kind = "naradio"`): RADIOv2.5 with NACLIP's
//! attention in its last block, read out in SigLIP's text space; pixel-aligned patch embeddings.
//!
//! Why it exists: the paper's pixel-aligned path needs an encoder whose patch features can be
//! compared with text directly. NARADIO (RayFronts) gets them from RADIOv2.5 by replacing the
//! last block's attention with NACLIP's neighbourhood attention (key-key similarity plus a
//! Gaussian spatial prior) and mapping every patch token through the `siglip` adaptor's summary
//! MLP; queries go through the SigLIP text tower the adaptor was distilled from. This module owns
//! the encoder's parameters, the whole-frame input (aspect-preserving resize to a multiple of 16)
//! and the prompt ensembling; [`model`] owns the trunk and [`text`] the text tower. The reference
//! behaviour, sources and file layout are in `docs/notes/naradio.md`.
//!
//! Image side ([`Encoder::encode_image`]): the frame resized so that its short side is
//! `short_side` (aspect ratio kept, both sides rounded to multiples of 16; RayFronts feeds its
//! 480 x 640 frames as they are, the default), RADIO's input conditioning, the trunk with the
//! NACLIP last block, the adaptor MLP on each patch token: a `h/16 x w/16` grid in the text
//! space, which [`PixelEmbeddings::from_patch_grid`] upsamples bilinearly and L2-normalises
//! where the map reads pixels. Text side ([`Encoder::encode_text`]): the query in each template
//! (RayFronts: the 80 ImageNet templates of OpenAI CLIP), each embedded and L2-normalised,
//! averaged (RayFronts stops here), then normalised again. The last 1,024 query texts are cached
//! ([`TextEmbeddingCache`]): asking again costs a lookup instead of 80 text-tower passes.
//!
//! ```toml
//! [encoder]
//! kind = "naradio"
//! model_dir = "models/naradio-l"   # else $VLEM_NARADIO_DIR; made by convert_radio.py
//! # short_side = 480               # input short side in pixels, a multiple of 16
//! # gauss_std = 7.0                # of the NACLIP prior, in patches
//! # gaussian_grid = "rayfronts"    # or "image" (NACLIP's layout; differs for non-square input)
//! # reduced_last_block = false     # true: NACLIP's block without residual and MLP
//! # templates = ["a photo of a {}."]  # default: the 80 OpenAI ImageNet templates
//! # device = "cpu"                # "cuda", "cuda:N" with feature `cuda`
//! # dtype = "f32"                 # "f16", "bf16": trunk, adaptor and text tower in half
//! # tf32 = true                   # on a GPU, f32 matrix products in TF32 (off by default)
//! ```

pub mod model;
pub mod text;

use std::path::{Path, PathBuf};

use candle_core::Tensor;
use serde::Deserialize;
use vlem_core::{BuildContext, CoreError, Encoder, PixelEmbeddings, Region, RgbImage, StageKind};

use crate::error::BackendError;
use crate::text_cache::TextEmbeddingCache;

pub use model::{
    GaussianGrid, LastBlock, MODEL, NARADIO_INSTALL_HINT, REQUIRED_FILES, RadioConfig, RadioModel,
    RadioOutput, check_model_dir, gaussian_prior,
};
pub use text::{SiglipText, canonicalize};

/// The name this encoder is registered under (`[encoder] kind = "naradio"`).
pub const NAME: &str = "naradio";

/// Environment variable naming the model folder when the config does not.
pub const MODEL_DIR_ENV: &str = "VLEM_NARADIO_DIR";

/// RayFronts' prompt templates (`openai_imagenet_template`, OpenAI CLIP's 80 ImageNet prompts).
pub const IMAGENET_TEMPLATES: [&str; 80] = [
    "a bad photo of a {}.",
    "a photo of many {}.",
    "a sculpture of a {}.",
    "a photo of the hard to see {}.",
    "a low resolution photo of the {}.",
    "a rendering of a {}.",
    "graffiti of a {}.",
    "a bad photo of the {}.",
    "a cropped photo of the {}.",
    "a tattoo of a {}.",
    "the embroidered {}.",
    "a photo of a hard to see {}.",
    "a bright photo of a {}.",
    "a photo of a clean {}.",
    "a photo of a dirty {}.",
    "a dark photo of the {}.",
    "a drawing of a {}.",
    "a photo of my {}.",
    "the plastic {}.",
    "a photo of the cool {}.",
    "a close-up photo of a {}.",
    "a black and white photo of the {}.",
    "a painting of the {}.",
    "a painting of a {}.",
    "a pixelated photo of the {}.",
    "a sculpture of the {}.",
    "a bright photo of the {}.",
    "a cropped photo of a {}.",
    "a plastic {}.",
    "a photo of the dirty {}.",
    "a jpeg corrupted photo of a {}.",
    "a blurry photo of the {}.",
    "a photo of the {}.",
    "a good photo of the {}.",
    "a rendering of the {}.",
    "a {} in a video game.",
    "a photo of one {}.",
    "a doodle of a {}.",
    "a close-up photo of the {}.",
    "a photo of a {}.",
    "the origami {}.",
    "the {} in a video game.",
    "a sketch of a {}.",
    "a doodle of the {}.",
    "a origami {}.",
    "a low resolution photo of a {}.",
    "the toy {}.",
    "a rendition of the {}.",
    "a photo of the clean {}.",
    "a photo of a large {}.",
    "a rendition of a {}.",
    "a photo of a nice {}.",
    "a photo of a weird {}.",
    "a blurry photo of a {}.",
    "a cartoon {}.",
    "art of a {}.",
    "a sketch of the {}.",
    "a embroidered {}.",
    "a pixelated photo of a {}.",
    "itap of the {}.",
    "a jpeg corrupted photo of the {}.",
    "a good photo of a {}.",
    "a plushie {}.",
    "a photo of the nice {}.",
    "a photo of the small {}.",
    "a photo of the weird {}.",
    "the cartoon {}.",
    "art of the {}.",
    "a drawing of the {}.",
    "a photo of the large {}.",
    "a black and white photo of a {}.",
    "the plushie {}.",
    "a dark photo of a {}.",
    "itap of a {}.",
    "graffiti of the {}.",
    "a toy {}.",
    "itap of my {}.",
    "a photo of a cool {}.",
    "a photo of a small {}.",
    "a tattoo of the {}.",
];

/// Parameters of the encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NaradioEncoderConfig {
    /// The model folder (`config.json`, `radio.safetensors`, `text/…`, see
    /// [`REQUIRED_FILES`]), relative to the config file's folder. Unset: the folder named by
    /// [`MODEL_DIR_ENV`].
    pub model_dir: Option<PathBuf>,
    /// The input's short side in pixels, a positive multiple of 16 (the long side keeps the
    /// aspect ratio, rounded to a multiple of 16). Default 480: RayFronts' 480 x 640 frames.
    pub short_side: u32,
    /// Standard deviation of the Gaussian prior, in patches. Default 7 (RayFronts).
    pub gauss_std: f64,
    /// Token layout of the prior. Default `rayfronts` (as RayFronts builds it).
    pub gaussian_grid: GaussianGrid,
    /// NACLIP's "reduced" last block (attention output only) instead of RayFronts' (which keeps
    /// the residual and the MLP). Default false.
    pub reduced_last_block: bool,
    /// Prompt templates, each with one `{}`. Default: [`IMAGENET_TEMPLATES`].
    pub templates: Vec<String>,
    /// Where the model runs: `"cpu"` (default), `"cuda"` or `"cuda:N"` (feature `cuda`).
    pub device: crate::ComputeDevice,
    /// What the trunk, the adaptor and the text tower compute in: `"f32"` (default), `"f16"` or
    /// `"bf16"` (for a GPU; on the CPU half precision runs through candle's plain ops, slower
    /// than f32's).
    pub dtype: crate::ModelDtype,
    /// `true`: on a GPU, f32 matrix products run on TF32 tensor cores (faster, 10-bit mantissa
    /// inputs); `false`: they do not; unset (default): left as it is, off unless a model asked.
    /// One setting per process (see [`crate::ComputeDevice::open_for`]).
    pub tf32: Option<bool>,
}

impl Default for NaradioEncoderConfig {
    fn default() -> Self {
        Self {
            model_dir: None,
            short_side: 480,
            gauss_std: 7.0,
            gaussian_grid: GaussianGrid::Rayfronts,
            reduced_last_block: false,
            templates: IMAGENET_TEMPLATES.iter().map(|t| (*t).to_owned()).collect(),
            device: crate::ComputeDevice::Cpu,
            dtype: crate::ModelDtype::F32,
            tf32: None,
        }
    }
}

/// Finds the model folder: `configured` (already resolved) if given, else [`MODEL_DIR_ENV`].
///
/// # Errors
/// [`BackendError::MissingModelFiles`] or [`BackendError::ModelNotFound`], each saying how to get
/// the model.
pub fn locate_model_dir(configured: Option<&Path>) -> Result<PathBuf, BackendError> {
    if let Some(dir) = configured {
        return check_model_dir(dir, "[encoder] model_dir".to_owned());
    }
    match std::env::var_os(MODEL_DIR_ENV) {
        Some(dir) if !dir.is_empty() => check_model_dir(
            Path::new(&dir),
            format!("the environment variable {MODEL_DIR_ENV}"),
        ),
        _ => Err(BackendError::ModelNotFound {
            model: MODEL,
            searched: vec![
                "[encoder] model_dir: not set".to_owned(),
                format!("{MODEL_DIR_ENV}: not set"),
            ],
            hint: NARADIO_INSTALL_HINT,
        }),
    }
}

/// The NARADIO encoder. See the [module documentation](self).
#[derive(Debug)]
pub struct NaradioEncoder {
    model: RadioModel,
    text: SiglipText,
    last: LastBlock,
    short_side: u32,
    templates: Vec<String>,
    dim: usize,
    /// Query embeddings (80 text-tower passes each with the default templates).
    text_cache: TextEmbeddingCache,
}

impl NaradioEncoder {
    /// Builds the encoder from its parameters: finds and loads the model, checks the rest.
    ///
    /// # Errors
    /// As [`crate::ComputeDevice::open`], [`locate_model_dir`], [`RadioModel::load`] and
    /// [`SiglipText::load`];
    /// [`BackendError::InvalidParams`] for a short side that is not a positive multiple of 16,
    /// a non-positive `gauss_std`, no template or a template without `{}`.
    pub fn from_config(
        config: NaradioEncoderConfig,
        ctx: &BuildContext,
    ) -> Result<Self, BackendError> {
        let bad = |m: String| Err(BackendError::InvalidParams(m));
        crate::prompts::check_templates(&config.templates, "[encoder]")?;
        // Below, the prior's 1 / (2 std²) overflows to NaN attention; above, it is flat.
        if let Err(range) = vlem_core::ranges::number(config.gauss_std, 0.1, 1000.0, "patches") {
            return bad(format!("gauss_std {range}"));
        }
        let configured = config.model_dir.as_deref().map(|p| ctx.resolve(p));
        let dir = locate_model_dir(configured.as_deref())?;
        let device = config.device.open_for(config.dtype, config.tf32)?;
        let model = RadioModel::load(&dir, &device, config.dtype)?;
        crate::patch_input::check_short_side(
            config.short_side,
            model.config().patch_size,
            NaradioEncoderConfig::default().short_side,
        )?;
        let text = SiglipText::load(&dir.join("text"), &device, config.dtype)?;
        let dim = model.adaptor_dim()?;
        Ok(Self {
            model,
            text,
            last: LastBlock::Naclip {
                std: config.gauss_std,
                grid: config.gaussian_grid,
                reduced: config.reduced_last_block,
            },
            short_side: config.short_side,
            templates: config.templates,
            dim,
            text_cache: TextEmbeddingCache::default(),
        })
    }

    /// The trunk and adaptor.
    pub fn model(&self) -> &RadioModel {
        &self.model
    }

    /// The text tower.
    pub fn text(&self) -> &SiglipText {
        &self.text
    }

    /// The input size `(width, height)` for a `width x height` frame.
    pub fn input_size(&self, width: u32, height: u32) -> (u32, u32) {
        let patch = u32::try_from(self.model.config().patch_size).unwrap_or(16);
        crate::patch_input::patch_aligned_size(width, height, self.short_side, patch)
    }

    /// The language-aligned patch grid of `image`: `(grid_width, grid_height, values)`, the
    /// values row-major `grid_height x grid_width x dim`, not normalised (RayFronts'
    /// `align_spatial_features_with_language(encode_image_to_feat_map(x))`).
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for an empty image; [`BackendError::Inference`].
    pub fn patch_grid(&self, image: &RgbImage) -> Result<(u32, u32, Vec<f32>), BackendError> {
        let (w, h) = self.input_size(image.width(), image.height());
        let c = self.model.config();
        let planes = crate::patch_input::normalised_planes(image, w, h, c.input_mean, c.input_std)?;
        let x = Tensor::from_vec(planes, (1, 3, h as usize, w as usize), self.model.device())
            .map_err(|e| BackendError::Inference {
                what: "the input tensor".to_owned(),
                source: Box::new(e),
            })?;
        let out = self.model.forward(&x, self.last)?;
        let lang = self.model.adapt(&out.features)?;
        let data = lang
            .flatten_all()
            .and_then(|t| t.to_dtype(candle_core::DType::F32))
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| BackendError::Inference {
                what: "reading the patch grid".to_owned(),
                source: Box::new(e),
            })?;
        let patch = u32::try_from(c.patch_size).unwrap_or(16);
        Ok((w / patch, h / patch, data))
    }

    /// RayFronts' `encode_labels` for each text: the mean of the unit-norm embeddings of the text
    /// in every template (not normalised again).
    ///
    /// # Errors
    /// [`BackendError::Inference`] when the text tower fails.
    pub fn label_embeddings(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        texts
            .iter()
            .map(|t| {
                let prompts = crate::prompts::fill(&self.templates, &[t]);
                let refs: Vec<&str> = prompts.iter().map(String::as_str).collect();
                let rows = self.text.embed(&refs)?;
                let mut mean = vec![0.0f32; self.dim];
                for row in &rows {
                    let n = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
                    for (m, v) in mean.iter_mut().zip(row) {
                        *m += v / n / rows.len() as f32;
                    }
                }
                Ok(mean)
            })
            .collect()
    }
}

impl Encoder for NaradioEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn encode_image(
        &self,
        image: &RgbImage,
        _regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        let (gw, gh, data) = self.patch_grid(image).map_err(|e| e.into_core(NAME))?;
        PixelEmbeddings::from_patch_grid(image.width(), image.height(), self.dim, gw, gh, data)
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        self.text_cache
            .get_or_embed(text, |text| self.embed_query(text))
    }
}

impl NaradioEncoder {
    /// [`Encoder::encode_text`] without the cache.
    fn embed_query(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        let mut rows = self
            .label_embeddings(&[text])
            .map_err(|e| e.into_core(NAME))?;
        let mut v = rows.pop().ok_or_else(|| {
            CoreError::stage(
                StageKind::Encoder,
                NAME,
                BackendError::Inference {
                    what: format!("embedding {text:?}"),
                    source: "no embedding came back".into(),
                },
            )
        })?;
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if !(n.is_finite() && n > 0.0) {
            return Err(CoreError::stage(
                StageKind::Encoder,
                NAME,
                BackendError::Inference {
                    what: format!("embedding {text:?}"),
                    source: "the embedding has no direction".into(),
                },
            ));
        }
        v.iter_mut().for_each(|x| *x /= n);
        Ok(v)
    }
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`CoreError::InvalidParams`] for unknown keys or bad values; a [`CoreError::Stage`] saying
/// how to get the model when it is missing.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: NaradioEncoderConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let encoder = NaradioEncoder::from_config(config, ctx).map_err(|e| e.into_core(NAME))?;
    Ok(Box::new(encoder))
}

vlem_core::register_encoder!(
    NAME,
    "NARADIO (RayFronts): RADIOv2.5 with a NACLIP last block, patch grid in SigLIP's text \
     space, candle CPU; needs a model folder made by convert_radio.py (model_dir)",
    build
);
