//! `dinov3`: the DINOv3 ViT backbone and the dino.txt heads on candle, CPU.
//!
//! Why it exists: the paper compares patch encoders, whose pixel-aligned embeddings come from a
//! ViT's patch grid rather than from region crops; DINOv3 with its dino.txt text alignment is
//! one of them. This module owns:
//! - the backbone ([`model`]): the released ViT-S/16, ViT-B/16, ViT-L/16 (and the gated "plus"
//!   sizes) in the Hugging Face `DINOv3ViTModel` layout, giving the patch tokens as a grid and
//!   the CLS and register tokens apart;
//! - the dino.txt vision head and text tower ([`dinotxt`]), read from Meta's released `.pth`
//!   checkpoint, which turn the ViT-L/16 tokens into per-patch embeddings and text into the
//!   same space;
//! - CLIP's BPE tokenizer ([`clip_bpe`]) that dino.txt's text tower was trained with;
//! - the registered patch encoder `dinov3` ([`encoder`]), which joins the three.

pub mod clip_bpe;
pub mod dinotxt;
pub mod encoder;
pub mod model;

pub use clip_bpe::ClipBpe;
pub use dinotxt::{DinoTxtHeads, TEXT_HEAD_DIM, VisionOutput};
pub use encoder::{Dinov3Encoder, Dinov3EncoderConfig};
pub use model::{
    Activation, BackboneOutput, DINOV3_INSTALL_HINT, Dinov3Backbone, Dinov3Config, rope_angles,
};
