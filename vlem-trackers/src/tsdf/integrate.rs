//! Fusing one RGB-D frame: allocate the blocks the frame touches, then update them in parallel.

use rayon::prelude::*;
use rustc_hash::FxHashSet;
use vlem_core::{DepthImage, Intrinsics, Pose, RgbImage};

use super::block::{
    BLOCK_RES, BLOCK_VOXELS, Block, COLOUR_SCALE, brick_index, march_value, voxel_index,
};
use super::{Camera32, TsdfVolume, floor_i32};
use vlem_core::RigidF32;

/// A pixel as the update reads it: the depth (−∞ where it must not be fused) and colour side by
/// side, so one cache line serves both.
#[derive(Clone, Copy)]
struct Pixel {
    depth: f32,
    rgb: [u8; 3],
}

/// Everything the per-block update reads, in `f32`.
struct FuseParams<'a> {
    camera: Camera32,
    pose: RigidF32,
    pixels: &'a [Pixel],
    voxel_size: f32,
    trunc: f32,
    max_weight: u16,
}

/// Tiles (of `SORT_TILE` pixels) order the touched blocks, so that blocks updated one after the
/// other read nearby pixels.
const SORT_TILE: f32 = 32.0;

impl TsdfVolume {
    /// Fuses a frame whose inputs were checked by `try_integrate`.
    pub(super) fn fuse(
        &mut self,
        depth: &DepthImage,
        colour: &RgbImage,
        k: &Intrinsics,
        camera_to_world: &Pose,
    ) {
        let (depth_min, depth_max) = (self.config.depth_min, self.config.depth_max);
        let pixels: Vec<Pixel> = depth
            .as_raw()
            .par_iter()
            .zip(colour.as_raw().par_chunks_exact(3))
            .map(|(&d, c)| Pixel {
                depth: if d >= depth_min && d <= depth_max {
                    d
                } else {
                    f32::NEG_INFINITY
                },
                rgb: [c[0], c[1], c[2]],
            })
            .collect();
        let params = FuseParams {
            camera: Camera32::new(k),
            pose: RigidF32::from_pose(camera_to_world),
            pixels: &pixels,
            voxel_size: self.config.voxel_size,
            trunc: self.config.sdf_trunc(),
            // Validated to lie in [1, 65535].
            max_weight: self.config.max_weight as u16,
        };
        let pass = self.next_pass();
        self.allocate_touched(depth.as_raw(), &params, pass);
        let mut touched: Vec<(u32, &mut Block)> = self
            .blocks
            .iter_mut()
            .zip(&self.stamps)
            .filter(|(_, stamp)| **stamp == pass)
            .map(|(block, _)| (image_order(block, &params), &mut **block))
            .collect();
        touched.sort_unstable_by_key(|(key, _)| *key);
        touched
            .par_iter_mut()
            .with_min_len(16)
            .for_each(|(_, block)| update_block(block, &params));
    }

    /// A fresh stamp for the blocks touched by this pass.
    fn next_pass(&mut self) -> u32 {
        if self.pass == u32::MAX {
            self.stamps.iter_mut().for_each(|s| *s = 0);
            self.pass = 0;
        }
        self.pass += 1;
        self.pass
    }

    /// Allocates (and stamps with `pass`) every block within the truncation distance of a
    /// sampled depth, along the viewing ray. Candidate blocks are gathered in parallel over
    /// bands of rows (deduplicated per band), then allocated serially. Returns the number of
    /// blocks touched.
    fn allocate_touched(&mut self, depth: &[f32], p: &FuseParams<'_>, pass: u32) -> usize {
        let cam = p.camera;
        let stride = self.config.allocation_stride;
        let (depth_min, depth_max) = (self.config.depth_min, self.config.depth_max);
        let block_size = p.voxel_size * BLOCK_RES as f32;
        let inv_block = 1.0 / block_size;
        // Half a voxel in block units.
        let half_voxel = 0.5 / BLOCK_RES as f32;
        let origin = p.pose.translation;
        let pose = p.pose;
        let trunc = p.trunc;
        // Samples along the ray every half block.
        let sample_spacing = 0.5 * block_size;
        // Every stride-th row and column, and the last ones, so that the image border is
        // covered too.
        let sampled = |size: usize| {
            let mut at: Vec<usize> = (stride / 2..size).step_by(stride).collect();
            if at.last().is_some_and(|&last| last + 1 < size) {
                at.push(size - 1);
            }
            at
        };
        let rows = sampled(cam.height);
        let columns = sampled(cam.width);
        let bands: Vec<Vec<[i32; 3]>> = rows
            .par_chunks(8)
            .map(|band| {
                let mut seen: FxHashSet<[i32; 3]> = FxHashSet::default();
                // Consecutive samples mostly fall in the block just seen: skip those lookups.
                let mut last = [i32::MIN; 3];
                for &v in band {
                    let Some(row) = depth.get(v * cam.width..(v + 1) * cam.width) else {
                        continue;
                    };
                    let ray_y = (v as f32 - cam.cy) / cam.fy;
                    for &u in &columns {
                        let Some(&d) = row.get(u) else {
                            continue;
                        };
                        if !(d >= depth_min && d <= depth_max) {
                            continue;
                        }
                        let ray_c = [(u as f32 - cam.cx) / cam.fx, ray_y, 1.0];
                        let ray_w = pose.rotate(ray_c);
                        let ray_len = (ray_c[0] * ray_c[0] + ray_c[1] * ray_c[1] + 1.0).sqrt();
                        let z0 = (d - trunc).max(1e-3);
                        let z1 = d + trunc;
                        let n = ((z1 - z0) * ray_len / sample_spacing).ceil().max(1.0) as usize;
                        let dz = (z1 - z0) / n as f32;
                        for s in 0..=n {
                            let z = z0 + dz * s as f32;
                            // The block of the voxel nearest to the sample.
                            let coord = [0, 1, 2].map(|a| {
                                floor_i32((origin[a] + z * ray_w[a]) * inv_block + half_voxel)
                            });
                            if coord != last {
                                last = coord;
                                seen.insert(coord);
                            }
                        }
                    }
                }
                seen.into_iter().collect()
            })
            .collect();
        let mut touched = 0;
        for band in bands {
            for coord in band {
                touched += usize::from(self.touch(coord, pass));
            }
        }
        touched
    }

    /// Stamps block `coord` with `pass`, allocating it if needed; true if it was not yet stamped.
    #[inline]
    fn touch(&mut self, coord: [i32; 3], pass: u32) -> bool {
        let next = self.blocks.len();
        let index = *self.index.entry(coord).or_insert_with(|| {
            // More than u32::MAX blocks would need hundreds of terabytes.
            u32::try_from(next).unwrap_or(u32::MAX)
        }) as usize;
        if index == next {
            self.blocks.push(Block::boxed(coord));
            self.stamps.push(pass);
            return true;
        }
        match self.stamps.get_mut(index) {
            Some(stamp) if *stamp != pass => {
                *stamp = pass;
                true
            }
            _ => false,
        }
    }
}

/// The sort key of a block: the image tile its centre projects to (row-major), blocks behind the
/// camera last.
fn image_order(block: &Block, p: &FuseParams<'_>) -> u32 {
    let half = 0.5 * BLOCK_RES as f32;
    let centre = block
        .coord
        .map(|c| (c as f32 * BLOCK_RES as f32 + half) * p.voxel_size);
    let c = p.pose.inverse_apply(centre);
    if c[2] <= 1e-3 {
        return u32::MAX;
    }
    let cam = &p.camera;
    let u = (cam.fx * c[0] / c[2] + cam.cx) / SORT_TILE;
    let v = (cam.fy * c[1] / c[2] + cam.cy) / SORT_TILE;
    // Clamped to the tile grid (plus a border row/column), so the casts are exact.
    let tiles_x = cam.width as f32 / SORT_TILE + 2.0;
    let tiles_y = cam.height as f32 / SORT_TILE + 2.0;
    let u = (u + 1.0).clamp(0.0, tiles_x) as u32;
    let v = (v + 1.0).clamp(0.0, tiles_y) as u32;
    v * (tiles_x as u32 + 1) + u
}

/// Projective TSDF update of every voxel of one block. Each row of 8 voxels is projected in a
/// branch-free pass (which the compiler vectorises), then updated voxel by voxel.
fn update_block(block: &mut Block, p: &FuseParams<'_>) {
    const N: usize = BLOCK_RES;
    let cam = &p.camera;
    let vs = p.voxel_size;
    let base = block.coord.map(|c| (c * BLOCK_RES as i32) as f32 * vs);
    let origin = p.pose.inverse_apply(base);
    let dx = p.pose.inverse_rotate([vs, 0.0, 0.0]);
    let dy = p.pose.inverse_rotate([0.0, vs, 0.0]);
    let dz = p.pose.inverse_rotate([0.0, 0.0, vs]);
    let inv_trunc = 1.0 / p.trunc;
    let neg_trunc = -p.trunc;
    let width = cam.width as f32;
    let height = cam.height as f32;
    // Pixel centres are at integer coordinates: round by adding 0.5 and truncating.
    let cx = cam.cx + 0.5;
    let cy = cam.cy + 0.5;
    let max_weight = f32::from(p.max_weight);
    let no_pixel = cam.width * cam.height;
    let mut near_surface = false;
    for z in 0..N {
        for y in 0..N {
            let (fy, fz) = (y as f32, z as f32);
            let row = [
                origin[0] + fy * dy[0] + fz * dz[0],
                origin[1] + fy * dy[1] + fz * dz[1],
                origin[2] + fy * dy[2] + fz * dz[2],
            ];
            // Project: the pixel index, or `no_pixel` outside the image.
            let mut pixel = [no_pixel; N];
            let mut voxel_z = [0.0_f32; N];
            for x in 0..N {
                let fx = x as f32;
                let pz = row[2] + fx * dx[2];
                let inv_z = 1.0 / pz;
                let uf = cam.fx * (row[0] + fx * dx[0]) * inv_z + cx;
                let vf = cam.fy * (row[1] + fx * dx[1]) * inv_z + cy;
                let inside = pz > 0.0 && uf >= 0.0 && vf >= 0.0 && uf < width && vf < height;
                // Non-negative and below the image size where used, so the casts are exact
                // there (and saturate elsewhere). Via i32, which x86-64 converts to in one
                // instruction; a float to usize conversion takes several.
                let (ui, vi) = ((uf as i32).max(0) as usize, (vf as i32).max(0) as usize);
                let index = vi * cam.width + ui;
                pixel[x] = if inside { index } else { no_pixel };
                voxel_z[x] = pz;
            }
            let first = voxel_index(0, y, z);
            for x in 0..N {
                let Some(px) = p.pixels.get(pixel[x]) else {
                    continue;
                };
                // Unusable depths are -inf, so they fail this test too.
                let sdf = px.depth - voxel_z[x];
                let in_band = sdf >= neg_trunc;
                if !in_band {
                    continue;
                }
                let observed = (sdf * inv_trunc).min(1.0);
                let i = (first + x) % BLOCK_VOXELS;
                let w_old = f32::from(block.weight[i]);
                let inv_w = 1.0 / (w_old + 1.0);
                // An unobserved voxel has weight 0, so its placeholder value drops out.
                let fused = (block.tsdf[i] * w_old + observed) * inv_w;
                block.tsdf[i] = fused;
                // In [1, max_weight] <= 65535.
                block.weight[i] = (w_old + 1.0).min(max_weight) as u16;
                for (channel, &c) in block.rgb.iter_mut().zip(&px.rgb) {
                    let mean =
                        (f32::from(channel[i]) * w_old + f32::from(c) * COLOUR_SCALE) * inv_w;
                    // In [0, 255 * 256]: fits u16.
                    channel[i] = (mean + 0.5) as u16;
                }
                near_surface |= fused.abs() < 0.2;
                block.march[brick_index(x, y, z) % BLOCK_VOXELS] = march_value(fused);
            }
        }
    }
    block.near_surface |= near_surface;
}
