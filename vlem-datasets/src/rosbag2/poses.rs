//! Poses of a bag's (or a live node's) frames looked up in the tf tree of `/tf` and `/tf_static`
//! along `[parent, child]`.
//!
//! Why its own module: tf is a tree of frames whose edges change over time at their own rates
//! (odometry at 50 Hz, a static camera mount once). A frame's pose is the product of the edges
//! from the parent down to the camera, each at the frame's stamp: static edges as they are,
//! moving edges interpolated between the two messages around the stamp (nearest within the
//! tolerance), as tf2's `lookupTransform` does.

use std::collections::HashMap;

use vlem_core::Pose;

use crate::tum::pose_at;

/// Edges longer than this chain are a cycle in a corrupt tree.
const MAX_DEPTH: usize = 64;

/// One edge of the tf tree: a child frame's pose in its parent.
#[derive(Debug, Default)]
struct Edge {
    parent: String,
    /// The transform of `/tf_static`, which holds at every time.
    fixed: Option<Pose>,
    /// `/tf` transforms by time (seconds), sorted once every message is in.
    moving: Vec<(f64, Pose)>,
}

/// The tf tree of a bag.
#[derive(Debug, Default)]
pub struct TfTree {
    /// Child frame id -> its edge.
    edges: HashMap<String, Edge>,
    /// Transforms whose child already had another parent (tf allows one parent per frame).
    pub reparented: usize,
}

impl TfTree {
    /// Adds one transform of `/tf` (`fixed = false`) or `/tf_static`.
    pub fn insert(&mut self, parent: &str, child: &str, time: f64, pose: Pose, fixed: bool) {
        let edge = self.edges.entry(child.to_owned()).or_insert_with(|| Edge {
            parent: parent.to_owned(),
            ..Edge::default()
        });
        if edge.parent != parent {
            self.reparented += 1;
            return;
        }
        if fixed {
            edge.fixed = Some(pose);
        } else {
            edge.moving.push((time, pose));
        }
    }

    /// Sorts the moving edges by time; call after the last [`TfTree::insert`] and before
    /// [`TfTree::lookup`] (cheap when transforms arrived in order, as they do live).
    pub fn finish(&mut self) {
        for edge in self.edges.values_mut() {
            if !edge.moving.is_sorted_by(|a, b| a.0 <= b.0) {
                edge.moving.sort_by(|a, b| a.0.total_cmp(&b.0));
            }
        }
    }

    /// Forgets moving transforms older than `time` but the last one before it, so a live tree
    /// stays small and can still interpolate at `time`.
    pub fn forget_before(&mut self, time: f64) {
        for edge in self.edges.values_mut() {
            let keep_from = edge
                .moving
                .partition_point(|(t, _)| *t < time)
                .saturating_sub(1);
            edge.moving.drain(..keep_from);
        }
    }

    /// The newest time at which every moving edge of `chain` has a transform (the earliest of
    /// their last stamps); `None` when an edge has none yet. Static-only chains: +infinity.
    pub fn covered_until(&self, chain: &[String]) -> Option<f64> {
        let mut until = f64::INFINITY;
        for frame in &chain[..chain.len().saturating_sub(1)] {
            let edge = self.edges.get(frame)?;
            if edge.fixed.is_none() {
                until = until.min(edge.moving.last()?.0);
            }
        }
        Some(until)
    }

    /// The frames from `child` up to `parent` (both included).
    ///
    /// # Errors
    /// A message naming the chain that was found when `parent` is not an ancestor of `child`.
    pub fn chain(&self, parent: &str, child: &str) -> Result<Vec<String>, String> {
        let mut chain = vec![child.to_owned()];
        let mut frame = child;
        while frame != parent {
            let Some(edge) = self.edges.get(frame) else {
                let mut roots: Vec<&str> = self
                    .edges
                    .values()
                    .map(|e| e.parent.as_str())
                    .filter(|p| !self.edges.contains_key(*p))
                    .collect();
                roots.sort_unstable();
                roots.dedup();
                return Err(if chain.len() == 1 {
                    format!(
                        "no transform has child frame `{child}` (frames with a parent: {}; roots: {})",
                        self.frame_list(),
                        roots.join(", ")
                    )
                } else {
                    format!(
                        "`{parent}` is not an ancestor of `{child}`: the chain {} ends at the root \
                         `{frame}`",
                        chain.join(" -> ")
                    )
                });
            };
            if chain.len() > MAX_DEPTH {
                return Err(format!("the tf tree has a cycle: {}", chain.join(" -> ")));
            }
            frame = &edge.parent;
            chain.push(frame.to_owned());
        }
        Ok(chain)
    }

    fn frame_list(&self) -> String {
        let mut frames: Vec<&str> = self.edges.keys().map(String::as_str).collect();
        frames.sort_unstable();
        if frames.is_empty() {
            "none".to_owned()
        } else {
            frames.join(", ")
        }
    }

    /// The pose of `chain[0]` in the last frame of `chain` (from [`TfTree::chain`]) at `time`, or
    /// `None` when a moving edge has no transform within `tolerance` and none on both sides.
    pub fn lookup(&self, chain: &[String], time: f64, tolerance: f64) -> Option<Pose> {
        let mut pose = Pose::identity();
        for frame in &chain[..chain.len().saturating_sub(1)] {
            let edge = self.edges.get(frame)?;
            let step = match edge.fixed {
                Some(fixed) => fixed,
                None => pose_at(&edge.moving, time, tolerance)?,
            };
            // Walking up: the parent's transform applies after the child's.
            pose = step * pose;
        }
        Some(pose)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn at(x: f64, y: f64, z: f64) -> Pose {
        Pose::translation(x, y, z)
    }

    #[test]
    fn chains_compose_fixed_and_interpolated_edges() {
        let mut tree = TfTree::default();
        tree.insert("map", "odom", 0.0, at(1.0, 0.0, 0.0), true);
        tree.insert("odom", "base", 10.0, at(0.0, 0.0, 0.0), false);
        tree.insert("odom", "base", 11.0, at(0.0, 2.0, 0.0), false);
        let yaw = Pose::from_parts(
            at(0.0, 0.0, 0.5).translation,
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
        );
        tree.insert("base", "camera", 0.0, yaw, true);
        tree.insert("odom", "wheel", 10.0, at(5.0, 5.0, 5.0), false);
        tree.finish();
        let chain = tree.chain("map", "camera").unwrap();
        assert_eq!(chain, ["camera", "base", "odom", "map"]);
        let pose = tree.lookup(&chain, 10.5, 0.02).unwrap();
        let expected = at(1.0, 0.0, 0.0) * at(0.0, 1.0, 0.0) * yaw;
        assert!(
            (pose.to_homogeneous() - expected.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
        // Outside the moving edge's time span: no pose.
        assert!(tree.lookup(&chain, 12.0, 0.02).is_none());
        assert!(tree.lookup(&chain, 11.01, 0.02).is_some());

        let err = tree.chain("wheel", "camera").unwrap_err();
        assert!(
            err.contains("not an ancestor") && err.contains("root `map`"),
            "{err}"
        );
        let err = tree.chain("map", "lidar").unwrap_err();
        assert!(
            err.contains("no transform has child frame `lidar`"),
            "{err}"
        );
        // Coverage: the moving edge ends at 11.0; forgetting keeps what interpolation needs.
        assert_eq!(tree.covered_until(&chain), Some(11.0));
        tree.forget_before(10.5);
        assert!(tree.lookup(&chain, 10.5, 0.02).is_some());
        tree.forget_before(11.5);
        assert!(tree.lookup(&chain, 11.0, 0.02).is_some());
        assert!(tree.lookup(&chain, 10.5, 0.02).is_none());
        // A second parent for a frame is counted and ignored.
        tree.insert("map", "base", 10.0, at(0.0, 0.0, 0.0), false);
        assert_eq!(tree.reparented, 1);
    }
}
