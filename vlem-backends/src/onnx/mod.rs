//! `onnx`: any CLIP-like encoder exported to ONNX, run on ONNX Runtime and configured entirely
//! in TOML (`[encoder] kind = "onnx"`).
//!
//! Why it exists: the paper compares vision-language backends, and researchers bring their own.
//! With this encoder a model that a user exports from PyTorch (`torch.onnx.export`) runs in the
//! pipeline without writing Rust: the config names the model files, the input size and
//! normalisation, the tensor names and what the output means. The module owns the two towers
//! (image, and optionally text with its tokenizer), their preprocessing, and the turning of model
//! outputs into [`PixelEmbeddings`]; the ONNX Runtime library and sessions belong to [`runtime`],
//! the region crops to [`crate::region_crops`].
//!
//! Image side: the image model takes one float input `N × 3 × height × width` (normalised RGB,
//! `(x / 255 - mean) / std` per channel) and gives one of two outputs, set by `output_kind`:
//! - `"global"`: one embedding per image, `N × dim` (a CLIP image tower with its projection).
//!   The encoder is then a region encoder ([`Encoder::needs_regions`]): each region of the
//!   frame is cropped, its background replaced as `background` says, resampled to `size × size`
//!   ([`crate::region_crops::crop_batch`]), embedded, and every pixel takes the embedding of
//!   the smallest region covering it ([`crate::region_crops::region_embeddings`]).
//! - `"patch-grid"`: one embedding per patch, `N × (h·w) × dim` (tokens, optionally after
//!   `skip_tokens` leading CLS/register tokens) or `N × h × w × dim`, with
//!   `h = height / patch_size` and `w = width / patch_size`. The whole frame is resampled to
//!   `width × height` (Catmull-Rom, i.e. PIL's bicubic, widened when shrinking; no crop), so the
//!   grid covers the whole frame, as [`PixelEmbeddings::from_patch_grid`] expects. Aspect
//!   ratio: a frame of another aspect than `width : height` is stretched, and the patches are
//!   then not square in the frame; for 640 × 480 frames choose a 4 : 3 input (e.g.
//!   `width = 448, height = 336` for 14-pixel patches) if the model accepts it (dynamic input
//!   size and interpolated position embeddings), or accept the stretch.
//!
//! Text side (optional, `[encoder.text]`): the text model takes token ids (`N × L`, int64 or
//! int32) and, when it has such an input, an attention mask (1 for tokens, 0 for padding) and
//! token type ids (zeros), and gives `N × dim`. Texts are tokenised with the `tokenizer.json`
//! (Hugging Face `tokenizers`), truncated to `max_length`, padded with `pad_id`. A query is
//! embedded as the L2-normalised mean of the unit-norm embeddings of the query put into each of
//! the `templates` (CLIP's prompt ensembling). Without a text model, [`Encoder::encode_text`]
//! answers unsupported.
//!
//! ```toml
//! [encoder]
//! kind = "onnx"
//! # library = "/opt/onnxruntime/lib/libonnxruntime.so" # else $ORT_DYLIB_PATH, else pip onnxruntime
//! # threads = 2                  # intra-op threads per model; default: one per physical core
//! # dim = 512                    # default: read from the model's output shape
//!
//! [encoder.image]
//! model = "models/clip-b16/image.onnx"      # relative to the config file's folder
//! output_kind = "global"                     # or "patch-grid" (then patch_size, skip_tokens)
//! size = 224                                 # or width/height; default: the model's input shape
//! mean = [0.48145466, 0.4578275, 0.40821073] # default: OpenAI CLIP's
//! std = [0.26862954, 0.26130258, 0.27577711] # default: OpenAI CLIP's
//! # input = "pixel_values"                   # default: the model's first input
//! # output = "image_embeds"                  # default: the model's first output
//! # background = "random"                    # global: none | random | static | mean-image | mean-segment
//! # batch = 16                               # global: crops per model call
//!
//! [encoder.text]
//! model = "models/clip-b16/text.onnx"
//! tokenizer = "models/clip-b16/tokenizer.json"
//! max_length = 77
//! pad_id = 49407
//! templates = ["a photo of a {}."]
//! ```

pub mod runtime;

use std::path::PathBuf;

use ort::value::TensorElementType;
use serde::Deserialize;
use tokenizers::{Tokenizer, TruncationParams};
use vlem_core::{BuildContext, CoreError, Encoder, PixelEmbeddings, Region, RgbImage, StageKind};

use crate::error::BackendError;
use crate::region_crops::{self, Background, CLIP_MEAN, CLIP_STD, CropSpec};
use runtime::{Input, Model, Output};

/// The name this encoder is registered under (`[encoder] kind = "onnx"`).
pub const NAME: &str = "onnx";

/// Crops per image-model call in the `global` kind, unless `batch` says otherwise.
pub const DEFAULT_BATCH: usize = 16;

/// Tokens per text at most, unless `max_length` says otherwise (CLIP's context length).
pub const DEFAULT_MAX_LENGTH: usize = 77;

/// What the image model's output is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OutputKind {
    /// One embedding per image, `N × dim`: a region encoder over region crops.
    Global,
    /// One embedding per patch, `N × tokens × dim` or `N × h × w × dim`.
    PatchGrid,
}

/// How texts of one batch are padded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Padding {
    /// To `max_length` tokens: works for models exported with a fixed sequence length.
    #[default]
    MaxLength,
    /// To the longest text of the batch: faster, needs a dynamic sequence axis.
    Longest,
}

/// Parameters of the encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OnnxConfig {
    /// The ONNX Runtime shared library (`libonnxruntime.so`, 1.31 or newer), relative to the
    /// config file's folder. Unset: the file named by `ORT_DYLIB_PATH`, else the library of the
    /// pip package `onnxruntime` found through `python3`.
    #[serde(default)]
    pub library: Option<PathBuf>,
    /// Intra-op threads of each model; unset: ONNX Runtime's default (one per physical core).
    #[serde(default)]
    pub threads: Option<usize>,
    /// Embedding dimension; unset: the last axis of the image model's output shape.
    #[serde(default)]
    pub dim: Option<usize>,
    /// The image tower.
    pub image: ImageConfig,
    /// The text tower; unset: the encoder embeds no text.
    #[serde(default)]
    pub text: Option<TextConfig>,
}

/// `[encoder.image]`: the image tower.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageConfig {
    /// The `.onnx` file, relative to the config file's folder.
    pub model: PathBuf,
    /// What the output is.
    pub output_kind: OutputKind,
    /// Square input side; exclusive with `width`/`height`.
    #[serde(default)]
    pub size: Option<u32>,
    /// Input width; with `height`.
    #[serde(default)]
    pub width: Option<u32>,
    /// Input height; with `width`.
    #[serde(default)]
    pub height: Option<u32>,
    /// Per-channel mean, in `[0, 1]` units; default OpenAI CLIP's.
    #[serde(default = "clip_mean")]
    pub mean: [f32; 3],
    /// Per-channel standard deviation; default OpenAI CLIP's.
    #[serde(default = "clip_std")]
    pub std: [f32; 3],
    /// The input tensor's name; default the model's first input.
    #[serde(default)]
    pub input: Option<String>,
    /// The output tensor's name; default the model's first output.
    #[serde(default)]
    pub output: Option<String>,
    /// `patch-grid`: patch side in input pixels (required).
    #[serde(default)]
    pub patch_size: Option<u32>,
    /// `patch-grid`: leading tokens (CLS, registers) to drop from a `N × tokens × dim` output.
    #[serde(default)]
    pub skip_tokens: Option<usize>,
    /// `global`: what replaces the crop pixels outside a region's mask; default `none`.
    #[serde(default)]
    pub background: Option<Background>,
    /// `global`: seed of the `random` background.
    #[serde(default)]
    pub seed: Option<u64>,
    /// `global`: crops per model call; default [`DEFAULT_BATCH`].
    #[serde(default)]
    pub batch: Option<usize>,
}

/// `[encoder.text]`: the text tower.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TextConfig {
    /// The `.onnx` file, relative to the config file's folder.
    pub model: PathBuf,
    /// The Hugging Face `tokenizer.json`, relative to the config file's folder.
    pub tokenizer: PathBuf,
    /// The token-id input's name; default the model's first input.
    #[serde(default)]
    pub input_ids: Option<String>,
    /// The attention-mask input's name; default `attention_mask` if the model has such an
    /// input, else the model gets no mask.
    #[serde(default)]
    pub attention_mask: Option<String>,
    /// The output tensor's name; default the model's first output.
    #[serde(default)]
    pub output: Option<String>,
    /// Tokens per text at most (special tokens included); default [`DEFAULT_MAX_LENGTH`].
    #[serde(default = "default_max_length")]
    pub max_length: usize,
    /// The padding token id; default the tokenizer's own, else 0.
    #[serde(default)]
    pub pad_id: Option<u32>,
    /// How a batch is padded; default `max-length`.
    #[serde(default)]
    pub padding: Padding,
    /// Prompt templates, each with one `{}` that the text replaces; default `["{}"]`.
    #[serde(default = "default_templates")]
    pub templates: Vec<String>,
}

fn clip_mean() -> [f32; 3] {
    CLIP_MEAN
}

fn clip_std() -> [f32; 3] {
    CLIP_STD
}

fn default_max_length() -> usize {
    DEFAULT_MAX_LENGTH
}

fn default_templates() -> Vec<String> {
    crate::prompts::default_templates()
}

/// The encoder. See the [module documentation](self).
#[derive(Debug)]
pub struct OnnxEncoder {
    image: ImageTower,
    text: Option<TextTower>,
    dim: usize,
}

#[derive(Debug)]
struct ImageTower {
    model: Model,
    input: String,
    output: String,
    width: u32,
    height: u32,
    mean: [f32; 3],
    std: [f32; 3],
    layout: ImageLayout,
}

#[derive(Debug)]
enum ImageLayout {
    Global {
        crop: CropSpec,
        batch: usize,
    },
    PatchGrid {
        grid_width: u32,
        grid_height: u32,
        skip_tokens: usize,
    },
}

/// An integer input of the text model and its element type.
#[derive(Debug)]
struct IdInput {
    name: String,
    int32: bool,
}

#[derive(Debug)]
struct TextTower {
    model: Model,
    tokenizer: Tokenizer,
    input_ids: IdInput,
    attention_mask: Option<IdInput>,
    token_type_ids: Option<IdInput>,
    output: String,
    max_length: usize,
    pad_id: u32,
    padding: Padding,
    templates: Vec<String>,
}

fn invalid(message: String) -> BackendError {
    BackendError::InvalidParams(message)
}

fn model_error(model: &Model, reason: String) -> BackendError {
    BackendError::InvalidModelFile {
        path: model.path().to_path_buf(),
        reason,
    }
}

/// The static length of axis `axis` of `shape`, `None` when dynamic or absent.
fn static_axis(shape: Option<&[i64]>, axis: usize) -> Option<usize> {
    shape
        .and_then(|s| s.get(axis))
        .and_then(|&d| usize::try_from(d).ok())
        .filter(|&d| d > 0)
}

impl OnnxEncoder {
    /// Builds the encoder from its parameters: loads ONNX Runtime and the models, checks the
    /// config against the models' inputs and outputs.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for inconsistent parameters; the errors of
    /// [`runtime::environment`] when ONNX Runtime cannot be loaded;
    /// [`BackendError::InvalidModelFile`] naming the file for a missing or unreadable model or
    /// tokenizer, or a model whose inputs or outputs do not fit the config.
    pub fn from_config(config: OnnxConfig, ctx: &BuildContext) -> Result<Self, BackendError> {
        // Parameter errors first: they need no library and no model.
        check_image_params(&config.image)?;
        if let Some(text) = &config.text {
            check_text_params(text)?;
        }
        if config.dim == Some(0) {
            return Err(invalid("dim must be positive".to_owned()));
        }
        let library = config.library.as_deref().map(|p| ctx.resolve(p));
        let environment = runtime::environment(library.as_deref())?;
        let image_model = Model::load(
            &environment,
            &ctx.resolve(&config.image.model),
            config.threads,
        )?;
        let (image, image_dim) = ImageTower::new(image_model, config.image)?;
        let dim = match (config.dim, image_dim) {
            (Some(configured), Some(found)) if configured != found => {
                return Err(model_error(
                    &image.model,
                    format!("the output has dimension {found}, the config says dim = {configured}"),
                ));
            }
            (Some(dim), _) | (None, Some(dim)) => dim,
            (None, None) => {
                return Err(model_error(
                    &image.model,
                    "the output's embedding axis is dynamic: set `dim` in [encoder]".to_owned(),
                ));
            }
        };
        let text = match config.text {
            Some(text) => {
                let model = Model::load(&environment, &ctx.resolve(&text.model), config.threads)?;
                let tokenizer = ctx.resolve(&text.tokenizer);
                Some(TextTower::new(model, &tokenizer, text, dim)?)
            }
            None => None,
        };
        Ok(Self { image, text, dim })
    }

    /// What the image model's output is.
    pub fn output_kind(&self) -> OutputKind {
        match self.image.layout {
            ImageLayout::Global { .. } => OutputKind::Global,
            ImageLayout::PatchGrid { .. } => OutputKind::PatchGrid,
        }
    }

    /// The image model's input size, `(width, height)`.
    pub fn input_size(&self) -> (u32, u32) {
        (self.image.width, self.image.height)
    }

    /// Whether the encoder has a text tower.
    pub fn has_text(&self) -> bool {
        self.text.is_some()
    }

    /// The image model.
    pub fn image_model(&self) -> &Model {
        &self.image.model
    }

    /// The image model's input for a whole frame, `3 × height × width` values: the frame
    /// resampled to the input size (unchanged when it has that size already) and normalised.
    /// This is what the `patch-grid` kind feeds the model.
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for an empty image.
    pub fn preprocess(&self, image: &RgbImage) -> Result<Vec<f32>, BackendError> {
        crate::patch_input::normalised_planes(
            image,
            self.image.width,
            self.image.height,
            self.image.mean,
            self.image.std,
        )
    }

    /// Runs the image model on `batch` preprocessed images (`batch × 3 × height × width`
    /// values, as [`OnnxEncoder::preprocess`] makes them) and returns its raw output. For tests
    /// and benchmarks that compare the model with a reference.
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] for a wrong input length; [`BackendError::Inference`].
    #[doc(hidden)]
    pub fn run_image_model(&self, input: &[f32], batch: usize) -> Result<Output, BackendError> {
        self.image.run(input, batch)
    }

    /// The model's embedding of each prompt, in order, as the text model gives it (not
    /// normalised, no templates), computed as one padded batch.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] when the encoder has no text model;
    /// [`BackendError::Inference`].
    pub fn embed_prompts(&self, prompts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        let text = self.text.as_ref().ok_or_else(|| {
            invalid("this onnx encoder has no text model ([encoder.text])".to_owned())
        })?;
        text.embed(prompts, self.dim)
    }

    /// The unit-norm embedding of each text: the normalised mean of the unit-norm embeddings
    /// of the text in every template.
    ///
    /// # Errors
    /// As [`OnnxEncoder::embed_prompts`].
    pub fn embed_texts(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        let text = self.text.as_ref().ok_or_else(|| {
            invalid("this onnx encoder has no text model ([encoder.text])".to_owned())
        })?;
        let templates = &text.templates;
        let prompts = crate::prompts::fill(templates, texts);
        let prompts: Vec<&str> = prompts.iter().map(String::as_str).collect();
        let embeddings = text.embed(&prompts, self.dim)?;
        embeddings
            .chunks(templates.len().max(1))
            .zip(texts)
            .map(|(group, t)| {
                crate::prompts::mean_of_unit(group, self.dim).ok_or_else(|| {
                    BackendError::Inference {
                        what: format!("embedding {t:?}"),
                        source: "the model gave a zero or non-finite embedding".into(),
                    }
                })
            })
            .collect()
    }

    fn encode(
        &self,
        image: &RgbImage,
        regions: &[Region],
    ) -> Result<PixelEmbeddings, BackendError> {
        match &self.image.layout {
            ImageLayout::Global { crop, batch } => {
                let crops = region_crops::crop_batch(image, regions, crop)?;
                let per_crop = 3 * crop.size as usize * crop.size as usize;
                let mut table = Vec::with_capacity(regions.len() * self.dim);
                for chunk in crops.chunks(batch * per_crop) {
                    let n = chunk.len() / per_crop;
                    let out = self.image.run(chunk, n)?;
                    check_shape(&out, &[n, self.dim], "the image model's output")?;
                    table.extend(out.data);
                }
                region_crops::region_embeddings(
                    image.width(),
                    image.height(),
                    regions,
                    self.dim,
                    table,
                )
            }
            ImageLayout::PatchGrid {
                grid_width,
                grid_height,
                skip_tokens,
            } => {
                let input = self.preprocess(image)?;
                let out = self.image.run(&input, 1)?;
                let (gw, gh) = (*grid_width as usize, *grid_height as usize);
                let data = match out.shape.len() {
                    3 => {
                        check_shape(
                            &out,
                            &[1, skip_tokens + gw * gh, self.dim],
                            "the image model's output",
                        )?;
                        out.data.get(skip_tokens * self.dim..).map(<[f32]>::to_vec)
                    }
                    _ => {
                        check_shape(&out, &[1, gh, gw, self.dim], "the image model's output")?;
                        Some(out.data)
                    }
                }
                .ok_or_else(|| inference("the image model's output", "too short"))?;
                PixelEmbeddings::from_patch_grid(
                    image.width(),
                    image.height(),
                    self.dim,
                    *grid_width,
                    *grid_height,
                    data,
                )
                .map_err(|e| BackendError::Inference {
                    what: "building the patch grid".to_owned(),
                    source: Box::new(e),
                })
            }
        }
    }
}

fn inference(what: &str, reason: impl Into<String>) -> BackendError {
    BackendError::Inference {
        what: what.to_owned(),
        source: reason.into().into(),
    }
}

/// Checks that `out` has exactly `shape`.
fn check_shape(out: &Output, shape: &[usize], what: &str) -> Result<(), BackendError> {
    let matches = out.shape.len() == shape.len()
        && out
            .shape
            .iter()
            .zip(shape)
            .all(|(&a, &b)| usize::try_from(a).is_ok_and(|a| a == b))
        && out.data.len() == shape.iter().product::<usize>();
    if matches {
        Ok(())
    } else {
        Err(inference(
            what,
            format!("has shape {:?}, expected {shape:?}", out.shape),
        ))
    }
}

/// Checks the image parameters that need no model.
fn check_image_params(c: &ImageConfig) -> Result<(), BackendError> {
    if c.size.is_some() && (c.width.is_some() || c.height.is_some()) {
        return Err(invalid(
            "[encoder.image] takes either size or width and height, not both".to_owned(),
        ));
    }
    if c.width.is_some() != c.height.is_some() {
        return Err(invalid(
            "[encoder.image] width and height go together (or use size for a square input)"
                .to_owned(),
        ));
    }
    for (key, side) in [("size", c.size), ("width", c.width), ("height", c.height)] {
        if let Some(side) = side
            && let Err(range) = vlem_core::ranges::count(side, 1, MAX_INPUT_SIDE, "pixels")
        {
            return Err(invalid(format!("[encoder.image] {key} {range}")));
        }
    }
    if let Some(bad) = c.std.iter().find(|s| !(s.is_finite() && **s != 0.0)) {
        return Err(invalid(format!(
            "[encoder.image] std must be finite and non-zero, got {bad}"
        )));
    }
    if c.mean.iter().any(|m| !m.is_finite()) {
        return Err(invalid("[encoder.image] mean must be finite".to_owned()));
    }
    let only = |what: &str, kind: &str| {
        invalid(format!(
            "[encoder.image] {what} applies to output_kind = \"{kind}\" only"
        ))
    };
    match c.output_kind {
        OutputKind::Global => {
            if c.patch_size.is_some() {
                return Err(only("patch_size", "patch-grid"));
            }
            if c.skip_tokens.is_some() {
                return Err(only("skip_tokens", "patch-grid"));
            }
            if c.width.is_some() && c.width != c.height {
                return Err(invalid(
                    "output_kind = \"global\" embeds square crops: set size, or width = height"
                        .to_owned(),
                ));
            }
            if let Some(batch) = c.batch
                && let Err(range) = vlem_core::ranges::count(batch, 1, MAX_BATCH, "")
            {
                return Err(invalid(format!("[encoder.image] batch {range}")));
            }
        }
        OutputKind::PatchGrid => {
            for (what, set) in [
                ("background", c.background.is_some()),
                ("seed", c.seed.is_some()),
                ("batch", c.batch.is_some()),
            ] {
                if set {
                    return Err(only(what, "global"));
                }
            }
            match c.patch_size {
                None => {
                    return Err(invalid(
                        "output_kind = \"patch-grid\" needs patch_size (e.g. 16)".to_owned(),
                    ));
                }
                Some(0) => return Err(invalid("patch_size must be positive".to_owned())),
                Some(_) => {}
            }
            if let Some(skip) = c.skip_tokens
                && let Err(range) = vlem_core::ranges::count(skip, 0, 1024, "tokens")
            {
                return Err(invalid(format!("[encoder.image] skip_tokens {range}")));
            }
        }
    }
    Ok(())
}

impl ImageTower {
    /// The tower over `model`, and the embedding dimension its output declares (`None` when
    /// dynamic).
    fn new(model: Model, c: ImageConfig) -> Result<(Self, Option<usize>), BackendError> {
        let (input, input_type) = model.input(c.input.as_deref())?.clone();
        if let Some(other) = model.inputs().iter().find(|(n, _)| *n != input) {
            return Err(model_error(
                &model,
                format!(
                    "the image model has inputs besides {input:?} (its inputs: {}); this \
                     encoder feeds one image input, {:?} has no value",
                    runtime::list_names(model.inputs()),
                    other.0
                ),
            ));
        }
        if runtime::element_type(&input_type) != Some(TensorElementType::Float32) {
            return Err(model_error(
                &model,
                format!("the image input {input:?} is not a float32 tensor: {input_type:?}"),
            ));
        }
        let shape = runtime::tensor_shape(&input_type);
        if let Some(shape) = shape
            && (shape.len() != 4 || static_axis(Some(shape), 1).is_some_and(|c| c != 3))
        {
            return Err(model_error(
                &model,
                format!(
                    "the image input {input:?} has shape {shape:?}; this encoder feeds \
                     batch × 3 × height × width"
                ),
            ));
        }
        let found = static_axis(shape, 3).zip(static_axis(shape, 2));
        let configured = match (c.size, c.width, c.height) {
            (Some(s), _, _) => Some((s, s)),
            (None, Some(w), Some(h)) => Some((w, h)),
            _ => None,
        };
        let (width, height) = match (configured, found) {
            (Some((w, h)), Some((fw, fh))) if (w as usize, h as usize) != (fw, fh) => {
                return Err(model_error(
                    &model,
                    format!(
                        "the image input {input:?} is {fw} wide and {fh} high, the config says \
                         {w} x {h}"
                    ),
                ));
            }
            (Some(size), _) => size,
            (None, Some((fw, fh))) => match (u32::try_from(fw), u32::try_from(fh)) {
                (Ok(w), Ok(h)) => (w, h),
                _ => {
                    return Err(model_error(
                        &model,
                        format!("input size {fw} x {fh} is too large"),
                    ));
                }
            },
            (None, None) => {
                return Err(model_error(
                    &model,
                    format!(
                        "the image input {input:?} has a dynamic size: set size (or width and \
                         height) in [encoder.image]"
                    ),
                ));
            }
        };
        let (output, output_type) = model.output(c.output.as_deref())?.clone();
        let out_shape = runtime::tensor_shape(&output_type);
        let rank = out_shape.map(<[i64]>::len);
        let dim = out_shape.and_then(|s| static_axis(Some(s), s.len().saturating_sub(1)));
        let layout = match c.output_kind {
            OutputKind::Global => {
                if width != height {
                    return Err(model_error(
                        &model,
                        format!(
                            "output_kind = \"global\" embeds square crops, but the input is \
                             {width} x {height}"
                        ),
                    ));
                }
                if rank.is_some_and(|r| r != 2) {
                    return Err(model_error(
                        &model,
                        format!(
                            "output {output:?} has shape {:?}; output_kind = \"global\" needs \
                             batch × dim",
                            out_shape.unwrap_or_default()
                        ),
                    ));
                }
                ImageLayout::Global {
                    crop: CropSpec {
                        size: width,
                        mean: c.mean,
                        std: c.std,
                        background: c.background.unwrap_or_default(),
                        seed: c.seed.unwrap_or(0),
                    },
                    batch: c.batch.unwrap_or(DEFAULT_BATCH),
                }
            }
            OutputKind::PatchGrid => {
                let patch = c.patch_size.unwrap_or(1);
                if width % patch != 0 || height % patch != 0 {
                    return Err(invalid(format!(
                        "the input size {width} x {height} is not a multiple of patch_size \
                         {patch}"
                    )));
                }
                let (gw, gh) = (width / patch, height / patch);
                let skip = c.skip_tokens.unwrap_or(0);
                let tokens = skip + gw as usize * gh as usize;
                match rank {
                    None => {}
                    Some(3) => {
                        if let Some(t) = static_axis(out_shape, 1)
                            && t != tokens
                        {
                            return Err(model_error(
                                &model,
                                format!(
                                    "output {output:?} has {t} tokens, but {skip} skipped \
                                     tokens and a {gw} x {gh} grid of {patch}-pixel patches \
                                     make {tokens}"
                                ),
                            ));
                        }
                    }
                    Some(4) => {
                        if skip != 0 {
                            return Err(invalid(
                                "skip_tokens applies to token outputs (batch × tokens × dim), \
                                 this output is batch × h × w × dim"
                                    .to_owned(),
                            ));
                        }
                        let grid = (static_axis(out_shape, 1), static_axis(out_shape, 2));
                        if grid.0.is_some_and(|h| h != gh as usize)
                            || grid.1.is_some_and(|w| w != gw as usize)
                        {
                            return Err(model_error(
                                &model,
                                format!(
                                    "output {output:?} has shape {:?}, but the grid of \
                                     {patch}-pixel patches is {gh} high and {gw} wide",
                                    out_shape.unwrap_or_default()
                                ),
                            ));
                        }
                    }
                    Some(_) => {
                        return Err(model_error(
                            &model,
                            format!(
                                "output {output:?} has shape {:?}; output_kind = \
                                 \"patch-grid\" needs batch × tokens × dim or \
                                 batch × h × w × dim",
                                out_shape.unwrap_or_default()
                            ),
                        ));
                    }
                }
                ImageLayout::PatchGrid {
                    grid_width: gw,
                    grid_height: gh,
                    skip_tokens: skip,
                }
            }
        };
        let tower = Self {
            model,
            input,
            output,
            width,
            height,
            mean: c.mean,
            std: c.std,
            layout,
        };
        Ok((tower, dim))
    }

    fn run(&self, input: &[f32], batch: usize) -> Result<Output, BackendError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if batch == 0 || input.len() != batch * 3 * w * h {
            return Err(BackendError::InvalidInput(format!(
                "{} input values for {batch} images of 3 x {h} x {w}",
                input.len()
            )));
        }
        let shape = vec![batch as i64, 3, h as i64, w as i64];
        let what = if batch == 1 {
            "running the image model".to_owned()
        } else {
            format!("running the image model on {batch} images")
        };
        self.model.run(
            vec![(self.input.as_str(), Input::F32(shape, input))],
            &self.output,
            &what,
        )
    }
}

/// The most crops in one image batch (`[encoder.image] batch`).
const MAX_BATCH: usize = 1024;
/// The widest or tallest model input accepted (`[encoder.image] size`, `width`, `height`).
const MAX_INPUT_SIDE: u32 = 4096;

/// Checks the text parameters that need no model.
fn check_text_params(c: &TextConfig) -> Result<(), BackendError> {
    // Every text batch holds texts × max_length ids (twice, with the mask): CLIP uses 77, and
    // text encoders of this kind stop at a few thousand positions.
    if let Err(range) = vlem_core::ranges::count(c.max_length, 2, 4096, "tokens") {
        return Err(invalid(format!("[encoder.text] max_length {range}")));
    }
    crate::prompts::check_templates(&c.templates, "[encoder.text]")
}

impl TextTower {
    fn new(
        model: Model,
        tokenizer_path: &std::path::Path,
        c: TextConfig,
        dim: usize,
    ) -> Result<Self, BackendError> {
        let tokenizer_error = |reason: String| BackendError::InvalidModelFile {
            path: tokenizer_path.to_path_buf(),
            reason,
        };
        if !tokenizer_path.is_file() {
            return Err(tokenizer_error("no such file".to_owned()));
        }
        let mut tokenizer = Tokenizer::from_file(tokenizer_path)
            .map_err(|e| tokenizer_error(format!("cannot load the tokenizer: {e}")))?;
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: c.max_length,
                ..TruncationParams::default()
            }))
            .map_err(|e| tokenizer_error(format!("cannot set truncation: {e}")))?;
        let pad_id = c
            .pad_id
            .or_else(|| tokenizer.get_padding().map(|p| p.pad_id))
            .unwrap_or(0);
        let vocabulary = tokenizer.get_vocab_size(true);
        if usize::try_from(pad_id).map_or(true, |id| id >= vocabulary) {
            return Err(invalid(format!(
                "[encoder.text] pad_id must be a token id of the tokenizer ({} holds {vocabulary} \
                 tokens, ids 0–{}), got {pad_id}",
                tokenizer_path.display(),
                vocabulary.saturating_sub(1)
            )));
        }
        // Padding is done per batch here, not by the tokenizer.
        tokenizer.with_padding(None);

        let id_input = |name: &str| -> Result<IdInput, BackendError> {
            let (_, dtype) = model.input(Some(name))?;
            match runtime::element_type(dtype) {
                Some(TensorElementType::Int64) => Ok(IdInput {
                    name: name.to_owned(),
                    int32: false,
                }),
                Some(TensorElementType::Int32) => Ok(IdInput {
                    name: name.to_owned(),
                    int32: true,
                }),
                _ => Err(model_error(
                    &model,
                    format!("the text input {name:?} is not an int64 or int32 tensor: {dtype:?}"),
                )),
            }
        };
        let ids_name = model.input(c.input_ids.as_deref())?.0.clone();
        let input_ids = id_input(&ids_name)?;
        let has = |name: &str| model.inputs().iter().any(|(n, _)| n == name);
        let attention_mask = match &c.attention_mask {
            Some(name) => Some(id_input(name)?),
            None if has("attention_mask") && ids_name != "attention_mask" => {
                Some(id_input("attention_mask")?)
            }
            None => None,
        };
        let token_type_ids = if has("token_type_ids") && ids_name != "token_type_ids" {
            Some(id_input("token_type_ids")?)
        } else {
            None
        };
        let fed: Vec<&str> = [
            Some(&input_ids),
            attention_mask.as_ref(),
            token_type_ids.as_ref(),
        ]
        .into_iter()
        .flatten()
        .map(|i| i.name.as_str())
        .collect();
        if let Some((unfed, _)) = model
            .inputs()
            .iter()
            .find(|(n, _)| !fed.contains(&n.as_str()))
        {
            return Err(model_error(
                &model,
                format!(
                    "the text model has an input {unfed:?} this encoder cannot feed (it feeds \
                     token ids, an attention mask and token type ids; the model's inputs: {})",
                    runtime::list_names(model.inputs())
                ),
            ));
        }
        let (output, output_type) = model.output(c.output.as_deref())?.clone();
        if let Some(shape) = runtime::tensor_shape(&output_type) {
            let last = static_axis(Some(shape), shape.len().saturating_sub(1));
            if shape.len() != 2 || last.is_some_and(|d| d != dim) {
                return Err(model_error(
                    &model,
                    format!(
                        "output {output:?} has shape {shape:?}; the text model must give \
                         batch × {dim} (the image embedding's dimension)"
                    ),
                ));
            }
        }
        Ok(Self {
            model,
            tokenizer,
            input_ids,
            attention_mask,
            token_type_ids,
            output,
            max_length: c.max_length,
            pad_id,
            padding: c.padding,
            templates: c.templates,
        })
    }

    /// The raw embeddings of `prompts`, one padded batch.
    fn embed(&self, prompts: &[&str], dim: usize) -> Result<Vec<Vec<f32>>, BackendError> {
        if prompts.is_empty() {
            return Ok(Vec::new());
        }
        let what = if prompts.len() == 1 {
            format!("embedding {:?}", prompts[0])
        } else {
            format!("embedding {} prompts", prompts.len())
        };
        let encodings = self
            .tokenizer
            .encode_batch(prompts.to_vec(), true)
            .map_err(|e| inference(&what, format!("tokenizer: {e}")))?;
        let longest = encodings.iter().map(|e| e.len()).max().unwrap_or(0);
        let length = match self.padding {
            Padding::MaxLength => self.max_length,
            Padding::Longest => longest.max(1),
        };
        let n = encodings.len();
        let mut ids = Vec::with_capacity(n * length);
        let mut mask = Vec::with_capacity(n * length);
        for e in &encodings {
            let tokens = e.get_ids();
            let kept = tokens.len().min(length);
            ids.extend(tokens.iter().take(kept).map(|&t| i64::from(t)));
            ids.extend(std::iter::repeat_n(i64::from(self.pad_id), length - kept));
            mask.extend(std::iter::repeat_n(1i64, kept));
            mask.extend(std::iter::repeat_n(0i64, length - kept));
        }
        let shape = vec![n as i64, length as i64];
        let as_input = |input: &IdInput, values: Vec<i64>| -> Input<'static> {
            if input.int32 {
                // Token ids and masks fit i32: ids come from a u32 vocabulary far below 2^31.
                Input::I32(
                    shape.clone(),
                    values.into_iter().map(|v| v as i32).collect(),
                )
            } else {
                Input::I64(shape.clone(), values)
            }
        };
        let mut inputs = vec![(self.input_ids.name.as_str(), as_input(&self.input_ids, ids))];
        if let Some(m) = &self.attention_mask {
            inputs.push((m.name.as_str(), as_input(m, mask)));
        }
        if let Some(t) = &self.token_type_ids {
            inputs.push((t.name.as_str(), as_input(t, vec![0; n * length])));
        }
        let out = self.model.run(inputs, &self.output, &what)?;
        check_shape(&out, &[n, dim], "the text model's output")?;
        Ok(out.data.chunks_exact(dim).map(<[f32]>::to_vec).collect())
    }
}

impl Encoder for OnnxEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn needs_regions(&self) -> bool {
        matches!(self.image.layout, ImageLayout::Global { .. })
    }

    fn encode_image(
        &self,
        image: &RgbImage,
        regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        self.encode(image, regions).map_err(|e| e.into_core(NAME))
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        if self.text.is_none() {
            return Err(CoreError::Unsupported {
                implementation: format!("encoder `{NAME}` without [encoder.text]"),
                capability: "text encoding",
            });
        }
        let mut out = self.embed_texts(&[text]).map_err(|e| e.into_core(NAME))?;
        out.pop().ok_or_else(|| {
            CoreError::stage(
                StageKind::Encoder,
                NAME,
                inference(&format!("embedding {text:?}"), "no embedding came back"),
            )
        })
    }
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`CoreError::InvalidParams`] for unknown keys or inconsistent parameters; a
/// [`CoreError::Stage`] naming the file when ONNX Runtime, a model or the tokenizer cannot be
/// loaded or does not fit the config.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: OnnxConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let encoder = OnnxEncoder::from_config(config, ctx).map_err(|e| e.into_core(NAME))?;
    Ok(Box::new(encoder))
}

vlem_core::register_encoder!(
    NAME,
    "any CLIP-like image (and text) encoder exported to ONNX, on ONNX Runtime; global or patch-grid output",
    build
);
