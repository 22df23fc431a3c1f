//! The mask generator's first filters on the model's device ([`super::MaskFiltering::Device`]).
//!
//! Why it exists: on a GPU, the host path copies every prompt's three 256 × 256 logit maps to
//! the host (768 KiB a prompt, 25 MiB for a batch of 32) and upsamples each candidate to the
//! image there, one pixel at a time, while the GPU waits. Here only the predicted IoUs cross
//! first; the masks that pass are upsampled on the device by two matrix products (the
//! reference's two bilinear steps as one dense map per axis), their stability counted and their
//! boxes found there (six numbers a mask cross), and the survivors wait there, one byte per
//! pixel, while NMS decides on the host from boxes and scores alone. Only the masks NMS keeps
//! cross, in one copy per pass. The arithmetic is the host path's, summed in another order: the
//! same masks up to logits within rounding of 0. Written in candle ops, so the CPU test suite
//! runs it too.
//!
//! NMS itself stays on the host: it needs only the boxes, a few hundred of them, and its greedy
//! order is sequential; a device version would cost a synchronisation per step or an n² IoU
//! matrix copied back, for work the host does in microseconds.

use candle_core::{DType, Device, Tensor};

use super::amg::MaskBox;
use super::{Candidate, CandidateSource, Frame, GeneratorParams, Pass, SamModel};
use crate::error::BackendError;

/// One frame's filtering on the device, for one image embedding.
pub(super) struct DeviceMasks<'a> {
    model: &'a SamModel,
    embeddings: &'a Tensor,
    /// `(height, 256)`: low-resolution rows to image rows.
    rows: Tensor,
    /// `(256, width)`: low-resolution columns to image columns (the transposed column map).
    columns_t: Tensor,
    /// `1, 2, …, n` and `n, …, 2, 1` along each image axis, `[x, y]`: the largest product with a
    /// row's or column's occupancy is one past its last occupied index, or `n` minus its first.
    ramps: [(Tensor, Tensor); 2],
    /// This pass's held masks: per batch, the first [`Candidate::held`] index of its rows and
    /// the masks `(k, height, width)` u8.
    held: Vec<(usize, Tensor)>,
    /// The next [`Candidate::held`] index.
    next: usize,
}

/// `1..=n` and its reverse on `device`.
fn ramps(n: usize, device: &Device) -> candle_core::Result<(Tensor, Tensor)> {
    let up: Vec<f32> = (1..=n).map(|v| v as f32).collect();
    let down: Vec<f32> = up.iter().rev().copied().collect();
    Ok((
        Tensor::from_vec(up, n, device)?,
        Tensor::from_vec(down, n, device)?,
    ))
}

impl<'a> DeviceMasks<'a> {
    /// The upsampling maps and box ramps of `frame` on the model's device.
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
            ramps: [ramps(frame.width, device)?, ramps(frame.height, device)?],
            held: Vec::new(),
            next: 0,
        })
    }

    /// The masks `passed` of `logits` `(n, 256, 256)` upsampled to the image, `(k, height,
    /// width)` f32, with six numbers per mask, `(k, 6)` flat: its count of logits above `offset`
    /// and above `-offset`, then its box of positive logits as `[x0, y0, x1 + 1, y1 + 1]`
    /// (`x1 + 1 = 0` when it has none).
    fn upsample_and_measure(
        &self,
        logits: &Tensor,
        passed: &[u32],
        offset: f32,
    ) -> candle_core::Result<(Tensor, Vec<u32>)> {
        let idx = Tensor::new(passed, logits.device())?;
        let low = logits.index_select(&idx, 0)?.to_dtype(DType::F32)?;
        // Columns first, `(k, 256, width)`, then rows, `(k, height, width)`: the host's order.
        let columns = low.broadcast_matmul(&self.columns_t)?;
        let up = self.rows.broadcast_matmul(&columns)?;
        let count = |above: f32| -> candle_core::Result<Tensor> {
            up.gt(above)?.to_dtype(DType::U32)?.flatten_from(1)?.sum(1)
        };
        // A column (dim 1 reduced) or row (dim 2 reduced) is occupied when its largest logit is
        // positive; its extremes come from the ramps.
        let extremes = |reduced: usize, (up_ramp, down_ramp): &(Tensor, Tensor)| {
            let occupied = up.max(reduced)?.gt(0f32)?.to_dtype(DType::F32)?;
            let n = up_ramp.dim(0)? as f64;
            let past_last = occupied.broadcast_mul(up_ramp)?.max(1)?;
            let first = occupied.broadcast_mul(down_ramp)?.max(1)?.affine(-1.0, n)?;
            candle_core::Result::Ok((first, past_last))
        };
        let (x0, x1) = extremes(1, &self.ramps[0])?;
        let (y0, y1) = extremes(2, &self.ramps[1])?;
        let boxes = Tensor::stack(&[x0, y0, x1, y1], 1)?.to_dtype(DType::U32)?;
        let counts = Tensor::stack(&[count(offset)?, count(-offset)?], 1)?;
        let measures = Tensor::cat(&[counts, boxes], 1)?.flatten_all()?.to_vec1()?;
        Ok((up, measures))
    }
}

impl CandidateSource for DeviceMasks<'_> {
    fn batch(
        &mut self,
        p: &GeneratorParams,
        _frame: &Frame,
        points: &[[f64; 2]],
        input_points: &[[f32; 2]],
        pass: Pass,
    ) -> Result<Vec<Candidate>, BackendError> {
        let low = super::image::LOW_RES;
        let (masks, ious) = self
            .model
            .decode_points(self.embeddings, input_points)
            .map_err(super::inference("running the mask decoder"))?;
        let n = 3 * input_points.len();
        // The multimask outputs (1-3) of each prompt, prompt-major as the host path's.
        let logits = masks
            .narrow(1, 1, 3)
            .and_then(|m| m.reshape((n, low, low)))
            .map_err(super::inference("reading the mask logits"))?;
        let ious: Vec<f32> = ious
            .narrow(1, 1, 3)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.to_vec1())
            .map_err(super::inference("reading the IoU predictions"))?;
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
        let (up, measures) =
            crate::profile::timed("sam: mask filtering", self.model.device(), || {
                self.upsample_and_measure(&logits, &passed, p.stability_score_offset)
            })
            .map_err(super::inference("upsampling the masks"))?;
        // The rows of `up` that become candidates, and the candidates.
        let mut rows: Vec<u32> = Vec::new();
        let mut out = Vec::new();
        for (k, (&j, m)) in passed.iter().zip(measures.chunks_exact(6)).enumerate() {
            let &[high, union, x0, y0, x1, y1] = m else {
                continue;
            };
            // Stability as the host computes it: intersections over unions, 0 for an empty
            // union.
            let stability = if union == 0 {
                0.0
            } else {
                high as f32 / union as f32
            };
            // `x1 == 0`: no positive logit, an empty mask (the host path drops it too).
            if !super::passes_stability(p, stability) || x1 == 0 {
                continue;
            }
            let j = j as usize;
            out.push(Candidate {
                bbox: [x0, y0, x1 - 1, y1 - 1],
                predicted_iou: ious.get(j).copied().unwrap_or(f32::NAN),
                stability_score: stability,
                point: points.get(j / 3).copied().unwrap_or([0.0, 0.0]),
                pass,
                held: self.next + rows.len(),
            });
            rows.push(k as u32);
        }
        if !rows.is_empty() {
            let binary = Tensor::new(rows.as_slice(), up.device())
                .and_then(|idx| up.index_select(&idx, 0))
                .and_then(|m| m.gt(0f32))
                .map_err(super::inference("holding the masks"))?;
            self.held.push((self.next, binary));
            self.next += rows.len();
        }
        Ok(out)
    }

    fn take_masks(
        &mut self,
        frame: &Frame,
        kept: &[&Candidate],
    ) -> Result<Vec<Vec<bool>>, BackendError> {
        let held = std::mem::take(&mut self.held);
        self.next = 0;
        if kept.is_empty() {
            return Ok(Vec::new());
        }
        // Per batch, its kept rows in NMS order; `slot[i]` is where kept mask `i` lands in the
        // one copy (the batches' selections one after another).
        let mut parts = Vec::new();
        let mut slot = vec![None; kept.len()];
        let mut landed = 0;
        for (first, masks) in &held {
            let count = masks
                .dim(0)
                .map_err(super::inference("collecting the kept masks"))?;
            let mut rows: Vec<u32> = Vec::new();
            for (i, c) in kept.iter().enumerate() {
                if (*first..first + count).contains(&c.held) {
                    rows.push((c.held - first) as u32);
                    slot[i] = Some(landed);
                    landed += 1;
                }
            }
            if !rows.is_empty() {
                let part = Tensor::new(rows.as_slice(), masks.device())
                    .and_then(|idx| masks.index_select(&idx, 0))
                    .map_err(super::inference("collecting the kept masks"))?;
                parts.push(part);
            }
        }
        let bytes: Vec<u8> =
            crate::profile::timed("sam: kept masks to the host", self.model.device(), || {
                Tensor::cat(&parts, 0)?.flatten_all()?.to_vec1()
            })
            .map_err(super::inference("copying the kept masks"))?;
        let pixels = frame.width * frame.height;
        kept.iter()
            .zip(slot)
            .map(|(c, s)| {
                let full = s
                    .and_then(|s| bytes.get(s * pixels..(s + 1) * pixels))
                    .ok_or_else(|| super::unheld(c.held))?;
                Ok(crop(full, frame.width, c.bbox))
            })
            .collect()
    }
}

/// The pixels of `bbox` (inclusive) in a full-frame `width`-wide byte mask.
fn crop(full: &[u8], width: usize, bbox: MaskBox) -> Vec<bool> {
    let [x0, y0, x1, y1] = bbox.map(|v| v as usize);
    let mut mask = Vec::with_capacity((x1 + 1 - x0) * (y1 + 1 - y0));
    for y in y0..=y1 {
        let row = full.get(y * width + x0..=y * width + x1).unwrap_or(&[]);
        mask.extend(row.iter().map(|&b| b != 0));
    }
    mask
}
