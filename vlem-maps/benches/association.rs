//! Projective association against the k-d tree on a real sequence: how often the two choose the
//! same correspondence, and what each costs (`cargo bench -p vlem-maps --bench association`).
//!
//! Frames: the shared 150-frame living-room sequence (`../shared/data/icl-livingroom1`), or the
//! committed 30 frames when it is absent; `VLEM_BENCH_FRAMES=N` uses the first N. Each frame is
//! integrated into a geometry-only point-cloud map (default parameters: 2 cm, window 3, budget
//! 1M) with the dataset's poses; before it is, both associations are asked for every map point's
//! correspondence in it. "Same" counts map points for which both give the same pixel or both give
//! none; the map is built with the association named by `VLEM_BENCH_ASSOCIATION` (`projective`,
//! the default, or `kd-tree`).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "bench binary"
)]

mod common;

use std::time::Instant;

use vlem_core::{EmbeddingMap, Observation};
use vlem_maps::point_cloud::{Association, PointCloudConfig};

fn main() {
    let (data, mut source, frames) = common::sequence();
    let association = match std::env::var("VLEM_BENCH_ASSOCIATION").as_deref() {
        Ok("kd-tree") => Association::KdTree,
        _ => Association::Projective,
    };
    let window = std::env::var("VLEM_BENCH_WINDOW")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(PointCloudConfig::default().window);
    let config = PointCloudConfig {
        association,
        window,
        ..PointCloudConfig::default()
    };
    let mut map = config.build(None).unwrap();
    println!(
        "{frames} frames of {}, map built with {association:?}, {} threads",
        data.display(),
        rayon::current_num_threads()
    );
    let (mut compared, mut same, mut both_found, mut only_kd, mut only_projective) =
        (0usize, 0usize, 0usize, 0usize, 0usize);
    let (mut kd_ms, mut projective_ms, mut integrate_ms) = (0.0f64, 0.0f64, 0.0f64);
    for index in 0..frames {
        let frame = source.frame(index).unwrap();
        let pose = frame.pose.unwrap();
        let obs = Observation {
            frame: &frame,
            pose: &pose,
            embeddings: None,
        };
        if index > 0 {
            let t = Instant::now();
            let kd = map
                .correspondence_pixels(&obs, Association::KdTree)
                .unwrap();
            kd_ms += t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let projective = map
                .correspondence_pixels(&obs, Association::Projective)
                .unwrap();
            projective_ms += t.elapsed().as_secs_f64() * 1e3;
            for (a, b) in kd.iter().zip(&projective) {
                compared += 1;
                same += usize::from(a == b);
                match (a, b) {
                    (Some(_), Some(_)) => both_found += 1,
                    (Some(_), None) => only_kd += 1,
                    (None, Some(_)) => only_projective += 1,
                    (None, None) => {}
                }
            }
        }
        let t = Instant::now();
        map.integrate(&obs).unwrap();
        integrate_ms += t.elapsed().as_secs_f64() * 1e3;
    }
    let pct = |n: usize| 100.0 * n as f64 / compared.max(1) as f64;
    let asked = (frames.saturating_sub(1)).max(1) as f64;
    println!("map points compared (summed over frames): {compared}");
    println!(
        "same correspondence (or both none): {:.2} %; both found one: {:.2} %; only the k-d tree: {:.3} %; only projective: {:.3} %",
        pct(same),
        pct(both_found),
        pct(only_kd),
        pct(only_projective)
    );
    println!(
        "mean ms per frame: k-d tree correspondences {:.1}, projective {:.1} (each including the back-projection), integrate {:.1}; final map {} points",
        kd_ms / asked,
        projective_ms / asked,
        integrate_ms / frames.max(1) as f64,
        map.len()
    );
}
