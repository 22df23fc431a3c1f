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
/// side, so one cache line serves both. The layout is fixed and has no padding (the spare byte
/// is zero) because [`wide::update_block`] gathers the depth and the four colour bytes of eight
/// pixels at a time by their offsets.
#[derive(Clone, Copy)]
#[repr(C)]
struct Pixel {
    depth: f32,
    rgb: [u8; 3],
    spare: u8,
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
                spare: 0,
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
            .for_each(|(_, block)| wide::update_block(block, &params));
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
                    let ray_y = (v as f32 - cam.k.cy) / cam.k.fy;
                    for &u in &columns {
                        let Some(&d) = row.get(u) else {
                            continue;
                        };
                        if !(d >= depth_min && d <= depth_max) {
                            continue;
                        }
                        let ray_c = [(u as f32 - cam.k.cx) / cam.k.fx, ray_y, 1.0];
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
    let u = (cam.k.fx * c[0] / c[2] + cam.k.cx) / SORT_TILE;
    let v = (cam.k.fy * c[1] / c[2] + cam.k.cy) / SORT_TILE;
    // Clamped to the tile grid (plus a border row/column), so the casts are exact.
    let tiles_x = cam.width as f32 / SORT_TILE + 2.0;
    let tiles_y = cam.height as f32 / SORT_TILE + 2.0;
    let u = (u + 1.0).clamp(0.0, tiles_x) as u32;
    let v = (v + 1.0).clamp(0.0, tiles_y) as u32;
    v * (tiles_x as u32 + 1) + u
}

/// What the update of one block shares between its voxels, derived once per block: the camera
/// coordinates of the block's first voxel and of one voxel step along each axis, and the frame's
/// constants in the form the update uses them.
struct BlockFrame {
    origin: [f32; 3],
    dx: [f32; 3],
    dy: [f32; 3],
    dz: [f32; 3],
    inv_trunc: f32,
    neg_trunc: f32,
    width: f32,
    height: f32,
    /// The principal point plus half a pixel: pixel centres are at integer coordinates, so a
    /// projection rounds by adding 0.5 and truncating.
    cx: f32,
    cy: f32,
    max_weight: f32,
}

impl BlockFrame {
    fn new(coord: [i32; 3], p: &FuseParams<'_>) -> Self {
        let vs = p.voxel_size;
        let base = coord.map(|c| (c * BLOCK_RES as i32) as f32 * vs);
        Self {
            origin: p.pose.inverse_apply(base),
            dx: p.pose.inverse_rotate([vs, 0.0, 0.0]),
            dy: p.pose.inverse_rotate([0.0, vs, 0.0]),
            dz: p.pose.inverse_rotate([0.0, 0.0, vs]),
            inv_trunc: 1.0 / p.trunc,
            neg_trunc: -p.trunc,
            width: p.camera.width as f32,
            height: p.camera.height as f32,
            cx: p.camera.k.cx + 0.5,
            cy: p.camera.k.cy + 0.5,
            max_weight: f32::from(p.max_weight),
        }
    }

    /// Camera coordinates of voxel `(0, y, z)` of the block.
    #[inline]
    fn row(&self, y: usize, z: usize) -> [f32; 3] {
        let (fy, fz) = (y as f32, z as f32);
        [0, 1, 2].map(|a| self.origin[a] + fy * self.dy[a] + fz * self.dz[a])
    }
}

/// Projective TSDF update of every voxel of one block. Each row of 8 voxels is projected in a
/// branch-free pass (which the compiler vectorises), then updated voxel by voxel. This is the
/// plain version; [`wide::update_block`] does the same eight voxels at a time.
fn update_block(block: &mut Block, p: &FuseParams<'_>) {
    const N: usize = BLOCK_RES;
    let cam = &p.camera;
    let f = BlockFrame::new(block.coord, p);
    let no_pixel = cam.width * cam.height;
    let mut near_surface = false;
    for z in 0..N {
        for y in 0..N {
            let row = f.row(y, z);
            // Project: the pixel index, or `no_pixel` outside the image.
            let mut pixel = [no_pixel; N];
            let mut voxel_z = [0.0_f32; N];
            for x in 0..N {
                let fx = x as f32;
                let pz = row[2] + fx * f.dx[2];
                let inv_z = 1.0 / pz;
                let uf = cam.k.fx * (row[0] + fx * f.dx[0]) * inv_z + f.cx;
                let vf = cam.k.fy * (row[1] + fx * f.dx[1]) * inv_z + f.cy;
                let inside = pz > 0.0 && uf >= 0.0 && vf >= 0.0 && uf < f.width && vf < f.height;
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
                let in_band = sdf >= f.neg_trunc;
                if !in_band {
                    continue;
                }
                let observed = (sdf * f.inv_trunc).min(1.0);
                let i = (first + x) % BLOCK_VOXELS;
                let w_old = f32::from(block.weight[i]);
                let inv_w = 1.0 / (w_old + 1.0);
                // An unobserved voxel has weight 0, so its placeholder value drops out.
                let fused = (block.tsdf[i] * w_old + observed) * inv_w;
                block.tsdf[i] = fused;
                // In [1, max_weight] <= 65535.
                block.weight[i] = (w_old + 1.0).min(f.max_weight) as u16;
                for (channel, &c) in block.rgb.iter_mut().zip(&px.rgb) {
                    let mean =
                        (f32::from(channel[i]) * w_old + f32::from(c) * COLOUR_SCALE) * inv_w;
                    // In [0, 255 * 256]: fits u16.
                    channel[i] = (mean + 0.5) as u16;
                }
                near_surface |= fused.abs() < NEAR_SURFACE;
                block.march[brick_index(x, y, z) % BLOCK_VOXELS] = march_value(fused);
            }
        }
    }
    block.near_surface |= near_surface;
}

/// A fused TSDF below this in magnitude marks its block as near a surface.
const NEAR_SURFACE: f32 = 0.2;

/// [`update_block`] eight voxels at a time, in AVX2 where the CPU has it.
///
/// Why it exists: the update is most of a frame-to-model frame's integration (17 of 19 ms on the
/// shared sequence, BENCHMARKS.md), and the plain version, though its projection vectorises,
/// updates voxel by voxel behind a branch on whether each is in the truncation band, which goes
/// either way within a row near a surface. A block row is 8 voxels, one 256-bit register: here the
/// row's depths and colours are gathered, the band is a lane mask, and every field of the row is
/// blended and stored at once. The lanes do the plain version's operations in its order (no fused
/// multiply-adds), so the volume is the same bit for bit (tested below). `unsafe` here is the
/// calls into the AVX2 build, the gathers from the frame's pixels and the loads and stores of
/// 8-voxel rows.
mod wide {
    use super::{Block, FuseParams};

    /// Updates `block` from the frame in `p`: the AVX2 build where the CPU has it, the plain
    /// [`super::update_block`] elsewhere.
    pub(super) fn update_block(block: &mut Block, p: &FuseParams<'_>) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && avx2::gathers_reach_every_pixel(p) {
            #[allow(
                unsafe_code,
                reason = "calls a function built for AVX2, on a CPU just found to have it"
            )]
            // SAFETY: `avx2::update_block` needs AVX2 and nothing else, and the CPU has it.
            unsafe {
                avx2::update_block(block, p);
            }
            return;
        }
        super::update_block(block, p);
    }

    #[cfg(target_arch = "x86_64")]
    #[allow(
        unsafe_code,
        reason = "AVX2 gathers, loads and stores take raw pointers; each says why it stays in bounds"
    )]
    pub(super) mod avx2 {
        use std::arch::x86_64::*;
        use std::mem::offset_of;

        use super::super::super::block::{
            BLOCK_RES, Block, COLOUR_SCALE, MARCH_SCALE, brick_index,
        };
        use super::super::{BlockFrame, FuseParams, NEAR_SURFACE, Pixel};

        // The gathers step by 8 bytes per pixel and read the depth at the pixel's start.
        const _: () = assert!(size_of::<Pixel>() == 8 && offset_of!(Pixel, depth) == 0);

        /// Whether every pixel index of the frame fits the gathers' 32-bit lane offsets and the
        /// pixel table holds the whole image (it always does; checked so that a lane inside the
        /// image cannot read past the table).
        pub fn gathers_reach_every_pixel(p: &FuseParams<'_>) -> bool {
            let pixels = p.camera.width * p.camera.height;
            p.pixels.len() == pixels && i32::try_from(pixels).is_ok()
        }

        /// The 8 values at `row` as a 256-bit vector.
        #[target_feature(enable = "avx2")]
        fn load_f32(row: &[f32; 8]) -> __m256 {
            // SAFETY: reads the 32 bytes of `row`; `loadu` needs no alignment.
            unsafe { _mm256_loadu_ps(row.as_ptr()) }
        }

        #[target_feature(enable = "avx2")]
        fn store_f32(row: &mut [f32; 8], v: __m256) {
            // SAFETY: writes the 32 bytes of `row`, which we hold mutably.
            unsafe { _mm256_storeu_ps(row.as_mut_ptr(), v) }
        }

        /// The 8 values at `row`, widened to 32-bit lanes.
        #[target_feature(enable = "avx2")]
        fn load_u16(row: &[u16; 8]) -> __m256i {
            // SAFETY: reads the 16 bytes of `row`; `loadu` needs no alignment.
            _mm256_cvtepu16_epi32(unsafe { _mm_loadu_si128(row.as_ptr().cast()) })
        }

        /// Narrows 8 lanes, each in `0..=65535`, into `row`.
        #[target_feature(enable = "avx2")]
        fn store_u16(row: &mut [u16; 8], v: __m256i) {
            // `packus` narrows within each 128-bit half: pack the two halves against each other.
            let narrow =
                _mm_packus_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            // SAFETY: writes the 16 bytes of `row`, which we hold mutably.
            unsafe { _mm_storeu_si128(row.as_mut_ptr().cast(), narrow) }
        }

        /// `super::super::update_block`, the voxels of a row in the lanes of a vector.
        ///
        /// # Safety
        /// The CPU must have AVX2, and [`gathers_reach_every_pixel`] must hold for `p`.
        #[target_feature(enable = "avx2")]
        pub unsafe fn update_block(block: &mut Block, p: &FuseParams<'_>) {
            const N: usize = BLOCK_RES;
            let cam = &p.camera;
            let f = BlockFrame::new(block.coord, p);
            let splat = _mm256_set1_ps;
            let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
            // `x * dx`, for the lanes' x.
            let step = f.dx.map(|d| _mm256_mul_ps(lanes, splat(d)));
            let (one, zero) = (splat(1.0), _mm256_setzero_ps());
            let sign = splat(-0.0);
            let width_i = _mm256_set1_epi32(cam.width as i32);
            let band_edge = splat(f.neg_trunc);
            let pixels = p.pixels.as_ptr();
            let depths = pixels.cast::<f32>();
            // The colour bytes and the zero spare byte after them, as one 32-bit value.
            let colours = pixels
                .cast::<u8>()
                .wrapping_add(offset_of!(Pixel, rgb))
                .cast::<i32>();
            let Block {
                tsdf,
                weight,
                rgb,
                march,
                ..
            } = block;
            let (tsdf, _) = tsdf.as_chunks_mut::<N>();
            let (weight, _) = weight.as_chunks_mut::<N>();
            let [red, green, blue] = rgb;
            let mut channels = [red, green, blue].map(|c| c.as_chunks_mut::<N>().0);
            let (march, _) = march.as_chunks_mut::<4>();
            let mut near_surface = 0;
            for z in 0..N {
                for y in 0..N {
                    let row = f.row(y, z);
                    let pz = _mm256_add_ps(splat(row[2]), step[2]);
                    let inv_z = _mm256_div_ps(one, pz);
                    let project = |focal: f32, start: f32, step: __m256, centre: f32| {
                        let along = _mm256_mul_ps(splat(focal), _mm256_add_ps(splat(start), step));
                        _mm256_add_ps(_mm256_mul_ps(along, inv_z), splat(centre))
                    };
                    let uf = project(cam.k.fx, row[0], step[0], f.cx);
                    let vf = project(cam.k.fy, row[1], step[1], f.cy);
                    let inside = _mm256_and_ps(
                        _mm256_and_ps(
                            _mm256_cmp_ps::<_CMP_GT_OQ>(pz, zero),
                            _mm256_and_ps(
                                _mm256_cmp_ps::<_CMP_GE_OQ>(uf, zero),
                                _mm256_cmp_ps::<_CMP_GE_OQ>(vf, zero),
                            ),
                        ),
                        _mm256_and_ps(
                            _mm256_cmp_ps::<_CMP_LT_OQ>(uf, splat(f.width)),
                            _mm256_cmp_ps::<_CMP_LT_OQ>(vf, splat(f.height)),
                        ),
                    );
                    if _mm256_movemask_ps(inside) == 0 {
                        continue;
                    }
                    let ui = _mm256_max_epi32(_mm256_cvttps_epi32(uf), _mm256_setzero_si256());
                    let vi = _mm256_max_epi32(_mm256_cvttps_epi32(vf), _mm256_setzero_si256());
                    let index = _mm256_add_epi32(_mm256_mullo_epi32(vi, width_i), ui);
                    // SAFETY: only lanes inside the image are read, and there `index` is a
                    // pixel of the image (u < width, v < height), below `p.pixels.len()` by
                    // `gathers_reach_every_pixel`; a `Pixel` is 8 bytes with the depth first.
                    let depth = unsafe {
                        _mm256_mask_i32gather_ps::<8>(
                            splat(f32::NEG_INFINITY),
                            depths,
                            index,
                            inside,
                        )
                    };
                    // Unusable depths are -inf, and lanes outside the image read -inf: neither
                    // passes the band test.
                    let sdf = _mm256_sub_ps(depth, pz);
                    let in_band = _mm256_cmp_ps::<_CMP_GE_OQ>(sdf, band_edge);
                    if _mm256_movemask_ps(in_band) == 0 {
                        continue;
                    }
                    let band = _mm256_castps_si256(in_band);
                    let observed = _mm256_min_ps(_mm256_mul_ps(sdf, splat(f.inv_trunc)), one);
                    let r = y | z << 3;
                    let w_old_int = load_u16(&weight[r]);
                    let w_old = _mm256_cvtepi32_ps(w_old_int);
                    let w_new = _mm256_add_ps(w_old, one);
                    let inv_w = _mm256_div_ps(one, w_new);
                    let t_old = load_f32(&tsdf[r]);
                    // An unobserved voxel has weight 0, so its placeholder value drops out.
                    let fused =
                        _mm256_mul_ps(_mm256_add_ps(_mm256_mul_ps(t_old, w_old), observed), inv_w);
                    store_f32(&mut tsdf[r], _mm256_blendv_ps(t_old, fused, in_band));
                    let capped = _mm256_cvttps_epi32(_mm256_min_ps(w_new, splat(f.max_weight)));
                    store_u16(&mut weight[r], _mm256_blendv_epi8(w_old_int, capped, band));
                    // SAFETY: the band's lanes are inside the image (see the depth gather); the
                    // 4 bytes at the colour's offset are the colour and the spare byte.
                    let rgbx = unsafe {
                        _mm256_mask_i32gather_epi32::<8>(
                            _mm256_setzero_si256(),
                            colours,
                            index,
                            band,
                        )
                    };
                    for (k, channel) in channels.iter_mut().enumerate() {
                        let shift = _mm256_set1_epi32(8 * k as i32);
                        let c = _mm256_and_si256(
                            _mm256_srlv_epi32(rgbx, shift),
                            _mm256_set1_epi32(0xff),
                        );
                        let old_int = load_u16(&channel[r]);
                        let mean = _mm256_mul_ps(
                            _mm256_add_ps(
                                _mm256_mul_ps(_mm256_cvtepi32_ps(old_int), w_old),
                                _mm256_mul_ps(_mm256_cvtepi32_ps(c), splat(COLOUR_SCALE)),
                            ),
                            inv_w,
                        );
                        let rounded = _mm256_cvttps_epi32(_mm256_add_ps(mean, splat(0.5)));
                        store_u16(&mut channel[r], _mm256_blendv_epi8(old_int, rounded, band));
                    }
                    let magnitude = _mm256_andnot_ps(sign, fused);
                    let near = _mm256_cmp_ps::<_CMP_LT_OQ>(magnitude, splat(NEAR_SURFACE));
                    near_surface |= _mm256_movemask_ps(_mm256_and_ps(near, in_band));
                    // `march_value`: clamp, scale, round half away from zero, truncate.
                    let q = _mm256_mul_ps(
                        _mm256_max_ps(_mm256_min_ps(fused, one), splat(-1.0)),
                        splat(MARCH_SCALE),
                    );
                    let half = _mm256_or_ps(splat(0.5), _mm256_and_ps(q, sign));
                    let level = _mm256_cvttps_epi32(_mm256_add_ps(q, half));
                    // Narrow to bytes (in -126..=126, and the mask's -1 and 0, survive the
                    // saturating packs); lanes 0..4 and 4..8 lie in neighbouring bricks.
                    let bytes = |v: __m256i| {
                        let words = _mm_packs_epi32(
                            _mm256_castsi256_si128(v),
                            _mm256_extracti128_si256::<1>(v),
                        );
                        _mm_packs_epi16(words, words)
                    };
                    let (low, high) = (brick_index(0, y, z) / 4, brick_index(4, y, z) / 4);
                    let word = |b: [i8; 4]| u32::from_le_bytes(b.map(|v| v as u8));
                    let old = u64::from(word(march[low])) | u64::from(word(march[high])) << 32;
                    let merged =
                        _mm_blendv_epi8(_mm_cvtsi64_si128(old as i64), bytes(level), bytes(band));
                    let new = _mm_cvtsi128_si64(merged) as u64;
                    march[low] = (new as u32).to_le_bytes().map(|v| v as i8);
                    march[high] = ((new >> 32) as u32).to_le_bytes().map(|v| v as i8);
                }
            }
            block.near_surface |= near_surface != 0;
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    use super::*;

    /// A small xorshift generator: the test needs varied inputs, not good randomness.
    struct Noise(u64);

    impl Noise {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A frame of random depths in 0.3–1.5 m (a tenth unusable) and random colours.
    fn random_pixels(noise: &mut Noise, count: usize) -> Vec<Pixel> {
        (0..count)
            .map(|_| Pixel {
                depth: if noise.next() < 0.1 {
                    f32::NEG_INFINITY
                } else {
                    0.3 + 1.2 * noise.next()
                },
                rgb: [0; 3].map(|_| (noise.next() * 256.0) as u8),
                spare: 0,
            })
            .collect()
    }

    /// The wide update leaves every field of every block as the plain one does, bit for bit,
    /// over several frames (so weights grow, and reach a low cap), with blocks inside, across
    /// the edge of and outside the view, and unusable depths.
    #[test]
    fn wide_update_matches_the_plain_one_bit_for_bit() {
        let mut noise = Noise(0x9e37_79b9_7f4a_7c15);
        let k = Intrinsics::new(64, 48, 50.0, 50.0, 31.5, 23.5).unwrap();
        let coords: Vec<[i32; 3]> = (-4..4)
            .flat_map(|x| (-3..3).flat_map(move |y| (1..10).map(move |z| [x, y, z])))
            .collect();
        let mut plain: Vec<Block> = coords.iter().map(|&c| *Block::boxed(c)).collect();
        let mut wide = plain.clone();
        for frame in 0..6 {
            let pixels = random_pixels(&mut noise, 64 * 48);
            let angle = 0.1 * f64::from(noise.next() - 0.5);
            let pose: Pose = Isometry3::from_parts(
                Translation3::new(
                    0.05 * f64::from(noise.next()),
                    0.05 * f64::from(noise.next()),
                    0.0,
                ),
                UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle),
            );
            let params = FuseParams {
                camera: Camera32::new(&k),
                pose: RigidF32::from_pose(&pose),
                pixels: &pixels,
                voxel_size: 0.02,
                trunc: 0.08,
                max_weight: if frame < 3 { 65535 } else { 4 },
            };
            for (a, b) in plain.iter_mut().zip(&mut wide) {
                update_block(a, &params);
                wide::update_block(b, &params);
            }
        }
        let mut observed = 0;
        for (a, b) in plain.iter().zip(&wide) {
            let bits = |block: &Block| block.tsdf.map(f32::to_bits);
            assert_eq!(bits(a), bits(b), "tsdf of block {:?}", a.coord);
            assert_eq!(a.weight, b.weight, "weights of block {:?}", a.coord);
            assert_eq!(a.rgb, b.rgb, "colours of block {:?}", a.coord);
            assert_eq!(a.march, b.march, "march of block {:?}", a.coord);
            assert_eq!(a.near_surface, b.near_surface, "block {:?}", a.coord);
            observed += a.weight.iter().filter(|&&w| w > 0).count();
        }
        // Most voxels in view were observed, and some blocks lie outside the view.
        let voxels = plain.len() * BLOCK_VOXELS;
        assert!(
            observed > voxels / 10 && observed < voxels,
            "{observed} of {voxels}"
        );
        assert!(plain.iter().any(|b| b.weight.contains(&4)));
        assert!(plain.iter().any(|b| b.near_surface));
    }
}
