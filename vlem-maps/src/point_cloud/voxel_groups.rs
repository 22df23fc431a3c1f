//! The point-cloud map's downsampling grid: which points share a voxel.
//!
//! Why a file of its own: keeping the map within its budget groups every point by voxel, once per
//! voxel size the budget search tries, on every frame that leaves the map over budget. At 1M
//! points a comparison sort of the (key, index) pairs took 30–40 ms a try on two cores, most of
//! an over-budget frame. Voxel keys are small integers (a few bits per axis at the sizes the
//! search tries), so a stable radix sort over just the bits in use does the same grouping, in the
//! same order, in a few passes over the array.

use rayon::prelude::*;

/// Voxels per axis that a key tells apart (21 bits per axis).
pub(super) const KEY_AXIS_VOXELS: f32 = ((1u32 << 21) - 1) as f32;

/// Bits per radix pass: 2048 buckets, whose counters stay in L1.
const DIGIT_BITS: u32 = 11;

/// The points grouped by voxel: runs of point indices, each run one voxel's points in index
/// order, the runs in voxel-key order.
pub(super) struct VoxelGroups {
    /// Point indices, run after run.
    order: Vec<u32>,
    /// Where each run ends in `order`.
    ends: Vec<u32>,
    /// The number of occupied voxels (runs).
    pub count: usize,
}

impl VoxelGroups {
    /// Groups `positions` by voxels of side `voxel` anchored at `origin`, the corner of the
    /// bounding box of the positions, whose largest side is `extent`.
    pub fn new(positions: &[[f32; 3]], voxel: f32, origin: [f32; 3], extent: f32) -> Self {
        // Bits per axis for the voxel coordinates in the box; never more than the key's 21.
        let axis_voxels = (extent / voxel).min(KEY_AXIS_VOXELS) as u64 + 1;
        let axis_bits = (u64::BITS - axis_voxels.leading_zeros()).clamp(1, 21);
        let key_bits = 3 * axis_bits;
        let index_bits = u64::BITS - (positions.len().max(2) as u64 - 1).leading_zeros();
        let key = |p: &[f32; 3]| voxel_key(p, voxel, origin, axis_bits);
        let (mut order, mut ends) = (Vec::with_capacity(positions.len()), Vec::new());
        if key_bits + index_bits <= u64::BITS {
            // Key and index in one word: half the bytes to move of a (key, index) pair.
            let mut packed: Vec<u64> = positions
                .par_iter()
                .enumerate()
                .map(|(i, p)| (key(p) << index_bits) | i as u64)
                .collect();
            // Stable, and the words start in index order: a voxel's indices stay sorted.
            radix_sort_bits(&mut packed, index_bits, key_bits);
            let index_mask = (1u64 << index_bits) - 1;
            for (i, w) in packed.iter().enumerate() {
                if i > 0 && packed[i - 1] >> index_bits != w >> index_bits {
                    ends.push(i as u32);
                }
                order.push((w & index_mask) as u32);
            }
        } else {
            // Very fine voxels over a large box: (key, index) pairs in a comparison sort.
            let mut pairs: Vec<(u64, u32)> = positions
                .par_iter()
                .enumerate()
                .map(|(i, p)| (key(p), i as u32))
                .collect();
            pairs.par_sort_unstable();
            for (i, &(k, index)) in pairs.iter().enumerate() {
                if i > 0 && pairs[i - 1].0 != k {
                    ends.push(i as u32);
                }
                order.push(index);
            }
        }
        if !order.is_empty() {
            ends.push(order.len() as u32);
        }
        Self {
            count: ends.len(),
            order,
            ends,
        }
    }

    /// The runs of point indices that share a voxel, in key order.
    pub fn runs(&self) -> impl Iterator<Item = &[u32]> {
        let starts = std::iter::once(0).chain(self.ends.iter().copied());
        starts
            .zip(&self.ends)
            .map(|(start, &end)| &self.order[start as usize..end as usize])
    }
}

/// The corner (per-axis minimum) and the largest side of the bounding box of `positions`.
pub(super) fn bounding_box(positions: &[[f32; 3]]) -> ([f32; 3], f32) {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    if positions.is_empty() {
        return ([0.0; 3], 0.0);
    }
    let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max);
    (lo, extent)
}

/// Packs the voxel coordinates of `p` relative to `origin`, `axis_bits` bits per axis (at most
/// 21: about 2 km at 1 mm voxels; the budget search picks voxels that keep the map within that
/// range). `p` is in the box that `origin` is the corner of, so the coordinates are not negative
/// and truncation is `floor` (without its libm call).
fn voxel_key(p: &[f32; 3], voxel: f32, origin: [f32; 3], axis_bits: u32) -> u64 {
    let mask = (1u64 << axis_bits) - 1;
    let axis = |k: usize| (((p[k] - origin[k]) / voxel) as u64).min(mask);
    (axis(0) << (2 * axis_bits)) | (axis(1) << axis_bits) | axis(2)
}

/// Sorts `words` by their bits `[low, low + bits)` (the bits above are zero), keeping the order
/// of words equal in them: least significant digit first, one counting pass and one scatter per
/// digit, a digit skipped where every word has the same value in it.
fn radix_sort_bits(words: &mut Vec<u64>, low: u32, bits: u32) {
    let buckets = 1usize << DIGIT_BITS;
    let mask = (buckets - 1) as u64;
    let mut other = vec![0u64; words.len()];
    let mut counts = vec![0usize; buckets];
    let mut shift = low;
    while shift < low + bits {
        counts.iter_mut().for_each(|c| *c = 0);
        for &w in words.iter() {
            counts[((w >> shift) & mask) as usize] += 1;
        }
        if counts.iter().all(|&c| c == 0 || c == words.len()) {
            shift += DIGIT_BITS;
            continue;
        }
        // Counts to start offsets.
        let mut start = 0;
        for c in counts.iter_mut() {
            (*c, start) = (start, start + *c);
        }
        for &w in words.iter() {
            let digit = ((w >> shift) & mask) as usize;
            other[counts[digit]] = w;
            counts[digit] += 1;
        }
        std::mem::swap(words, &mut other);
        shift += DIGIT_BITS;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn the_radix_sort_orders_like_a_sort_of_the_words() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for (low, bits) in [(0u32, 1u32), (12, 5), (12, 11), (12, 12), (20, 33), (0, 63)] {
            // Few distinct keys, so equal keys are common; the low bits count up (an index), so
            // a stable sort leaves the words fully sorted.
            let distinct = 1u64 << bits.min(9);
            let mut words: Vec<u64> = (0..3000u64)
                .map(|i| {
                    let k = rng.random_range(0..distinct);
                    // Spread over the bits in use.
                    let key = k.wrapping_mul(0x9E37_79B9_7F4A_7C15) & ((1u128 << bits) - 1) as u64;
                    (key << low) | (i & ((1u64 << low) - 1))
                })
                .collect();
            let mut expected = words.clone();
            expected.sort_by_key(|w| w >> low);
            radix_sort_bits(&mut words, low, bits);
            assert_eq!(words, expected, "bits {low}..{}", low + bits);
        }
    }

    #[test]
    fn groups_are_the_voxels_of_the_points() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let positions: Vec<[f32; 3]> = (0..5000)
            .map(|_| [0; 3].map(|_: i32| rng.random_range(-1.0f32..2.0)))
            .collect();
        let (origin, extent) = bounding_box(&positions);
        // 1e-5: fine enough for the (key, index) pairs' path.
        for voxel in [1e-5f32, 0.01, 0.3, 1.0, 4.0] {
            let groups = VoxelGroups::new(&positions, voxel, origin, extent);
            let cell =
                |p: &[f32; 3]| [0, 1, 2].map(|k| ((p[k] - origin[k]) / voxel).floor() as i64);
            let mut seen = std::collections::HashSet::new();
            let mut members = 0;
            for run in groups.runs() {
                let first = cell(&positions[run[0] as usize]);
                assert!(seen.insert(first), "voxel {first:?} in two runs");
                assert!(run.windows(2).all(|w| w[0] < w[1]));
                for &i in run {
                    assert_eq!(cell(&positions[i as usize]), first);
                }
                members += run.len();
            }
            assert_eq!(members, positions.len());
            assert_eq!(seen.len(), groups.count);
        }
    }
}
