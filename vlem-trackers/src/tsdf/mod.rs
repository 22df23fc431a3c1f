//! A TSDF voxel-block map: fuses posed RGB-D frames into a truncated signed distance field with
//! colour, ray-casts it into model depth + colour images, and extracts its surface.
//!
//! Why it exists: frame-to-model tracking (KinectFusion; Open3D's `t.pipelines.slam.Model`)
//! registers each new frame against an image ray-cast from everything fused so far rather than
//! against the previous frame alone, which averages sensor noise and cuts drift. The same volume
//! gives the dense coloured mesh a tracker exports beside the embedding map.
//!
//! What it owns: the voxels. Space is cut into blocks of `8 x 8 x 8` voxels, allocated only where a
//! frame observed a surface (within the truncation distance of a measured depth), so memory grows
//! with the observed surface, not with the bounding box. A hash map ([`rustc_hash::FxHashMap`])
//! maps block coordinates to indices into a vector of blocks. Each block keeps its voxels' TSDF
//! (`f32`), weight (`u16`) and colour (`u16` fixed point per channel) in one array per field,
//! plus an 8-bit copy of the TSDF in `4³` bricks that ray marching reads (6.5 KiB per block).
//!
//! How the work is done:
//! - [`TsdfVolume::integrate`] gathers the blocks a frame touches (in parallel over bands of
//!   rows), allocates the new ones serially, then updates the touched blocks in parallel, ordered
//!   by where they project so that neighbouring blocks read neighbouring pixels; no hash lookup
//!   per voxel.
//! - [`TsdfVolume::raycast`] first projects the blocks in view into 8x8-pixel tiles to get, per
//!   tile, the depth range worth marching (Open3D's range map), and builds a dense grid of the
//!   blocks in view (plus a coarse occupancy grid of `4³`-block superblocks) so that marching
//!   rays look blocks up by index and skip empty space a superblock at a time; rows are cast in
//!   parallel. See the `raycast` module for the march and the sub-voxel refinement.
//! - [`TsdfVolume::extract_mesh`] / [`TsdfVolume::extract_points`] run per block in parallel on a
//!   copy of the block and the first layer of its `+x, +y, +z` neighbours.
//!
//! Conventions follow Open3D's voxel block grid so that results compare one to one:
//! - the voxel with integer index `g` has its centre at `g * voxel_size` (world, metres);
//! - the signed distance is projective: `sdf = depth(pixel) - z_camera(voxel)`, positive in front
//!   of the surface; voxels with `sdf < -trunc` are left alone, and the stored value is
//!   `min(sdf, trunc) / trunc` in `[-1, 1]`, averaged over frames with weight `+1` per frame
//!   (capped at [`TsdfConfig::max_weight`]);
//! - blocks are allocated around the depth of every `allocation_stride`-th pixel in each direction
//!   (Open3D uses 4), along the viewing ray from `depth - trunc` to `depth + trunc`;
//! - a ray cast reports camera-z depth of the first + to − zero crossing whose voxel has at least
//!   `min(frames fused, 3)` observations (Open3D's SLAM model's weight threshold).
//!
//! Unlike Open3D, blocks are `8³` voxels (Open3D's SLAM model uses `16³`; the memory is the
//! same per voxel, the allocation follows the surface more tightly), weights are capped, and the
//! ray-cast depth is refined on the trilinearly interpolated TSDF (one Newton step) rather than
//! interpolated between the two nearest-voxel samples.
//!
//! See [`TsdfVolume`] for the operations.

mod block;
mod integrate;
mod mc_table;
mod mesh;
mod raycast;
#[cfg(test)]
mod tests;

use std::fmt;

use rustc_hash::FxHashMap;
use vlem_core::types::pose_is_finite;
use vlem_core::{DepthImage, Intrinsics, PinholeF32, Pose, RgbImage};

use crate::error::TrackerError;
use block::{BLOCK_RES, Block};
pub use raycast::{RaycastImage, RaycastOptions};

/// Parameters of a [`TsdfVolume`]. The defaults are those of Open3D's `t.pipelines.slam.Model`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TsdfConfig {
    /// Voxel edge in metres. Default 3/512 m (a 3 m cube at 512³).
    pub voxel_size: f32,
    /// Voxels per block edge. Only 8 is supported (blocks of `8³` voxels).
    pub block_resolution: usize,
    /// Truncation distance in voxels: `sdf_trunc = truncation_voxels * voxel_size`. Default 8
    /// (Open3D's `trunc_voxel_multiplier`). At least 1.
    pub truncation_voxels: f32,
    /// Depths nearer than this many metres are not fused, and ray casts start here. Default 0.1.
    pub depth_min: f32,
    /// Depths beyond this many metres are not fused, and ray casts stop here. Default 3.
    pub depth_max: f32,
    /// Cap of a voxel's fusion weight (observations counted), in `[1, 65535]`; past it the
    /// running average becomes a moving average, so the map can follow changes. Default 255.
    pub max_weight: f32,
    /// Blocks are allocated around every `allocation_stride`-th pixel in x and y. Default 4, as
    /// Open3D; 1 allocates around every pixel (slower, fewer holes at grazing angles).
    pub allocation_stride: usize,
}

impl Default for TsdfConfig {
    fn default() -> Self {
        Self {
            voxel_size: 3.0 / 512.0,
            block_resolution: BLOCK_RES,
            truncation_voxels: 8.0,
            depth_min: 0.1,
            depth_max: 3.0,
            max_weight: 255.0,
            allocation_stride: 4,
        }
    }
}

/// The finest TSDF voxel accepted (1 mm): finer, a frame's blocks number in the millions.
pub const MIN_VOXEL_SIZE: f32 = 0.001;
/// The coarsest TSDF voxel accepted (1 m).
pub const MAX_VOXEL_SIZE: f32 = 1.0;
/// The widest truncation band accepted, in voxels (Open3D's examples use 4–8).
pub const MAX_TRUNCATION_VOXELS: f32 = 64.0;
/// The farthest depth fused, in metres (no RGB-D sensor measures farther).
const MAX_DEPTH_M: f32 = 100.0;

impl TsdfConfig {
    /// Checks every parameter.
    ///
    /// # Errors
    /// [`TrackerError::InvalidParameter`] naming the first bad parameter.
    pub fn validate(&self) -> Result<(), TrackerError> {
        let fail = |name: &'static str, reason: String| {
            Err(TrackerError::InvalidParameter { name, reason })
        };
        if !(self.voxel_size.is_finite() && self.voxel_size > 0.0) {
            return fail(
                "voxel_size",
                format!(
                    "must be a positive number of metres, got {}",
                    self.voxel_size
                ),
            );
        }
        if !(MIN_VOXEL_SIZE..=MAX_VOXEL_SIZE).contains(&self.voxel_size) {
            return fail(
                "voxel_size",
                format!(
                    "must lie in {MIN_VOXEL_SIZE}–{MAX_VOXEL_SIZE} m (a finer grid allocates \
                     blocks without bound, a coarser one is no model of a room), got {}",
                    self.voxel_size
                ),
            );
        }
        if self.block_resolution != BLOCK_RES {
            return fail(
                "block_resolution",
                format!(
                    "must be {BLOCK_RES} (blocks of {BLOCK_RES}³ voxels), got {}",
                    self.block_resolution
                ),
            );
        }
        // Each ray allocates the blocks within the truncation distance of its surface, so a
        // wide band allocates without bound (1e6 voxels: kilometres of blocks per ray).
        if let Err(range) =
            vlem_core::ranges::number(self.truncation_voxels, 1.0, MAX_TRUNCATION_VOXELS, "voxels")
        {
            return fail("truncation_voxels", range);
        }
        if !(self.depth_min.is_finite() && self.depth_min >= 0.0) {
            return fail(
                "depth_min",
                format!(
                    "must be a finite, non-negative number of metres, got {}",
                    self.depth_min
                ),
            );
        }
        if !(self.depth_max.is_finite() && self.depth_max > self.depth_min) {
            return fail(
                "depth_max",
                format!(
                    "must be finite and greater than depth_min = {}, got {}",
                    self.depth_min, self.depth_max
                ),
            );
        }
        if let Err(range) = vlem_core::ranges::number(self.depth_max, 0.0, MAX_DEPTH_M, "m") {
            return fail("depth_max", range);
        }
        if !(self.max_weight >= 1.0 && self.max_weight <= f32::from(u16::MAX)) {
            return fail(
                "max_weight",
                format!("must lie in [1, 65535], got {}", self.max_weight),
            );
        }
        if !(1..=64).contains(&self.allocation_stride) {
            return fail(
                "allocation_stride",
                format!("must lie in [1, 64] pixels, got {}", self.allocation_stride),
            );
        }
        Ok(())
    }

    /// The truncation distance in metres.
    pub fn sdf_trunc(&self) -> f32 {
        self.truncation_voxels * self.voxel_size
    }
}

/// Pinhole intrinsics in `f32`, with the image size.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Camera32 {
    width: usize,
    height: usize,
    k: PinholeF32,
}

impl Camera32 {
    fn new(k: &Intrinsics) -> Self {
        Self {
            width: k.width as usize,
            height: k.height as usize,
            k: PinholeF32::from_intrinsics(k),
        }
    }
}

/// `floor(x)` as an integer, without a libm call (saturating for huge values).
#[inline]
pub(crate) fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    if (i as f32) > x { i - 1 } else { i }
}

/// A TSDF voxel-block map with colour (see the [module docs](self)).
///
/// Typical use, once per frame: [`TsdfVolume::integrate`] the frame at its pose, then
/// [`TsdfVolume::raycast`] at a pose to get a model depth + colour image to track against.
/// [`TsdfVolume::extract_mesh`] / [`TsdfVolume::extract_points`] export the surface.
pub struct TsdfVolume {
    config: TsdfConfig,
    /// Block coordinate to index into `blocks`.
    index: FxHashMap<[i32; 3], u32>,
    blocks: Vec<Box<Block>>,
    /// Per block: the integration pass that last touched it (dedupes the touched list).
    stamps: Vec<u32>,
    /// The current integration pass (stamps start at 0, so passes start at 1).
    pass: u32,
    /// Frames fused so far.
    frames: usize,
    /// A 0x0 ray-cast image, the answer when image buffers could not be wrapped.
    empty_cast: RaycastImage,
}

impl fmt::Debug for TsdfVolume {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("TsdfVolume")
            .field("config", &self.config)
            .field("blocks", &self.blocks.len())
            .field("frames", &self.frames)
            .field("memory_bytes", &self.memory_bytes())
            .finish_non_exhaustive()
    }
}

impl TsdfVolume {
    /// An empty volume.
    ///
    /// # Errors
    /// [`TrackerError::InvalidParameter`] naming the first bad parameter (see
    /// [`TsdfConfig::validate`]).
    pub fn new(config: TsdfConfig) -> Result<Self, TrackerError> {
        config.validate()?;
        let empty_cast = RaycastImage::empty().map_err(|e| TrackerError::TsdfInput {
            what: "ray-cast image",
            reason: e.to_string(),
        })?;
        Ok(Self {
            config,
            index: FxHashMap::default(),
            blocks: Vec::new(),
            stamps: Vec::new(),
            pass: 0,
            frames: 0,
            empty_cast,
        })
    }

    /// The parameters.
    pub fn config(&self) -> &TsdfConfig {
        &self.config
    }

    /// Number of allocated voxel blocks (`8³` voxels each).
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Number of frames fused so far.
    pub fn frame_count(&self) -> usize {
        self.frames
    }

    /// Heap memory held by the volume, in bytes (blocks, the block index and bookkeeping).
    pub fn memory_bytes(&self) -> usize {
        let blocks = self.blocks.capacity() * size_of::<Box<Block>>()
            + self.blocks.len() * size_of::<Block>();
        // hashbrown: one control byte per bucket beside the entries.
        let index = self.index.capacity() * (size_of::<([i32; 3], u32)>() + 1);
        blocks + index + self.stamps.capacity() * size_of::<u32>()
    }

    /// Forgets everything fused (keeps the parameters).
    pub fn clear(&mut self) {
        self.index.clear();
        self.blocks.clear();
        self.stamps.clear();
        self.pass = 0;
        self.frames = 0;
    }

    /// Fuses one RGB-D frame seen from `camera_to_world`.
    ///
    /// Invalid depths (0, negative, non-finite) and depths outside
    /// `[depth_min, depth_max]` are ignored. Inputs that [`TsdfVolume::try_integrate`] refuses
    /// (images whose size is not the intrinsics', invalid intrinsics, a non-finite pose) fuse
    /// nothing; call `try_integrate` to learn why.
    pub fn integrate(
        &mut self,
        depth: &DepthImage,
        colour: &RgbImage,
        k: &Intrinsics,
        camera_to_world: &Pose,
    ) {
        // Refused inputs fuse nothing, as documented; the error is for `try_integrate` callers.
        let _refused = self.try_integrate(depth, colour, k, camera_to_world);
    }

    /// [`TsdfVolume::integrate`], reporting refused inputs.
    ///
    /// # Errors
    /// [`TrackerError::TsdfInput`] when the intrinsics are invalid, the depth or colour image is
    /// not the size the intrinsics give, or the pose is not finite; nothing is fused then.
    pub fn try_integrate(
        &mut self,
        depth: &DepthImage,
        colour: &RgbImage,
        k: &Intrinsics,
        camera_to_world: &Pose,
    ) -> Result<(), TrackerError> {
        k.validate().map_err(|e| TrackerError::TsdfInput {
            what: "intrinsics",
            reason: format!("are unusable: {e}"),
        })?;
        let size_check = |what: &'static str, w: u32, h: u32| {
            if (w, h) == (k.width, k.height) {
                Ok(())
            } else {
                Err(TrackerError::TsdfInput {
                    what,
                    reason: format!(
                        "is {w}x{h}, the intrinsics are for {}x{}",
                        k.width, k.height
                    ),
                })
            }
        };
        size_check("depth image", depth.width(), depth.height())?;
        size_check("colour image", colour.width(), colour.height())?;
        if !pose_is_finite(camera_to_world) {
            return Err(TrackerError::TsdfInput {
                what: "pose",
                reason: "is not finite (or its rotation is not a unit quaternion)".to_owned(),
            });
        }
        if !self.in_range(camera_to_world) {
            return Err(TrackerError::TsdfInput {
                what: "pose",
                reason: format!(
                    "lies too far from the origin for {} m voxels (voxel indices would overflow)",
                    self.config.voxel_size
                ),
            });
        }
        self.fuse(depth, colour, k, camera_to_world);
        self.frames += 1;
        Ok(())
    }

    /// Whether everything a camera at `camera_to_world` can see has voxel indices well inside
    /// `i32` (below `2^28` in magnitude).
    fn in_range(&self, camera_to_world: &Pose) -> bool {
        let reach = camera_to_world.translation.vector.amax() + f64::from(self.config.depth_max);
        reach / f64::from(self.config.voxel_size) < f64::from(1_u32 << 28)
    }

    /// Ray-casts the model from `camera_to_world` through the camera `k`: per pixel, the depth
    /// (camera z, metres; 0 where the ray meets no surface) and colour of the first surface
    /// (zero crossing of the TSDF, + to −) between `depth_min` and `depth_max`. No normals; see
    /// [`TsdfVolume::raycast_with`].
    ///
    /// Invalid intrinsics or a pose that `try_integrate` would refuse give an image with no
    /// surface.
    pub fn raycast(&self, k: &Intrinsics, camera_to_world: &Pose) -> RaycastImage {
        self.raycast_with(k, camera_to_world, &RaycastOptions::default())
    }
}
