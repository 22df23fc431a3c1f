//! `sam`: the Segment Anything region proposer (`[proposer] kind = "sam"`), with the paper's
//! fill-in refinement.
//!
//! Why it exists: the paper's segment embeddings (section "Segment-Embeddings") encode one crop
//! per SAM region, and fill the areas SAM left unsegmented with a second round of point prompts.
//! This module owns that proposer: SAM (ViT-B/L/H or MobileSAM's TinyViT, on candle, CPU) run as
//! the reference's automatic mask generator, then the refinement. The mask decoder runs once per
//! grid point, so on the CPU its per-prompt image side is fused (`image_side`, `mask_head`); the
//! same network as candle ops is the path of other devices and the tests' reference.
//!
//! Per frame:
//! 1. The image is resized (longest side 1024, Pillow's bilinear filter), normalised, padded and
//!    embedded once.
//! 2. Automatic mask generator, as `SamAutomaticMaskGenerator` of the `segment-anything` package
//!    with one crop layer (the whole image; the reference's extra crop layers, off by default
//!    there too, are not implemented): a `points_per_side` grid of single foreground points,
//!    decoded `points_per_batch` at a time with multimask output (three masks per point); masks
//!    whose predicted IoU is not above `pred_iou_thresh` are dropped, the rest upsampled to the
//!    image (the reference's two bilinear steps) and kept if their stability score (IoU of the
//!    masks thresholded at ±`stability_score_offset`) reaches `stability_score_thresh`; box NMS at
//!    `box_nms_thresh` by predicted IoU; with `min_mask_region_area > 0`, holes and islands
//!    smaller than that are removed (8-connected components) and NMS runs again preferring
//!    unchanged masks. On a GPU the upsampling, the two thresholds and the masks' boxes run there
//!    ([`MaskFiltering`], `device_masks`); the masks wait there through NMS, which needs only
//!    their boxes and scores, and only those it keeps cross to the host, in one copy per pass.
//! 3. Refinement (`refine = true`): `refine_points` pixels drawn uniformly (seeded by `seed`)
//!    among those no mask covers are each decoded as a single foreground point and filtered the
//!    same way (IoU, stability, NMS, small regions); a fill-in mask whose box overlaps a kept
//!    mask's box by more than `box_nms_thresh` is dropped, the others are added.
//! 4. Each mask becomes a [`Region`]: its box (inclusive pixel extremes) and the mask inside it.
//!    Regions come in the order kept: first-pass masks by decreasing predicted IoU, then the
//!    fill-in masks.
//!
//! ```toml
//! [proposer]
//! kind = "sam"
//! weights = "models/mobile_sam.safetensors" # relative to the config file's folder
//! variant = "mobile-sam"                    # or "vit-b" (also "vit-l", "vit-h")
//! # points_per_side = 32
//! # points_per_batch = 32
//! # pred_iou_thresh = 0.88
//! # stability_score_thresh = 0.95
//! # stability_score_offset = 1.0
//! # box_nms_thresh = 0.7
//! # min_mask_region_area = 0
//! # refine = true
//! # refine_points = 32
//! # seed = 0
//! # device = "cpu"                         # "cuda", "cuda:N" with feature `cuda`
//! # dtype = "f32"                          # "f16", "bf16": the network in half precision
//! # tf32 = true                            # on a GPU, f32 products in TF32 (off by default)
//! ```
//!
//! Weights: the official checkpoints converted to safetensors with their tensor names, by
//! `vlem-backends/goldens/sam/convert_checkpoint.py` (see [`weights_hint`]).

pub mod amg;
pub mod decoder;
mod device_masks;
pub mod image;
mod image_side;
pub mod layers;
mod mask_head;
pub mod model;
pub mod synthetic;
pub mod tiny_vit;
pub mod vit;

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use serde::Deserialize;
use vlem_core::{BuildContext, PixelRect, Region, RegionProposer, RgbImage, StageKind};

use crate::error::BackendError;
use amg::{MaskBox, SmallRegions};
use image::AxisMap;
use model::{EncoderConfig, SamModel};

/// The name this proposer is registered under (`[proposer] kind = "sam"`).
pub const NAME: &str = "sam";

/// Which SAM checkpoint the weights are.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SamVariant {
    /// SAM ViT-B (`sam_vit_b_01ec64.pth`).
    VitB,
    /// SAM ViT-L (`sam_vit_l_0b3195.pth`).
    VitL,
    /// SAM ViT-H (`sam_vit_h_4b8939.pth`).
    VitH,
    /// MobileSAM (`mobile_sam.pt`, TinyViT encoder): the default.
    #[default]
    MobileSam,
}

impl SamVariant {
    /// The network shape of the variant's image encoder.
    pub fn encoder(self) -> EncoderConfig {
        match self {
            SamVariant::VitB => EncoderConfig::Vit(vit::VitConfig::vit_b()),
            SamVariant::VitL => EncoderConfig::Vit(vit::VitConfig::vit_l()),
            SamVariant::VitH => EncoderConfig::Vit(vit::VitConfig::vit_h()),
            SamVariant::MobileSam => EncoderConfig::TinyVit(tiny_vit::TinyVitConfig::mobile_sam()),
        }
    }

    /// A human name of the model, for messages.
    pub fn model_name(self) -> &'static str {
        match self {
            SamVariant::VitB => "SAM ViT-B",
            SamVariant::VitL => "SAM ViT-L",
            SamVariant::VitH => "SAM ViT-H",
            SamVariant::MobileSam => "MobileSAM",
        }
    }

    /// The official checkpoint's URL.
    pub fn checkpoint_url(self) -> &'static str {
        match self {
            SamVariant::VitB => {
                "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth"
            }
            SamVariant::VitL => {
                "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth"
            }
            SamVariant::VitH => {
                "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth"
            }
            SamVariant::MobileSam => {
                "https://github.com/ChaoningZhang/MobileSAM/raw/master/weights/mobile_sam.pt"
            }
        }
    }
}

/// How to get and convert the weights of `variant` into `path`.
pub fn weights_hint(variant: SamVariant, path: &Path) -> String {
    let url = variant.checkpoint_url();
    let file = url.rsplit('/').next().unwrap_or(url);
    format!(
        "download {url} on a connected machine, convert it with `python3 \
         vlem-backends/goldens/sam/convert_checkpoint.py {file} {}` (needs torch and \
         safetensors), and copy the result there",
        path.display()
    )
}

/// Parameters of the proposer: the `[proposer]` section without `kind`: the model's keys here,
/// every other key the mask generator's ([`GeneratorParams`]), each written once.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(try_from = "toml::Table")]
pub struct SamConfig {
    /// The safetensors weights (the official checkpoint's tensor names), relative to the config
    /// file's folder. Required.
    pub weights: Option<PathBuf>,
    /// Which checkpoint the weights are. Default `"mobile-sam"`.
    pub variant: SamVariant,
    /// Where the network runs: `"cpu"` (default), `"cuda"` or `"cuda:N"` (feature `cuda`). On a
    /// GPU the masks' upsampling and thresholds run there too ([`MaskFiltering::Device`]); box
    /// NMS and small-region removal run on the CPU.
    pub device: crate::ComputeDevice,
    /// What the network computes in: `"f32"` (default), `"f16"` or `"bf16"` (for a GPU; on the
    /// CPU half precision runs through candle's plain ops, slower than f32's fused decoder).
    pub dtype: crate::ModelDtype,
    /// `true`: on a GPU, f32 matrix products run on TF32 tensor cores (faster, 10-bit mantissa
    /// inputs); `false`: they do not; unset (default): left as it is, off unless a model asked.
    /// One setting per process (see [`crate::ComputeDevice::open_for`]).
    pub tf32: Option<bool>,
    /// The mask generator's parameters: the section's other keys.
    pub generator: GeneratorParams,
}

/// The keys of [`SamConfig`] that describe the model.
#[derive(Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct ModelKeys {
    weights: Option<PathBuf>,
    variant: SamVariant,
    device: crate::ComputeDevice,
    dtype: crate::ModelDtype,
    tf32: Option<bool>,
}

impl TryFrom<toml::Table> for SamConfig {
    type Error = toml::de::Error;

    /// Splits the section: the model's keys, then the generator's, which refuse any other key
    /// (`deny_unknown_fields`), so a typo is still an error naming it.
    fn try_from(mut section: toml::Table) -> Result<Self, Self::Error> {
        let mut model = toml::Table::new();
        for key in ["weights", "variant", "device", "dtype", "tf32"] {
            if let Some(value) = section.remove(key) {
                model.insert(key.to_owned(), value);
            }
        }
        let ModelKeys {
            weights,
            variant,
            device,
            dtype,
            tf32,
        } = model.try_into()?;
        Ok(Self {
            weights,
            variant,
            device,
            dtype,
            tf32,
            generator: section.try_into()?,
        })
    }
}

/// The mask generator's parameters (the `[proposer]` keys of `sam` besides the model's), with
/// the reference's defaults; [`GeneratorParams::check`] validates them.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GeneratorParams {
    /// Grid points per image side (the first pass decodes `points_per_side²` prompts).
    pub points_per_side: usize,
    /// Prompts decoded in one batch (memory: ~10 MB per prompt).
    pub points_per_batch: usize,
    /// Masks whose predicted IoU is not above this are dropped.
    pub pred_iou_thresh: f32,
    /// Masks whose stability score is below this are dropped.
    pub stability_score_thresh: f32,
    /// Logit offset of the two thresholds of the stability score.
    pub stability_score_offset: f32,
    /// Box IoU above which the lower-scored of two masks is dropped.
    pub box_nms_thresh: f32,
    /// Holes and islands smaller than this many pixels are removed; 0 turns it off (the
    /// reference's default).
    pub min_mask_region_area: usize,
    /// Whether to run the paper's fill-in refinement.
    pub refine: bool,
    /// Points sampled among the uncovered pixels for the refinement.
    pub refine_points: usize,
    /// Seed of the refinement's sampling.
    pub seed: u64,
}

impl Default for GeneratorParams {
    fn default() -> Self {
        Self {
            points_per_side: 32,
            points_per_batch: 32,
            pred_iou_thresh: 0.88,
            stability_score_thresh: 0.95,
            stability_score_offset: 1.0,
            box_nms_thresh: 0.7,
            min_mask_region_area: 0,
            refine: true,
            refine_points: 32,
            seed: 0,
        }
    }
}

impl GeneratorParams {
    /// Checks every value's range.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for values out of range.
    pub fn check(&self) -> Result<(), BackendError> {
        let bad = |m: String| Err(BackendError::InvalidParams(m));
        if !(1..=256).contains(&self.points_per_side) {
            return bad(format!(
                "points_per_side must be in 1..=256, got {}",
                self.points_per_side
            ));
        }
        if !(1..=1024).contains(&self.points_per_batch) {
            return bad(format!(
                "points_per_batch must be in 1..=1024, got {}",
                self.points_per_batch
            ));
        }
        for (name, v) in [
            ("pred_iou_thresh", self.pred_iou_thresh),
            ("stability_score_thresh", self.stability_score_thresh),
            ("box_nms_thresh", self.box_nms_thresh),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return bad(format!("{name} must be in [0, 1], got {v}"));
            }
        }
        // In mask-logit units (SAM's logits lie within a few tens): past 100 no mask is stable.
        if let Err(range) = vlem_core::ranges::number(self.stability_score_offset, 0.0, 100.0, "") {
            return bad(format!("stability_score_offset {range}"));
        }
        if let Err(range) =
            vlem_core::ranges::count(self.min_mask_region_area, 0, 1 << 24, "pixels")
        {
            return bad(format!("min_mask_region_area {range}"));
        }
        if self.refine_points > 65_536 {
            return bad(format!(
                "refine_points must be at most 65536, got {}",
                self.refine_points
            ));
        }
        Ok(())
    }
}

/// Which pass produced a mask.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    /// The automatic mask generator's grid.
    Grid,
    /// The fill-in refinement.
    Refine,
}

/// One generated mask with the reference's record fields.
#[derive(Clone, Debug, PartialEq)]
pub struct GeneratedMask {
    /// Inclusive box `[x0, y0, x1, y1]`.
    pub bbox: MaskBox,
    /// Row-major mask of the box's pixels.
    pub mask: Vec<bool>,
    /// The decoder's predicted IoU.
    pub predicted_iou: f32,
    /// The stability score.
    pub stability_score: f32,
    /// The prompt point, in image pixels.
    pub point: [f64; 2],
    /// The pass that made it.
    pub pass: Pass,
}

impl GeneratedMask {
    /// The mask's pixel count.
    pub fn area(&self) -> usize {
        self.mask.iter().filter(|&&m| m).count()
    }

    /// The mask as a [`Region`].
    pub fn to_region(&self) -> Region {
        let [x0, y0, x1, y1] = self.bbox;
        Region {
            bbox: PixelRect {
                x: x0,
                y: y0,
                width: x1 - x0 + 1,
                height: y1 - y0 + 1,
            },
            mask: self.mask.clone(),
        }
    }

    /// Sets the mask's pixels in a full-frame `width`-wide buffer.
    fn paint(&self, frame: &mut [bool], width: usize) {
        let [x0, y0, x1, _] = self.bbox.map(|v| v as usize);
        let bw = x1 - x0 + 1;
        for (r, row) in self.mask.chunks(bw).enumerate() {
            let start = (y0 + r) * width + x0;
            if let Some(dst) = frame.get_mut(start..start + bw) {
                for (d, &m) in dst.iter_mut().zip(row) {
                    *d |= m;
                }
            }
        }
    }

    /// The mask in a full `width x height` frame.
    fn full(&self, width: usize, height: usize) -> Vec<bool> {
        let mut frame = vec![false; width * height];
        self.paint(&mut frame, width);
        frame
    }
}

/// A mask cropped to its box: the box and the box's pixels.
type Cropped = (MaskBox, Vec<bool>);

/// Crops a full-frame mask to its box; `None` when empty.
fn crop_to_box(frame: &[bool], width: usize) -> Option<Cropped> {
    let bbox = amg::mask_to_box(frame, width)?;
    let [x0, y0, x1, y1] = bbox.map(|v| v as usize);
    let mut mask = Vec::with_capacity((x1 - x0 + 1) * (y1 - y0 + 1));
    for y in y0..=y1 {
        mask.extend_from_slice(&frame[y * width + x0..=y * width + x1]);
    }
    Some((bbox, mask))
}

/// A [`Candidate::held`] its source does not hold (a bug, reported rather than panicking).
fn unheld(held: usize) -> BackendError {
    BackendError::Inference {
        what: "collecting the kept masks".to_owned(),
        source: format!("no held mask {held}").into(),
    }
}

fn inference(what: &str) -> impl FnOnce(candle_core::Error) -> BackendError + '_ {
    move |e| BackendError::Inference {
        what: what.to_owned(),
        source: Box::new(e),
    }
}

/// Why SAM refuses bf16 on the CPU.
pub(crate) const BF16_ON_CPU: &str = "dtype = \"bf16\" runs SAM on a GPU only: candle's CPU \
     convolutions have no bf16 kernels; on the CPU use \"f32\" (fastest there) or \"f16\"";

/// SAM with the automatic mask generator and the fill-in refinement; see the
/// [module documentation](self).
#[derive(Debug)]
pub struct SamProposer {
    model: SamModel,
    params: GeneratorParams,
}

impl SamProposer {
    /// A proposer over a loaded network.
    pub fn new(model: SamModel, params: GeneratorParams) -> Self {
        Self { model, params }
    }

    /// Builds the proposer from its parameters: checks them, loads the weights.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for bad or missing parameters,
    /// [`BackendError::MissingWeights`] naming the file and how to get it,
    /// [`BackendError::InvalidModelFile`] for weights that do not fit the variant,
    /// [`BackendError::DeviceUnavailable`] for a `device` that cannot run it here.
    pub fn from_config(config: SamConfig, ctx: &BuildContext) -> Result<Self, BackendError> {
        config.generator.check()?;
        if config.dtype == crate::ModelDtype::Bf16 && config.device == crate::ComputeDevice::Cpu {
            return Err(BackendError::InvalidParams(BF16_ON_CPU.to_owned()));
        }
        let params = config.generator.clone();
        let variant = config.variant;
        let Some(weights) = config.weights.as_deref() else {
            return Err(BackendError::InvalidParams(format!(
                "`weights` must name the {} weights in safetensors form, e.g. weights = \
                 \"models/{}.safetensors\"; {}",
                variant.model_name(),
                match variant {
                    SamVariant::MobileSam => "mobile_sam",
                    SamVariant::VitB => "sam_vit_b",
                    SamVariant::VitL => "sam_vit_l",
                    SamVariant::VitH => "sam_vit_h",
                },
                weights_hint(variant, Path::new("<weights>"))
            )));
        };
        let path = ctx.resolve(weights);
        if !path.is_file() {
            return Err(BackendError::MissingWeights {
                model: variant.model_name(),
                hint: weights_hint(variant, &path),
                path,
            });
        }
        let device = config.device.open_for(config.dtype, config.tf32)?;
        let invalid = |reason: String| BackendError::InvalidModelFile {
            path: path.clone(),
            reason,
        };
        let tensors = candle_core::safetensors::load(&path, &device)
            .map_err(|e| invalid(format!("not a readable safetensors file: {e}")))?;
        let vb = VarBuilder::from_tensors(tensors, config.dtype.candle(), &device);
        let model = SamModel::new(vb, &variant.encoder()).map_err(|e| {
            invalid(format!(
                "does not hold {} weights with the official tensor names (variant = \"{}\"): {e}",
                variant.model_name(),
                match variant {
                    SamVariant::VitB => "vit-b",
                    SamVariant::VitL => "vit-l",
                    SamVariant::VitH => "vit-h",
                    SamVariant::MobileSam => "mobile-sam",
                }
            ))
        })?;
        Ok(Self::new(model, params))
    }

    /// The network.
    pub fn model(&self) -> &SamModel {
        &self.model
    }

    /// The generator parameters.
    pub fn params(&self) -> &GeneratorParams {
        &self.params
    }

    /// Gives the network and the parameters back (e.g. to rerun with other parameters without
    /// reloading the weights).
    pub fn into_parts(self) -> (SamModel, GeneratorParams) {
        (self.model, self.params)
    }

    /// Every mask of `image` with its record (see the [module documentation](self)), the masks
    /// filtered where the network runs: [`MaskFiltering::for_device`].
    ///
    /// # Errors
    /// [`BackendError::Inference`].
    pub fn generate(&self, image: &RgbImage) -> Result<Vec<GeneratedMask>, BackendError> {
        self.generate_with(image, MaskFiltering::for_device(self.model.device()))
    }

    /// [`Self::generate`] with the first filters (predicted IoU, stability) where `filtering`
    /// says: the same masks either way, up to logits within float rounding of 0.
    ///
    /// # Errors
    /// [`BackendError::Inference`].
    pub fn generate_with(
        &self,
        image: &RgbImage,
        filtering: MaskFiltering,
    ) -> Result<Vec<GeneratedMask>, BackendError> {
        let (w, h) = (image.width() as usize, image.height() as usize);
        if w == 0 || h == 0 {
            return Ok(Vec::new());
        }
        let pre = self
            .model
            .preprocess(image.as_raw(), w, h)
            .map_err(inference("preprocessing the image"))?;
        let embeddings = self
            .model
            .embed(&pre.tensor)
            .map_err(inference("running the image encoder"))?;
        match filtering {
            MaskFiltering::Host => {
                let mut decode = |points: &[[f32; 2]]| self.decode_multimask(&embeddings, points);
                generate_masks(&self.params, (w, h), pre.input, &mut decode)
            }
            MaskFiltering::Device => {
                let frame = Frame::new((w, h), pre.input);
                let mut device = device_masks::DeviceMasks::new(&self.model, &embeddings, &frame)
                    .map_err(inference("the mask filters' upsampling matrices"))?;
                generate_with(&self.params, &frame, &mut device)
            }
        }
    }

    /// The multimask outputs (masks 1-3) of single-point prompts, as flat vectors.
    fn decode_multimask(
        &self,
        embeddings: &Tensor,
        points: &[[f32; 2]],
    ) -> Result<(Vec<f32>, Vec<f32>), BackendError> {
        let (masks, ious) = self
            .model
            .decode_points(embeddings, points)
            .map_err(inference("running the mask decoder"))?;
        let device = self.model.device();
        let masks = crate::profile::timed("sam: mask logits to the host", device, || {
            masks
                .narrow(1, 1, 3)?
                .flatten_all()?
                .to_dtype(DType::F32)?
                .to_vec1::<f32>()
        })
        .map_err(inference("reading the mask logits"))?;
        let ious = ious
            .narrow(1, 1, 3)
            .and_then(|m| m.flatten_all())
            .and_then(|m| m.to_dtype(DType::F32))
            .and_then(|m| m.to_vec1::<f32>())
            .map_err(inference("reading the IoU predictions"))?;
        Ok((masks, ious))
    }
}

/// Decodes single-foreground-point prompts given in input (1024-scale) pixels: three
/// `256 x 256` logit maps per prompt (flat, prompt-major) and three predicted IoUs per prompt.
pub type DecodeFn<'a> = dyn FnMut(&[[f32; 2]]) -> Result<(Vec<f32>, Vec<f32>), BackendError> + 'a;

/// Where the generator's first filters run: each prompt's three masks are upsampled to the image
/// and held to the predicted-IoU and stability thresholds, and the survivors' boxes found. Box
/// NMS runs on the host either way, over boxes and scores only; small-region removal (off by
/// default) on the host, over the masks NMS kept, as in the reference (OpenCV on the CPU).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskFiltering {
    /// Every mask's low-resolution logits cross to the host, and those that pass the predicted
    /// IoU are upsampled there by their few taps per pixel: the CPU's fastest path.
    Host,
    /// On the model's device: only the predicted IoUs cross first; the masks that pass are
    /// upsampled there (two matrix products), their stability counted and their boxes found
    /// there, and they stay there through NMS: only the masks NMS keeps cross, in one copy per
    /// pass, as one byte per pixel. A GPU's path (tested on the CPU).
    Device,
}

impl MaskFiltering {
    /// [`Self::Host`] for the CPU, [`Self::Device`] for a GPU.
    pub fn for_device(device: &candle_core::Device) -> Self {
        if device.is_cpu() {
            Self::Host
        } else {
            Self::Device
        }
    }
}

/// A mask that passed the first filters, its pixels held by the [`CandidateSource`] that made it
/// until NMS has decided.
struct Candidate {
    bbox: MaskBox,
    predicted_iou: f32,
    stability_score: f32,
    point: [f64; 2],
    pass: Pass,
    /// Which of its source's held masks is this one's.
    held: usize,
}

/// Where the generator's candidates come from and where their masks wait: the host
/// ([`HostCandidates`]) or the model's device (`device_masks`).
trait CandidateSource {
    /// The candidates of one batch of prompts (`points` in image pixels, `input_points` the same
    /// in input pixels): each non-empty mask whose predicted IoU and stability pass.
    fn batch(
        &mut self,
        p: &GeneratorParams,
        frame: &Frame,
        points: &[[f64; 2]],
        input_points: &[[f32; 2]],
        pass: Pass,
    ) -> Result<Vec<Candidate>, BackendError>;

    /// The masks of `kept`, in that order, each cropped to its box; every held mask is
    /// forgotten, kept or not.
    fn take_masks(
        &mut self,
        frame: &Frame,
        kept: &[&Candidate],
    ) -> Result<Vec<Vec<bool>>, BackendError>;
}

/// The automatic mask generator and the refinement (steps 2-3 of the
/// [module documentation](self)) over any decoder: an image of `(width, height)` that was resized
/// to `input` = `(height, width)` for the network.
///
/// # Errors
/// The decoder's, and [`BackendError::Inference`] when it returns too few values.
pub fn generate_masks(
    params: &GeneratorParams,
    (w, h): (usize, usize),
    input: (usize, usize),
    decode: &mut DecodeFn<'_>,
) -> Result<Vec<GeneratedMask>, BackendError> {
    if w == 0 || h == 0 {
        return Ok(Vec::new());
    }
    let frame = Frame::new((w, h), input);
    let mut host = HostCandidates {
        decode,
        held: Vec::new(),
    };
    generate_with(params, &frame, &mut host)
}

/// [`generate_masks`] over any source of candidates.
fn generate_with(
    params: &GeneratorParams,
    frame: &Frame,
    candidates: &mut dyn CandidateSource,
) -> Result<Vec<GeneratedMask>, BackendError> {
    let (w, h) = (frame.width, frame.height);
    let grid: Vec<[f64; 2]> = amg::point_grid(params.points_per_side)
        .into_iter()
        .map(|[x, y]| [x * w as f64, y * h as f64])
        .collect();
    let mut masks = masks_for_points(params, frame, &grid, Pass::Grid, candidates)?;

    if params.refine && params.refine_points > 0 {
        let mut covered = vec![false; w * h];
        for m in &masks {
            m.paint(&mut covered, w);
        }
        // Pixel indices: the prompt encoder adds the half-pixel offset itself.
        let points: Vec<[f64; 2]> =
            amg::sample_uncovered(&covered, params.refine_points, params.seed)
                .into_iter()
                .map(|i| [(i % w) as f64, (i / w) as f64])
                .collect();
        if !points.is_empty() {
            let fill = masks_for_points(params, frame, &points, Pass::Refine, candidates)?;
            let kept: Vec<GeneratedMask> = fill
                .into_iter()
                .filter(|f| {
                    masks
                        .iter()
                        .all(|m| amg::box_iou(&m.bbox, &f.bbox) <= params.box_nms_thresh)
                })
                .collect();
            masks.extend(kept);
        }
    }
    Ok(masks)
}

/// Decodes `points` (image pixels) in batches and filters the masks: predicted IoU and stability
/// (by `source`), then NMS over the candidates' boxes, then the kept masks from `source`, then
/// small regions.
fn masks_for_points(
    p: &GeneratorParams,
    frame: &Frame,
    points: &[[f64; 2]],
    pass: Pass,
    source: &mut dyn CandidateSource,
) -> Result<Vec<GeneratedMask>, BackendError> {
    let mut candidates: Vec<Candidate> = Vec::new();
    for chunk in points.chunks(p.points_per_batch.max(1)) {
        let input_points: Vec<[f32; 2]> = chunk
            .iter()
            .map(|[x, y]| [(x * frame.scale[0]) as f32, (y * frame.scale[1]) as f32])
            .collect();
        candidates.extend(source.batch(p, frame, chunk, &input_points, pass)?);
    }
    let boxes: Vec<MaskBox> = candidates.iter().map(|c| c.bbox).collect();
    let scores: Vec<f32> = candidates.iter().map(|c| c.predicted_iou).collect();
    let keep = amg::nms(&boxes, &scores, p.box_nms_thresh);
    let kept: Vec<&Candidate> = keep.iter().filter_map(|&i| candidates.get(i)).collect();
    let masks = source.take_masks(frame, &kept)?;
    let kept: Vec<GeneratedMask> = kept
        .into_iter()
        .zip(masks)
        .map(|(c, mask)| GeneratedMask {
            bbox: c.bbox,
            mask,
            predicted_iou: c.predicted_iou,
            stability_score: c.stability_score,
            point: c.point,
            pass: c.pass,
        })
        .collect();
    if p.min_mask_region_area == 0 || kept.is_empty() {
        return Ok(kept);
    }
    Ok(remove_small_regions(p, kept, frame))
}

/// Whether a predicted IoU passes `pred_iou_thresh` (NaN-safe: one that is not above it, or NaN,
/// does not).
fn passes_predicted_iou(p: &GeneratorParams, iou: f32) -> bool {
    p.pred_iou_thresh <= 0.0 || iou.partial_cmp(&p.pred_iou_thresh) == Some(Ordering::Greater)
}

/// Whether a stability score passes `stability_score_thresh` (NaN-safe).
fn passes_stability(p: &GeneratorParams, stability: f32) -> bool {
    p.stability_score_thresh <= 0.0
        || matches!(
            stability.partial_cmp(&p.stability_score_thresh),
            Some(Ordering::Greater | Ordering::Equal)
        )
}

/// Candidates from a host decoder ([`MaskFiltering::Host`]): every mask's logits on the host,
/// upsampled there when its predicted IoU passes; the masks are held cropped to their boxes.
struct HostCandidates<'d, 'a> {
    decode: &'d mut DecodeFn<'a>,
    /// The cropped masks of this pass's candidates, by [`Candidate::held`].
    held: Vec<Option<Vec<bool>>>,
}

impl CandidateSource for HostCandidates<'_, '_> {
    fn batch(
        &mut self,
        p: &GeneratorParams,
        frame: &Frame,
        points: &[[f64; 2]],
        input_points: &[[f32; 2]],
        pass: Pass,
    ) -> Result<Vec<Candidate>, BackendError> {
        let plane = image::LOW_RES * image::LOW_RES;
        let (masks, ious) = (self.decode)(input_points)?;
        if masks.len() < points.len() * 3 * plane || ious.len() < points.len() * 3 {
            return Err(BackendError::Inference {
                what: "running the mask decoder".to_owned(),
                source: format!(
                    "{} logits and {} IoUs for {} prompts",
                    masks.len(),
                    ious.len(),
                    points.len()
                )
                .into(),
            });
        }
        let held = &mut self.held;
        let filter = || {
            let mut out = Vec::new();
            for (j, (logits, &iou)) in masks.chunks_exact(plane).zip(&ious).enumerate() {
                if !passes_predicted_iou(p, iou) {
                    continue;
                }
                let up = image::upsample_logits(logits, &frame.xs, &frame.ys);
                let stability = amg::stability_score(&up, 0.0, p.stability_score_offset);
                if !passes_stability(p, stability) {
                    continue;
                }
                let binary: Vec<bool> = up.iter().map(|&l| l > 0.0).collect();
                let Some((bbox, mask)) = crop_to_box(&binary, frame.width) else {
                    continue;
                };
                out.push(Candidate {
                    bbox,
                    predicted_iou: iou,
                    stability_score: stability,
                    point: points.get(j / 3).copied().unwrap_or([0.0, 0.0]),
                    pass,
                    held: held.len(),
                });
                held.push(Some(mask));
            }
            Ok(out)
        };
        crate::profile::timed("sam: mask filtering", &candle_core::Device::Cpu, filter).map_err(
            |e| BackendError::Inference {
                what: "filtering the masks".to_owned(),
                source: Box::new(e),
            },
        )
    }

    fn take_masks(
        &mut self,
        _frame: &Frame,
        kept: &[&Candidate],
    ) -> Result<Vec<Vec<bool>>, BackendError> {
        let mut held = std::mem::take(&mut self.held);
        kept.iter()
            .map(|c| {
                held.get_mut(c.held)
                    .and_then(Option::take)
                    .ok_or_else(|| unheld(c.held))
            })
            .collect()
    }
}

/// The reference's `postprocess_small_regions`: fills small holes, drops small islands, then
/// NMS again with unchanged masks first.
fn remove_small_regions(
    p: &GeneratorParams,
    masks: Vec<GeneratedMask>,
    frame: &Frame,
) -> Vec<GeneratedMask> {
    let (w, h) = (frame.width, frame.height);
    let area = p.min_mask_region_area;
    let mut updated = Vec::with_capacity(masks.len());
    let mut scores = Vec::with_capacity(masks.len());
    for m in &masks {
        let full = m.full(w, h);
        let (full, holes) = amg::remove_small_regions(&full, w, area, SmallRegions::Holes);
        let (full, islands) = amg::remove_small_regions(&full, w, area, SmallRegions::Islands);
        let changed = holes || islands;
        scores.push(if changed { 0.0 } else { 1.0 });
        updated.push(if changed { crop_to_box(&full, w) } else { None });
    }
    let boxes: Vec<MaskBox> = masks
        .iter()
        .zip(&updated)
        .map(|(m, u)| u.as_ref().map_or(m.bbox, |(b, _)| *b))
        .collect();
    // The reference uses max(box_nms_thresh, crop_nms_thresh) here; its crop default is 0.7.
    let keep = amg::nms(&boxes, &scores, p.box_nms_thresh.max(0.7));
    let mut slots: Vec<Option<(GeneratedMask, Option<Cropped>)>> =
        masks.into_iter().zip(updated).map(Some).collect();
    keep.iter()
        .filter_map(|&i| slots[i].take())
        .map(|(mut m, u)| {
            if let Some((bbox, mask)) = u {
                m.bbox = bbox;
                m.mask = mask;
            }
            m
        })
        .collect()
}

/// Per-frame geometry of the mask postprocessing.
struct Frame {
    width: usize,
    height: usize,
    /// Image pixels to input pixels, `[x, y]`.
    scale: [f64; 2],
    xs: AxisMap,
    ys: AxisMap,
}

impl Frame {
    /// An image of `(width, height)` resized to `input` = `(height, width)` for the network.
    fn new((w, h): (usize, usize), input: (usize, usize)) -> Self {
        Self {
            width: w,
            height: h,
            scale: [input.1 as f64 / w as f64, input.0 as f64 / h as f64],
            xs: AxisMap::new(input.1, w),
            ys: AxisMap::new(input.0, h),
        }
    }
}

impl RegionProposer for SamProposer {
    fn name(&self) -> &'static str {
        NAME
    }

    fn propose(&self, image: &RgbImage) -> vlem_core::Result<Vec<Region>> {
        let masks = self
            .generate(image)
            .map_err(|e| e.into_core_for(StageKind::Proposer, NAME))?;
        Ok(masks.iter().map(GeneratedMask::to_region).collect())
    }
}

/// Builds the proposer from its `[proposer]` parameters (the registered build function).
///
/// # Errors
/// [`vlem_core::CoreError::InvalidParams`] for unknown keys and bad values; a
/// [`vlem_core::CoreError::Stage`] naming the weights file and how to get it when it is missing.
pub fn build(
    params: &toml::Table,
    ctx: &BuildContext,
) -> vlem_core::Result<Box<dyn RegionProposer>> {
    let config: SamConfig = vlem_core::parse_params(StageKind::Proposer, NAME, params)?;
    let proposer = SamProposer::from_config(config, ctx)
        .map_err(|e| e.into_core_for(StageKind::Proposer, NAME))?;
    Ok(Box::new(proposer))
}

vlem_core::register_proposer!(
    NAME,
    "Segment Anything (MobileSAM or ViT-B) automatic masks with the paper's fill-in refinement \
     (needs converted weights, see `weights`)",
    build
);
