//! The mask generator's first filters on the model's device ([`super::MaskFiltering::Device`]).
//!
//! Why it exists: on a GPU, the host path copies every prompt's three 256 × 256 logit maps to
//! the host (768 KiB a prompt, 25 MiB for a batch of 32) and upsamples each candidate to the
//! image there, one pixel at a time, while the GPU waits. Here only the predicted IoUs cross
//! first; the masks that pass are upsampled on the device by two matrix products (the
//! reference's two bilinear steps as one dense map per axis), their stability counted there,
//! and only the survivors cross, one byte per pixel. The arithmetic is the host path's, summed
//! in another order: the same masks up to logits within rounding of 0. Written in candle ops,
//! so the CPU test suite runs it too.

use candle_core::{DType, Device, Tensor};

use super::{Frame, GeneratedMask, GeneratorParams, Pass, SamModel};
use crate::error::BackendError;

/// One frame's upsampling on the device, for one image embedding.
pub(super) struct DeviceMasks<'a> {
    model: &'a SamModel,
    embeddings: &'a Tensor,
    /// `(height, 256)`: low-resolution rows to image rows.
    rows: Tensor,
    /// `(256, width)`: low-resolution columns to image columns (the transposed column map).
    columns_t: Tensor,
}

impl<'a> DeviceMasks<'a> {
    /// The upsampling maps of `frame` on the model's device.
    pub(super) fn new(
        model: &'a SamModel,
        embeddings: &'a Tensor,
        frame: &Frame,
    ) -> candle_core::Result<Self> {
        let device: &Device = model.device();
        let low = super::image::LOW_RES;
        let rows = Tensor::from_vec(frame.ys.matrix(), (frame.height, low), device)?;
        let columns_t = Tensor::from_vec(frame.xs.matrix(), (frame.width, low), device)?
            .t()?
            .contiguous()?;
        Ok(Self {
            model,
            embeddings,
            rows,
            columns_t,
        })
    }

    /// The candidates of one batch of prompts (see [`super::CandidatesFn`]).
    pub(super) fn candidates(
        &self,
        p: &GeneratorParams,
        frame: &Frame,
        points: &[[f64; 2]],
        input_points: &[[f32; 2]],
        pass: Pass,
    ) -> Result<Vec<GeneratedMask>, BackendError> {
        let failed = |what: &'static str| {
            move |e: candle_core::Error| BackendError::Inference {
                what: what.to_owned(),
                source: Box::new(e),
            }
        };
        let low = super::image::LOW_RES;
        let (masks, ious) = self
            .model
            .decode_points(self.embeddings, input_points)
            .map_err(failed("running the mask decoder"))?;
        let n = 3 * input_points.len();
        // The multimask outputs (1-3) of each prompt, prompt-major as the host path's.
        let logits = masks
            .narrow(1, 1, 3)
            .and_then(|m| m.reshape((n, low, low)))
            .map_err(failed("reading the mask logits"))?;
        let ious: Vec<f32> = ious
            .narrow(1, 1, 3)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.to_vec1())
            .map_err(failed("reading the IoU predictions"))?;
        let passed: Vec<u32> = (0..n)
            .filter(|&j| {
                ious.get(j)
                    .is_some_and(|&iou| super::passes_predicted_iou(p, iou))
            })
            .filter_map(|j| u32::try_from(j).ok())
            .collect();
        if passed.is_empty() {
            return Ok(Vec::new());
        }
        let (up, high, union) =
            crate::profile::timed("sam: mask filtering", self.model.device(), || {
                self.upsample_and_count(&logits, &passed, p.stability_score_offset)
            })
            .map_err(failed("upsampling the masks"))?;
        // Stability as the host computes it: intersections over unions, 0 for an empty union.
        let mut kept = Vec::new();
        let mut scores = Vec::new();
        for (k, (&h, &u)) in high.iter().zip(&union).enumerate() {
            let stability = if u == 0 { 0.0 } else { h as f32 / u as f32 };
            if super::passes_stability(p, stability) {
                kept.push(k as u32);
                scores.push(stability);
            }
        }
        if kept.is_empty() {
            return Ok(Vec::new());
        }
        let pixels = frame.width * frame.height;
        let binary: Vec<u8> = Tensor::new(kept.as_slice(), up.device())
            .and_then(|idx| up.index_select(&idx, 0))
            .and_then(|m| m.gt(0f32))
            .and_then(|m| m.flatten_all())
            .and_then(|m| m.to_vec1())
            .map_err(failed("reading the kept masks"))?;
        let mut out = Vec::with_capacity(kept.len());
        for ((&k, stability), bytes) in kept.iter().zip(scores).zip(binary.chunks_exact(pixels)) {
            let j = passed[k as usize] as usize;
            let mask: Vec<bool> = bytes.iter().map(|&b| b != 0).collect();
            let point = points.get(j / 3).copied().unwrap_or([0.0, 0.0]);
            out.extend(super::candidate(
                &mask,
                frame,
                (ious[j], stability),
                point,
                pass,
            ));
        }
        Ok(out)
    }

    /// The masks `passed` of `logits` `(n, 256, 256)` upsampled to the image, `(k, height,
    /// width)` f32, with each one's count of logits above `offset` and above `-offset`.
    fn upsample_and_count(
        &self,
        logits: &Tensor,
        passed: &[u32],
        offset: f32,
    ) -> candle_core::Result<(Tensor, Vec<u32>, Vec<u32>)> {
        let idx = Tensor::new(passed, logits.device())?;
        let low = logits.index_select(&idx, 0)?.to_dtype(DType::F32)?;
        // Columns first, `(k, 256, width)`, then rows, `(k, height, width)`: the host's order.
        let columns = low.broadcast_matmul(&self.columns_t)?;
        let up = self.rows.broadcast_matmul(&columns)?;
        let count = |above: f32| -> candle_core::Result<Vec<u32>> {
            up.gt(above)?
                .to_dtype(DType::U32)?
                .flatten_from(1)?
                .sum(1)?
                .to_vec1()
        };
        let high = count(offset)?;
        let union = count(-offset)?;
        Ok((up, high, union))
    }
}
