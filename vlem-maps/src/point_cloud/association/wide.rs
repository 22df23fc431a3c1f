//! The projective search eight map points at a time, in AVX2.
//!
//! Why: the search is a third of a 512-d frame's time above the memory floor, and nearly all of it
//! is the same straight-line work per point: transform and project the point, then take the
//! nearest of the nine cells around its projection. Eight lanes do that for eight points with two
//! gathers per cell (its depth and its point's index), and the rare points that need more (near
//! the border of the image, or without a close point in the 3x3 block so that the outer rings
//! are searched) finish in the plain code.
//!
//! It is the plain search's IEEE arithmetic in the same order (no fused multiply-add is enabled),
//! and it takes the same candidate: the lower squared distance, then the lower index, which is
//! the order of the plain search's [`Candidate`](super::Candidate) keys. A unit test checks that
//! the two find the same points.

use super::ProjectiveSearch;

/// Writes into `found` the correspondence of each of `points` by `search` ([`super::NONE`] for
/// none and out of view): eight at a time where the CPU has AVX2 and the grid suits the lanes,
/// one at a time elsewhere.
pub(super) fn nearest_points(
    search: &ProjectiveSearch<'_, '_>,
    points: &[[f32; 3]],
    found: &mut [u32],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && avx2::suits(search) {
        #[allow(
            unsafe_code,
            reason = "calls a function built for AVX2, on a CPU just found to have it"
        )]
        // SAFETY: `avx2::nearest_points` needs AVX2 and nothing else, and the CPU has it.
        unsafe {
            avx2::nearest_points(search, points, found);
        }
        return;
    }
    plain(search, points, found);
}

/// [`nearest_points`] one point at a time.
fn plain(search: &ProjectiveSearch<'_, '_>, points: &[[f32; 3]], found: &mut [u32]) {
    for (&q, found) in points.iter().zip(found) {
        *found = search.nearest(q);
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(
    unsafe_code,
    reason = "AVX2 gathers take raw pointers; each says why it stays in bounds"
)]
mod avx2 {
    use std::arch::x86_64::*;
    use std::mem::offset_of;

    use super::super::{Candidate, Cell, NONE, ProjectiveSearch};

    // The gathers step by 8 bytes per cell, the depth at its start and the index 4 bytes on.
    const _: () = assert!(
        size_of::<Cell>() == 8 && offset_of!(Cell, depth) == 0 && offset_of!(Cell, index) == 4
    );

    const LANES: usize = 8;

    /// Whether the lanes can run `search`: a window of at least one ring (the 3x3 block), a grid
    /// with an interior, and cell and ray indices that fit the gathers' 32-bit lane offsets.
    pub fn suits(search: &ProjectiveSearch<'_, '_>) -> bool {
        let grid = search.grid;
        search.window >= 1
            && grid.columns >= 3
            && grid.rows >= 3
            && grid.cells.len() == grid.columns * grid.rows
            && grid.ray_x.len() == grid.columns
            && grid.ray_y.len() == grid.rows
            && i32::try_from(grid.cells.len()).is_ok()
    }

    /// [`super::nearest_points`] for a search that [`suits`] the lanes.
    #[target_feature(enable = "avx2")]
    pub fn nearest_points(
        search: &ProjectiveSearch<'_, '_>,
        points: &[[f32; 3]],
        found: &mut [u32],
    ) {
        let lanes = Lanes::new(search);
        let mut groups = points.chunks_exact(LANES);
        let mut outs = found.chunks_exact_mut(LANES);
        for (group, out) in (&mut groups).zip(&mut outs) {
            if let (Ok(group), Ok(out)) = (group.try_into(), out.try_into()) {
                lanes.search(search, group, out);
            }
        }
        super::plain(search, groups.remainder(), outs.into_remainder());
    }

    /// The search's constants, one per lane.
    struct Lanes {
        rotation: [[__m256; 3]; 3],
        translation: [__m256; 3],
        fx: __m256,
        fy: __m256,
        cx: __m256,
        cy: __m256,
        u_end: __m256,
        v_end: __m256,
        inverse_stride: __m256,
        /// The last cell column and row, and the last an interior cell can have.
        last_column: __m256i,
        last_row: __m256i,
        last_inner_column: __m256i,
        last_inner_row: __m256i,
        columns: __m256i,
        /// `reach / f` of [`PixelGrid::per_ring`] for x and y, as it computes them.
        reach_x: __m256,
        reach_y: __m256,
        stride: __m256,
        focal: __m256,
    }

    impl Lanes {
        #[target_feature(enable = "avx2")]
        fn new(search: &ProjectiveSearch<'_, '_>) -> Self {
            let (projector, grid) = (search.projector, search.grid);
            let r = &projector.to_camera.rotation;
            let t = &projector.to_camera.translation;
            let reach = search.window as f32 * grid.stride;
            // `suits` has checked that the counts fit an `i32`.
            let count = |n: usize| _mm256_set1_epi32(n as i32);
            Self {
                rotation: r.map(|row| row.map(|x| _mm256_set1_ps(x))),
                translation: t.map(|x| _mm256_set1_ps(x)),
                fx: _mm256_set1_ps(projector.k.fx),
                fy: _mm256_set1_ps(projector.k.fy),
                cx: _mm256_set1_ps(projector.k.cx),
                cy: _mm256_set1_ps(projector.k.cy),
                u_end: _mm256_set1_ps(projector.u_end),
                v_end: _mm256_set1_ps(projector.v_end),
                inverse_stride: _mm256_set1_ps(grid.inverse_stride),
                last_column: count(grid.columns - 1),
                last_row: count(grid.rows - 1),
                last_inner_column: count(grid.columns - 2),
                last_inner_row: count(grid.rows - 2),
                columns: count(grid.columns),
                reach_x: _mm256_set1_ps(reach * grid.inverse_fx),
                reach_y: _mm256_set1_ps(reach * grid.inverse_fy),
                stride: _mm256_set1_ps(grid.stride),
                focal: _mm256_set1_ps(grid.focal),
            }
        }

        /// Finds the correspondences of eight map points.
        #[target_feature(enable = "avx2")]
        fn search(
            &self,
            search: &ProjectiveSearch<'_, '_>,
            points: &[[f32; 3]; LANES],
            out: &mut [u32; LANES],
        ) {
            let grid = search.grid;
            let zero = _mm256_setzero_ps();
            let half = _mm256_set1_ps(0.5);
            let one = _mm256_set1_ps(1.0);

            // The eight points' coordinates, one vector each.
            let base = points.as_ptr().cast::<f32>();
            let strided = _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21);
            // SAFETY: lane offsets 0..=21 (+ 2) stay in the 24 floats of `points`.
            let q = unsafe {
                [
                    _mm256_i32gather_ps::<4>(base, strided),
                    _mm256_i32gather_ps::<4>(base.add(1), strided),
                    _mm256_i32gather_ps::<4>(base.add(2), strided),
                ]
            };

            // `Projector::project`: the camera-frame point, `R q + t` as `RigidF32::apply`
            // sums it, then the projection and the view test.
            let camera = [0, 1, 2].map(|i| {
                let r = &self.rotation[i];
                let sum = _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(r[0], q[0]), _mm256_mul_ps(r[1], q[1])),
                    _mm256_mul_ps(r[2], q[2]),
                );
                _mm256_add_ps(sum, self.translation[i])
            });
            let inverse_depth = _mm256_div_ps(one, camera[2]);
            let x = _mm256_mul_ps(camera[0], inverse_depth);
            let y = _mm256_mul_ps(camera[1], inverse_depth);
            let u = _mm256_add_ps(_mm256_mul_ps(self.fx, x), self.cx);
            let v = _mm256_add_ps(_mm256_mul_ps(self.fy, y), self.cy);
            let minus_half = _mm256_set1_ps(-0.5);
            let in_view = and(
                and(
                    _mm256_cmp_ps::<_CMP_GT_OQ>(camera[2], zero),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(u, minus_half),
                ),
                and(
                    and(
                        _mm256_cmp_ps::<_CMP_GE_OQ>(v, minus_half),
                        _mm256_cmp_ps::<_CMP_LT_OQ>(u, self.u_end),
                    ),
                    _mm256_cmp_ps::<_CMP_LT_OQ>(v, self.v_end),
                ),
            );

            // `PixelGrid::cell_of` and `is_interior`. Truncation gives `i32::MIN` for a lane
            // out of range (out of view, so its result is dropped); clamping it into the
            // interior keeps every lane's gathers inside the grid.
            let gu =
                _mm256_cvttps_epi32(_mm256_add_ps(_mm256_mul_ps(u, self.inverse_stride), half));
            let gv =
                _mm256_cvttps_epi32(_mm256_add_ps(_mm256_mul_ps(v, self.inverse_stride), half));
            let ones = _mm256_set1_epi32(1);
            let clamp =
                |g, last| _mm256_min_epi32(_mm256_max_epi32(g, _mm256_setzero_si256()), last);
            let (gu, gv) = (clamp(gu, self.last_column), clamp(gv, self.last_row));
            // 0 < g < last.
            let inner = |g, last| {
                _mm256_and_si256(
                    _mm256_cmpgt_epi32(g, _mm256_setzero_si256()),
                    _mm256_cmpgt_epi32(last, g),
                )
            };
            let interior = _mm256_castsi256_ps(_mm256_and_si256(
                inner(gu, self.last_column),
                inner(gv, self.last_row),
            ));
            let inside = |g, last_inner| _mm256_min_epi32(_mm256_max_epi32(g, ones), last_inner);
            let (gu, gv) = (
                inside(gu, self.last_inner_column),
                inside(gv, self.last_inner_row),
            );

            // `PixelGrid::block3`: the nearest of the nine cells around (gu, gv).
            let mut best = _mm256_set1_ps(search.r2);
            let mut best_index = _mm256_set1_epi32(NONE as i32);
            let sign = _mm256_set1_epi32(i32::MIN);
            let cells = grid.cells.as_ptr();
            let centre = _mm256_add_epi32(_mm256_mullo_epi32(gv, self.columns), gu);
            // SAFETY: 1 <= gu <= columns - 2, so gu - 1 ..= gu + 1 index `ray_x` (`suits`
            // checked its length), and likewise gv and `ray_y`.
            let ray_x = [-1, 0, 1].map(|du| unsafe {
                _mm256_i32gather_ps::<4>(
                    grid.ray_x.as_ptr(),
                    _mm256_add_epi32(gu, _mm256_set1_epi32(du)),
                )
            });
            for dv in [-1, 0, 1] {
                let row = _mm256_add_epi32(gv, _mm256_set1_epi32(dv));
                // SAFETY: as for `ray_x` above.
                let ray_y = unsafe { _mm256_i32gather_ps::<4>(grid.ray_y.as_ptr(), row) };
                let row_start = _mm256_add_epi32(
                    centre,
                    _mm256_mullo_epi32(_mm256_set1_epi32(dv), self.columns),
                );
                for (du, &ray_x) in [-1, 0, 1].iter().zip(&ray_x) {
                    let cell = _mm256_add_epi32(row_start, _mm256_set1_epi32(*du));
                    // SAFETY: the cell (gu + du, gv + dv) lies in the grid of columns x rows
                    // cells, `cells.len()` (checked by `suits`); the depth is a cell's first 4
                    // bytes and the index its last 4 (the assertion above).
                    let (depth, index) = unsafe {
                        (
                            _mm256_i32gather_ps::<8>(cells.cast::<f32>(), cell),
                            _mm256_i32gather_epi32::<8>(cells.cast::<i32>().add(1), cell),
                        )
                    };
                    // `ray_distance2`.
                    let d = [
                        _mm256_sub_ps(_mm256_mul_ps(depth, ray_x), camera[0]),
                        _mm256_sub_ps(_mm256_mul_ps(depth, ray_y), camera[1]),
                        _mm256_sub_ps(depth, camera[2]),
                    ];
                    let d2 = _mm256_add_ps(
                        _mm256_add_ps(_mm256_mul_ps(d[0], d[0]), _mm256_mul_ps(d[1], d[1])),
                        _mm256_mul_ps(d[2], d[2]),
                    );
                    // The smaller `Candidate` key: the nearer point, or the lower index at
                    // the same distance (indices compared unsigned, by flipping the sign
                    // bits). A NaN distance compares false and never wins.
                    let lower_index = _mm256_castsi256_ps(_mm256_cmpgt_epi32(
                        _mm256_xor_si256(best_index, sign),
                        _mm256_xor_si256(index, sign),
                    ));
                    let take = _mm256_or_ps(
                        _mm256_cmp_ps::<_CMP_LT_OQ>(d2, best),
                        and(_mm256_cmp_ps::<_CMP_EQ_OQ>(d2, best), lower_index),
                    );
                    best = _mm256_blendv_ps(best, d2, take);
                    best_index = _mm256_castps_si256(_mm256_blendv_ps(
                        _mm256_castsi256_ps(best_index),
                        _mm256_castsi256_ps(index),
                        take,
                    ));
                }
            }

            // `PixelGrid::outer_rings`' test for ring 2: which lanes its bound leaves to search.
            let more = if search.window >= 2 {
                let abs = _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX));
                let bx = _mm256_add_ps(_mm256_and_ps(x, abs), self.reach_x);
                let by = _mm256_add_ps(_mm256_and_ps(y, abs), self.reach_y);
                let norm = _mm256_sqrt_ps(_mm256_add_ps(
                    _mm256_add_ps(one, _mm256_mul_ps(bx, bx)),
                    _mm256_mul_ps(by, by),
                ));
                let per_ring = _mm256_div_ps(
                    _mm256_mul_ps(camera[2], self.stride),
                    _mm256_mul_ps(self.focal, norm),
                );
                let bound = _mm256_mul_ps(_mm256_set1_ps(1.5), per_ring);
                _mm256_cmp_ps::<_CMP_NGT_UQ>(_mm256_mul_ps(bound, bound), best)
            } else {
                zero
            };

            let done = and(in_view, interior);
            let result = _mm256_blendv_ps(
                _mm256_castsi256_ps(_mm256_set1_epi32(NONE as i32)),
                _mm256_castsi256_ps(best_index),
                done,
            );
            // SAFETY: writes the 32 bytes of `out`, which we hold mutably.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), _mm256_castps_si256(result)) };

            // The lanes the plain search finishes: in view but at the border, or with outer
            // rings to search.
            let border = _mm256_movemask_ps(_mm256_andnot_ps(interior, in_view));
            let outer = _mm256_movemask_ps(and(done, more));
            if border | outer == 0 {
                return;
            }
            let mut best_d2 = [0.0f32; LANES];
            let mut best_at = [0u32; LANES];
            // SAFETY: each writes the 32 bytes of a local array.
            unsafe {
                _mm256_storeu_ps(best_d2.as_mut_ptr(), best);
                _mm256_storeu_si256(best_at.as_mut_ptr().cast(), best_index);
            }
            for lane in 0..LANES {
                let bit = 1 << lane;
                if (border | outer) & bit == 0 {
                    continue;
                }
                // The same arithmetic, so the same projection, in view.
                let Some(p) = search.projector.project(points[lane]) else {
                    continue;
                };
                out[lane] = if border & bit != 0 {
                    grid.nearest(p, search.r2, search.window)
                } else {
                    let nearest = Candidate::new(best_d2[lane], best_at[lane]);
                    grid.outer_rings(&p, grid.cell_of(&p), 2, search.window, nearest)
                        .index()
                };
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn and(a: __m256, b: __m256) -> __m256 {
        _mm256_and_ps(a, b)
    }
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use vlem_core::{Intrinsics, Pose, RigidF32};

    use super::super::tests::rough_surface;
    use super::super::{FrameView, NONE, PixelGrid, Projector};
    use super::*;

    /// The dispatched search (AVX2 on a CPU with it) against the plain one, point for point, on
    /// map points near a rough surface, off it, behind the camera, out of view and at the border
    /// of the image, for several strides, windows and radii.
    #[test]
    fn the_wide_search_finds_what_the_plain_one_finds() {
        let mut rng = StdRng::seed_from_u64(5);
        let intrinsics = Intrinsics {
            width: 80,
            height: 60,
            fx: 70.5,
            fy: 69.0,
            cx: 39.5,
            cy: 29.5,
        };
        // A camera turned and moved a little, so that the transform's every term matters.
        let pose = Pose::from_parts(
            nalgebra::Translation3::new(0.1, -0.05, 0.2),
            nalgebra::UnitQuaternion::from_euler_angles(0.05, -0.1, 0.03),
        );
        let to_camera = RigidF32::from_pose(&pose.inverse());
        let from_camera = RigidF32::from_pose(&pose);
        let mut searched_outer_rings = false;
        for stride in [1u32, 2, 3] {
            let (positions, pixels) = rough_surface(&mut rng, &intrinsics, stride, &from_camera);
            let view = FrameView {
                intrinsics: &intrinsics,
                to_camera,
                positions: &positions,
                pixels: &pixels,
                stride,
            };
            let mut cells = Vec::new();
            let grid = PixelGrid::new(&view, &mut cells);
            let projector = Projector::new(&view);
            let map: Vec<[f32; 3]> = (0..5003)
                .map(|i| match i % 10 {
                    // Off the surface, behind the camera, anywhere.
                    0 => from_camera.apply([0.1, 0.0, -0.5]),
                    1 => std::array::from_fn(|_| rng.random_range(-3.0..3.0)),
                    2 => [f32::NAN, 0.0, 1.0],
                    _ => {
                        let p = positions[rng.random_range(0..positions.len())];
                        let jitter = if i % 10 == 3 { 0.1 } else { 0.01 };
                        p.map(|x| x + rng.random_range(-jitter..jitter))
                    }
                })
                .collect();
            for window in [0u32, 1, 2, 3, 5] {
                for max_distance in [0.005f32, 0.02, 0.3] {
                    let r2 = max_distance * max_distance;
                    let mut wide = vec![0; map.len()];
                    let mut plain_found = vec![0; map.len()];
                    let search = ProjectiveSearch {
                        projector: &projector,
                        grid: &grid,
                        r2,
                        window,
                    };
                    nearest_points(&search, &map, &mut wide);
                    plain(&search, &map, &mut plain_found);
                    assert_eq!(
                        wide, plain_found,
                        "stride {stride}, window {window}, max distance {max_distance}"
                    );
                    assert!(plain_found.iter().any(|m| *m != NONE));
                    searched_outer_rings |= window >= 2
                        && map.iter().zip(&plain_found).any(|(q, &m)| {
                            projector.project(*q).is_some_and(|p| {
                                let cell = grid.cell_of(&p);
                                grid.is_interior(cell.0, cell.1)
                                    && m != NONE
                                    && !block3_holds(&grid, cell, m)
                            })
                        });
                }
            }
        }
        assert!(
            searched_outer_rings,
            "no case took a point outside the 3x3 block"
        );
    }

    /// Whether point `m` lies in the 3x3 block around `cell`.
    fn block3_holds(grid: &PixelGrid<'_>, cell: (i64, i64), m: u32) -> bool {
        (-1..=1).any(|dv| {
            (-1..=1).any(|du| {
                let (cu, cv) = ((cell.0 + du) as usize, (cell.1 + dv) as usize);
                grid.cells[cv * grid.columns + cu].index == m
            })
        })
    }
}
