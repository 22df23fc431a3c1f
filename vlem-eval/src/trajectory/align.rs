//! Least-squares alignment of two point sets (Horn 1987, Umeyama 1991).
//!
//! An estimated trajectory lives in its own world frame (usually the first camera's), the
//! reference in another, so positions can only be compared after mapping one frame onto the other.
//! ATE uses the transform that fits best, in closed form: with centroids `μx`, `μy`, covariance
//! `Σ = 1/n Σ (y − μy)(x − μx)ᵀ = U D Vᵀ` and `S = diag(1, 1, sign(det U det V))`, the rotation is
//! `R = U S Vᵀ` (never a reflection), the scale `s = tr(D S) / σx²` (or 1 for a rigid fit) and the
//! translation `t = μy − s R μx`, so that `y ≈ s R x + t`.

use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, UnitQuaternion, Vector3};
use vlem_core::Pose;

use crate::error::{EvalError, Result};

/// The similarity transform `p ↦ s R p + t` that maps estimated positions into the reference
/// frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Alignment {
    /// `R`.
    pub rotation: UnitQuaternion<f64>,
    /// `t`, metres.
    pub translation: Vector3<f64>,
    /// `s`; exactly 1 for a rigid alignment.
    pub scale: f64,
}

impl Default for Alignment {
    fn default() -> Self {
        Self::identity()
    }
}

impl Alignment {
    /// The transform that changes nothing.
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// `s R p + t`.
    pub fn apply(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.rotation * p.coords * self.scale + self.translation)
    }

    /// A camera-to-world pose of the estimate expressed in the reference frame: its position
    /// mapped by [`apply`](Self::apply), its orientation rotated by `R` (the scale changes
    /// distances, not directions).
    pub fn align_pose(&self, pose: &Pose) -> Pose {
        let position = self.apply(&Point3::from(pose.translation.vector));
        Pose::from_parts(position.coords.into(), self.rotation * pose.rotation)
    }

    /// The 4x4 matrix `[sR t; 0 1]`.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(self.rotation.to_rotation_matrix().into_inner() * self.scale));
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }
}

/// The JSON form of an [`Alignment`] (nalgebra's own serde support is not compiled in).
#[derive(serde::Serialize)]
struct AlignmentJson {
    scale: f64,
    /// Row-major.
    rotation: [[f64; 3]; 3],
    rotation_quaternion_xyzw: [f64; 4],
    rotation_angle_deg: f64,
    translation: [f64; 3],
}

impl serde::Serialize for Alignment {
    fn serialize<S: serde::Serializer>(
        &self,
        serializer: S,
    ) -> std::result::Result<S::Ok, S::Error> {
        let r = self.rotation.to_rotation_matrix().into_inner();
        let q = self.rotation.quaternion();
        AlignmentJson {
            scale: self.scale,
            rotation: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            rotation_quaternion_xyzw: [q.i, q.j, q.k, q.w],
            rotation_angle_deg: self.rotation.angle().to_degrees(),
            translation: [self.translation.x, self.translation.y, self.translation.z],
        }
        .serialize(serializer)
    }
}

/// The least-squares transform mapping `estimate[k]` onto `reference[k]`: rotation and
/// translation, plus a uniform scale when `with_scale` (for trajectories of unknown scale, e.g.
/// monocular ones). See the module documentation for the closed form.
///
/// # Errors
/// [`EvalError::LengthMismatch`] for lists of different lengths, [`EvalError::TooFewPoses`] for
/// fewer than 3 points, [`EvalError::NonFinitePose`] for a non-finite point, and
/// [`EvalError::Degenerate`] when `with_scale` and the estimated points all coincide (no scale
/// fits) or the decomposition fails.
pub fn align_umeyama(
    estimate: &[Point3<f64>],
    reference: &[Point3<f64>],
    with_scale: bool,
) -> Result<Alignment> {
    if estimate.len() != reference.len() {
        return Err(EvalError::LengthMismatch {
            estimate: estimate.len(),
            reference: reference.len(),
        });
    }
    if estimate.len() < 3 {
        return Err(EvalError::TooFewPoses {
            metric: "alignment".to_owned(),
            needed: 3,
            found: estimate.len(),
        });
    }
    for (role, points) in [("estimate", estimate), ("reference", reference)] {
        if let Some(index) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
            return Err(EvalError::NonFinitePose {
                role: role.to_owned(),
                index,
            });
        }
    }
    let n = estimate.len() as f64;
    let mean = |points: &[Point3<f64>]| {
        points
            .iter()
            .fold(Vector3::zeros(), |acc: Vector3<f64>, p| acc + p.coords)
            / n
    };
    let (mu_x, mu_y) = (mean(estimate), mean(reference));
    let mut covariance = Matrix3::zeros();
    let mut variance_x = 0.0;
    for (x, y) in estimate.iter().zip(reference) {
        let (dx, dy) = (x.coords - mu_x, y.coords - mu_y);
        covariance += dy * dx.transpose();
        variance_x += dx.norm_squared();
    }
    covariance /= n;
    variance_x /= n;
    let degenerate = |reason: &str| EvalError::Degenerate {
        what: "the trajectory alignment".to_owned(),
        reason: reason.to_owned(),
    };
    if !covariance.iter().all(|x| x.is_finite()) {
        return Err(degenerate("the positions are too large to be summed"));
    }
    let svd = covariance
        .try_svd(true, true, f64::EPSILON, 0)
        .ok_or_else(|| degenerate("the singular value decomposition did not converge"))?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(degenerate("the singular value decomposition gave no basis"));
    };
    // Flip the axis of the smallest singular value (the last: they are sorted) if U Vᵀ would be
    // a reflection.
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s.z = -1.0;
    }
    let rotation = u * Matrix3::from_diagonal(&s) * v_t;
    let scale = if with_scale {
        if variance_x <= f64::MIN_POSITIVE {
            return Err(degenerate(
                "every estimated position is the same point, so no scale fits",
            ));
        }
        svd.singular_values.dot(&s) / variance_x
    } else {
        1.0
    };
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rotation));
    let rotation = UnitQuaternion::new_normalize(rotation.into_inner());
    let translation = mu_y - rotation * mu_x * scale;
    Ok(Alignment {
        rotation,
        translation,
        scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points() -> Vec<Point3<f64>> {
        // Not coplanar, so the rotation is unique.
        vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.2, -0.3),
            Point3::new(0.5, 1.5, 0.1),
            Point3::new(-0.7, 0.4, 1.2),
            Point3::new(2.0, -1.0, 0.5),
        ]
    }

    #[test]
    fn a_known_similarity_is_recovered() {
        let reference = points();
        let rotation = UnitQuaternion::from_euler_angles(0.4, -1.1, 2.5);
        let translation = Vector3::new(3.0, -2.0, 0.5);
        let truth = Alignment {
            rotation,
            translation,
            scale: 2.5,
        };
        // The estimate is the reference seen through the inverse transform.
        let estimate: Vec<Point3<f64>> = reference
            .iter()
            .map(|y| Point3::from(rotation.inverse() * (y.coords - translation) / 2.5))
            .collect();
        let fit = align_umeyama(&estimate, &reference, true).unwrap();
        assert!((fit.scale - 2.5).abs() < 1e-12, "{}", fit.scale);
        assert!(fit.rotation.angle_to(&rotation) < 1e-12);
        assert!((fit.translation - translation).norm() < 1e-12);
        assert!((fit.matrix() - truth.matrix()).abs().max() < 1e-12);
        // Without scale the rotation is still the true one (the scale does not bias it), the
        // scale stays 1.
        let rigid = align_umeyama(&estimate, &reference, false).unwrap();
        assert_eq!(rigid.scale, 1.0);
        assert!(rigid.rotation.angle_to(&rotation) < 1e-12);
    }

    #[test]
    fn mirrored_points_get_a_rotation_not_a_reflection() {
        let reference = points();
        let estimate: Vec<Point3<f64>> = reference
            .iter()
            .map(|p| Point3::new(-p.x, p.y, p.z))
            .collect();
        let fit = align_umeyama(&estimate, &reference, false).unwrap();
        let r = fit.rotation.to_rotation_matrix().into_inner();
        assert!((r.determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn poses_are_aligned_with_their_orientation() {
        let a = Alignment {
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            translation: Vector3::new(1.0, 0.0, 0.0),
            scale: 2.0,
        };
        let pose = Pose::from_parts(
            Vector3::new(1.0, 0.0, 0.0).into(),
            UnitQuaternion::identity(),
        );
        let aligned = a.align_pose(&pose);
        // (1,0,0) → scaled (2,0,0) → rotated (0,2,0) → shifted (1,2,0).
        assert!((aligned.translation.vector - Vector3::new(1.0, 2.0, 0.0)).norm() < 1e-12);
        assert!(aligned.rotation.angle_to(&a.rotation) < 1e-12);
        assert_eq!(
            a.apply(&Point3::new(1.0, 0.0, 0.0)),
            aligned.translation.vector.into()
        );
    }

    #[test]
    fn bad_inputs_are_refused() {
        let p = points();
        assert!(matches!(
            align_umeyama(&p[..2], &p[..2], false),
            Err(EvalError::TooFewPoses { found: 2, .. })
        ));
        assert!(matches!(
            align_umeyama(&p[..3], &p[..4], false),
            Err(EvalError::LengthMismatch { .. })
        ));
        let mut nan = p.clone();
        nan[3].y = f64::NAN;
        assert!(matches!(
            align_umeyama(&p, &nan, false),
            Err(EvalError::NonFinitePose { index: 3, .. })
        ));
        let same = vec![Point3::new(1.0, 1.0, 1.0); 5];
        assert!(matches!(
            align_umeyama(&same, &p, true),
            Err(EvalError::Degenerate { .. })
        ));
        // Without scale, coinciding points still align: onto the reference centroid.
        let fit = align_umeyama(&same, &p, false).unwrap();
        let centroid = p.iter().fold(Vector3::zeros(), |a, q| a + q.coords) / 5.0;
        assert!((fit.apply(&same[0]).coords - centroid).norm() < 1e-12);
    }
}
