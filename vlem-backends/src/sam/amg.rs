//! The model-free steps of the automatic mask generator: the point grid, the stability score,
//! mask boxes, box non-maximum suppression, small-region and hole removal, and the sampling of
//! uncovered pixels for the fill-in refinement.
//!
//! Why it exists: these steps decide which of SAM's raw masks become regions, and they are plain
//! arithmetic that can be tested by hand, apart from the network. Each follows the function of the
//! same purpose in `segment_anything/utils/amg.py` and `automatic_mask_generator.py` of the
//! reference package; where a choice was made it is said at the function.

/// A pixel box `[x0, y0, x1, y1]` with inclusive corners: the columns and rows of the first and
/// last foreground pixels (the reference's `batched_mask_to_box`).
pub type MaskBox = [u32; 4];

/// The reference's point grid: `n * n` points at the centres of an `n x n` tiling of the unit
/// square, as `[x, y]` in `[0, 1]`, row by row (y outer, x inner).
pub fn point_grid(n: usize) -> Vec<[f64; 2]> {
    let offset = 1.0 / (2 * n.max(1)) as f64;
    let step = if n > 1 {
        (1.0 - 2.0 * offset) / (n - 1) as f64
    } else {
        0.0
    };
    let mut points = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            points.push([offset + i as f64 * step, offset + j as f64 * step]);
        }
    }
    points
}

/// The stability score of mask logits: the IoU of the masks thresholded at
/// `threshold + offset` and at `threshold - offset` (strictly greater, as the reference). The
/// first is a subset of the second, so it is their pixel-count ratio. 0 when even the low
/// threshold leaves the mask empty (the reference gets NaN there, which no filter keeps).
pub fn stability_score(logits: &[f32], threshold: f32, offset: f32) -> f32 {
    let (high, low) = (threshold + offset, threshold - offset);
    let mut intersections = 0usize;
    let mut unions = 0usize;
    for &l in logits {
        intersections += usize::from(l > high);
        unions += usize::from(l > low);
    }
    if unions == 0 {
        0.0
    } else {
        intersections as f32 / unions as f32
    }
}

/// The box of a row-major `width`-wide mask; `None` when it is empty.
pub fn mask_to_box(mask: &[bool], width: usize) -> Option<MaskBox> {
    if width == 0 {
        return None;
    }
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
    for (y, row) in mask.chunks(width).enumerate() {
        let Some(first) = row.iter().position(|&m| m) else {
            continue;
        };
        let last = row.iter().rposition(|&m| m).unwrap_or(first);
        x0 = x0.min(first);
        x1 = x1.max(last);
        y0 = y0.min(y);
        y1 = y;
    }
    (x0 != usize::MAX).then(|| [x0, y0, x1, y1].map(|v| v as u32))
}

/// IoU of two boxes as torchvision's `box_iou` computes it on these boxes: area
/// `(x1 - x0) * (y1 - y0)`, so a one-pixel-wide box has area 0 (the reference feeds the inclusive
/// mask boxes to it as they are; kept for the same suppressions). 0 when the union is empty.
pub fn box_iou(a: &MaskBox, b: &MaskBox) -> f32 {
    let [ax0, ay0, ax1, ay1] = a.map(|v| v as f32);
    let [bx0, by0, bx1, by1] = b.map(|v| v as f32);
    let iw = (ax1.min(bx1) - ax0.max(bx0)).max(0.0);
    let ih = (ay1.min(by1) - ay0.max(by0)).max(0.0);
    let inter = iw * ih;
    let union = (ax1 - ax0) * (ay1 - ay0) + (bx1 - bx0) * (by1 - by0) - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

/// Greedy box non-maximum suppression: visits the boxes by decreasing score (ties by index) and
/// keeps a box unless its IoU with a kept one exceeds `iou_threshold`. Returns the kept indices
/// in that visiting order, like torchvision's `batched_nms` with one category.
pub fn nms(boxes: &[MaskBox], scores: &[f32], iou_threshold: f32) -> Vec<usize> {
    let mut order: Vec<usize> = (0..boxes.len().min(scores.len())).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let mut kept: Vec<usize> = Vec::new();
    for i in order {
        if kept
            .iter()
            .all(|&k| box_iou(&boxes[k], &boxes[i]) <= iou_threshold)
        {
            kept.push(i);
        }
    }
    kept
}

/// What [`remove_small_regions`] removes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SmallRegions {
    /// Background components (holes) smaller than the area are filled.
    Holes,
    /// Foreground components (islands) smaller than the area are dropped; if all are small, the
    /// largest stays.
    Islands,
}

/// 8-connected component labels of the `true` pixels of a row-major mask: the label of each pixel
/// (0 for `false`) and the size of each component (index `label - 1`). Components are numbered
/// in the order of the first 2 x 2 block (blocks in raster order) that holds one of their pixels,
/// as OpenCV's block-based labelling numbers them: the reference keeps the first of equally large
/// islands, so the numbering decides ties. (A 2 x 2 block never holds two components.)
pub fn connected_components(mask: &[bool], width: usize) -> (Vec<u32>, Vec<usize>) {
    let mut labels = vec![0u32; mask.len()];
    let mut sizes = Vec::new();
    if width == 0 {
        return (labels, sizes);
    }
    let height = mask.len() / width;
    let mut stack = Vec::new();
    for by in (0..height).step_by(2) {
        for bx in (0..width).step_by(2) {
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let (x, y) = (bx + dx, by + dy);
                if x >= width || y >= height {
                    continue;
                }
                let start = y * width + x;
                if !mask[start] || labels[start] != 0 {
                    continue;
                }
                let label = sizes.len() as u32 + 1;
                let mut size = 0usize;
                labels[start] = label;
                stack.push(start);
                while let Some(p) = stack.pop() {
                    size += 1;
                    let (x, y) = (p % width, p / width);
                    for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
                        for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                            let q = ny * width + nx;
                            if mask[q] && labels[q] == 0 {
                                labels[q] = label;
                                stack.push(q);
                            }
                        }
                    }
                }
                sizes.push(size);
            }
        }
    }
    (labels, sizes)
}

/// The reference's `remove_small_regions` (OpenCV's 8-connected components there, ours here):
/// fills holes, or drops islands, of fewer than `min_area` pixels. Returns the new mask and
/// whether anything changed.
pub fn remove_small_regions(
    mask: &[bool],
    width: usize,
    min_area: usize,
    mode: SmallRegions,
) -> (Vec<bool>, bool) {
    let holes = mode == SmallRegions::Holes;
    let working: Vec<bool> = mask.iter().map(|&m| m != holes).collect();
    let (labels, sizes) = connected_components(&working, width);
    let small: Vec<bool> = sizes.iter().map(|&s| s < min_area).collect();
    if !small.iter().any(|&s| s) {
        return (mask.to_vec(), false);
    }
    let out = if holes {
        // Keep the mask, and fill the small background components.
        labels
            .iter()
            .map(|&l| l == 0 || small[l as usize - 1])
            .collect()
    } else {
        let mut keep: Vec<bool> = small.iter().map(|&s| !s).collect();
        if !keep.iter().any(|&k| k) {
            // All islands are small: keep the largest (the first of equals).
            let mut largest = 0;
            for (i, &s) in sizes.iter().enumerate() {
                if s > sizes[largest] {
                    largest = i;
                }
            }
            keep[largest] = true;
        }
        labels
            .iter()
            .map(|&l| l != 0 && keep[l as usize - 1])
            .collect()
    };
    (out, true)
}

/// A small seeded pseudo-random generator (SplitMix64): the fill-in refinement needs
/// reproducible samples, not cryptographic ones, and no extra dependency.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator started from `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        splitmix64_mix(self.0)
    }

    /// A uniform integer in `0..n` (`n > 0`; 0 for `n == 0`), by Lemire's multiply-shift.
    pub fn below(&mut self, n: usize) -> usize {
        ((u128::from(self.next_u64()) * n as u128) >> 64) as usize
    }
}

/// The SplitMix64 output function.
pub fn splitmix64_mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Up to `n` distinct pixel indices drawn uniformly (without replacement) among the pixels that
/// `covered` leaves `false`, in draw order; all of them when fewer remain. The fill-in
/// refinement's query points.
pub fn sample_uncovered(covered: &[bool], n: usize, seed: u64) -> Vec<usize> {
    let mut free: Vec<usize> = covered
        .iter()
        .enumerate()
        .filter_map(|(i, &c)| (!c).then_some(i))
        .collect();
    let n = n.min(free.len());
    let mut rng = SplitMix64::new(seed);
    // Partial Fisher-Yates: the first `n` entries become a uniform sample.
    for i in 0..n {
        let j = i + rng.below(free.len() - i);
        free.swap(i, j);
    }
    free.truncate(n);
    free
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_grid_matches_the_reference_layout() {
        let g = point_grid(2);
        assert_eq!(
            g,
            vec![[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]
        );
        let g = point_grid(4);
        assert_eq!(g.len(), 16);
        assert!((g[1][0] - 0.375).abs() < 1e-12 && (g[1][1] - 0.125).abs() < 1e-12);
        assert!((g[15][0] - 0.875).abs() < 1e-12 && (g[15][1] - 0.875).abs() < 1e-12);
        assert_eq!(point_grid(1), vec![[0.5, 0.5]]);
    }

    #[test]
    fn stability_score_counts_strictly_above_the_shifted_thresholds() {
        // > 1: {2, 3} (not 1 itself) = 2 pixels; > -1: {0, 0.5, 1, 2, 3} (not -1) = 5 pixels.
        let logits = [-2.0, -1.0, 0.0, 0.5, 1.0, 2.0, 3.0];
        assert_eq!(stability_score(&logits, 0.0, 1.0), 2.0 / 5.0);
        assert_eq!(stability_score(&[-5.0, -3.0], 0.0, 1.0), 0.0);
        assert_eq!(stability_score(&[5.0, 3.0], 0.0, 1.0), 1.0);
    }

    #[test]
    fn mask_to_box_is_inclusive_and_none_when_empty() {
        #[rustfmt::skip]
        let mask = [
            false, false, false, false,
            false, true,  false, false,
            false, false, true,  false,
        ];
        assert_eq!(mask_to_box(&mask, 4), Some([1, 1, 2, 2]));
        assert_eq!(mask_to_box(&[false; 12], 4), None);
        assert_eq!(mask_to_box(&[true], 1), Some([0, 0, 0, 0]));
    }

    #[test]
    fn box_iou_uses_the_reference_areas() {
        // (0,0)-(10,10) area 100 and (5,0)-(15,10) area 100 overlap 5 x 10 = 50: 50 / 150.
        assert!((box_iou(&[0, 0, 10, 10], &[5, 0, 15, 10]) - 1.0 / 3.0).abs() < 1e-6);
        assert_eq!(box_iou(&[0, 0, 10, 10], &[20, 20, 30, 30]), 0.0);
        assert_eq!(box_iou(&[3, 3, 3, 3], &[3, 3, 3, 3]), 0.0);
    }

    #[test]
    fn nms_keeps_the_best_of_overlapping_boxes_in_score_order() {
        let boxes = [
            [0, 0, 10, 10],
            [1, 0, 11, 10],
            [20, 20, 30, 30],
            [0, 0, 10, 4],
        ];
        let scores = [0.8, 0.9, 0.5, 0.7];
        // 1 (0.9) beats 0 (IoU 90/110 = 0.82 > 0.7); 3 overlaps 1 by 36/(100+40-36) = 0.35.
        assert_eq!(nms(&boxes, &scores, 0.7), vec![1, 3, 2]);
        // A threshold of 0.9 keeps box 0 too.
        assert_eq!(nms(&boxes, &scores, 0.9), vec![1, 0, 3, 2]);
        assert!(nms(&[], &[], 0.7).is_empty());
    }

    #[test]
    fn connected_components_use_eight_neighbours() {
        #[rustfmt::skip]
        let mask = [
            true,  false, false, true,
            false, true,  false, false,
            false, false, false, true,
        ];
        let (labels, sizes) = connected_components(&mask, 4);
        // (0,0)-(1,1) touch diagonally; (3,0) and (3,2) do not touch anything.
        assert_eq!(sizes, vec![2, 1, 1]);
        assert_eq!(labels, vec![1, 0, 0, 2, 0, 1, 0, 0, 0, 0, 0, 3]);
        // Numbered by 2 x 2 blocks, not raster order: (0,1) shares the first block.
        #[rustfmt::skip]
        let mask = [
            false, false, false, true,
            true,  false, false, false,
        ];
        let (labels, _) = connected_components(&mask, 4);
        assert_eq!(labels, vec![0, 0, 0, 2, 1, 0, 0, 0]);
    }

    #[test]
    fn small_holes_are_filled_and_small_islands_dropped() {
        #[rustfmt::skip]
        let mask = [
            true, true,  true, false, false,
            true, false, true, false, true,
            true, true,  true, false, false,
        ];
        // Background components: the hole at (1,1) (1 pixel) and the right part (5 pixels).
        let (filled, changed) = remove_small_regions(&mask, 5, 2, SmallRegions::Holes);
        assert!(changed);
        assert!(filled[6], "hole filled");
        assert!(!filled[3] && !filled[8], "large background kept");
        // Islands: the ring (8 pixels) and the dot at (4,1) (1 pixel).
        let (cleaned, changed) = remove_small_regions(&mask, 5, 2, SmallRegions::Islands);
        assert!(changed);
        assert!(!cleaned[9], "dot dropped");
        assert_eq!(cleaned.iter().filter(|&&m| m).count(), 8);
        // Nothing small: unchanged.
        let (same, changed) = remove_small_regions(&mask, 5, 1, SmallRegions::Islands);
        assert!(!changed);
        assert_eq!(same, mask.to_vec());
        // All islands small: the largest stays.
        let (largest, changed) = remove_small_regions(&mask, 5, 100, SmallRegions::Islands);
        assert!(changed);
        assert_eq!(largest.iter().filter(|&&m| m).count(), 8);
    }

    #[test]
    fn uncovered_samples_are_distinct_uncovered_and_seeded() {
        let covered: Vec<bool> = (0..100).map(|i| i % 3 != 0).collect();
        let a = sample_uncovered(&covered, 10, 7);
        assert_eq!(a.len(), 10);
        assert!(a.iter().all(|&i| !covered[i]));
        let mut sorted = a.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), 10);
        assert_eq!(a, sample_uncovered(&covered, 10, 7));
        assert_ne!(a, sample_uncovered(&covered, 10, 8));
        // Fewer free pixels than asked: all of them.
        let mut all = sample_uncovered(&covered, 1000, 1);
        all.sort_unstable();
        assert_eq!(all, (0..100).filter(|i| i % 3 == 0).collect::<Vec<_>>());
        assert!(sample_uncovered(&[true; 5], 3, 0).is_empty());
    }

    #[test]
    fn uncovered_sampling_is_roughly_uniform() {
        // 4 free pixels, 1 draw each time: every pixel is drawn about a quarter of the time.
        let covered = [false, true, false, true, false, false];
        let mut counts = [0usize; 6];
        for seed in 0..4000 {
            counts[sample_uncovered(&covered, 1, seed)[0]] += 1;
        }
        for (i, &c) in counts.iter().enumerate() {
            if covered[i] {
                assert_eq!(c, 0);
            } else {
                assert!((800..1200).contains(&c), "{counts:?}");
            }
        }
    }
}
