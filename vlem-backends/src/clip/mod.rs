//! `clip`: CLIP region embeddings (`[encoder] kind = "clip"`), the paper's segment-embedding
//! path with a CLIP ViT on candle (CPU, or a CUDA GPU with feature `cuda`).
//!
//! Why it exists: CLIP embeds whole images, not pixels. The paper's answer (section
//! "Segment-Embeddings") is to embed each region of a frame, found by a region proposer, as its
//! own crop, and give every pixel of the region that embedding; this module is that encoder for
//! the CLIP models users have, any ViT size in the Hugging Face layout ([`model`]).
//!
//! What it owns: the loaded model, the crop settings ([`crate::region_crops::CropSpec`]: the
//! tower's input size, the normalisation of the model's `preprocessor_config.json`, the
//! background strategy) and the prompt templates.
//!
//! Image side ([`Encoder::encode_image`]): the regions' crops (one call of
//! [`crate::region_crops::crop_batch`], so a frame's random backgrounds do not depend on the
//! batch size) run through the image tower `batch_size` crops at a time, each projected and
//! L2-normalised, then laid out by [`crate::region_crops::region_embeddings`] (the smaller
//! region wins a pixel two regions cover). A frame without regions embeds nothing: every pixel
//! is [`vlem_core::NO_REGION`], which the maps skip. Text side ([`Encoder::encode_text`]): the
//! query put into each template, embedded, L2-normalised, averaged and normalised again (CLIP's
//! prompt ensembling); with the default template `"{}"`, the query alone.
//!
//! ```toml
//! [proposer]
//! kind = "graph"
//!
//! [encoder]
//! kind = "clip"
//! model_dir = "models/clip-vit-base-patch16"  # else $VLEM_CLIP_DIR
//! # background = "none"     # "random", "static", "mean-image", "mean-segment"
//! # seed = 0                # of the random background
//! # templates = ["a photo of a {}."]
//! # batch_size = 16         # crops per forward pass
//! # device = "cpu"          # "cuda", "cuda:N" with feature `cuda`
//! # dtype = "f32"           # "f16", "bf16": the towers in half precision
//! # tf32 = true             # on a GPU, f32 matrix products in TF32 (off by default)
//! ```

pub mod model;

use std::path::{Path, PathBuf};

use serde::Deserialize;
use vlem_core::{BuildContext, Encoder, PixelEmbeddings, Region, RgbImage, StageKind};

use crate::error::BackendError;
use crate::region_crops::{self, Background, CLIP_MEAN, CLIP_STD, CropSpec};

pub use model::{CLIP_CONVERT_HINT, CLIP_INSTALL_HINT, ClipConfig, ClipModel};

/// The name this encoder is registered under (`[encoder] kind = "clip"`).
pub const NAME: &str = "clip";

/// Environment variable naming the model folder when the config does not.
pub const MODEL_DIR_ENV: &str = "VLEM_CLIP_DIR";

/// Crops per image-tower call when the config does not say.
pub const DEFAULT_BATCH_SIZE: usize = 16;

/// The largest `batch_size` accepted (crops per forward pass).
pub const MAX_BATCH: usize = 1024;

/// Parameters of the encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClipEncoderConfig {
    /// The Hugging Face `CLIPModel` folder (`config.json`, `model.safetensors`, `tokenizer.json`,
    /// optionally `preprocessor_config.json`), relative to the config file's folder. Unset: the
    /// folder named by the environment variable [`MODEL_DIR_ENV`].
    pub model_dir: Option<PathBuf>,
    /// What replaces the crop pixels outside a region's mask.
    pub background: Background,
    /// Seed of the `random` background.
    pub seed: u64,
    /// Prompt templates, each with one `{}` that the query replaces. Default: `["{}"]`.
    pub templates: Vec<String>,
    /// Crops per image-tower call: bounds the memory of the forward pass. Default 16.
    pub batch_size: usize,
    /// Where the model runs: `"cpu"` (default), `"cuda"` or `"cuda:N"` (feature `cuda`).
    pub device: crate::ComputeDevice,
    /// What both towers compute in: `"f32"` (default), `"f16"` or `"bf16"` (for a GPU; on the CPU
    /// half precision runs through candle's plain ops, slower than f32's fused kernels).
    pub dtype: crate::ModelDtype,
    /// `true`: on a GPU, f32 matrix products run on TF32 tensor cores (faster, 10-bit mantissa
    /// inputs); `false`: they do not; unset (default): left as it is, off unless a model asked.
    /// One setting per process (see [`crate::ComputeDevice::open_for`]).
    pub tf32: Option<bool>,
}

impl Default for ClipEncoderConfig {
    fn default() -> Self {
        Self {
            model_dir: None,
            background: Background::None,
            seed: 0,
            templates: crate::prompts::default_templates(),
            batch_size: DEFAULT_BATCH_SIZE,
            device: crate::ComputeDevice::Cpu,
            dtype: crate::ModelDtype::F32,
            tf32: None,
        }
    }
}

/// Finds the model folder: `configured` (already resolved against the config's directory) if
/// given, else the folder named by [`MODEL_DIR_ENV`]. A folder that is named but lacks files is an
/// error naming them.
///
/// # Errors
/// [`BackendError::MissingModelFiles`] or [`BackendError::ModelNotFound`], each saying how to get
/// a model.
pub fn locate_model_dir(configured: Option<&Path>) -> Result<PathBuf, BackendError> {
    if let Some(dir) = configured {
        return model::check_model_dir(dir, "[encoder] model_dir".to_owned());
    }
    match std::env::var_os(MODEL_DIR_ENV) {
        Some(dir) if !dir.is_empty() => model::check_model_dir(
            Path::new(&dir),
            format!("the environment variable {MODEL_DIR_ENV}"),
        ),
        _ => Err(BackendError::ModelNotFound {
            model: model::MODEL,
            searched: vec![
                "[encoder] model_dir: not set".to_owned(),
                format!("{MODEL_DIR_ENV}: not set"),
            ],
            hint: CLIP_INSTALL_HINT,
        }),
    }
}

/// The image normalisation of the model folder: `image_mean` and `image_std` of its
/// `preprocessor_config.json`, else CLIP's.
///
/// # Errors
/// [`BackendError::InvalidModelFile`] for a file that is not JSON or whose values are not three
/// finite numbers (a std also non-zero).
pub fn read_normalisation(dir: &Path) -> Result<([f32; 3], [f32; 3]), BackendError> {
    let path = dir.join("preprocessor_config.json");
    if !path.is_file() {
        return Ok((CLIP_MEAN, CLIP_STD));
    }
    let invalid = |reason: String| BackendError::InvalidModelFile {
        path: path.clone(),
        reason,
    };
    let text =
        std::fs::read_to_string(&path).map_err(|e| invalid(format!("cannot read it: {e}")))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| invalid(format!("not valid JSON: {e}")))?;
    let triple = |key: &str, default: [f32; 3]| -> Result<[f32; 3], BackendError> {
        let Some(v) = json.get(key) else {
            return Ok(default);
        };
        let values: Option<Vec<f32>> = v
            .as_array()
            .map(|a| a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect())
            .and_then(|x: Option<Vec<f32>>| x);
        match values.as_deref() {
            Some(&[a, b, c]) if [a, b, c].iter().all(|x| x.is_finite()) => Ok([a, b, c]),
            _ => Err(invalid(format!("{key} is {v}, expected three numbers"))),
        }
    };
    let mean = triple("image_mean", CLIP_MEAN)?;
    let std = triple("image_std", CLIP_STD)?;
    if std.contains(&0.0) {
        return Err(invalid(format!("image_std {std:?} holds a zero")));
    }
    Ok((mean, std))
}

/// The CLIP region encoder. See the [module documentation](self).
#[derive(Debug)]
pub struct ClipEncoder {
    model: ClipModel,
    crops: CropSpec,
    templates: Vec<String>,
    batch_size: usize,
}

impl ClipEncoder {
    /// An encoder over a loaded model.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for no template, a template without `{}`, or a zero
    /// batch size.
    pub fn new(
        model: ClipModel,
        crops: CropSpec,
        templates: Vec<String>,
        batch_size: usize,
    ) -> Result<Self, BackendError> {
        crate::prompts::check_templates(&templates, "[encoder]")?;
        // A batch is batch_size crops of 3 × 224² values: past this it is only memory.
        if let Err(range) = vlem_core::ranges::count(batch_size, 1, MAX_BATCH, "crops") {
            return Err(BackendError::InvalidParams(format!("batch_size {range}")));
        }
        Ok(Self {
            model,
            crops,
            templates,
            batch_size,
        })
    }

    /// Builds the encoder from its parameters: finds and loads the model, reads its
    /// normalisation, checks the rest.
    ///
    /// # Errors
    /// As [`crate::ComputeDevice::open`], [`locate_model_dir`], [`ClipModel::load`],
    /// [`read_normalisation`] and [`ClipEncoder::new`].
    pub fn from_config(
        config: ClipEncoderConfig,
        ctx: &BuildContext,
    ) -> Result<Self, BackendError> {
        let configured = config.model_dir.as_deref().map(|p| ctx.resolve(p));
        let dir = locate_model_dir(configured.as_deref())?;
        let device = config.device.open_for(config.dtype, config.tf32)?;
        let model = ClipModel::load(&dir, &device, config.dtype)?;
        let (mean, std) = read_normalisation(&dir)?;
        let size =
            u32::try_from(model.image_size()).map_err(|_| BackendError::InvalidModelFile {
                path: dir.join("config.json"),
                reason: format!("image_size {} is too large", model.image_size()),
            })?;
        let crops = CropSpec {
            size,
            mean,
            std,
            background: config.background,
            seed: config.seed,
        };
        Self::new(model, crops, config.templates, config.batch_size)
    }

    /// The model.
    pub fn model(&self) -> &ClipModel {
        &self.model
    }

    /// How regions become crops.
    pub fn crop_spec(&self) -> &CropSpec {
        &self.crops
    }

    /// The prompt templates.
    pub fn templates(&self) -> &[String] {
        &self.templates
    }

    /// Crops per image-tower call.
    pub fn batch_size(&self) -> usize {
        self.batch_size
    }

    /// The unit-norm embeddings of `count` crops (`count x 3 x S x S` normalised values),
    /// `batch_size` at a time, as one row-major `count x dim` table.
    ///
    /// # Errors
    /// [`BackendError::Inference`] for a wrong length, a failing model or an embedding that
    /// cannot be normalised.
    pub fn embed_crops(&self, pixels: &[f32], count: usize) -> Result<Vec<f32>, BackendError> {
        let dim = self.model.projection_dim();
        if count == 0 {
            return Ok(Vec::new());
        }
        let per_crop = pixels.len() / count;
        if per_crop * count != pixels.len() {
            return Err(BackendError::Inference {
                what: format!("embedding {count} crops"),
                source: format!("{} values are not {count} equal crops", pixels.len()).into(),
            });
        }
        let mut table = Vec::with_capacity(count * dim);
        for (chunk_index, chunk) in pixels.chunks(self.batch_size * per_crop).enumerate() {
            let batch = chunk.len() / per_crop;
            for mut row in self.model.image_features(chunk, batch)? {
                if !vlem_core::embeddings::normalise(&mut row) {
                    return Err(BackendError::Inference {
                        what: format!("embedding crop batch {chunk_index}"),
                        source: "an image embedding is zero or not finite".into(),
                    });
                }
                table.extend_from_slice(&row);
            }
        }
        Ok(table)
    }

    /// The unit-norm embedding of each text through the templates: each prompt embedded and
    /// normalised, their mean normalised again.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when tokenising or the model fails, or an embedding cannot
    /// be normalised.
    pub fn embed_texts(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        let prompts = crate::prompts::fill(&self.templates, texts);
        let dim = self.model.projection_dim();
        let mut embeddings = Vec::with_capacity(prompts.len());
        for chunk in prompts.chunks(self.batch_size.max(self.templates.len())) {
            let chunk: Vec<&str> = chunk.iter().map(String::as_str).collect();
            embeddings.extend(self.model.text_features(&chunk)?);
        }
        texts
            .iter()
            .zip(embeddings.chunks(self.templates.len()))
            .map(|(text, group)| {
                crate::prompts::mean_of_unit(group, dim).ok_or_else(|| BackendError::Inference {
                    what: format!("embedding {text:?}"),
                    source: "the text embedding is zero or not finite".into(),
                })
            })
            .collect()
    }

    /// The image side with this crate's error.
    fn encode_regions(
        &self,
        image: &RgbImage,
        regions: &[Region],
    ) -> Result<PixelEmbeddings, BackendError> {
        let dim = self.model.projection_dim();
        if regions.is_empty() {
            return region_crops::region_embeddings(
                image.width(),
                image.height(),
                &[],
                dim,
                Vec::new(),
            );
        }
        let pixels = region_crops::crop_batch(image, regions, &self.crops)?;
        let table = self.embed_crops(&pixels, regions.len())?;
        region_crops::region_embeddings(image.width(), image.height(), regions, dim, table)
    }
}

impl Encoder for ClipEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.model.projection_dim()
    }

    fn needs_regions(&self) -> bool {
        true
    }

    /// One embedding per region, from its crop; pixels in no region have none.
    fn encode_image(
        &self,
        image: &RgbImage,
        regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        self.encode_regions(image, regions)
            .map_err(|e| e.into_core(NAME))
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        let mut out = self.embed_texts(&[text]).map_err(|e| e.into_core(NAME))?;
        out.pop().ok_or_else(|| {
            BackendError::Inference {
                what: format!("embedding {text:?}"),
                source: "no embedding came back".into(),
            }
            .into_core(NAME)
        })
    }
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`vlem_core::CoreError::InvalidParams`] for unknown keys or bad values; a
/// [`vlem_core::CoreError::Stage`] saying how to get the model when it is missing.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: ClipEncoderConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let encoder = ClipEncoder::from_config(config, ctx).map_err(|e| e.into_core(NAME))?;
    Ok(Box::new(encoder))
}

vlem_core::register_encoder!(
    NAME,
    "CLIP ViT (Hugging Face layout, candle CPU) on region crops: region embeddings; needs a \
     [proposer] and a model folder (model_dir)",
    build
);
