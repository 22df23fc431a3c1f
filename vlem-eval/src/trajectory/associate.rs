//! Pairing the poses of two trajectories.
//!
//! An estimate and its reference rarely hold the same poses: a tracker may start late, lose
//! frames or run on a strided sequence, and ground truth is often sampled at another rate. The
//! metrics compare pose `k` of one list with pose `k` of the other, so this module builds those
//! lists.
//!
//! The rule:
//! - **by timestamp** when both files are TUM: each estimated pose is paired with the reference
//!   pose nearest in time, if within `max_time_diff` seconds, one to one. As in the TUM benchmark's
//!   `associate.py`, candidate pairs are taken greedily by increasing time difference, so a pose
//!   already taken by a closer partner is not reused.
//! - **by frame index** when either file is a `.log` (which has no timestamps): the `.log`'s poses
//!   are stamped with their frame index 0, 1, 2, …, and the same matching applies. For the usual
//!   `max_time_diff` below 0.5, this pairs a TUM pose stamped `t` with `.log` frame `round(t)` when
//!   `|t − round(t)| ≤ max_time_diff`. That is what `vlem run` needs: on datasets without
//!   timestamps (ICL-NUIM, Redwood) it stamps each pose of `trajectory.tum` with the frame's index
//!   in the recording (also when strided), so such an estimate pairs with the dataset's `.log`.
//!   Two `.log` files pair frame `i` with frame `i`.
//!
//! Pairs are returned in increasing estimate stamp order.

use crate::error::{EvalError, Result};

use super::{Trajectory, TrajectoryFormat};

/// The default association tolerance in seconds (the TUM benchmark's).
pub const DEFAULT_MAX_TIME_DIFF: f64 = 0.02;

/// The fewest pairs [`associate`] accepts: a rigid alignment needs three points.
pub const MIN_ASSOCIATED: usize = 3;

/// How two trajectories were paired.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum AssociationMode {
    /// Both have timestamps: nearest in time.
    Timestamp,
    /// A `.log` is involved: its frame indices serve as stamps.
    FrameIndex,
}

impl AssociationMode {
    /// How the mode reads in a sentence (`by timestamp`, `by frame index`).
    pub fn describe(self) -> &'static str {
        match self {
            Self::Timestamp => "by timestamp",
            Self::FrameIndex => "by frame index",
        }
    }
}

/// The result of [`associate`]: which estimated pose goes with which reference pose.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Association {
    /// How the pairs were found.
    pub mode: AssociationMode,
    /// The tolerance used, seconds (or frames, by frame index).
    pub max_time_diff: f64,
    /// `(estimate index, reference index)` into the trajectories' pose lists, in increasing
    /// estimate stamp order.
    #[serde(skip)]
    pub pairs: Vec<(usize, usize)>,
}

impl Association {
    /// Number of pairs.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// True when nothing was paired.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// The paired poses as two lists of equal length, estimate first, ready for
    /// [`ate`](super::ate) and [`rpe`](super::rpe).
    pub fn poses(
        &self,
        estimate: &Trajectory,
        reference: &Trajectory,
    ) -> (Vec<vlem_core::Pose>, Vec<vlem_core::Pose>) {
        self.pairs
            .iter()
            .filter_map(|&(e, r)| Some((estimate.poses.get(e)?.1, reference.poses.get(r)?.1)))
            .unzip()
    }
}

/// Pairs the poses of `estimate` and `reference` (see the module documentation for the rule).
///
/// # Errors
/// [`EvalError::InvalidParameter`] when `max_time_diff` is negative or not finite, and
/// [`EvalError::TooFewAssociated`] when fewer than [`MIN_ASSOCIATED`] pairs are found.
pub fn associate(
    estimate: &Trajectory,
    reference: &Trajectory,
    max_time_diff: f64,
) -> Result<Association> {
    let mode =
        if estimate.format == TrajectoryFormat::Log || reference.format == TrajectoryFormat::Log {
            AssociationMode::FrameIndex
        } else {
            AssociationMode::Timestamp
        };
    let pairs = associate_stamps(&estimate.stamps(), &reference.stamps(), max_time_diff)?;
    if pairs.len() < MIN_ASSOCIATED {
        return Err(EvalError::TooFewAssociated {
            associated: pairs.len(),
            needed: MIN_ASSOCIATED,
            mode: mode.describe().to_owned(),
            estimate_poses: estimate.len(),
            estimate_stamps: estimate.stamp_range(),
            reference_poses: reference.len(),
            reference_stamps: reference.stamp_range(),
            max_time_diff,
            hint: hint(mode, estimate, reference),
        });
    }
    Ok(Association {
        mode,
        max_time_diff,
        pairs,
    })
}

/// A suggestion for an association that found (almost) nothing.
fn hint(mode: AssociationMode, estimate: &Trajectory, reference: &Trajectory) -> String {
    let (e0, e1) = estimate.stamp_range();
    let (r0, r1) = reference.stamp_range();
    let timed = [estimate, reference]
        .into_iter()
        .find(|t| t.format == TrajectoryFormat::Tum);
    match (mode, timed) {
        (AssociationMode::FrameIndex, Some(t)) if t.poses.iter().any(|(s, _)| *s > 1e6) => format!(
            "; {} holds timestamps, not frame indices, so it cannot be paired with a .log: \
             compare it with a TUM reference",
            t.path.display()
        ),
        _ if e1 < r0 || r1 < e0 => "; the stamp ranges do not overlap".to_owned(),
        _ => "; a larger max time difference may pair more poses".to_owned(),
    }
}

/// One-to-one nearest-stamp pairing within `max_diff`: `(estimate index, reference index)` in
/// increasing estimate stamp order (ties by index). Candidate pairs closer than `max_diff` are
/// taken by increasing difference, skipping any whose poses are already taken. Non-finite stamps
/// are never paired.
///
/// # Errors
/// [`EvalError::InvalidParameter`] when `max_diff` is negative or not finite.
pub fn associate_stamps(
    estimate: &[f64],
    reference: &[f64],
    max_diff: f64,
) -> Result<Vec<(usize, usize)>> {
    if !max_diff.is_finite() || max_diff < 0.0 {
        return Err(EvalError::InvalidParameter {
            name: "max time difference".to_owned(),
            value: max_diff.to_string(),
            reason: "must be a finite number of seconds ≥ 0".to_owned(),
        });
    }
    let mut sorted: Vec<(f64, usize)> = reference
        .iter()
        .enumerate()
        .filter(|(_, t)| t.is_finite())
        .map(|(j, &t)| (t, j))
        .collect();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut candidates: Vec<(f64, usize, usize)> = Vec::new();
    for (i, &t) in estimate.iter().enumerate() {
        if !t.is_finite() {
            continue;
        }
        let start = sorted.partition_point(|&(s, _)| s < t - max_diff);
        for &(s, j) in &sorted[start..] {
            let diff = (s - t).abs();
            if s > t && diff > max_diff {
                break;
            }
            if diff <= max_diff {
                candidates.push((diff, i, j));
            }
        }
    }
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut estimate_used = vec![false; estimate.len()];
    let mut reference_used = vec![false; reference.len()];
    let mut pairs = Vec::new();
    for (_, i, j) in candidates {
        if estimate_used[i] || reference_used[j] {
            continue;
        }
        estimate_used[i] = true;
        reference_used[j] = true;
        pairs.push((i, j));
    }
    pairs.sort_by(|a, b| estimate[a.0].total_cmp(&estimate[b.0]).then(a.cmp(b)));
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use vlem_core::Pose;

    fn trajectory(format: TrajectoryFormat, stamps: &[f64]) -> Trajectory {
        Trajectory::new(
            "t",
            format,
            stamps.iter().map(|&t| (t, Pose::identity())).collect(),
        )
    }

    #[test]
    fn timestamps_pair_nearest_within_tolerance_one_to_one() {
        // 0.0 ↔ 0.01 (0.01 off); 1.0 has no partner within 0.02 (1.03 is 0.03 off);
        // 2.0 and 2.005 both want 2.001: the closer (2.0, 0.001 off) wins, 2.005 gets 2.02
        // (0.015 off); 3.0 ↔ 2.99.
        let est = [0.0, 1.0, 2.0, 2.005, 3.0];
        let reference = [2.99, 0.01, 1.03, 2.001, 2.02];
        let pairs = associate_stamps(&est, &reference, 0.02).unwrap();
        assert_eq!(pairs, vec![(0, 1), (2, 3), (3, 4), (4, 0)]);
        // A tolerance of zero pairs only equal stamps.
        assert_eq!(
            associate_stamps(&[1.0, 2.0], &[2.0, 1.5], 0.0).unwrap(),
            vec![(1, 0)]
        );
    }

    #[test]
    fn unsorted_estimates_come_back_in_stamp_order_and_nan_never_pairs() {
        let pairs = associate_stamps(&[2.0, f64::NAN, 0.0, 1.0], &[0.0, 1.0, 2.0], 0.02).unwrap();
        assert_eq!(pairs, vec![(2, 0), (3, 1), (0, 2)]);
    }

    #[test]
    fn bad_tolerances_are_refused() {
        for bad in [-0.1, f64::NAN, f64::INFINITY] {
            let err = associate_stamps(&[0.0], &[0.0], bad).unwrap_err();
            assert!(matches!(err, EvalError::InvalidParameter { .. }), "{err}");
        }
    }

    #[test]
    fn a_log_pairs_by_rounded_frame_index() {
        // `vlem run` on a strided ICL sequence: stamps are recording frame indices 0, 2, 4, …
        let est = trajectory(TrajectoryFormat::Tum, &[0.0, 2.0, 4.0, 6.0, 7.4]);
        let log = trajectory(
            TrajectoryFormat::Log,
            &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0],
        );
        let a = associate(&est, &log, DEFAULT_MAX_TIME_DIFF).unwrap();
        assert_eq!(a.mode, AssociationMode::FrameIndex);
        // 7.4 is 0.4 from frame 7: not an index within the tolerance.
        assert_eq!(a.pairs, vec![(0, 0), (1, 2), (2, 4), (3, 6)]);
        // Two .log files: frame i with frame i, as far as the shorter goes.
        let short = trajectory(TrajectoryFormat::Log, &[0.0, 1.0, 2.0]);
        let a = associate(&short, &log, DEFAULT_MAX_TIME_DIFF).unwrap();
        assert_eq!(a.pairs, vec![(0, 0), (1, 1), (2, 2)]);
        assert_eq!(a.mode, AssociationMode::FrameIndex);
    }

    #[test]
    fn two_tum_files_pair_by_timestamp_and_too_few_pairs_say_why() {
        let est = trajectory(TrajectoryFormat::Tum, &[10.0, 10.1, 10.2, 10.3]);
        let reference = trajectory(TrajectoryFormat::Tum, &[10.01, 10.11, 10.19, 10.5]);
        let a = associate(&est, &reference, DEFAULT_MAX_TIME_DIFF).unwrap();
        assert_eq!(a.mode, AssociationMode::Timestamp);
        assert_eq!(a.len(), 3);
        let (e, r) = a.poses(&est, &reference);
        assert_eq!((e.len(), r.len()), (3, 3));

        let late = trajectory(TrajectoryFormat::Tum, &[20.0, 20.1, 20.2]);
        let err = associate(&late, &reference, DEFAULT_MAX_TIME_DIFF).unwrap_err();
        let text = err.to_string();
        assert!(
            text.starts_with("only 0 pose pairs associated by timestamp (at least 3 needed)"),
            "{text}"
        );
        assert!(text.ends_with("the stamp ranges do not overlap"), "{text}");

        let timed = trajectory(TrajectoryFormat::Tum, &[1.3e9, 1.3e9 + 0.1, 1.3e9 + 0.2]);
        let log = trajectory(TrajectoryFormat::Log, &[0.0, 1.0, 2.0]);
        let err = associate(&timed, &log, DEFAULT_MAX_TIME_DIFF).unwrap_err();
        assert!(
            err.to_string()
                .contains("holds timestamps, not frame indices"),
            "{err}"
        );
    }
}
