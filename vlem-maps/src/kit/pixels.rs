//! [`FramePixels`]: the pixels of one frame that a map integrates, back-projected into the world.
//!
//! Why it exists: every map starts its integration by walking the frame's depth image at its
//! `pixel_stride`, keeping the pixels with a valid depth (finite, > 0) no deeper than `max_depth`
//! that carry an embedding, and back-projecting them through the intrinsics and the camera pose.
//! It is the hot loop of integration, and the ground truth of `vlem-eval` needs the same points;
//! written once here, every map (and the ground truth) sees exactly the same points.

use std::iter::StepBy;
use std::ops::Range;

use rayon::prelude::*;
use vlem_core::types::valid_depth;
use vlem_core::{
    DepthImage, Intrinsics, Observation, PinholeF32, PixelEmbeddings, Pose, RgbImage, RigidF32,
};

use super::config::MapCommon;

/// One pixel of a frame with a valid depth, in world (map) coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pixel {
    /// Column.
    pub u: u32,
    /// Row.
    pub v: u32,
    /// Linear index `v * width + u` into the frame's images.
    pub index: u32,
    /// Depth in metres (the camera-frame `z`).
    pub depth: f32,
    /// The back-projected point in the world (map) frame.
    pub world: [f32; 3],
}

impl Pixel {
    /// The pixel's colour in `image` (the frame's colour image).
    #[inline]
    pub fn colour(&self, image: &RgbImage) -> [u8; 3] {
        image.at_index(self.index as usize)
    }
}

/// The valid pixels of one frame at a stride, in world coordinates: row-major with
/// [`FramePixels::iter`], or a row per task with [`FramePixels::par_iter`] (same order once
/// collected).
///
/// A pixel is yielded when its depth is finite, positive and at most `max_depth`, and, when the
/// frame has embeddings, [`PixelEmbeddings::has_embedding`] holds for it. Its world point is
/// `pose * ((u - cx) z / fx, (v - cy) z / fy, z)` in `f32`.
#[derive(Clone, Copy, Debug)]
pub struct FramePixels<'a> {
    depth: &'a [f32],
    width: u32,
    height: u32,
    k: PinholeF32,
    to_world: RigidF32,
    max_depth: f32,
    stride: u32,
    embeddings: Option<&'a PixelEmbeddings>,
}

impl<'a> FramePixels<'a> {
    /// The pixels a map with the shared parameters `common` integrates from `obs`: its
    /// `max_depth` and `pixel_stride`, and only pixels with an embedding when `obs` has
    /// embeddings. Check the observation first ([`check_observation`](super::check_observation)):
    /// the embeddings must be the size of the depth image.
    pub fn new(obs: &Observation<'a>, common: &MapCommon) -> Self {
        let frame = obs.frame;
        let mut pixels = Self::of_depth(
            &frame.depth,
            &frame.intrinsics,
            obs.pose,
            common.pixel_stride,
        );
        pixels.max_depth = common.max_depth;
        pixels.embeddings = obs.embeddings;
        pixels
    }

    /// Every `stride`-th pixel (in both directions, at least 1) of `depth` with a valid depth,
    /// at any depth, seen with `intrinsics` from the camera-to-world `pose`: the ground truth's
    /// view of a labelled frame. The intrinsics must be those of an image of the depth's size.
    pub fn of_depth(
        depth: &'a DepthImage,
        intrinsics: &Intrinsics,
        pose: &Pose,
        stride: u32,
    ) -> Self {
        Self {
            depth: depth.as_raw(),
            width: depth.width(),
            height: depth.height(),
            k: PinholeF32::from_intrinsics(intrinsics),
            to_world: RigidF32::from_pose(pose),
            max_depth: f32::INFINITY,
            stride: stride.max(1),
            embeddings: None,
        }
    }

    /// Width of the frame in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// The rows visited (every `stride`-th).
    pub fn rows(&self) -> StepBy<Range<u32>> {
        (0..self.height).step_by(self.stride as usize)
    }

    /// The yielded pixels of row `v`, left to right.
    #[inline]
    pub fn row(&self, v: u32) -> impl Iterator<Item = Pixel> + use<'a> {
        let this = *self;
        (0..this.width)
            .step_by(this.stride as usize)
            .filter_map(move |u| this.pixel(u, v))
    }

    /// Every yielded pixel, row-major.
    pub fn iter(&self) -> impl Iterator<Item = Pixel> + use<'a> {
        let this = *self;
        self.rows().flat_map(move |v| this.row(v))
    }

    /// Every yielded pixel, a row per task; `collect` keeps the row-major order of
    /// [`FramePixels::iter`].
    pub fn par_iter(&self) -> impl ParallelIterator<Item = Pixel> + use<'a> {
        let this = *self;
        (0..self.height)
            .into_par_iter()
            .step_by(self.stride as usize)
            .flat_map_iter(move |v| this.row(v))
    }

    /// Writes the world point and the linear pixel index of every yielded pixel into
    /// `positions` and `pixels` (cleared first; row-major, the order of [`FramePixels::iter`]),
    /// reusing their capacity, and returns the sum of the yielded depths.
    ///
    /// Why not `collect`: a map integrates a frame after frame, and fresh vectors of a frame's
    /// size cost a page fault per 4 KiB on every frame (milliseconds at 640×480). This counts the
    /// pixels of each row first and then fills each row's slice in parallel.
    pub fn collect_into(&self, positions: &mut Vec<[f32; 3]>, pixels: &mut Vec<u32>) -> f64 {
        let rows: Vec<u32> = self.rows().collect();
        let counts: Vec<usize> = rows
            .par_iter()
            .map(|&v| {
                (0..self.width)
                    .step_by(self.stride as usize)
                    .filter(|&u| self.kept_depth(u, v).is_some())
                    .count()
            })
            .collect();
        let total = counts.iter().sum();
        positions.clear();
        pixels.clear();
        positions.resize(total, [0.0; 3]);
        pixels.resize(total, 0);
        let mut row_slices = Vec::with_capacity(rows.len());
        let (mut positions_left, mut pixels_left) = (&mut positions[..], &mut pixels[..]);
        for (&v, &n) in rows.iter().zip(&counts) {
            let (p, p_rest) = std::mem::take(&mut positions_left).split_at_mut(n);
            let (i, i_rest) = std::mem::take(&mut pixels_left).split_at_mut(n);
            (positions_left, pixels_left) = (p_rest, i_rest);
            row_slices.push((v, p, i));
        }
        row_slices
            .into_par_iter()
            .map(|(v, positions, pixels)| {
                let mut depth_sum = 0.0f64;
                for ((position, index), pixel) in
                    positions.iter_mut().zip(pixels.iter_mut()).zip(self.row(v))
                {
                    *position = pixel.world;
                    *index = pixel.index;
                    depth_sum += f64::from(pixel.depth);
                }
                depth_sum
            })
            .sum()
    }

    /// The depth of pixel `(u, v)` if it is one to yield.
    #[inline]
    fn kept_depth(&self, u: u32, v: u32) -> Option<f32> {
        let z = valid_depth(self.depth[(v * self.width + u) as usize])?;
        if z > self.max_depth {
            return None;
        }
        if let Some(e) = self.embeddings
            && !e.has_embedding(u, v)
        {
            return None;
        }
        Some(z)
    }

    /// Pixel `(u, v)` if it is one to yield.
    #[inline]
    fn pixel(&self, u: u32, v: u32) -> Option<Pixel> {
        let z = self.kept_depth(u, v)?;
        let camera = [
            (u as f32 - self.k.cx) * z / self.k.fx,
            (v as f32 - self.k.cy) * z / self.k.fy,
            z,
        ];
        Some(Pixel {
            u,
            v,
            index: v * self.width + u,
            depth: z,
            world: self.to_world.apply(camera),
        })
    }
}

/// The embedding of the pixel with linear index `pixel`: the stored row in the region layout
/// (no copy), interpolated into `scratch` (of the embeddings' dimension) for a patch grid. `None`
/// for a pixel without one (outside every segment, or an interpolation that cancels out).
#[inline]
pub fn embedding<'s>(
    embeddings: &'s PixelEmbeddings,
    pixel: u32,
    scratch: &'s mut [f32],
) -> Option<&'s [f32]> {
    if let Some(row) = embeddings.region_row_at_index(pixel as usize) {
        return Some(row);
    }
    let width = embeddings.width();
    let (u, v) = (pixel % width, pixel / width);
    embeddings.embedding_at(u, v, scratch).then_some(&*scratch)
}
