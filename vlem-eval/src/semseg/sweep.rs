//! The paper's threshold-sweep IoU: a class's IoU averaged over similarity thresholds spanning the
//! whole range of the normalised similarity.
//!
//! For class `c` and threshold `t`, an element (ground-truth point or pixel) is *predicted* `c`
//! when its similarity to the text of `c` is at least `t`; it *is* `c` when its ground-truth label
//! is `c`. Then `IoU_c(t) = TP / (TP + FP + FN)`, and the class IoU is the mean of `IoU_c(t)` over
//! the thresholds `t_k = k / steps`, `k = 0..=steps` (101 thresholds 0.00, 0.01, …, 1.00 by
//! default). A class without ground-truth elements has no IoU. Elements without a similarity (no
//! map point near them, a pixel without an embedding) are predicted negative for every class.
//!
//! [`ThresholdSweep`] counts elements in one histogram bin per threshold interval, so adding an
//! element costs O(1) and the IoUs come out exactly as if every threshold had been applied.

use crate::error::{EvalError, Result};

/// The number of threshold intervals by default: thresholds 0.00, 0.01, …, 1.00.
pub const DEFAULT_THRESHOLD_STEPS: usize = 100;

/// Per-class histograms of similarities of the class's own elements and of the others.
#[derive(Clone, Debug)]
pub struct ThresholdSweep {
    steps: usize,
    classes: usize,
    /// `classes x (steps + 2)`: bin `b` holds elements with exactly `b` thresholds at or below
    /// their similarity (bin 0: predicted negative at every threshold).
    positives: Vec<u64>,
    negatives: Vec<u64>,
}

impl ThresholdSweep {
    /// An empty sweep over `classes` classes with thresholds `k / steps`, `k = 0..=steps`.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] for `steps` 0.
    pub fn new(classes: usize, steps: usize) -> Result<Self> {
        if steps == 0 {
            return Err(EvalError::InvalidParameter {
                name: "threshold steps".into(),
                value: "0".into(),
                reason: "at least one interval is needed (thresholds k / steps, k = 0..=steps)"
                    .into(),
            });
        }
        Ok(Self {
            steps,
            classes,
            positives: vec![0; classes * (steps + 2)],
            negatives: vec![0; classes * (steps + 2)],
        })
    }

    /// Number of classes.
    pub fn classes(&self) -> usize {
        self.classes
    }

    /// Threshold `k` (`0..=steps`), `k / steps` rounded to `f32`, the precision of scores.
    #[inline]
    pub fn threshold(&self, k: usize) -> f32 {
        k as f32 / self.steps as f32
    }

    /// The bin of a similarity: how many thresholds are at or below it (`0..=steps + 1`); `None`
    /// and NaN go to bin 0.
    #[inline]
    pub fn bin(&self, score: Option<f32>) -> usize {
        let Some(s) = score.filter(|s| !s.is_nan()) else {
            return 0;
        };
        // Thresholds 0..=k are <= s; start from the rounded guess and correct it exactly.
        let guess = (s * self.steps as f32).floor();
        let mut k = if guess < 0.0 {
            -1
        } else {
            (guess as i64).min(self.steps as i64)
        };
        while k < self.steps as i64 && self.threshold((k + 1) as usize) <= s {
            k += 1;
        }
        while k >= 0 && self.threshold(k as usize) > s {
            k -= 1;
        }
        (k + 1) as usize
    }

    /// Adds one element to the histograms of class `class`: a positive when the element's ground
    /// truth is `class` (`is_class`), else a negative; `score` is its similarity to the class's
    /// text (`None`: no similarity, predicted negative at every threshold).
    #[inline]
    pub fn add(&mut self, class: usize, is_class: bool, score: Option<f32>) {
        let b = self.bin(score);
        self.add_bin(class, is_class, b, 1);
    }

    /// Adds `count` elements to bin `bin` of class `class` (positives when `is_class`).
    #[inline]
    pub fn add_bin(&mut self, class: usize, is_class: bool, bin: usize, count: u64) {
        if class >= self.classes || bin > self.steps + 1 {
            return;
        }
        let i = class * (self.steps + 2) + bin;
        if is_class {
            self.positives[i] += count;
        } else {
            self.negatives[i] += count;
        }
    }

    /// Adds an element that has no similarity at all (predicted negative for every class) with
    /// ground-truth class `truth`.
    pub fn add_unscored(&mut self, truth: usize) {
        self.add_bin(truth, true, 0, 1);
        for c in 0..self.classes {
            if c != truth {
                self.add_bin(c, false, 0, 1);
            }
        }
    }

    /// Merges the counts of another sweep of the same shape.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] when the shapes differ.
    pub fn merge(&mut self, other: &Self) -> Result<()> {
        if (self.classes, self.steps) != (other.classes, other.steps) {
            return Err(EvalError::InvalidParameter {
                name: "sweep shape".into(),
                value: format!("{} classes x {} steps", other.classes, other.steps),
                reason: format!(
                    "cannot merge into {} classes x {} steps",
                    self.classes, self.steps
                ),
            });
        }
        for (a, b) in self.positives.iter_mut().zip(&other.positives) {
            *a += b;
        }
        for (a, b) in self.negatives.iter_mut().zip(&other.negatives) {
            *a += b;
        }
        Ok(())
    }

    /// Number of ground-truth elements of class `class`.
    pub fn support(&self, class: usize) -> u64 {
        self.row(&self.positives, class).iter().sum()
    }

    fn row<'a>(&self, table: &'a [u64], class: usize) -> &'a [u64] {
        let n = self.steps + 2;
        table.get(class * n..(class + 1) * n).unwrap_or(&[])
    }

    /// `IoU(t_k)` for every threshold of class `class`; `None` when the class has no elements.
    pub fn iou_curve(&self, class: usize) -> Option<Vec<f64>> {
        let pos = self.row(&self.positives, class);
        let neg = self.row(&self.negatives, class);
        let total: u64 = pos.iter().sum();
        if total == 0 {
            return None;
        }
        // Predicted positive at threshold k: bins k + 1 and above. Walk from the top down.
        let mut curve = vec![0.0; self.steps + 1];
        let (mut tp, mut fp) = (0u64, 0u64);
        for k in (0..=self.steps).rev() {
            tp += pos[k + 1];
            fp += neg[k + 1];
            let fn_ = total - tp;
            curve[k] = tp as f64 / (tp + fp + fn_) as f64;
        }
        Some(curve)
    }

    /// The class IoU: the mean of [`ThresholdSweep::iou_curve`]; `None` without elements.
    pub fn class_iou(&self, class: usize) -> Option<f64> {
        self.iou_curve(class)
            .map(|c| c.iter().sum::<f64>() / c.len() as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_count_thresholds_at_or_below_the_score() {
        let s = ThresholdSweep::new(1, 4).unwrap();
        assert_eq!(s.bin(None), 0);
        assert_eq!(s.bin(Some(f32::NAN)), 0);
        assert_eq!(s.bin(Some(-0.1)), 0);
        assert_eq!(s.bin(Some(0.0)), 1);
        assert_eq!(s.bin(Some(0.2)), 1);
        assert_eq!(s.bin(Some(0.25)), 2);
        assert_eq!(s.bin(Some(0.99)), 4);
        assert_eq!(s.bin(Some(1.0)), 5);
        assert_eq!(s.bin(Some(7.0)), 5);
        // With 100 steps a score equal to a threshold's f32 value is at that threshold.
        let s = ThresholdSweep::new(1, 100).unwrap();
        for k in 0..=100 {
            let t = s.threshold(k);
            assert_eq!(s.bin(Some(t)), k + 1, "threshold {t}");
            let below = if k == 0 {
                -f32::MIN_POSITIVE
            } else {
                f32::from_bits(t.to_bits() - 1)
            };
            assert_eq!(s.bin(Some(below)), k, "below {t}");
        }
        assert!(ThresholdSweep::new(1, 0).is_err());
    }

    /// Two classes, four thresholds (0, 0.25, 0.5, 0.75, 1), worked by hand.
    #[test]
    fn class_iou_averages_iou_over_thresholds() {
        let mut s = ThresholdSweep::new(2, 4).unwrap();
        // Class 0: two of its own elements scoring 0.9 and 0.3, one other scoring 0.6, one
        // unscored element of class 0.
        s.add(0, true, Some(0.9));
        s.add(0, true, Some(0.3));
        s.add(0, false, Some(0.6));
        s.add_unscored(0);
        // t = 0: TP 2, FP 1, FN 1 -> 2/4; t = .25: same 2/4; t = .5: TP 1 (0.9), FP 1, FN 2 -> 1/4;
        // t = .75: TP 1, FP 0, FN 2 -> 1/3; t = 1: TP 0 -> 0.
        let curve = s.iou_curve(0).unwrap();
        let expected = [0.5, 0.5, 0.25, 1.0 / 3.0, 0.0];
        for (a, b) in curve.iter().zip(expected) {
            assert!((a - b).abs() < 1e-12, "{curve:?}");
        }
        let mean = (0.5 + 0.5 + 0.25 + 1.0 / 3.0) / 5.0;
        assert!((s.class_iou(0).unwrap() - mean).abs() < 1e-12);
        assert_eq!(s.support(0), 3);
        // Class 1 got only the unscored element as a negative: no ground truth, no IoU.
        assert_eq!(s.class_iou(1), None);
        assert_eq!(s.support(1), 0);
    }

    #[test]
    fn a_perfect_score_has_iou_one_except_above_it() {
        let mut s = ThresholdSweep::new(1, 100).unwrap();
        s.add(0, true, Some(1.0));
        s.add(0, false, Some(0.0));
        // t = 0: TP 1, FP 1 -> 0.5; every t in (0, 1]: TP 1, FP 0 -> 1.
        let iou = s.class_iou(0).unwrap();
        assert!((iou - (0.5 + 100.0) / 101.0).abs() < 1e-12, "{iou}");
    }

    #[test]
    fn merging_adds_counts() {
        let mut a = ThresholdSweep::new(1, 4).unwrap();
        let mut b = ThresholdSweep::new(1, 4).unwrap();
        a.add(0, true, Some(0.9));
        b.add(0, false, Some(0.9));
        a.merge(&b).unwrap();
        // t = 0..=.75: TP 1, FP 1 -> 1/2; t = 1: 0.
        assert!((a.class_iou(0).unwrap() - 2.0 / 5.0).abs() < 1e-12);
        assert!(a.merge(&ThresholdSweep::new(2, 4).unwrap()).is_err());
    }
}
