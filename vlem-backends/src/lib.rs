//! vlem-backends: vision-language encoders and region proposers, one cargo feature per backend.
//!
//! No backend is implemented yet. CLIP with SAM regions (`clip`, `sam`), generic ONNX encoders
//! (`onnx`), DINOv3 with dino.txt (`dinov3`) and NARADIO (`naradio`) will live here, each behind the
//! feature of its name. Until then the weight-free reference encoder is the plugin
//! `plugins/vlem-plugin-colour-names`.
