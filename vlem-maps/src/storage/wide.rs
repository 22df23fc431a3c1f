//! The fusion of one embedding row, `e_M := (1 - w) e_P + w e_M` renormalised, built twice: for
//! the CPU the crate targets and for AVX2, chosen at run time.
//!
//! Why: at 512 dimensions the point-cloud map fuses a million rows a frame, and with the
//! baseline x86-64 target (SSE2, four lanes) that pass cost more CPU than its memory traffic, so
//! it ran well above the memory floor. The AVX2 build does the same loops eight lanes wide. Both
//! builds blend the row and sum its squares in one pass (the renormalisation then scales it),
//! where blending, then [`normalise`](vlem_core::embeddings::normalise) took three: with the
//! squares summed in `dot`'s eight accumulators and order, it is the same IEEE arithmetic (no
//! fused multiply-add is enabled), and a unit test checks the rows bit for bit.

/// Fuses `observed` into `map` with `map_weight` and renormalises; falls back to `observed`
/// when the two cancel out.
#[inline]
pub(super) fn fuse_into(map: &mut [f32], observed: &[f32], map_weight: f32) {
    // A short row (colour names' 11 values) is less work than the call into the AVX2 build:
    // the 11-d fusion pass took 12.3 ms inline and 13.9 ms through the call (fusion bench,
    // timers, 1M points). It stays inline in the caller's loop.
    #[cfg(target_arch = "x86_64")]
    if map.len() >= WIDE_FROM && std::arch::is_x86_feature_detected!("avx2") {
        #[allow(
            unsafe_code,
            reason = "calls a function built for AVX2, on a CPU just found to have it"
        )]
        // SAFETY: `fuse_into_avx2` needs AVX2 and nothing else, and the CPU has it.
        unsafe {
            fuse_into_avx2(map, observed, map_weight);
        }
        return;
    }
    fuse(map, observed, map_weight);
}

/// The row length from which [`fuse_into`] calls the AVX2 build.
#[cfg(target_arch = "x86_64")]
const WIDE_FROM: usize = 64;

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn fuse_into_avx2(map: &mut [f32], observed: &[f32], map_weight: f32) {
    fuse(map, observed, map_weight);
}

/// The fusion itself, inlined into each build.
#[inline(always)]
fn fuse(map: &mut [f32], observed: &[f32], map_weight: f32) {
    let observed_weight = 1.0 - map_weight;
    // `vlem_core::query::dot(map, map)` of the blended row: eight accumulators over the whole
    // groups of eight, then the rest summed on its own.
    let whole = map.len() - map.len() % 8;
    let (map_groups, map_rest) = map.split_at_mut(whole);
    let (observed_groups, observed_rest) = observed.split_at(whole.min(observed.len()));
    let mut acc = [0.0f32; 8];
    for (m, p) in map_groups
        .chunks_exact_mut(8)
        .zip(observed_groups.chunks_exact(8))
    {
        for k in 0..8 {
            m[k] = observed_weight * p[k] + map_weight * m[k];
            acc[k] += m[k] * m[k];
        }
    }
    for (m, p) in map_rest.iter_mut().zip(observed_rest) {
        *m = observed_weight * p + map_weight * *m;
    }
    let rest: f32 = map_rest.iter().map(|x| x * x).sum();
    let norm = (acc.iter().sum::<f32>() + rest).sqrt();
    if !(norm.is_finite() && norm > 0.0) {
        map.copy_from_slice(observed);
        return;
    }
    let inverse = 1.0 / norm;
    map.iter_mut().for_each(|x| *x *= inverse);
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};

    use super::*;

    /// The fusion as the blend, then `normalise`.
    fn in_two_steps(map: &mut [f32], observed: &[f32], map_weight: f32) {
        for (m, p) in map.iter_mut().zip(observed) {
            *m = (1.0 - map_weight) * p + map_weight * *m;
        }
        if !vlem_core::embeddings::normalise(map) {
            map.copy_from_slice(observed);
        }
    }

    #[test]
    fn the_one_pass_fusion_matches_blend_then_normalise_bit_for_bit() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for dim in [1usize, 3, 8, 11, 16, 29, 512, 768] {
            for map_weight in [0.5f32, 0.3, 0.9] {
                for _ in 0..20 {
                    let map: Vec<f32> = (0..dim).map(|_| rng.random_range(-1.0..1.0)).collect();
                    let observed: Vec<f32> =
                        (0..dim).map(|_| rng.random_range(-1.0..1.0)).collect();
                    let mut expected = map.clone();
                    in_two_steps(&mut expected, &observed, map_weight);
                    let mut dispatched = map.clone();
                    fuse_into(&mut dispatched, &observed, map_weight);
                    let mut plain = map.clone();
                    fuse(&mut plain, &observed, map_weight);
                    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&dispatched), bits(&expected), "dim {dim}");
                    assert_eq!(bits(&plain), bits(&expected), "dim {dim}");
                }
            }
        }
        // Rows that cancel out fall back to the observed row.
        let observed = [0.6, -0.8, 0.0];
        let mut map = [-0.6, 0.8, 0.0];
        fuse_into(&mut map, &observed, 0.5);
        assert_eq!(map, observed);
    }
}
