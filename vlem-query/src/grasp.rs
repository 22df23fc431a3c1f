//! Grasp poses for a parallel gripper from a point set (e.g. the best cluster of a query).
//!
//! The gripper approaches along a fixed direction (default +y: downwards in the camera-style map
//! frame of the datasets, whose first camera has y pointing down, i.e. a grasp from above). The
//! highest point is the one furthest against the approach direction; the fingers close at `depth`
//! below it. The points in a thin slab around that level are projected onto the plane orthogonal to
//! the approach, and the fingers close across the narrowest extent of that 2-D set (its minimum
//! width over the convex hull, by rotating calipers): the direction a parallel gripper can span
//! with the smallest opening.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};

use crate::error::QueryError;

/// Gripper geometry and approach.
#[derive(Clone, Debug, PartialEq)]
pub struct GraspParams {
    /// Approach direction (normalised on use); default `[0, 1, 0]`: +y, downwards in the
    /// camera-style map frame, i.e. approaching from above.
    pub approach: [f64; 3],
    /// How far below the highest point the fingers close (m); default 0.02.
    pub depth: f64,
    /// Thickness of the slab around that level whose points are used (m); default 0.02 (±0.01).
    pub slab: f64,
    /// The gripper's maximum opening (m); default 0.08.
    pub max_width: f64,
    /// Minimum number of points in the slab; default 3.
    pub min_points: usize,
}

impl Default for GraspParams {
    fn default() -> Self {
        Self {
            approach: [0.0, 1.0, 0.0],
            depth: 0.02,
            slab: 0.02,
            max_width: 0.08,
            min_points: 3,
        }
    }
}

/// A parallel-gripper grasp in the map frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Grasp {
    /// Centre between the fingertips (m).
    pub position: [f64; 3],
    /// Gripper orientation; its rotation matrix has the columns closing direction, in-plane
    /// direction (approach × closing) and approach.
    pub rotation: UnitQuaternion<f64>,
    /// Unit direction along which the fingers close (sign normalised: largest component positive).
    pub closing: [f64; 3],
    /// Unit approach direction.
    pub approach: [f64; 3],
    /// Extent of the object along the closing direction at the grasp depth (m).
    pub width: f64,
}

/// The grasp for `points` (see the module docs).
///
/// # Errors
/// [`QueryError::InvalidParameter`] for a zero or non-finite approach, a negative or non-finite
/// depth, slab or maximum width; [`QueryError::GraspPoints`] when fewer than `min_points` (at least
/// 3) finite points lie in the slab, or they all project onto one spot;
/// [`QueryError::GraspWidth`] when the object is wider than `max_width` there.
pub fn grasp_from_points(points: &[[f32; 3]], params: &GraspParams) -> Result<Grasp, QueryError> {
    let approach = Vector3::from(params.approach);
    let norm = approach.norm();
    if !(norm > 1e-9 && norm.is_finite()) {
        return Err(QueryError::InvalidParameter {
            name: "approach",
            reason: format!("must be a non-zero direction, got {:?}", params.approach),
        });
    }
    for (name, value) in [
        ("depth", params.depth),
        ("slab", params.slab),
        ("max_width", params.max_width),
    ] {
        if !(value >= 0.0 && value.is_finite()) {
            return Err(QueryError::InvalidParameter {
                name,
                reason: format!("must be a non-negative length in metres, got {value}"),
            });
        }
    }
    let a = approach / norm;
    let needed = params.min_points.max(3);
    let pts: Vec<Vector3<f64>> = points
        .iter()
        .map(|p| Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
        .filter(|p| p.iter().all(|x| x.is_finite()))
        .collect();
    let top = pts.iter().map(|p| p.dot(&a)).fold(f64::INFINITY, f64::min);
    let level = top + params.depth;
    let slab: Vec<&Vector3<f64>> = pts
        .iter()
        .filter(|p| (p.dot(&a) - level).abs() <= params.slab / 2.0)
        .collect();
    if slab.len() < needed {
        return Err(QueryError::GraspPoints {
            found: slab.len(),
            needed,
        });
    }
    // An orthonormal basis (u, v) of the plane orthogonal to the approach, from the world axis
    // least aligned with it (the most stable cross product).
    let axis = (0..3)
        .min_by(|&i, &j| a[i].abs().total_cmp(&a[j].abs()))
        .map_or(Vector3::x(), |i| {
            let mut e = Vector3::zeros();
            e[i] = 1.0;
            e
        });
    let u = a.cross(&axis).normalize();
    let v = a.cross(&u);
    let projected: Vec<Vector2<f64>> = slab
        .iter()
        .map(|p| Vector2::new(p.dot(&u), p.dot(&v)))
        .collect();
    let hull = convex_hull(&projected);
    let Some((dir, width)) = min_width(&hull) else {
        return Err(QueryError::GraspPoints {
            found: hull.len(),
            needed,
        });
    };
    // Centre of the extent along the closing direction and along the in-plane direction.
    let other = Vector2::new(-dir.y, dir.x);
    let extent = |d: &Vector2<f64>| {
        projected
            .iter()
            .map(|p| p.dot(d))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
                (lo.min(x), hi.max(x))
            })
    };
    let (c_lo, c_hi) = extent(&dir);
    let (o_lo, o_hi) = extent(&other);
    let centre_2d = dir * ((c_lo + c_hi) / 2.0) + other * ((o_lo + o_hi) / 2.0);
    let position = u * centre_2d.x + v * centre_2d.y + a * level;
    let mut closing = (u * dir.x + v * dir.y).normalize();
    let largest = (0..3)
        .max_by(|&i, &j| closing[i].abs().total_cmp(&closing[j].abs()))
        .unwrap_or(0);
    if closing[largest] < 0.0 {
        closing = -closing;
    }
    if width > params.max_width {
        return Err(QueryError::GraspWidth {
            width,
            max_width: params.max_width,
        });
    }
    let binormal = a.cross(&closing);
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        Matrix3::from_columns(&[closing, binormal, a]),
    ));
    Ok(Grasp {
        position: position.into(),
        rotation,
        closing: closing.into(),
        approach: a.into(),
        width,
    })
}

/// The 2-D convex hull (Andrew's monotone chain), counter-clockwise, without collinear points.
fn convex_hull(points: &[Vector2<f64>]) -> Vec<Vector2<f64>> {
    let mut pts = points.to_vec();
    pts.sort_by(|p, q| p.x.total_cmp(&q.x).then(p.y.total_cmp(&q.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let cross = |o: &Vector2<f64>, a: &Vector2<f64>, b: &Vector2<f64>| {
        (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
    };
    let mut hull: Vec<Vector2<f64>> = Vec::with_capacity(2 * pts.len());
    for pass in 0..2 {
        let start = hull.len();
        let ordered: Box<dyn Iterator<Item = &Vector2<f64>>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for p in ordered {
            while hull.len() >= start + 2
                && cross(&hull[hull.len() - 2], &hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(*p);
        }
        // The last point of each chain starts the other one.
        hull.pop();
    }
    hull
}

/// The unit direction across which the hull is narrowest and that width: for every hull edge, the
/// farthest hull point from its line (the minimum width is attained with an edge flush to one
/// side). `None` for fewer than 2 distinct points; collinear points give width 0 across the line.
fn min_width(hull: &[Vector2<f64>]) -> Option<(Vector2<f64>, f64)> {
    if hull.len() < 2 {
        return None;
    }
    let mut best: Option<(Vector2<f64>, f64)> = None;
    for i in 0..hull.len() {
        let edge = hull[(i + 1) % hull.len()] - hull[i];
        let len = edge.norm();
        if len <= f64::EPSILON {
            continue;
        }
        let normal = Vector2::new(-edge.y, edge.x) / len;
        let width = hull
            .iter()
            .map(|p| (p - hull[i]).dot(&normal).abs())
            .fold(0.0, f64::max);
        if best.is_none_or(|(_, w)| width < w) {
            best = Some((normal, width));
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Surface samples of an axis-aligned box `size` centred at `c`, every 5 mm.
    fn box_surface(c: [f64; 3], size: [f64; 3]) -> Vec<[f64; 3]> {
        let steps = size.map(|s| (s / 0.005).round() as i32);
        let mut out = Vec::new();
        for i in 0..=steps[0] {
            for j in 0..=steps[1] {
                for k in 0..=steps[2] {
                    let on_face = i == 0
                        || j == 0
                        || k == 0
                        || i == steps[0]
                        || j == steps[1]
                        || k == steps[2];
                    if on_face {
                        out.push([
                            c[0] - size[0] / 2.0 + size[0] * f64::from(i) / f64::from(steps[0]),
                            c[1] - size[1] / 2.0 + size[1] * f64::from(j) / f64::from(steps[1]),
                            c[2] - size[2] / 2.0 + size[2] * f64::from(k) / f64::from(steps[2]),
                        ]);
                    }
                }
            }
        }
        out
    }

    fn f32s(points: &[[f64; 3]]) -> Vec<[f32; 3]> {
        points.iter().map(|p| p.map(|x| x as f32)).collect()
    }

    #[test]
    fn box_is_grasped_across_its_narrow_side() {
        // 0.04 (x) × 0.05 (y, height along the approach) × 0.10 (z), centred at (1, 2, 3).
        let points = f32s(&box_surface([1.0, 2.0, 3.0], [0.04, 0.05, 0.10]));
        let g = grasp_from_points(&points, &GraspParams::default()).unwrap();
        assert!((g.width - 0.04).abs() < 1e-4, "{g:?}");
        assert!((g.closing[0] - 1.0).abs() < 1e-6, "{g:?}");
        // Top at y = 1.975; the fingers close 2 cm below it.
        let want = [1.0, 1.995, 3.0];
        for (p, w) in g.position.iter().zip(want) {
            assert!((p - w).abs() < 1e-4, "{g:?}");
        }
        assert_eq!(g.approach, [0.0, 1.0, 0.0]);
        let m = g.rotation.to_rotation_matrix();
        let m = m.matrix();
        assert!((m.column(0) - Vector3::from(g.closing)).norm() < 1e-9);
        assert!((m.column(2) - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-9);
    }

    #[test]
    fn rotated_box_closes_along_its_rotated_narrow_side() {
        let angle = 0.5_f64;
        let r = Rotation3::from_axis_angle(&Vector3::y_axis(), angle);
        let points: Vec<[f64; 3]> = box_surface([0.0; 3], [0.04, 0.05, 0.10])
            .into_iter()
            .map(|p| (r * Vector3::from(p) + Vector3::new(0.5, 0.0, 1.0)).into())
            .collect();
        let g = grasp_from_points(&f32s(&points), &GraspParams::default()).unwrap();
        assert!((g.width - 0.04).abs() < 1e-4, "{g:?}");
        let expected = r * Vector3::x();
        assert!(
            Vector3::from(g.closing).dot(&expected).abs() > 1.0 - 1e-6,
            "{g:?}"
        );
        for (p, w) in g.position.iter().zip([0.5, -0.005, 1.0]) {
            assert!((p - w).abs() < 1e-4, "{g:?}");
        }
    }

    #[test]
    fn approach_along_another_axis() {
        // Approach along -z: the "top" is the largest z.
        let points = f32s(&box_surface([0.0; 3], [0.10, 0.03, 0.05]));
        let params = GraspParams {
            approach: [0.0, 0.0, -2.0],
            ..GraspParams::default()
        };
        let g = grasp_from_points(&points, &params).unwrap();
        assert!((g.width - 0.03).abs() < 1e-4 && (g.closing[1] - 1.0).abs() < 1e-6);
        assert!((g.position[2] - 0.005).abs() < 1e-4, "{g:?}");
        assert_eq!(g.approach, [0.0, 0.0, -1.0]);
    }

    #[test]
    fn refusals_name_the_reason() {
        let err =
            grasp_from_points(&[[0.0; 3], [0.01, 0.0, 0.0]], &GraspParams::default()).unwrap_err();
        assert!(
            matches!(err, QueryError::GraspPoints { needed: 3, .. }),
            "{err}"
        );
        assert!(grasp_from_points(&[], &GraspParams::default()).is_err());
        // All points on one spot.
        let err = grasp_from_points(&[[0.0, 0.02, 0.0]; 5], &GraspParams::default()).unwrap_err();
        assert!(matches!(err, QueryError::GraspPoints { .. }), "{err}");
        let wide = f32s(&box_surface([0.0; 3], [0.12, 0.05, 0.15]));
        let err = grasp_from_points(&wide, &GraspParams::default()).unwrap_err();
        assert!(err.to_string().contains("0.120 m wide"), "{err}");
        let bad = GraspParams {
            approach: [0.0; 3],
            ..GraspParams::default()
        };
        assert!(grasp_from_points(&wide, &bad).is_err());
    }
}
