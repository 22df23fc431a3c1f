//! The whole SAM network: an image encoder (ViT or TinyViT), the prompt encoder and the mask
//! decoder, with the reference's preprocessing around them.
//!
//! Why it exists: the automatic mask generator needs two calls, "embed this image" (once per
//! frame) and "decode these point prompts" (once per batch of points); this module owns them and
//! the architecture choice, and knows nothing of grids, filters or regions.

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::VarBuilder;

use super::decoder::{MaskDecoder, PromptEncoder};
use super::image::{INPUT_SIZE, normalise_and_pad, preprocess_shape, resize_rgb_like_pillow};
use super::tiny_vit::{TinyVit, TinyVitConfig};
use super::vit::{ImageEncoderVit, VitConfig};

/// Which image encoder a SAM network has.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum EncoderConfig {
    /// SAM's ViT (`sam_vit_b_01ec64.pth` and the larger ones).
    Vit(VitConfig),
    /// MobileSAM's TinyViT (`mobile_sam.pt`).
    TinyVit(TinyVitConfig),
}

#[derive(Debug)]
enum ImageEncoder {
    Vit(Box<ImageEncoderVit>),
    TinyVit(Box<TinyVit>),
}

/// An image after SAM's preprocessing: its sizes before and after the resize, and the model
/// input.
#[derive(Debug)]
pub struct Preprocessed {
    /// Original `(height, width)`.
    pub original: (usize, usize),
    /// Resized `(height, width)`, longest side 1024.
    pub input: (usize, usize),
    /// The resized bytes (`input.1 * input.0 * 3`, interleaved RGB).
    pub resized: Vec<u8>,
    /// `(1, 3, 1024, 1024)` normalised, zero-padded input.
    pub tensor: Tensor,
}

/// A loaded SAM network; see the [module documentation](self).
#[derive(Debug)]
pub struct SamModel {
    encoder: ImageEncoder,
    prompt: PromptEncoder,
    decoder: MaskDecoder,
    dense_pe: Tensor,
    device: Device,
    /// What the network computes in (the var builder's type).
    dtype: DType,
}

impl SamModel {
    /// Loads the network from a var builder over a checkpoint with the reference's tensor names
    /// (`image_encoder.*`, `prompt_encoder.*`, `mask_decoder.*`); it computes in the builder's
    /// type.
    ///
    /// # Errors
    /// A missing tensor or one of the wrong shape; bf16 on the CPU (candle has no bf16
    /// convolutions there).
    pub fn new(vb: VarBuilder, encoder: &EncoderConfig) -> candle_core::Result<Self> {
        let device = vb.device().clone();
        let dtype = vb.dtype();
        if device.is_cpu() && dtype == DType::BF16 {
            candle_core::bail!("{}", super::BF16_ON_CPU);
        }
        let encoder = match encoder {
            EncoderConfig::Vit(cfg) => {
                ImageEncoder::Vit(Box::new(ImageEncoderVit::new(vb.pp("image_encoder"), cfg)?))
            }
            EncoderConfig::TinyVit(cfg) => {
                ImageEncoder::TinyVit(Box::new(TinyVit::new(vb.pp("image_encoder"), cfg)?))
            }
        };
        let prompt = PromptEncoder::new(vb.pp("prompt_encoder"))?;
        let decoder = MaskDecoder::new(vb.pp("mask_decoder"))?;
        let dense_pe = prompt.dense_pe()?;
        Ok(Self {
            encoder,
            prompt,
            decoder,
            dense_pe,
            device,
            dtype,
        })
    }

    /// The reference's preprocessing of an interleaved RGB image (resize longest side to 1024
    /// with Pillow's bilinear filter, normalise, pad).
    ///
    /// # Errors
    /// Only tensor creation failures.
    pub fn preprocess(
        &self,
        rgb: &[u8],
        width: usize,
        height: usize,
    ) -> candle_core::Result<Preprocessed> {
        let (ih, iw) = preprocess_shape(height, width, INPUT_SIZE);
        let resized = resize_rgb_like_pillow(rgb, width, height, iw, ih);
        let input = normalise_and_pad(&resized, iw, ih);
        let tensor = Tensor::from_vec(input, (1, 3, INPUT_SIZE, INPUT_SIZE), &self.device)?;
        Ok(Preprocessed {
            original: (height, width),
            input: (ih, iw),
            resized,
            tensor,
        })
    }

    /// `(1, 256, 64, 64)` image embeddings of a preprocessed input (any float type), in the
    /// network's [`dtype`](Self::dtype).
    ///
    /// # Errors
    /// Failures of the network.
    pub fn embed(&self, input: &Tensor) -> candle_core::Result<Tensor> {
        let input = input.to_dtype(self.dtype)?;
        crate::profile::timed("sam: image encoder (all)", &self.device, || {
            match &self.encoder {
                ImageEncoder::Vit(e) => e.forward(&input),
                ImageEncoder::TinyVit(e) => e.forward(&input),
            }
        })
    }

    /// Decodes one single-foreground-point prompt per entry of `points` (input-scale pixel
    /// coordinates `[x, y]`): all four mask logits `(B, 4, 256, 256)` and IoU predictions
    /// `(B, 4)`, in the network's type; index 0 is the single-mask output, 1-3 the multimask
    /// outputs.
    ///
    /// # Errors
    /// Failures of the network.
    pub fn decode_points(
        &self,
        embeddings: &Tensor,
        points: &[[f32; 2]],
    ) -> candle_core::Result<(Tensor, Tensor)> {
        crate::profile::timed("sam: mask decoder (all)", &self.device, || {
            let sparse = self.prompt.embed_points(points)?;
            let dense = self.prompt.no_mask_dense()?;
            self.decoder
                .forward(embeddings, &self.dense_pe, &dense, &sparse)
        })
    }

    /// The device the network runs on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The type the network computes in, and its outputs'.
    pub fn dtype(&self) -> DType {
        self.dtype
    }
}
