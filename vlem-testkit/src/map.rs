//! The conformance suite for [`EmbeddingMap`] implementations: [`map_conformance!`](crate::map_conformance).
//!
//! Every map gets the same contract checked on small synthetic frames (a textured plane seen by a
//! 64x48 pinhole camera): the point budget is never exceeded, embeddings stay finite and unit-norm
//! even with NaN, infinite and negative depth, re-observing a static scene converges, a save →
//! load round trip is lossless, an element outside the view is never modified, queries score every
//! element in `[0, 1]`, and inputs of the wrong dimension are refused.
#![allow(
    clippy::panic,
    reason = "a conformance check reports a broken contract by panicking, like assert!"
)]

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use vlem_core::{
    DepthImage, EmbeddingMap, Frame, Intrinsics, NO_REGION, Observation, PixelEmbeddings, Pose,
    RgbImage,
};

/// Builds a map for a given embedding dimension and point (element) budget.
pub type MapFactory = fn(dim: usize, max_points: usize) -> Box<dyn EmbeddingMap>;

/// Embedding dimension the suite uses.
pub const DIM: usize = 8;

/// A 64x48 frame of a fronto-parallel plane at `depth` metres, coloured by column.
pub fn plane_frame(index: usize, depth: f32) -> Frame {
    let (w, h) = (64u32, 48u32);
    let k = Intrinsics::new(w, h, 50.0, 50.0, 31.5, 23.5).unwrap_or_else(|e| unreachable(e));
    let colour: Vec<u8> = (0..w * h)
        .flat_map(|i| [(i % w * 4) as u8, 128, 255 - (i % w * 4) as u8])
        .collect();
    let colour = RgbImage::new(w, h, colour).unwrap_or_else(|e| unreachable(e));
    let depth =
        DepthImage::new(w, h, vec![depth; (w * h) as usize]).unwrap_or_else(|e| unreachable(e));
    Frame::new(index, index as f64, colour, depth, k, None).unwrap_or_else(|e| unreachable(e))
}

/// Two segments (left and right half of the image), embeddings `e_k` and `e_(k+1)` of the
/// standard basis; the bottom row has no segment.
pub fn half_segments(frame: &Frame, k: usize) -> PixelEmbeddings {
    let (w, h) = (frame.depth.width(), frame.depth.height());
    let index = (0..w * h)
        .map(|i| {
            if i / w == h - 1 {
                NO_REGION
            } else if i % w < w / 2 {
                0
            } else {
                1
            }
        })
        .collect();
    let mut table = vec![0.0; 2 * DIM];
    table[k % DIM] = 1.0;
    table[DIM + (k + 1) % DIM] = 1.0;
    PixelEmbeddings::from_regions(w, h, DIM, index, table).unwrap_or_else(|e| unreachable(e))
}

/// A pose translated by `(x, y, z)` and rotated by `yaw` radians about the camera's y axis.
pub fn pose(x: f64, y: f64, z: f64, yaw: f64) -> Pose {
    Pose::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw),
    )
}

fn unreachable(e: vlem_core::CoreError) -> ! {
    panic!("the conformance fixtures are valid by construction: {e}")
}

/// Integrates `frame` with `embeddings` at `pose`, panicking with context on error.
pub fn integrate(map: &mut dyn EmbeddingMap, frame: &Frame, pose: &Pose, e: &PixelEmbeddings) {
    if let Err(err) = map.integrate(&Observation {
        frame,
        pose,
        embeddings: Some(e),
    }) {
        panic!(
            "{} failed to integrate frame {}: {err}",
            map.name(),
            frame.index
        );
    }
}

/// Asserts every embedding of the map's snapshot is finite and unit-norm, and positions finite.
pub fn assert_well_formed(map: &dyn EmbeddingMap) {
    let snap = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    assert_eq!(snap.len(), map.len(), "snapshot and len() disagree");
    assert_eq!(snap.dim, map.dim());
    assert!(
        snap.validate().is_ok(),
        "snapshot arrays disagree in length"
    );
    for p in &snap.positions {
        assert!(p.iter().all(|x| x.is_finite()), "non-finite position {p:?}");
    }
    for (i, row) in snap.embeddings.chunks_exact(snap.dim.max(1)).enumerate() {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-4, "embedding {i} has norm {norm}");
    }
}

/// The budget holds after every frame of a moving sequence.
pub fn check_budget(build: MapFactory) {
    let budget = 500;
    let mut map = build(DIM, budget);
    for i in 0..8 {
        let frame = plane_frame(i, 1.5 + 0.1 * i as f32);
        let e = half_segments(&frame, i);
        integrate(
            map.as_mut(),
            &frame,
            &pose(0.05 * i as f64, 0.0, 0.0, 0.1 * i as f64),
            &e,
        );
        assert!(
            map.len() <= budget,
            "{} points after frame {i}, budget {budget}",
            map.len()
        );
        assert!(!map.is_empty(), "the map dropped everything");
    }
    assert_well_formed(map.as_ref());
    assert!(
        map.memory_bytes() + map.device_memory_bytes() >= map.len() * DIM * 4,
        "memory report below the stored embeddings"
    );
}

/// NaN, infinite, negative and zero depth never reach the map.
pub fn check_invalid_depth(build: MapFactory) {
    let mut map = build(DIM, 100_000);
    let mut frame = plane_frame(0, 2.0);
    let mut depth = frame.depth.as_raw().to_vec();
    let specials = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, 0.0];
    for (i, d) in depth.iter_mut().enumerate() {
        if i % 3 == 0 {
            *d = specials[i / 3 % specials.len()];
        }
    }
    frame.depth = DepthImage::new(64, 48, depth).unwrap_or_else(|e| unreachable(e));
    let e = half_segments(&frame, 0);
    integrate(map.as_mut(), &frame, &Pose::identity(), &e);
    assert!(!map.is_empty(), "valid pixels were not integrated");
    assert_well_formed(map.as_ref());
    let all_invalid =
        DepthImage::new(64, 48, vec![f32::NAN; 64 * 48]).unwrap_or_else(|e| unreachable(e));
    let before = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    frame.depth = all_invalid;
    integrate(map.as_mut(), &frame, &Pose::identity(), &e);
    let after = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    assert!(
        after.positions == before.positions && after.embeddings == before.embeddings,
        "a frame without valid depth changed the map"
    );
}

/// Observing the same static scene again converges: the second pass adds (almost) nothing and
/// embeddings keep pointing at what was observed.
pub fn check_static_convergence(build: MapFactory) {
    let mut map = build(DIM, 100_000);
    let frame = plane_frame(0, 2.0);
    let e = half_segments(&frame, 2);
    integrate(map.as_mut(), &frame, &Pose::identity(), &e);
    let first = map.len();
    for _ in 0..3 {
        integrate(map.as_mut(), &frame, &Pose::identity(), &e);
    }
    assert!(
        map.len() <= first + first / 20,
        "re-observing a static scene grew the map from {first} to {}",
        map.len()
    );
    let mut left = vec![0.0; DIM];
    left[2] = 1.0;
    let mut scores = Vec::new();
    map.similarity(&left, &mut scores)
        .unwrap_or_else(|e| unreachable(e));
    let snap = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    // Points on the left half (x < 0 in the camera = map frame) match the left segment.
    for (p, s) in snap.positions.iter().zip(&scores) {
        if p[0] < -0.1 {
            assert!(
                *s > 0.99,
                "left point {p:?} scores {s} against its own embedding"
            );
        } else if p[0] > 0.1 {
            assert!(
                *s < 0.51,
                "right point {p:?} scores {s} against the left embedding"
            );
        }
    }
}

/// Save → load → restore reproduces the map exactly (skipped for maps without `restore`), and
/// [`EmbeddingMap::coloured_points`] matches the snapshot.
pub fn check_save_load(build: MapFactory) {
    let mut map = build(DIM, 100_000);
    for i in 0..3 {
        let frame = plane_frame(i, 2.0);
        let e = half_segments(&frame, i);
        integrate(
            map.as_mut(),
            &frame,
            &pose(0.02 * i as f64, 0.0, 0.0, 0.0),
            &e,
        );
    }
    let snap = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    let points = map.coloured_points();
    assert!(
        points.vertices == snap.positions && points.colours == snap.colours,
        "coloured_points() disagrees with the snapshot's positions and colours"
    );
    assert!(
        points.triangles.is_empty(),
        "coloured_points() returned triangles"
    );
    let path = std::env::temp_dir().join(format!(
        "vlem-conformance-{}-{}.vlem",
        std::process::id(),
        map.name()
    ));
    vlem_core::write_map_file(&path, &snap).unwrap_or_else(|e| unreachable(e));
    let loaded = vlem_core::read_map_file(&path).unwrap_or_else(|e| unreachable(e));
    let _ = std::fs::remove_file(&path);
    assert!(loaded == snap, "the map file did not round-trip");
    let mut fresh = build(DIM, 100_000);
    match fresh.restore(loaded) {
        Ok(()) => {
            let restored = fresh
                .snapshot()
                .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
            assert!(
                restored.positions == snap.positions && restored.embeddings == snap.embeddings,
                "restoring a saved map changed it"
            );
        }
        Err(vlem_core::CoreError::Unsupported { .. }) => {}
        Err(e) => panic!("restore failed: {e}"),
    }
}

/// Elements outside the current view are never modified.
pub fn check_outside_view_untouched(build: MapFactory) {
    let mut map = build(DIM, 100_000);
    let frame = plane_frame(0, 2.0);
    integrate(
        map.as_mut(),
        &frame,
        &Pose::identity(),
        &half_segments(&frame, 0),
    );
    let before = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    // Turn around: the plane is now behind the camera.
    let back = pose(0.0, 0.0, 0.0, std::f64::consts::PI);
    let frame = plane_frame(1, 2.0);
    integrate(map.as_mut(), &frame, &back, &half_segments(&frame, 4));
    let after = map
        .snapshot()
        .unwrap_or_else(|e| panic!("the map's snapshot failed: {e}"));
    let old: std::collections::HashMap<[u32; 3], usize> = after
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| (p.map(f32::to_bits), i))
        .collect();
    let d = before.dim;
    for (i, p) in before.positions.iter().enumerate() {
        let Some(&j) = old.get(&p.map(f32::to_bits)) else {
            panic!("point {p:?} outside the view moved or vanished");
        };
        assert!(
            before.embeddings[i * d..(i + 1) * d] == after.embeddings[j * d..(j + 1) * d],
            "embedding of point {p:?} outside the view changed"
        );
    }
}

/// Queries score every element in `[0, 1]`; inputs of the wrong dimension are refused.
pub fn check_query_and_dimensions(build: MapFactory) {
    let mut map = build(DIM, 100_000);
    assert_eq!(map.dim(), DIM);
    let frame = plane_frame(0, 2.0);
    integrate(
        map.as_mut(),
        &frame,
        &Pose::identity(),
        &half_segments(&frame, 0),
    );
    let mut text = vec![0.0; DIM];
    text[1] = 1.0;
    let mut scores = Vec::new();
    map.similarity(&text, &mut scores)
        .unwrap_or_else(|e| unreachable(e));
    assert_eq!(scores.len(), map.len());
    assert!(scores.iter().all(|s| (0.0..=1.0).contains(s)));
    // Several texts at once score exactly as one at a time (one pass or the default loop).
    let mut other = vec![0.0; DIM];
    other[0] = 0.6;
    other[2] = 0.8;
    let mut many = Vec::new();
    map.similarity_many(&[&text, &other, &text], &mut many)
        .unwrap_or_else(|e| unreachable(e));
    let mut other_scores = Vec::new();
    map.similarity(&other, &mut other_scores)
        .unwrap_or_else(|e| unreachable(e));
    assert_eq!(many, vec![scores.clone(), other_scores, scores.clone()]);
    assert!(
        map.similarity_many(&[&text, &[1.0; 3]], &mut many).is_err(),
        "wrong query dimension accepted among several texts"
    );
    assert!(
        map.similarity(&[1.0; 3], &mut scores).is_err(),
        "wrong query dimension accepted"
    );
    let wrong = PixelEmbeddings::from_regions(64, 48, 3, vec![0; 64 * 48], vec![1.0, 0.0, 0.0])
        .unwrap_or_else(|e| unreachable(e));
    let err = map.integrate(&Observation {
        frame: &frame,
        pose: &Pose::identity(),
        embeddings: Some(&wrong),
    });
    assert!(
        err.is_err(),
        "embeddings of the wrong dimension were accepted"
    );
    let err = map.integrate(&Observation {
        frame: &frame,
        pose: &Pose::identity(),
        embeddings: None,
    });
    assert!(
        err.is_err(),
        "a frame without embeddings was accepted by a {DIM}-d map"
    );
}

/// Expands into one `#[test]` per map contract, for a [`MapFactory`]:
///
/// ```ignore
/// vlem_testkit::map_conformance!(|dim, max_points| {
///     Box::new(MyMap::new(dim, max_points)) as Box<dyn vlem_core::EmbeddingMap>
/// });
/// ```
#[macro_export]
macro_rules! map_conformance {
    ($build:expr) => {
        mod map_conformance {
            use super::*;
            const BUILD: $crate::map::MapFactory = $build;
            #[test]
            fn budget_is_never_exceeded() {
                $crate::map::check_budget(BUILD);
            }
            #[test]
            fn invalid_depth_never_reaches_the_map() {
                $crate::map::check_invalid_depth(BUILD);
            }
            #[test]
            fn static_scene_converges() {
                $crate::map::check_static_convergence(BUILD);
            }
            #[test]
            fn save_load_is_lossless() {
                $crate::map::check_save_load(BUILD);
            }
            #[test]
            fn outside_view_is_untouched() {
                $crate::map::check_outside_view_untouched(BUILD);
            }
            #[test]
            fn queries_and_dimensions() {
                $crate::map::check_query_and_dimensions(BUILD);
            }
        }
    };
}
