//! The SigLIP text tower that RADIO's `siglip` adaptor pairs with (open_clip
//! `ViT-SO400M-14-SigLIP-384`), on candle-transformers' `siglip` text model.
//!
//! Why it exists: NARADIO's patch grid lives in SigLIP's text space, so queries must be embedded
//! by the same tower, tokenised the way open_clip does it. This module owns the folder's `text/`
//! files (written by `convert_radio.py` under Hugging Face `SiglipTextModel` names), open_clip's
//! text cleaning ("canonicalize") and the fixed-length padding.

use std::path::Path;

use candle_core::{Device, Tensor};
use candle_nn::{Module, VarBuilder};
use candle_transformers::models::siglip;
use serde::Deserialize;
use tokenizers::{PaddingParams, PaddingStrategy, Tokenizer, TruncationParams};

use crate::ModelDtype;
use crate::error::BackendError;

/// The extra keys `convert_radio.py` writes into `text/config.json`.
#[derive(Clone, Debug, Deserialize)]
struct TextExtras {
    context_length: usize,
    pad_token_id: u32,
    #[serde(default = "default_clean")]
    text_clean: String,
}

fn default_clean() -> String {
    "canonicalize".to_owned()
}

/// open_clip's `canonicalize_text` (big_vision's): `_` to space, ASCII punctuation removed,
/// lower case, runs of whitespace collapsed, trimmed.
pub fn canonicalize(text: &str) -> String {
    let kept: String = text
        .chars()
        .map(|c| if c == '_' { ' ' } else { c })
        .filter(|c| !c.is_ascii_punctuation())
        .collect::<String>()
        .to_lowercase();
    kept.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// The SigLIP text tower with its tokenizer. Thread-safe.
#[derive(Clone)]
pub struct SiglipText {
    model: siglip::TextModel,
    tokenizer: Tokenizer,
    canonicalize: bool,
    context: usize,
    device: Device,
}

impl std::fmt::Debug for SiglipText {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SiglipText")
            .field("context", &self.context)
            .finish_non_exhaustive()
    }
}

fn invalid(path: &Path, reason: impl Into<String>) -> BackendError {
    BackendError::InvalidModelFile {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

impl SiglipText {
    /// Loads `dir/config.json`, `dir/model.safetensors` and `dir/tokenizer.json` onto `device`,
    /// the weights converted to `dtype`, the type the tower computes in (its output stays f32).
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] naming the file that cannot be read or does not fit.
    pub fn load(dir: &Path, device: &Device, dtype: ModelDtype) -> Result<Self, BackendError> {
        let config_path = dir.join("config.json");
        let text = crate::model_files::read_text(&config_path)?;
        let config: siglip::TextConfig =
            serde_json::from_str(&text).map_err(|e| invalid(&config_path, e.to_string()))?;
        let extras: TextExtras =
            serde_json::from_str(&text).map_err(|e| invalid(&config_path, e.to_string()))?;
        if extras.context_length == 0 || extras.context_length > config.max_position_embeddings {
            return Err(invalid(
                &config_path,
                format!(
                    "context_length {} outside 1..={}",
                    extras.context_length, config.max_position_embeddings
                ),
            ));
        }
        let canonicalize = match extras.text_clean.as_str() {
            "canonicalize" => true,
            "whitespace" => false,
            other => return Err(invalid(&config_path, format!("text_clean {other:?}"))),
        };
        let device = device.clone();
        let weights = dir.join("model.safetensors");
        let tensors = candle_core::safetensors::load(&weights, &device)
            .map_err(|e| invalid(&weights, format!("cannot read it: {e}")))?;
        let tensors = tensors
            .into_iter()
            .map(|(k, v)| v.to_dtype(dtype.candle()).map(|v| (k, v)))
            .collect::<candle_core::Result<std::collections::HashMap<_, _>>>()
            .map_err(|e| invalid(&weights, e.to_string()))?;
        let vb = VarBuilder::from_tensors(tensors, dtype.candle(), &device);
        let model = siglip::TextModel::new(&config, vb.pp("text_model"))
            .map_err(|e| invalid(&weights, e.to_string()))?;
        let tokenizer_path = dir.join("tokenizer.json");
        let mut tokenizer = Tokenizer::from_file(&tokenizer_path)
            .map_err(|e| invalid(&tokenizer_path, e.to_string()))?;
        let context = extras.context_length;
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: context,
                ..TruncationParams::default()
            }))
            .map_err(|e| invalid(&tokenizer_path, e.to_string()))?;
        let pad_token = tokenizer
            .id_to_token(extras.pad_token_id)
            .unwrap_or_default();
        tokenizer.with_padding(Some(PaddingParams {
            strategy: PaddingStrategy::Fixed(context),
            pad_id: extras.pad_token_id,
            pad_token,
            ..PaddingParams::default()
        }));
        Ok(Self {
            model,
            tokenizer,
            canonicalize,
            context,
            device,
        })
    }

    /// The token ids of each prompt, `context_length` each, as open_clip's `HFTokenizer` makes
    /// them (cleaned, `</s>` appended, truncated, padded).
    ///
    /// # Errors
    /// [`BackendError::Inference`] when the tokenizer fails.
    pub fn token_ids(&self, prompts: &[&str]) -> Result<Vec<Vec<u32>>, BackendError> {
        prompts
            .iter()
            .map(|p| {
                let text = if self.canonicalize {
                    canonicalize(p)
                } else {
                    p.split_whitespace().collect::<Vec<_>>().join(" ")
                };
                self.tokenizer
                    .encode(text, true)
                    .map(|e| e.get_ids().to_vec())
                    .map_err(|e| BackendError::Inference {
                        what: format!("tokenising {p:?}"),
                        source: e,
                    })
            })
            .collect()
    }

    /// The tower's output for each prompt (not normalised), `(prompts, width)` row-major.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when tokenising or the model fails.
    pub fn embed(&self, prompts: &[&str]) -> Result<Vec<Vec<f32>>, BackendError> {
        if prompts.is_empty() {
            return Ok(Vec::new());
        }
        let ids = self.token_ids(prompts)?;
        let flat: Vec<u32> = ids.iter().flatten().copied().collect();
        let run = || -> candle_core::Result<Vec<Vec<f32>>> {
            let input = Tensor::from_vec(flat, (prompts.len(), self.context), &self.device)?;
            self.model
                .forward(&input)?
                .to_dtype(candle_core::DType::F32)?
                .to_vec2::<f32>()
        };
        run().map_err(|e| BackendError::Inference {
            what: "the SigLIP text tower".to_owned(),
            source: Box::new(e),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonicalize_is_open_clips() {
        // Python: canonicalize_text("  The_Red SOFA!! , x-y ") == "the red sofa xy"
        assert_eq!(canonicalize("  The_Red SOFA!! , x-y "), "the red sofa xy");
        assert_eq!(canonicalize("a photo of a {}."), "a photo of a");
        assert_eq!(canonicalize(""), "");
    }
}
