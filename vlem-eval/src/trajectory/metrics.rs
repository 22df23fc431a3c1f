//! The two error measures of the TUM RGB-D benchmark (Sturm et al., IROS 2012) on paired poses.
//!
//! Each produces one error per pose (ATE) or per pose pair (RPE); [`ErrorStats`] summarises them
//! the way the benchmark's `evaluate_ate.py` / `evaluate_rpe.py` do (RMSE, mean, median,
//! population standard deviation, min, max), so numbers can be compared with published ones.

use nalgebra::Point3;
use vlem_core::Pose;
use vlem_core::types::pose_is_finite;

use crate::error::{EvalError, Result};

use super::align::{Alignment, align_umeyama};

/// Summary of a list of non-negative errors.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ErrorStats {
    /// How many errors.
    pub count: usize,
    /// Root mean square.
    pub rmse: f64,
    /// Arithmetic mean.
    pub mean: f64,
    /// Median (mean of the two middle values for an even count).
    pub median: f64,
    /// Population standard deviation (about the mean).
    pub std: f64,
    /// Smallest error.
    pub min: f64,
    /// Largest error.
    pub max: f64,
}

impl ErrorStats {
    /// The statistics of `errors`; `None` when there are none.
    pub fn from_errors(errors: &[f64]) -> Option<Self> {
        if errors.is_empty() {
            return None;
        }
        let n = errors.len() as f64;
        let mean = errors.iter().sum::<f64>() / n;
        let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
        let std = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / n).sqrt();
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let middle = sorted.len() / 2;
        let median = match (sorted.get(middle.wrapping_sub(1)), sorted.get(middle)) {
            (Some(lo), Some(hi)) if sorted.len().is_multiple_of(2) => (lo + hi) / 2.0,
            (_, Some(m)) => *m,
            // Not reached: `errors` is not empty.
            _ => f64::NAN,
        };
        Some(Self {
            count: errors.len(),
            rmse,
            mean,
            median,
            std,
            min: sorted.first().copied().unwrap_or(f64::NAN),
            max: sorted.last().copied().unwrap_or(f64::NAN),
        })
    }
}

/// Absolute trajectory error: position errors after the best alignment.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct AteStats {
    /// The transform applied to the estimate (estimate frame → reference frame).
    pub alignment: Alignment,
    /// Whether the alignment was allowed a scale.
    pub with_scale: bool,
    /// Statistics of `errors`, metres.
    #[serde(rename = "position_m")]
    pub position: ErrorStats,
    /// Per pair `k`: `‖alignment(estimate_k position) − reference_k position‖`, metres.
    #[serde(skip)]
    pub errors: Vec<f64>,
}

/// Relative pose error over a fixed frame step.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RpeStats {
    /// The step: pose pairs `(k, k + delta)` of the associated lists.
    pub delta: usize,
    /// Statistics of the translation of each error transform, metres per `delta` frames.
    #[serde(rename = "translation_m")]
    pub translation: ErrorStats,
    /// Statistics of the rotation angle of each error transform, degrees per `delta` frames.
    #[serde(rename = "rotation_deg")]
    pub rotation: ErrorStats,
}

/// Checks that two associated lists pair up and hold finite poses.
fn check_pairs(estimate: &[Pose], reference: &[Pose]) -> Result<()> {
    if estimate.len() != reference.len() {
        return Err(EvalError::LengthMismatch {
            estimate: estimate.len(),
            reference: reference.len(),
        });
    }
    for (role, poses) in [("estimate", estimate), ("reference", reference)] {
        if let Some(index) = poses.iter().position(|p| !pose_is_finite(p)) {
            return Err(EvalError::NonFinitePose {
                role: role.to_owned(),
                index,
            });
        }
    }
    Ok(())
}

/// The absolute trajectory error of `estimate[k]` against `reference[k]` (associated lists):
/// positions are aligned with [`align_umeyama`] (`with_scale`: similarity, else rigid), then each
/// pair's remaining distance is an error.
///
/// # Errors
/// [`EvalError::LengthMismatch`], [`EvalError::NonFinitePose`], [`EvalError::TooFewPoses`] (fewer
/// than 3 pairs) and [`EvalError::Degenerate`] from the alignment.
pub fn ate(estimate: &[Pose], reference: &[Pose], with_scale: bool) -> Result<AteStats> {
    check_pairs(estimate, reference)?;
    if estimate.len() < 3 {
        return Err(EvalError::TooFewPoses {
            metric: "ATE".to_owned(),
            needed: 3,
            found: estimate.len(),
        });
    }
    let position = |p: &Pose| Point3::from(p.translation.vector);
    let x: Vec<Point3<f64>> = estimate.iter().map(position).collect();
    let y: Vec<Point3<f64>> = reference.iter().map(position).collect();
    let alignment = align_umeyama(&x, &y, with_scale)?;
    let errors: Vec<f64> = x
        .iter()
        .zip(&y)
        .map(|(x, y)| (alignment.apply(x) - y).norm())
        .collect();
    let position = ErrorStats::from_errors(&errors).ok_or_else(|| EvalError::TooFewPoses {
        metric: "ATE".to_owned(),
        needed: 3,
        found: 0,
    })?;
    Ok(AteStats {
        alignment,
        with_scale,
        position,
        errors,
    })
}

/// The error transform of one pose pair: `E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)` with `P` the estimate
/// and `Q` the reference. Identity when the estimated motion from `i` to `j` is the true one.
pub fn relative_error(
    estimate_i: &Pose,
    estimate_j: &Pose,
    reference_i: &Pose,
    reference_j: &Pose,
) -> Pose {
    let estimated_motion = estimate_i.inv_mul(estimate_j);
    let true_motion = reference_i.inv_mul(reference_j);
    true_motion.inv_mul(&estimated_motion)
}

/// The relative pose error of `estimate` against `reference` (associated lists) over pairs
/// `(k, k + delta)`: for each, the length of the translation and the angle of the rotation of
/// [`relative_error`]. `delta` counts positions in the associated lists, so where association
/// dropped poses a pair spans more frames of the recording. No alignment is needed: the error is
/// unchanged by a rigid change of either world frame (not by a scale: scale the estimate first if
/// it has none).
///
/// # Errors
/// [`EvalError::InvalidParameter`] for `delta` 0, [`EvalError::LengthMismatch`],
/// [`EvalError::NonFinitePose`], and [`EvalError::TooFewPoses`] when the lists are not longer than
/// `delta`.
pub fn rpe(estimate: &[Pose], reference: &[Pose], delta: usize) -> Result<RpeStats> {
    if delta == 0 {
        return Err(EvalError::InvalidParameter {
            name: "RPE delta".to_owned(),
            value: "0".to_owned(),
            reason: "must be at least 1 frame".to_owned(),
        });
    }
    check_pairs(estimate, reference)?;
    let too_few = || EvalError::TooFewPoses {
        metric: format!("RPE with delta {delta}"),
        needed: delta + 1,
        found: estimate.len(),
    };
    let (translations, rotations): (Vec<f64>, Vec<f64>) = estimate
        .iter()
        .zip(reference)
        .zip(estimate.iter().zip(reference).skip(delta))
        .map(|((p_i, q_i), (p_j, q_j))| {
            let e = relative_error(p_i, p_j, q_i, q_j);
            (e.translation.vector.norm(), e.rotation.angle().to_degrees())
        })
        .unzip();
    Ok(RpeStats {
        delta,
        translation: ErrorStats::from_errors(&translations).ok_or_else(too_few)?,
        rotation: ErrorStats::from_errors(&rotations).ok_or_else(too_few)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    /// A camera moving along a curve while turning: not planar, so alignments are unique.
    fn reference(n: usize) -> Vec<Pose> {
        (0..n)
            .map(|i| {
                let t = i as f64;
                Pose::from_parts(
                    Vector3::new(0.3 * t, 0.1 * t * t, (0.5 * t).sin()).into(),
                    UnitQuaternion::from_euler_angles(0.05 * t, -0.1 * t, 0.02 * t),
                )
            })
            .collect()
    }

    #[test]
    fn statistics_match_hand_computed_values() {
        let s = ErrorStats::from_errors(&[3.0, 1.0, 4.0, 0.0]).unwrap();
        assert_eq!(s.count, 4);
        assert!(close(s.mean, 2.0));
        assert!(close(s.median, 2.0)); // (1 + 3) / 2
        assert!(close(s.rmse, (26.0f64 / 4.0).sqrt()));
        assert!(close(s.std, (10.0f64 / 4.0).sqrt())); // deviations 1, -1, 2, -2
        assert_eq!((s.min, s.max), (0.0, 4.0));
        assert!(close(
            ErrorStats::from_errors(&[5.0, 1.0, 2.0]).unwrap().median,
            2.0
        ));
        assert!(ErrorStats::from_errors(&[]).is_none());
    }

    #[test]
    fn identical_trajectories_have_no_error() {
        let q = reference(10);
        let a = ate(&q, &q, false).unwrap();
        assert!(a.position.max < 1e-12 && a.position.rmse < 1e-12);
        assert!(a.alignment.rotation.angle() < 1e-9);
        let r = rpe(&q, &q, 1).unwrap();
        assert_eq!(r.translation.count, 9);
        assert!(r.translation.max < 1e-12 && r.rotation.max < 1e-9);
    }

    #[test]
    fn a_rigidly_moved_estimate_aligns_back_exactly() {
        let q = reference(12);
        let g = Pose::from_parts(
            Vector3::new(1.0, -2.0, 0.5).into(),
            UnitQuaternion::from_euler_angles(0.3, 0.2, -1.4),
        );
        // The estimate's world frame is g⁻¹ of the reference's: P_k = g⁻¹ Q_k.
        let p: Vec<Pose> = q.iter().map(|qk| g.inverse() * qk).collect();
        let a = ate(&p, &q, false).unwrap();
        assert!(a.position.max < 1e-9, "{:?}", a.position);
        assert!(a.alignment.rotation.angle_to(&g.rotation) < 1e-9);
        assert!((a.alignment.translation - g.translation.vector).norm() < 1e-9);
        assert!(
            a.alignment
                .align_pose(&p[5])
                .rotation
                .angle_to(&q[5].rotation)
                < 1e-9
        );
        // RPE needs no alignment.
        let r = rpe(&p, &q, 2).unwrap();
        assert!(r.translation.max < 1e-9 && r.rotation.max < 1e-6);
    }

    #[test]
    fn one_displaced_pose_gives_the_known_ate() {
        // Four reference positions around the origin; the estimate pushes pose 0 by 0.4 m along
        // its own axis. The estimate's centroid moves by 0.1 m and the cross-covariance stays
        // diagonal and positive, so the best rigid fit is the translation (−0.1, 0, 0) without
        // rotation, leaving 0.3 m of error on pose 0 and 0.1 m on each of the others.
        let positions = [
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(-1.0, 0.0, 0.0),
            Vector3::new(0.0, 1.0, 0.0),
            Vector3::new(0.0, -1.0, 0.0),
        ];
        let q: Vec<Pose> = positions
            .iter()
            .map(|&t| Pose::from_parts(t.into(), UnitQuaternion::identity()))
            .collect();
        let mut p = q.clone();
        p[0].translation.vector.x += 0.4;
        let a = ate(&p, &q, false).unwrap();
        let rmse = ((0.09 + 3.0 * 0.01) / 4.0f64).sqrt();
        assert!(close(a.position.rmse, rmse), "{:?}", a.position);
        assert!(close(a.position.mean, 0.15));
        assert!(close(a.position.median, 0.1));
        assert!(close(a.position.max, 0.3));
        assert!((a.alignment.translation - Vector3::new(-0.1, 0.0, 0.0)).norm() < 1e-9);
        assert!(a.alignment.rotation.angle() < 1e-9);
    }

    #[test]
    fn a_scaled_estimate_needs_the_scale_option() {
        let q = reference(10);
        let p: Vec<Pose> = q
            .iter()
            .map(|qk| Pose::from_parts((qk.translation.vector * 0.5).into(), qk.rotation))
            .collect();
        let with = ate(&p, &q, true).unwrap();
        assert!(close(with.alignment.scale, 2.0), "{}", with.alignment.scale);
        assert!(with.position.max < 1e-9);
        let without = ate(&p, &q, false).unwrap();
        assert_eq!(without.alignment.scale, 1.0);
        assert!(without.position.rmse > 0.1, "{:?}", without.position);
    }

    #[test]
    fn a_constant_step_overestimate_gives_the_known_translational_rpe() {
        // True motion: 0.1 m along x per frame; the estimate moves 1.1 × that, i.e. 0.11 m.
        let step = 0.1;
        let q: Vec<Pose> = (0..8)
            .map(|i| Pose::translation(step * i as f64, 0.0, 0.0))
            .collect();
        let p: Vec<Pose> = (0..8)
            .map(|i| Pose::translation(1.1 * step * i as f64, 0.0, 0.0))
            .collect();
        let r1 = rpe(&p, &q, 1).unwrap();
        assert_eq!(r1.translation.count, 7);
        assert!(close(r1.translation.rmse, 0.01) && close(r1.translation.mean, 0.01));
        assert!(r1.rotation.max < 1e-12);
        let r3 = rpe(&p, &q, 3).unwrap();
        assert_eq!(r3.translation.count, 5);
        assert!(close(r3.translation.rmse, 0.03));
    }

    #[test]
    fn a_constant_extra_rotation_gives_the_known_rotational_rpe() {
        // The reference turns 10° about y per frame while moving along z; the estimate turns
        // 12°: 2° of rotational error per frame, 4° per two frames.
        let n = 6;
        let make = |deg: f64| -> Vec<Pose> {
            (0..n)
                .map(|i| {
                    Pose::from_parts(
                        Vector3::new(0.0, 0.0, 0.2 * i as f64).into(),
                        UnitQuaternion::from_euler_angles(0.0, (deg * i as f64).to_radians(), 0.0),
                    )
                })
                .collect()
        };
        let (q, p) = (make(10.0), make(12.0));
        let r = rpe(&p, &q, 1).unwrap();
        assert!(
            close(r.rotation.rmse, 2.0) && close(r.rotation.mean, 2.0),
            "{:?}",
            r.rotation
        );
        assert!(close(r.rotation.max, 2.0));
        // E's translation is R_step,qᵀ (t_p − t_q) with t = R(i)ᵀ (0, 0, 0.2) the step in camera i's
        // frame: R_y(−12i°) e_z and R_y(−10i°) e_z are 2i° apart, so |t_p − t_q| = 0.4 sin(i°).
        for i in 0..n - 1 {
            let e = relative_error(&p[i], &p[i + 1], &q[i], &q[i + 1]);
            let expected = 0.4 * (i as f64).to_radians().sin();
            assert!(close(e.translation.vector.norm(), expected), "pair {i}");
        }
        let expected: Vec<f64> = (0..n - 1)
            .map(|i| 0.4 * (i as f64).to_radians().sin())
            .collect();
        let stats = ErrorStats::from_errors(&expected).unwrap();
        assert!(close(r.translation.rmse, stats.rmse) && close(r.translation.max, stats.max));
        let r2 = rpe(&p, &q, 2).unwrap();
        assert!(close(r2.rotation.mean, 4.0), "{:?}", r2.rotation);
    }

    #[test]
    fn relative_error_is_the_sturm_formula() {
        let q = reference(3);
        let extra = Pose::from_parts(
            Vector3::new(0.01, -0.02, 0.03).into(),
            UnitQuaternion::from_euler_angles(0.01, 0.0, 0.0),
        );
        // P_j = P_i (Q_i⁻¹ Q_j) extra, with P_i = Q_i: the error is exactly `extra`.
        let p_j = q[0] * q[0].inv_mul(&q[2]) * extra;
        let e = relative_error(&q[0], &p_j, &q[0], &q[2]);
        assert!((e.translation.vector - extra.translation.vector).norm() < 1e-12);
        assert!(e.rotation.angle_to(&extra.rotation) < 1e-12);
    }

    #[test]
    fn bad_inputs_are_refused() {
        let q = reference(4);
        assert!(matches!(
            ate(&q[..2], &q[..2], false),
            Err(EvalError::TooFewPoses { found: 2, .. })
        ));
        assert!(matches!(
            ate(&q[..3], &q, false),
            Err(EvalError::LengthMismatch { .. })
        ));
        assert!(matches!(
            rpe(&q, &q, 0),
            Err(EvalError::InvalidParameter { .. })
        ));
        let err = rpe(&q, &q, 4).unwrap_err();
        assert_eq!(
            err.to_string(),
            "RPE with delta 4 needs at least 5 poses, found 4"
        );
        let mut bad = q.clone();
        bad[1].translation.vector.z = f64::INFINITY;
        assert!(matches!(
            rpe(&bad, &q, 1),
            Err(EvalError::NonFinitePose { index: 1, .. })
        ));
    }
}
