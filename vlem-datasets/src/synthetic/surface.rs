//! Ground-truth labelled surface points of the synthetic scene.
//!
//! Every surface of the scene is sampled on a regular grid (per face of a box, around and up a
//! cylinder, by latitude rings on a sphere); samples buried inside another solid or in the floor,
//! walls or ceiling (contact faces, leg tops under a table top) are dropped, so what is left is the
//! boundary of the furnished room, whether or not the camera path sees it.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::geometry::grid;
use super::layout::{CEILING, FLOOR, Layout};
use super::render::Surface;
use super::{SurfacePoint, SyntheticScene};
use crate::error::{DatasetError, Result};

/// Points closer than this to another solid count as inside it (metres).
const CONTACT: f64 = 1e-4;

/// Smallest sample spacing accepted (metres): finer spacings give tens of millions of points.
const MIN_SPACING: f64 = 0.002;

impl SyntheticScene {
    /// Samples every visible-in-principle surface about `spacing` metres apart (0.01–0.02 suits a
    /// map evaluation), with its label, instance, normal and colour.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] when `spacing` is not a finite number of at least 0.002 m.
    pub fn surface_points(&self, spacing: f64) -> Result<Vec<SurfacePoint>> {
        if !(spacing.is_finite() && spacing >= MIN_SPACING) {
            return Err(DatasetError::Synthetic {
                message: format!(
                    "surface point spacing must be at least {MIN_SPACING} m, got {spacing}"
                ),
            });
        }
        let layout = &self.layout;
        let room: Vec<SurfacePoint> = (0..6)
            .into_par_iter()
            .flat_map_iter(|face| {
                let mut samples = Vec::new();
                room_face_samples(layout, face, spacing, &mut samples);
                samples
                    .into_iter()
                    .filter(|(p, _)| !inside_any_part(layout, p, None))
                    .map(move |(p, n)| self.point(Surface::Room(face), p, n))
                    .collect::<Vec<_>>()
            })
            .collect();
        let parts: Vec<SurfacePoint> = (0..layout.parts.len())
            .into_par_iter()
            .flat_map_iter(|i| {
                let mut samples = Vec::new();
                layout.parts[i].shape.sample_surface(spacing, &mut samples);
                samples
                    .into_iter()
                    .filter(|(p, _)| inside_room(layout, p) && !inside_any_part(layout, p, Some(i)))
                    .map(move |(p, n)| self.point(Surface::Part(i), p, n))
                    .collect::<Vec<_>>()
            })
            .collect();
        let mut points = room;
        points.extend(parts);
        Ok(points)
    }

    fn point(&self, surface: Surface, p: Vector3<f64>, n: Vector3<f64>) -> SurfacePoint {
        let (colour, label, instance) = self.surface_look(surface, &p, &n);
        SurfacePoint {
            position: Point3::from(p),
            normal: n,
            label,
            instance,
            colour,
        }
    }
}

/// Grid samples of room surface `face` with its inward normal.
fn room_face_samples(
    layout: &Layout,
    face: usize,
    spacing: f64,
    out: &mut Vec<(Vector3<f64>, Vector3<f64>)>,
) {
    let (min, max) = (layout.min, layout.max);
    let size = max - min;
    // (fixed axis, its value, inward normal sign, the two free axes)
    let (axis, value, sign) = match face {
        FLOOR => (2, min.z, 1.0),
        CEILING => (2, max.z, -1.0),
        2 => (0, min.x, 1.0),
        3 => (0, max.x, -1.0),
        4 => (1, min.y, 1.0),
        _ => (1, max.y, -1.0),
    };
    let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
    let mut normal = Vector3::zeros();
    normal[axis] = sign;
    grid(size[a], size[b], spacing, |u, v| {
        let mut p = Vector3::zeros();
        p[axis] = value;
        p[a] = min[a] + u;
        p[b] = min[b] + v;
        out.push((p, normal));
    });
}

/// Whether `p` lies strictly inside the room (not on or beyond a room surface).
fn inside_room(layout: &Layout, p: &Vector3<f64>) -> bool {
    (0..3).all(|k| p[k] > layout.min[k] + CONTACT && p[k] < layout.max[k] - CONTACT)
}

/// Whether `p` lies in (or on) a part other than `except`.
fn inside_any_part(layout: &Layout, p: &Vector3<f64>, except: Option<usize>) -> bool {
    layout.spans.iter().any(|span| {
        span.aabb.contains(p, CONTACT)
            && span.parts.clone().any(|j| {
                Some(j) != except
                    && layout.parts[j].aabb.contains(p, CONTACT)
                    && layout.parts[j].shape.contains(p, CONTACT)
            })
    })
}
