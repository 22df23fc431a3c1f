//! 3D ground truth from labelled RGB-D frames: every labelled pixel with a valid depth is
//! back-projected with the frame's pose (by the maps' own [`FramePixels`], so the ground truth
//! and the maps see the same points) and the points are merged per voxel, keeping the majority
//! label.
//!
//! The same code serves every dataset that has label images (the synthetic scene, a folder with
//! `label/` and `labels.json`, ScanNet exports): the ground truth is the labelled surface the
//! camera saw. A voxel's position is the mean of its points (closer to the surface than the voxel
//! centre); its label is the id most of its pixels carry, the smallest id on a tie. Unlabelled
//! pixels (id 0) take part in the vote, and voxels where they win are dropped.

use rustc_hash::FxHashMap;
use serde::Serialize;
use vlem_core::{DepthImage, Frame, FrameSource, Intrinsics, Pose};
use vlem_maps::kit::FramePixels;

use super::classes::LabelRemap;
use crate::error::{EvalError, Result};

/// The voxel size of the VLEM protocol's ground truth (metres).
pub const DEFAULT_GT_VOXEL_SIZE: f64 = 0.02;

/// Labelled 3D points, one per occupied voxel.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct GroundTruth {
    /// Voxel size used (metres).
    pub voxel_size: f64,
    /// Positions (mean of the voxel's points), world frame, metres.
    pub positions: Vec<[f32; 3]>,
    /// Majority label per position (never 0).
    pub labels: Vec<u16>,
    /// Pixels back-projected in all.
    pub pixels: u64,
    /// Views added.
    pub views: usize,
}

impl GroundTruth {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// The points of one voxel: their sum, their count and a vote per label.
#[derive(Default)]
pub(crate) struct Voxel {
    sum: [f64; 3],
    points: u32,
    /// Count per label; few labels meet in one voxel, so a short list.
    labels: Vec<(u16, u32)>,
}

impl Voxel {
    /// Adds a point with its label.
    pub(crate) fn add(&mut self, p: [f32; 3], label: u16) {
        for (s, x) in self.sum.iter_mut().zip(p) {
            *s += f64::from(x);
        }
        self.points += 1;
        match self.labels.iter_mut().find(|(l, _)| *l == label) {
            Some((_, n)) => *n += 1,
            None => self.labels.push((label, 1)),
        }
    }

    /// The mean position and the majority label ([`majority`]); `None` for an empty voxel.
    pub(crate) fn result(&self) -> Option<([f32; 3], u16)> {
        let label = majority(&self.labels)?;
        let n = f64::from(self.points.max(1));
        Some((self.sum.map(|s| (s / n) as f32), label))
    }
}

/// The voxel of a point, for voxels `1 / inv` metres wide.
#[inline]
pub(crate) fn voxel_key(p: [f32; 3], inv: f64) -> [i32; 3] {
    p.map(|x| (f64::from(x) * inv).floor() as i32)
}

/// Accumulates labelled views into voxels; [`GroundTruthBuilder::finish`] gives the
/// [`GroundTruth`].
pub struct GroundTruthBuilder {
    voxel_size: f64,
    voxels: FxHashMap<[i32; 3], Voxel>,
    pixels: u64,
    views: usize,
}

impl GroundTruthBuilder {
    /// An empty builder with voxels of `voxel_size` metres.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] for a voxel size that is not positive and finite.
    pub fn new(voxel_size: f64) -> Result<Self> {
        if !(voxel_size.is_finite() && voxel_size > 0.0) {
            return Err(EvalError::InvalidParameter {
                name: "ground-truth voxel size".into(),
                value: voxel_size.to_string(),
                reason: "must be a positive number of metres".into(),
            });
        }
        Ok(Self {
            voxel_size,
            voxels: FxHashMap::default(),
            pixels: 0,
            views: 0,
        })
    }

    /// Back-projects every labelled pixel of one view (row-major `labels`, one id per pixel of
    /// `depth`) at its valid depth with the camera-to-world `pose`, every `pixel_stride`-th pixel
    /// in each direction. Returns the number of pixels added.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] when the label image, the depth image and the intrinsics
    /// disagree in size, or `pixel_stride` is 0.
    pub fn add_view(
        &mut self,
        labels: &[u16],
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        pose: &Pose,
        pixel_stride: usize,
    ) -> Result<usize> {
        let (w, h) = (depth.width(), depth.height());
        if labels.len() != w as usize * h as usize
            || (intrinsics.width, intrinsics.height) != (w, h)
        {
            return Err(EvalError::InvalidParameter {
                name: "label image".into(),
                value: format!("{} labels", labels.len()),
                reason: format!(
                    "the depth image is {w}x{h} and the intrinsics {}x{}",
                    intrinsics.width, intrinsics.height
                ),
            });
        }
        if pixel_stride == 0 {
            return Err(EvalError::InvalidParameter {
                name: "pixel stride".into(),
                value: "0".into(),
                reason: "must be at least 1".into(),
            });
        }
        let stride = u32::try_from(pixel_stride).unwrap_or(u32::MAX);
        let inv = 1.0 / self.voxel_size;
        let mut added = 0;
        for pixel in FramePixels::of_depth(depth, intrinsics, pose, stride).iter() {
            let label = labels[pixel.index as usize];
            let p = pixel.world;
            if !p.iter().all(|x| x.is_finite()) {
                continue;
            }
            self.voxels
                .entry(voxel_key(p, inv))
                .or_default()
                .add(p, label);
            added += 1;
        }
        self.pixels += added as u64;
        self.views += 1;
        Ok(added)
    }

    /// The labelled points, ordered by voxel (x, then y, then z index) so that runs are
    /// reproducible.
    pub fn finish(self) -> GroundTruth {
        let mut voxels: Vec<([i32; 3], Voxel)> = self.voxels.into_iter().collect();
        voxels.sort_unstable_by_key(|(key, _)| *key);
        let mut gt = GroundTruth {
            voxel_size: self.voxel_size,
            pixels: self.pixels,
            views: self.views,
            ..GroundTruth::default()
        };
        for (_, voxel) in voxels {
            if let Some((position, label)) = voxel.result()
                && label != 0
            {
                gt.positions.push(position);
                gt.labels.push(label);
            }
        }
        gt
    }
}

/// A frame's labels as NYU40 ids, through a remapping by class name that is rebuilt only when
/// the dataset's class table changes.
///
/// # Errors
/// [`EvalError::MissingLabels`] for a frame without labels (`dataset` names the dataset).
pub fn nyu40_labels(
    frame: &Frame,
    remap: &mut Option<LabelRemap>,
    dataset: &str,
) -> Result<Vec<u16>> {
    let Some(labels) = &frame.labels else {
        return Err(EvalError::MissingLabels {
            dataset: dataset.to_owned(),
        });
    };
    let current = match remap.take() {
        Some(r) if r.is_for(labels.names()) => r,
        _ => LabelRemap::new(labels.names()),
    };
    let ids = current.apply(labels.ids());
    *remap = Some(current);
    Ok(ids)
}

/// The ground truth of a whole dataset: every `stride`-th frame of `source` (its labels as NYU40
/// ids, its depth and pose) into voxels of `voxel_size` metres. `progress` is called after each
/// frame with the frames done and the frames to do. Also returns the dataset's class names that
/// are no NYU40 class (ignored).
///
/// # Errors
/// [`EvalError::MissingLabels`], [`EvalError::MissingPose`], a frame that cannot be read, or an
/// invalid voxel size or stride.
pub fn from_source(
    source: &mut dyn FrameSource,
    stride: usize,
    voxel_size: f64,
    mut progress: impl FnMut(usize, usize),
) -> Result<(GroundTruth, Vec<(u16, String)>)> {
    if stride == 0 {
        return Err(EvalError::InvalidParameter {
            name: "stride".into(),
            value: "0".into(),
            reason: "must be at least 1".into(),
        });
    }
    let dataset = source.describe();
    let mut builder = GroundTruthBuilder::new(voxel_size)?;
    let mut remap = None;
    let indices: Vec<usize> = (0..source.len()).step_by(stride).collect();
    for (done, &i) in indices.iter().enumerate() {
        let frame = source.frame(i)?;
        let ids = nyu40_labels(&frame, &mut remap, &dataset)?;
        let Some(pose) = frame.pose else {
            return Err(EvalError::MissingPose { frame: i, dataset });
        };
        builder.add_view(&ids, &frame.depth, &frame.intrinsics, &pose, 1)?;
        progress(done + 1, indices.len());
    }
    let unknown = remap.map(|r| r.unknown).unwrap_or_default();
    Ok((builder.finish(), unknown))
}

/// The label with the largest count, the smallest label on a tie; `None` for no labels.
pub fn majority(counts: &[(u16, u32)]) -> Option<u16> {
    counts
        .iter()
        .copied()
        .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)))
        .map(|(label, _)| label)
}

#[cfg(test)]
mod tests {
    use nalgebra::{Translation3, UnitQuaternion};

    use super::*;

    fn camera() -> Intrinsics {
        // 2x2 pixels, principal point between them: at depth 1 the four rays are ±5 mm apart.
        Intrinsics::new(2, 2, 100.0, 100.0, 0.5, 0.5).unwrap()
    }

    fn shifted() -> Pose {
        // Shift by (1, 1) cm so the four points (±5 mm) fall into the voxel [0, 2 cm)².
        Pose::from_parts(
            Translation3::new(0.01, 0.01, 0.0),
            UnitQuaternion::identity(),
        )
    }

    #[test]
    fn majority_prefers_count_then_smallest_label() {
        assert_eq!(majority(&[(5, 2), (3, 2), (7, 1)]), Some(3));
        assert_eq!(majority(&[(5, 3), (3, 2)]), Some(5));
        assert_eq!(majority(&[]), None);
    }

    #[test]
    fn views_merge_into_voxels_with_majority_labels() {
        let k = camera();
        let mut b = GroundTruthBuilder::new(0.02).unwrap();
        // View 1: labels 3, 3, 5 and an invalid depth.
        let depth = DepthImage::new(2, 2, vec![1.01, 1.01, 1.01, 0.0]).unwrap();
        assert_eq!(
            b.add_view(&[3, 3, 5, 0], &depth, &k, &shifted(), 1)
                .unwrap(),
            3
        );
        let gt = GroundTruthBuilder::finish(std::mem::replace(
            &mut b,
            GroundTruthBuilder::new(0.02).unwrap(),
        ));
        assert_eq!(gt.labels, vec![3]);
        assert_eq!(gt.pixels, 3);
        // Mean of (0.005, 0.005), (0.015, 0.005), (0.005, 0.015) times depth 1.01, plus the shift.
        let p = gt.positions[0];
        let expected = [
            0.01 + 1.01 * (-0.005 - 0.005 + 0.005) / 3.0,
            0.01 + 1.01 * (-0.005 - 0.005 + 0.005) / 3.0,
            1.01,
        ];
        for a in 0..3 {
            assert!(
                (f64::from(p[a]) - expected[a]).abs() < 1e-6,
                "{p:?} vs {expected:?}"
            );
        }

        // Label 5 wins over two views; an unlabelled voxel at depth 1.5 is dropped.
        let depth = DepthImage::new(2, 2, vec![1.01, 1.01, 1.01, 0.0]).unwrap();
        b.add_view(&[3, 3, 5, 0], &depth, &k, &shifted(), 1)
            .unwrap();
        let all = DepthImage::new(2, 2, vec![1.01; 4]).unwrap();
        b.add_view(&[5, 5, 5, 5], &all, &k, &shifted(), 1).unwrap();
        let far = DepthImage::new(2, 2, vec![1.51; 4]).unwrap();
        b.add_view(&[0, 0, 0, 4], &far, &k, &shifted(), 1).unwrap();
        let gt = b.finish();
        assert_eq!(gt.labels, vec![5]);
        assert_eq!(gt.pixels, 11);
        assert_eq!(gt.views, 3);
    }

    #[test]
    fn voxels_split_by_position_and_stride_skips_pixels() {
        // Without the shift, x = ±5 mm falls into voxels -1 and 0.
        let k = camera();
        let depth = DepthImage::new(2, 2, vec![1.01; 4]).unwrap();
        let mut b = GroundTruthBuilder::new(0.02).unwrap();
        b.add_view(&[1, 2, 3, 4], &depth, &k, &Pose::identity(), 1)
            .unwrap();
        let gt = b.finish();
        assert_eq!(gt.len(), 4);
        // Sorted by voxel index (x, y, z): (-1,-1), (-1,0), (0,-1), (0,0) are pixels 0, 2, 1, 3.
        assert_eq!(gt.labels, vec![1, 3, 2, 4]);
        let mut b = GroundTruthBuilder::new(0.02).unwrap();
        assert_eq!(
            b.add_view(&[1, 2, 3, 4], &depth, &k, &Pose::identity(), 2)
                .unwrap(),
            1
        );
    }

    #[test]
    fn bad_inputs_are_refused() {
        assert!(GroundTruthBuilder::new(0.0).is_err());
        assert!(GroundTruthBuilder::new(f64::NAN).is_err());
        let mut b = GroundTruthBuilder::new(0.02).unwrap();
        let depth = DepthImage::new(2, 2, vec![1.0; 4]).unwrap();
        let err = b
            .add_view(&[1, 2, 3], &depth, &camera(), &Pose::identity(), 1)
            .unwrap_err();
        assert!(err.to_string().contains("3 labels"), "{err}");
        assert!(
            b.add_view(&[1, 2, 3, 4], &depth, &camera(), &Pose::identity(), 0)
                .is_err()
        );
    }
}
