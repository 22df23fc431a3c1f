//! The point-cloud map's downsampling grid: which points share a voxel.
//!
//! Why a file of its own: keeping the map within its budget groups every point by voxel, once per
//! voxel size the budget search tries, on every frame that leaves the map over budget. At 1M
//! points a comparison sort of the (key, index) pairs took 30–40 ms a try on two cores, most of
//! an over-budget frame. Voxel keys are small integers (a few bits per axis at the sizes the
//! search tries), so a stable radix sort over just the bits in use does the same grouping, in the
//! same order, in a few passes over the array.
//!
//! The buffers are kept between groupings and between frames ([`GroupingBuffers`]): at 1M points
//! a grouping fills 8 MB of words and sorts them through 8 MB more, and on this project's VMs a
//! page the process has not touched before costs more than the sort's pass over it. A try of the
//! search only counts the voxels; the runs of points that share one are listed once, for the size
//! the search keeps.

use rayon::prelude::*;

/// Voxels per axis that a key tells apart (21 bits per axis).
pub(super) const KEY_AXIS_VOXELS: f32 = ((1u32 << 21) - 1) as f32;

/// Bits per radix pass: 2048 buckets, whose counters stay in L1.
const DIGIT_BITS: u32 = 11;

/// The points grouped by voxel at one size, sorted so that each voxel's points are a run in
/// index order, the runs in voxel-key order.
#[derive(Clone, Default)]
pub(super) struct VoxelGroups {
    /// Per point its voxel key above its index (the low `index_bits` bits), sorted; used when
    /// key and index fit one word, half the bytes to move of a (key, index) pair.
    words: Vec<u64>,
    /// (key, index) pairs, sorted: for very fine voxels over a large box.
    pairs: Vec<(u64, u32)>,
    /// Whether `words` (or else `pairs`) holds the grouping.
    packed: bool,
    index_bits: u32,
    /// The number of occupied voxels (runs).
    pub count: usize,
}

impl VoxelGroups {
    /// Groups `positions` by voxels of side `voxel` anchored at `origin`, the corner of the
    /// bounding box of the positions, whose largest side is `extent`. `spare` is the radix
    /// sort's second buffer; it and this grouping's own buffers keep their allocations.
    pub fn group(
        &mut self,
        positions: &[[f32; 3]],
        voxel: f32,
        origin: [f32; 3],
        extent: f32,
        spare: &mut Vec<u64>,
    ) {
        // Bits per axis for the voxel coordinates in the box; never more than the key's 21.
        let axis_voxels = (extent / voxel).min(KEY_AXIS_VOXELS) as u64 + 1;
        let axis_bits = (u64::BITS - axis_voxels.leading_zeros()).clamp(1, 21);
        let key_bits = 3 * axis_bits;
        let index_bits = u64::BITS - (positions.len().max(2) as u64 - 1).leading_zeros();
        let key = |p: &[f32; 3]| voxel_key(p, voxel, origin, axis_bits);
        self.packed = key_bits + index_bits <= u64::BITS;
        self.index_bits = index_bits;
        if self.packed {
            // In chunks with a plain loop inside, which the compiler vectorises.
            const CHUNK: usize = 1 << 14;
            self.words.resize(positions.len(), 0);
            self.words
                .par_chunks_mut(CHUNK)
                .zip(positions.par_chunks(CHUNK))
                .enumerate()
                .for_each(|(chunk, (words, points))| {
                    let first = (chunk * CHUNK) as u64;
                    for ((w, p), i) in words.iter_mut().zip(points).zip(first..) {
                        *w = (key(p) << index_bits) | i;
                    }
                });
            // Stable, and the words start in index order: a voxel's indices stay sorted.
            radix_sort_bits(&mut self.words, spare, index_bits, key_bits);
            self.count = count_runs(&self.words, |a, b| a >> index_bits == b >> index_bits);
        } else {
            // Very fine voxels over a large box: (key, index) pairs in a comparison sort.
            self.pairs.clear();
            self.pairs.par_extend(
                positions
                    .par_iter()
                    .enumerate()
                    .map(|(i, p)| (key(p), i as u32)),
            );
            self.pairs.par_sort_unstable();
            self.count = count_runs(&self.pairs, |a, b| a.0 == b.0);
        }
    }

    /// Lists the voxels of at least `min_points` points: their point indices run after run in
    /// `members` (each run in index order, the runs in key order), and where each run ends in
    /// `ends`. Both buffers are cleared first.
    pub fn runs_into(&self, min_points: usize, members: &mut Vec<u32>, ends: &mut Vec<u32>) {
        members.clear();
        ends.clear();
        if self.packed {
            let index_bits = self.index_bits;
            let index_mask = (1u64 << index_bits) - 1;
            list_runs(
                &self.words,
                |a, b| a >> index_bits == b >> index_bits,
                |w| (w & index_mask) as u32,
                min_points,
                members,
                ends,
            );
        } else {
            list_runs(
                &self.pairs,
                |a, b| a.0 == b.0,
                |p| p.1,
                min_points,
                members,
                ends,
            );
        }
    }

    /// The heap bytes the kept buffers hold.
    fn memory_bytes(&self) -> usize {
        self.words.capacity() * std::mem::size_of::<u64>()
            + self.pairs.capacity() * std::mem::size_of::<(u64, u32)>()
    }
}

/// The runs listed by [`VoxelGroups::runs_into`], as slices of point indices.
pub(super) fn runs<'a>(members: &'a [u32], ends: &'a [u32]) -> impl Iterator<Item = &'a [u32]> {
    let starts = std::iter::once(0).chain(ends.iter().copied());
    starts
        .zip(ends)
        .map(|(start, &end)| &members[start as usize..end as usize])
}

/// The number of runs of neighbours that `same` puts together in sorted `items`.
fn count_runs<T: Sync>(items: &[T], same: impl Fn(&T, &T) -> bool + Sync) -> usize {
    if items.is_empty() {
        return 0;
    }
    1 + items
        .par_windows(2)
        .with_min_len(1 << 14)
        .filter(|w| !same(&w[0], &w[1]))
        .count()
}

/// Appends the runs of at least `min_points` items of sorted `items` to `members` (as `index`
/// gives them) and their ends to `ends`.
fn list_runs<T>(
    items: &[T],
    same: impl Fn(&T, &T) -> bool,
    index: impl Fn(&T) -> u32,
    min_points: usize,
    members: &mut Vec<u32>,
    ends: &mut Vec<u32>,
) {
    let mut start = 0;
    for end in 1..=items.len() {
        if end < items.len() && same(&items[start], &items[end]) {
            continue;
        }
        if end - start >= min_points {
            members.extend(items[start..end].iter().map(&index));
            ends.push(members.len() as u32);
        }
        start = end;
    }
}

/// The budget search's buffers, kept between frames: the grouping the search holds, the one it
/// tries, the sort's second buffer and the runs to merge. All scale with the point count, not the
/// embedding width; the merged embeddings (runs × dimensions) are not kept, so a 512-d map does
/// not hold a second copy of its largest merge.
#[derive(Clone, Default)]
pub(super) struct GroupingBuffers {
    pub held: VoxelGroups,
    pub tried: VoxelGroups,
    pub spare: Vec<u64>,
    pub members: Vec<u32>,
    pub ends: Vec<u32>,
}

impl GroupingBuffers {
    /// The heap bytes the kept buffers hold.
    pub fn memory_bytes(&self) -> usize {
        use std::mem::size_of;
        self.held.memory_bytes()
            + self.tried.memory_bytes()
            + self.spare.capacity() * size_of::<u64>()
            + (self.members.capacity() + self.ends.capacity()) * size_of::<u32>()
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
/// and truncation is `floor` (without its libm call). Through `i32`, which the lanes convert to
/// and `u64` they do not: the coordinate is clamped to the mask's range either way.
#[inline(always)]
fn voxel_key(p: &[f32; 3], voxel: f32, origin: [f32; 3], axis_bits: u32) -> u64 {
    let mask = (1i32 << axis_bits) - 1;
    let axis = |k: usize| (((p[k] - origin[k]) / voxel) as i32).clamp(0, mask) as u64;
    (axis(0) << (2 * axis_bits)) | (axis(1) << axis_bits) | axis(2)
}

/// Sorts `words` by their bits `[low, low + bits)` (the bits above are zero), keeping the order
/// of words equal in them. `other` is a second buffer (resized to fit; its old contents do not
/// matter).
///
/// A large array is scattered by its top digit first, into buckets that then sort on their own,
/// in parallel: each is small enough to stay in cache, and the two cores share them. A small one,
/// or a key of one digit, sorts in place ([`sort_digits`]).
fn radix_sort_bits(words: &mut Vec<u64>, other: &mut Vec<u64>, low: u32, bits: u32) {
    other.resize(words.len(), 0);
    if words.len() < BUCKETED_FROM || bits <= DIGIT_BITS {
        if sort_digits(words, other, low, bits, DIGIT_BITS) {
            std::mem::swap(words, other);
        }
        return;
    }
    let top_shift = low + bits - DIGIT_BITS;
    let digit = |w: u64| ((w >> top_shift) as usize) & ((1 << DIGIT_BITS) - 1);
    let counts = words
        .par_chunks(1 << 16)
        .fold(
            || vec![0usize; 1 << DIGIT_BITS],
            |mut counts, chunk| {
                chunk.iter().for_each(|&w| counts[digit(w)] += 1);
                counts
            },
        )
        .reduce(
            || vec![0usize; 1 << DIGIT_BITS],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                a
            },
        );
    // Stable, so each bucket keeps the words' order for the sort on the digits below.
    let mut next = Vec::with_capacity(counts.len());
    let mut start = 0;
    for &c in &counts {
        next.push(start);
        start += c;
    }
    for &w in words.iter() {
        let d = digit(w);
        other[next[d]] = w;
        next[d] += 1;
    }
    // The buckets, each with a same-sized piece of `words` as its second buffer.
    let (mut buckets, mut spares) = (&mut other[..], &mut words[..]);
    let mut pairs = Vec::with_capacity(counts.len());
    for &c in counts.iter().filter(|&&c| c > 0) {
        let (bucket, rest) = buckets.split_at_mut(c);
        let (spare, spare_rest) = spares.split_at_mut(c);
        pairs.push((bucket, spare));
        (buckets, spares) = (rest, spare_rest);
    }
    pairs.into_par_iter().for_each(|(bucket, spare)| {
        if sort_digits(bucket, spare, low, top_shift - low, BUCKET_DIGIT_BITS) {
            bucket.copy_from_slice(spare);
        }
    });
    std::mem::swap(words, other);
}

/// From this many words on, [`radix_sort_bits`] sorts by buckets.
const BUCKETED_FROM: usize = 1 << 16;

/// Bits per pass inside a bucket: a bucket holds about a thousand words at 1M points, which a
/// pass over 256 counters suits better than one over 2048.
const BUCKET_DIGIT_BITS: u32 = 8;

/// Sorts `words` by their bits `[low, low + bits)`, keeping the order of words equal in them:
/// least significant digit first (`digit_bits` a digit), one counting pass and one scatter per
/// digit through `other` (as long as `words`), a digit skipped where every word has the same
/// value in it. Returns whether the result ended in `other` (after an odd number of scatters)
/// rather than in `words`.
#[must_use]
fn sort_digits(words: &mut [u64], other: &mut [u64], low: u32, bits: u32, digit_bits: u32) -> bool {
    let mask = (1u64 << digit_bits) - 1;
    let mut counts = vec![0usize; 1 << digit_bits];
    let mut in_other = false;
    let mut shift = low;
    while shift < low + bits {
        let (from, to) = if in_other {
            (&mut *other, &mut *words)
        } else {
            (&mut *words, &mut *other)
        };
        counts.iter_mut().for_each(|c| *c = 0);
        for &w in from.iter() {
            counts[((w >> shift) & mask) as usize] += 1;
        }
        shift += digit_bits;
        if counts.iter().all(|&c| c == 0 || c == from.len()) {
            continue;
        }
        // Counts to start offsets.
        let mut start = 0;
        for c in counts.iter_mut() {
            (*c, start) = (start, start + *c);
        }
        for &w in from.iter() {
            let digit = ((w >> (shift - digit_bits)) & mask) as usize;
            to[counts[digit]] = w;
            counts[digit] += 1;
        }
        in_other = !in_other;
    }
    in_other
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn the_radix_sort_orders_like_a_sort_of_the_words() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        // Arrays below and above `BUCKETED_FROM`: sorted in place, and by buckets.
        let cases = [
            (0u32, 1u32),
            (12, 5),
            (12, 11),
            (12, 12),
            (20, 33),
            (0, 63),
            (20, 36),
        ];
        for ((low, bits), len) in cases.into_iter().flat_map(|c| [(c, 3000), (c, 100_000u64)]) {
            // Few distinct keys, so equal keys are common (and, in the large arrays, buckets
            // that hold several); the low bits count up (an index), so a stable sort leaves the
            // words fully sorted.
            let distinct = 1u64 << bits.min(if len > 10_000 { 15 } else { 9 });
            let mut words: Vec<u64> = (0..len)
                .map(|i| {
                    let k = rng.random_range(0..distinct);
                    // Spread over the bits in use.
                    let key = k.wrapping_mul(0x9E37_79B9_7F4A_7C15) & ((1u128 << bits) - 1) as u64;
                    (key << low) | (i & ((1u64 << low) - 1))
                })
                .collect();
            let mut expected = words.clone();
            expected.sort_by_key(|w| w >> low);
            radix_sort_bits(&mut words, &mut Vec::new(), low, bits);
            assert_eq!(words, expected, "bits {low}..{}, {len} words", low + bits);
        }
    }

    #[test]
    fn the_key_clamps_every_coordinate_as_a_conversion_to_u64_would() {
        let axis_bits = 5;
        let mask = (1u64 << axis_bits) - 1;
        let edges = [
            f32::NAN,
            f32::NEG_INFINITY,
            -1e30,
            -3.7,
            -0.5,
            0.0,
            0.99,
            1.0,
            30.5,
            31.0,
        ];
        let more = [31.99, 32.0, 1e9, 3e9, 1e30, f32::INFINITY];
        for x in edges.into_iter().chain(more) {
            let key = voxel_key(&[x, 0.0, 1.5], 1.0, [0.0; 3], axis_bits);
            let expected = ((x as u64).min(mask) << (2 * axis_bits)) | 1;
            assert_eq!(key, expected, "coordinate {x}");
        }
    }

    #[test]
    fn groups_are_the_voxels_of_the_points() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let positions: Vec<[f32; 3]> = (0..5000)
            .map(|_| [0; 3].map(|_: i32| rng.random_range(-1.0f32..2.0)))
            .collect();
        let (origin, extent) = bounding_box(&positions);
        // One set of buffers through all sizes, as the budget search keeps them. 1e-5: fine
        // enough for the (key, index) pairs' path.
        let (mut groups, mut spare) = (VoxelGroups::default(), Vec::new());
        let (mut members, mut ends) = (Vec::new(), Vec::new());
        for voxel in [0.01f32, 1e-5, 0.3, 1.0, 4.0, 0.01] {
            groups.group(&positions, voxel, origin, extent, &mut spare);
            groups.runs_into(1, &mut members, &mut ends);
            let cell =
                |p: &[f32; 3]| [0, 1, 2].map(|k| ((p[k] - origin[k]) / voxel).floor() as i64);
            let mut seen = std::collections::HashSet::new();
            let mut listed = 0;
            for run in runs(&members, &ends) {
                let first = cell(&positions[run[0] as usize]);
                assert!(seen.insert(first), "voxel {first:?} in two runs");
                assert!(run.windows(2).all(|w| w[0] < w[1]));
                for &i in run {
                    assert_eq!(cell(&positions[i as usize]), first);
                }
                listed += run.len();
            }
            assert_eq!(listed, positions.len());
            assert_eq!(seen.len(), groups.count);
            // The voxels shared by two or more points, and nothing else.
            let shared: Vec<Vec<u32>> = runs(&members, &ends)
                .filter(|run| run.len() > 1)
                .map(<[u32]>::to_vec)
                .collect();
            groups.runs_into(2, &mut members, &mut ends);
            assert!(runs(&members, &ends).map(<[u32]>::to_vec).eq(shared));
        }
    }
}
