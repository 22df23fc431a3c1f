//! The analytic shapes the synthetic scene is built from, and what the renderer and the surface
//! sampler ask of them: nearest ray entry with its outward normal, point containment, bounds and
//! evenly spaced surface samples.
//!
//! Boxes turn about the vertical (z) axis only and cylinders stand upright, which keeps every test
//! a few lines of closed-form algebra.

use nalgebra::Vector3;

/// Hits closer than this (metres along a ray whose camera-frame z component is 1) are ignored, so
/// that a ray never re-hits the surface it starts on.
pub(crate) const T_MIN: f64 = 1e-6;

/// An axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Aabb {
    pub(crate) min: Vector3<f64>,
    pub(crate) max: Vector3<f64>,
}

impl Aabb {
    /// The empty box (the identity of [`Aabb::union`]).
    pub(crate) fn empty() -> Self {
        Self {
            min: Vector3::repeat(f64::INFINITY),
            max: Vector3::repeat(f64::NEG_INFINITY),
        }
    }

    /// The smallest box holding both.
    pub(crate) fn union(&self, other: &Self) -> Self {
        Self {
            min: self.min.inf(&other.min),
            max: self.max.sup(&other.max),
        }
    }

    /// The eight corners.
    pub(crate) fn corners(&self) -> [Vector3<f64>; 8] {
        let (a, b) = (self.min, self.max);
        [
            Vector3::new(a.x, a.y, a.z),
            Vector3::new(b.x, a.y, a.z),
            Vector3::new(a.x, b.y, a.z),
            Vector3::new(b.x, b.y, a.z),
            Vector3::new(a.x, a.y, b.z),
            Vector3::new(b.x, a.y, b.z),
            Vector3::new(a.x, b.y, b.z),
            Vector3::new(b.x, b.y, b.z),
        ]
    }

    /// Whether `p` lies inside, grown by `eps` on every side.
    pub(crate) fn contains(&self, p: &Vector3<f64>, eps: f64) -> bool {
        (0..3).all(|k| p[k] >= self.min[k] - eps && p[k] <= self.max[k] + eps)
    }
}

/// One analytic solid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Shape {
    /// A box turned by a yaw about the vertical axis.
    Cuboid {
        /// Centre in world coordinates.
        centre: Vector3<f64>,
        /// Cosine of the yaw (local x axis = (cos, sin, 0)).
        cos: f64,
        /// Sine of the yaw.
        sin: f64,
        /// Half extents along the local axes.
        half: Vector3<f64>,
    },
    /// An upright cylinder with flat caps.
    Cylinder {
        /// Axis position.
        x: f64,
        /// Axis position.
        y: f64,
        /// Bottom cap height.
        z0: f64,
        /// Top cap height.
        z1: f64,
        /// Radius.
        r: f64,
    },
    /// A sphere.
    Sphere {
        /// Centre in world coordinates.
        centre: Vector3<f64>,
        /// Radius.
        r: f64,
    },
}

/// Where a ray enters a shape.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Entry {
    /// Ray parameter of the hit.
    pub(crate) t: f64,
    /// Outward unit normal there (world frame).
    pub(crate) normal: Vector3<f64>,
}

impl Shape {
    /// A box of half extents `half` centred at `centre`, turned by `yaw` radians.
    pub(crate) fn cuboid(centre: Vector3<f64>, yaw: f64, half: Vector3<f64>) -> Self {
        Self::Cuboid {
            centre,
            cos: yaw.cos(),
            sin: yaw.sin(),
            half,
        }
    }

    /// World-frame bounds.
    pub(crate) fn aabb(&self) -> Aabb {
        match *self {
            Self::Cuboid {
                centre,
                cos,
                sin,
                half,
            } => {
                let ex = (half.x * cos).abs() + (half.y * sin).abs();
                let ey = (half.x * sin).abs() + (half.y * cos).abs();
                let e = Vector3::new(ex, ey, half.z);
                Aabb {
                    min: centre - e,
                    max: centre + e,
                }
            }
            Self::Cylinder { x, y, z0, z1, r } => Aabb {
                min: Vector3::new(x - r, y - r, z0),
                max: Vector3::new(x + r, y + r, z1),
            },
            Self::Sphere { centre, r } => Aabb {
                min: centre - Vector3::repeat(r),
                max: centre + Vector3::repeat(r),
            },
        }
    }

    /// Eight points whose convex hull holds the shape (its corners for a box, else the corners
    /// of its bounds).
    pub(crate) fn hull(&self) -> [Vector3<f64>; 8] {
        match *self {
            Self::Cuboid {
                centre,
                cos,
                sin,
                half,
            } => {
                let mut corners = [Vector3::zeros(); 8];
                for (i, c) in corners.iter_mut().enumerate() {
                    let sign = |bit: usize| if i & bit == 0 { -1.0 } else { 1.0 };
                    let l = Vector3::new(sign(1) * half.x, sign(2) * half.y, sign(4) * half.z);
                    *c = centre + to_world(&l, cos, sin);
                }
                corners
            }
            _ => self.aabb().corners(),
        }
    }

    /// The ray origin `o` relative to the shape, as [`Shape::entry_relative`] takes it: in the
    /// box's own frame, relative to a cylinder's axis (z unchanged) or a sphere's centre.
    #[inline]
    pub(crate) fn relative_origin(&self, o: &Vector3<f64>) -> Vector3<f64> {
        match *self {
            Self::Cuboid {
                centre, cos, sin, ..
            } => to_local(&(o - centre), cos, sin),
            Self::Cylinder { x, y, .. } => Vector3::new(o.x - x, o.y - y, o.z),
            Self::Sphere { centre, .. } => o - centre,
        }
    }

    /// The nearest point where the ray `o + t d` enters the shape with `T_MIN < t < t_max`. A ray
    /// starting inside the shape reports nothing (cameras are never inside furniture).
    #[cfg(test)]
    pub(crate) fn entry(&self, o: &Vector3<f64>, d: &Vector3<f64>, t_max: f64) -> Option<Entry> {
        self.entry_relative(&self.relative_origin(o), d, t_max)
    }

    /// [`Shape::entry`] with the origin already made relative by [`Shape::relative_origin`] (a
    /// renderer does that once per view, not once per pixel).
    #[inline]
    pub(crate) fn entry_relative(
        &self,
        rel: &Vector3<f64>,
        d: &Vector3<f64>,
        t_max: f64,
    ) -> Option<Entry> {
        match *self {
            Self::Cuboid { cos, sin, half, .. } => cuboid_entry(rel, cos, sin, &half, d, t_max),
            Self::Cylinder { z0, z1, r, .. } => cylinder_entry(rel, z0, z1, r, d, t_max),
            Self::Sphere { r, .. } => sphere_entry(rel, r, d, t_max),
        }
    }

    /// Whether `p` lies inside the shape grown by `eps` (surface points count as inside).
    pub(crate) fn contains(&self, p: &Vector3<f64>, eps: f64) -> bool {
        match *self {
            Self::Cuboid {
                centre,
                cos,
                sin,
                half,
            } => {
                let l = to_local(&(p - centre), cos, sin);
                (0..3).all(|k| l[k].abs() <= half[k] + eps)
            }
            Self::Cylinder { x, y, z0, z1, r } => {
                let (dx, dy) = (p.x - x, p.y - y);
                p.z >= z0 - eps && p.z <= z1 + eps && (dx * dx + dy * dy).sqrt() <= r + eps
            }
            Self::Sphere { centre, r } => (p - centre).norm() <= r + eps,
        }
    }

    /// Points on the surface about `spacing` apart, each with its outward normal.
    pub(crate) fn sample_surface(&self, spacing: f64, out: &mut Vec<(Vector3<f64>, Vector3<f64>)>) {
        match *self {
            Self::Cuboid {
                centre,
                cos,
                sin,
                half,
            } => {
                for axis in 0..3 {
                    let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                    for sign in [-1.0, 1.0] {
                        let mut n = Vector3::zeros();
                        n[axis] = sign;
                        grid(2.0 * half[a], 2.0 * half[b], spacing, |u, v| {
                            let mut l = Vector3::zeros();
                            l[axis] = sign * half[axis];
                            l[a] = u - half[a];
                            l[b] = v - half[b];
                            out.push((centre + to_world(&l, cos, sin), to_world(&n, cos, sin)));
                        });
                    }
                }
            }
            Self::Cylinder { x, y, z0, z1, r } => {
                let around = steps(std::f64::consts::TAU * r, spacing);
                let up = steps(z1 - z0, spacing);
                for i in 0..around {
                    let a = std::f64::consts::TAU * (i as f64 + 0.5) / around as f64;
                    let n = Vector3::new(a.cos(), a.sin(), 0.0);
                    for j in 0..up {
                        let z = z0 + (z1 - z0) * (j as f64 + 0.5) / up as f64;
                        out.push((Vector3::new(x + r * n.x, y + r * n.y, z), n));
                    }
                }
                for (z, nz) in [(z0, -1.0), (z1, 1.0)] {
                    grid(2.0 * r, 2.0 * r, spacing, |u, v| {
                        let (dx, dy) = (u - r, v - r);
                        if dx * dx + dy * dy <= r * r {
                            out.push((Vector3::new(x + dx, y + dy, z), Vector3::new(0.0, 0.0, nz)));
                        }
                    });
                }
            }
            Self::Sphere { centre, r } => {
                let rings = steps(std::f64::consts::PI * r, spacing);
                for i in 0..rings {
                    let polar = std::f64::consts::PI * (i as f64 + 0.5) / rings as f64;
                    let around = steps(std::f64::consts::TAU * r * polar.sin(), spacing);
                    for j in 0..around {
                        let a = std::f64::consts::TAU * (j as f64 + 0.5) / around as f64;
                        let n =
                            Vector3::new(polar.sin() * a.cos(), polar.sin() * a.sin(), polar.cos());
                        out.push((centre + r * n, n));
                    }
                }
            }
        }
    }
}

/// How many samples cover `length` at `spacing` (at least one).
fn steps(length: f64, spacing: f64) -> usize {
    ((length / spacing).ceil() as usize).max(1)
}

/// Calls `f(u, v)` at the cell centres of a `width` x `height` rectangle cut into cells of about
/// `spacing`.
pub(crate) fn grid(width: f64, height: f64, spacing: f64, mut f: impl FnMut(f64, f64)) {
    let (nu, nv) = (steps(width, spacing), steps(height, spacing));
    for i in 0..nu {
        let u = width * (i as f64 + 0.5) / nu as f64;
        for j in 0..nv {
            f(u, height * (j as f64 + 0.5) / nv as f64);
        }
    }
}

/// World offset to the frame turned by the yaw whose cosine and sine are given.
#[inline]
pub(crate) fn to_local(v: &Vector3<f64>, cos: f64, sin: f64) -> Vector3<f64> {
    Vector3::new(cos * v.x + sin * v.y, -sin * v.x + cos * v.y, v.z)
}

/// The inverse of [`to_local`].
#[inline]
pub(crate) fn to_world(v: &Vector3<f64>, cos: f64, sin: f64) -> Vector3<f64> {
    Vector3::new(cos * v.x - sin * v.y, sin * v.x + cos * v.y, v.z)
}

/// Slab test of a box in its own frame (`o` relative to its centre).
#[inline]
fn cuboid_entry(
    o: &Vector3<f64>,
    cos: f64,
    sin: f64,
    half: &Vector3<f64>,
    d: &Vector3<f64>,
    t_max: f64,
) -> Option<Entry> {
    let dl = to_local(d, cos, sin);
    // A zero direction component gives infinite slab bounds of the right signs (a NaN, for a ray
    // exactly on a face plane, is ignored by min/max).
    let slab = |o: f64, d: f64, h: f64| {
        let inv = 1.0 / d;
        let a = (-h - o) * inv;
        let b = (h - o) * inv;
        (a.min(b), a.max(b))
    };
    let (nx, fx) = slab(o.x, dl.x, half.x);
    let (ny, fy) = slab(o.y, dl.y, half.y);
    let (nz, fz) = slab(o.z, dl.z, half.z);
    let near = nx.max(ny).max(nz);
    let far = fx.min(fy).min(fz);
    if !(near <= far && near > T_MIN && near < t_max) {
        return None;
    }
    // The entry face is on the slab whose near bound is the largest.
    let n = if near == nx {
        Vector3::new(-dl.x.signum(), 0.0, 0.0)
    } else if near == ny {
        Vector3::new(0.0, -dl.y.signum(), 0.0)
    } else {
        Vector3::new(0.0, 0.0, -dl.z.signum())
    };
    Some(Entry {
        t: near,
        normal: to_world(&n, cos, sin),
    })
}

/// Upright cylinder, `o` relative to its axis (z unchanged).
#[inline]
fn cylinder_entry(
    o: &Vector3<f64>,
    z0: f64,
    z1: f64,
    r: f64,
    d: &Vector3<f64>,
    t_max: f64,
) -> Option<Entry> {
    let mut best: Option<Entry> = None;
    let mut limit = t_max;
    let a = d.x * d.x + d.y * d.y;
    if a > 0.0 {
        let b = o.x * d.x + o.y * d.y;
        let c = o.x * o.x + o.y * o.y - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = o.z + t * d.z;
            if t > T_MIN && t < limit && z >= z0 && z <= z1 {
                limit = t;
                best = Some(Entry {
                    t,
                    normal: Vector3::new((o.x + t * d.x) / r, (o.y + t * d.y) / r, 0.0),
                });
            }
        }
    }
    if d.z != 0.0 {
        // A ray going up can only enter through the bottom cap, one going down through the top.
        let (z, nz) = if d.z > 0.0 { (z0, -1.0) } else { (z1, 1.0) };
        let t = (z - o.z) / d.z;
        if t > T_MIN && t < limit {
            let (px, py) = (o.x + t * d.x, o.y + t * d.y);
            if px * px + py * py <= r * r {
                best = Some(Entry {
                    t,
                    normal: Vector3::new(0.0, 0.0, nz),
                });
            }
        }
    }
    best
}

/// Sphere, `o` relative to its centre.
#[inline]
fn sphere_entry(o: &Vector3<f64>, r: f64, d: &Vector3<f64>, t_max: f64) -> Option<Entry> {
    let a = d.norm_squared();
    let b = o.dot(d);
    let c = o.norm_squared() - r * r;
    let disc = b * b - a * c;
    if disc < 0.0 || c <= 0.0 {
        return None;
    }
    let t = (-b - disc.sqrt()) / a;
    if t <= T_MIN || t >= t_max {
        return None;
    }
    Some(Entry {
        t,
        normal: (o + t * d) / r,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(x: f64, y: f64, z: f64) -> Vector3<f64> {
        Vector3::new(x, y, z)
    }

    #[test]
    fn turned_box_is_entered_where_the_algebra_says() {
        // A unit cube turned by 45°: its corner points at -x, at distance √2/2 from the centre.
        let s = Shape::cuboid(
            v(0.0, 0.0, 0.0),
            std::f64::consts::FRAC_PI_4,
            v(0.5, 0.5, 0.5),
        );
        let e = s
            .entry(&v(-3.0, 0.0, 0.0), &v(1.0, 0.0, 0.0), 10.0)
            .unwrap();
        assert!((e.t - (3.0 - 0.5 * 2f64.sqrt())).abs() < 1e-12, "{}", e.t);
        let e = s
            .entry(&v(0.0, 0.0, 3.0), &v(0.0, 0.0, -1.0), 10.0)
            .unwrap();
        assert!((e.t - 2.5).abs() < 1e-12);
        assert!((e.normal - v(0.0, 0.0, 1.0)).norm() < 1e-12);
        assert!(
            s.entry(&v(0.0, 0.0, 3.0), &v(0.0, 0.0, -1.0), 2.0)
                .is_none()
        );
        assert!(
            s.entry(&v(0.0, 0.0, 0.0), &v(1.0, 0.0, 0.0), 10.0)
                .is_none()
        );
        assert!(s.contains(&v(0.7, 0.0, 0.0), 0.0));
        assert!(!s.contains(&v(0.5, 0.5, 0.0), 0.0));
    }

    #[test]
    fn cylinder_side_and_caps() {
        let s = Shape::Cylinder {
            x: 1.0,
            y: 0.0,
            z0: 0.0,
            z1: 2.0,
            r: 0.5,
        };
        let e = s
            .entry(&v(-1.0, 0.0, 1.0), &v(1.0, 0.0, 0.0), 10.0)
            .unwrap();
        assert!((e.t - 1.5).abs() < 1e-12);
        assert!((e.normal - v(-1.0, 0.0, 0.0)).norm() < 1e-12);
        let e = s
            .entry(&v(1.2, 0.1, 5.0), &v(0.0, 0.0, -1.0), 10.0)
            .unwrap();
        assert!((e.t - 3.0).abs() < 1e-12);
        assert!((e.normal - v(0.0, 0.0, 1.0)).norm() < 1e-12);
        // Passes above the top.
        assert!(
            s.entry(&v(-1.0, 0.0, 2.5), &v(1.0, 0.0, 0.0), 10.0)
                .is_none()
        );
    }

    #[test]
    fn sphere_entry_and_samples_lie_on_the_surface() {
        let s = Shape::Sphere {
            centre: v(0.0, 0.0, 1.0),
            r: 0.25,
        };
        let e = s
            .entry(&v(0.0, -2.0, 1.0), &v(0.0, 2.0, 0.0), 10.0)
            .unwrap();
        assert!((e.t - 0.875).abs() < 1e-12);
        let mut pts = Vec::new();
        s.sample_surface(0.02, &mut pts);
        assert!(pts.len() > 400);
        for (p, n) in &pts {
            assert!(((p - v(0.0, 0.0, 1.0)).norm() - 0.25).abs() < 1e-12);
            assert!((n.norm() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn aabb_holds_the_shape_samples() {
        let shapes = [
            Shape::cuboid(v(1.0, 2.0, 0.5), 0.3, v(0.4, 0.2, 0.5)),
            Shape::Cylinder {
                x: 0.0,
                y: 0.0,
                z0: 0.0,
                z1: 1.0,
                r: 0.1,
            },
        ];
        for s in shapes {
            let mut pts = Vec::new();
            s.sample_surface(0.05, &mut pts);
            let b = s.aabb();
            assert!(pts.iter().all(|(p, _)| b.contains(p, 1e-12)));
            assert!(pts.iter().all(|(p, _)| s.contains(p, 1e-9)));
            assert!(s.hull().iter().all(|p| b.contains(p, 1e-12)));
        }
    }
}
