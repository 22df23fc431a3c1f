//! Dense tracking timing on the committed living-room frames (640×480):
//! `cargo bench -p vlem-trackers --bench odometry`. Prints milliseconds per frame for preparing
//! the pyramid and for registering consecutive frames, per method, then for both trackers end to
//! end. `RAYON_NUM_THREADS` sets the thread count; `VLEM_BENCH_SEQUENCE=DIR` times another
//! RGB-D folder (all its frames are loaded first, so loading is not timed).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "bench binary")]

use std::path::Path;
use std::time::Instant;

use nalgebra::Isometry3;
use vlem_core::Tracker;
use vlem_core::config::DatasetConfig;
use vlem_trackers::frame_to_model::{FrameToModelConfig, FrameToModelTracker};
use vlem_trackers::odometry::{Method, OdometryConfig, OdometryTracker, Pyramid, register};

fn main() {
    let dir = std::env::var_os("VLEM_BENCH_SEQUENCE").map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/living-room"),
        std::path::PathBuf::from,
    );
    let mut source = vlem_datasets::open(&DatasetConfig::default(), &dir).unwrap();
    let frames: Vec<_> = (0..source.len())
        .map(|i| source.frame(i).unwrap())
        .collect();
    println!(
        "{} frames {}x{}, {} threads",
        frames.len(),
        frames[0].intrinsics.width,
        frames[0].intrinsics.height,
        rayon::current_num_threads()
    );
    for method in [Method::Hybrid, Method::PointToPlane, Method::Intensity] {
        let config = OdometryConfig {
            method,
            ..OdometryConfig::default()
        };
        let pyramids: Vec<Pyramid> = frames
            .iter()
            .map(|f| Pyramid::build(&f.colour, &f.depth, &f.intrinsics, &config.pyramid_params()))
            .collect();
        // Rebuilding into existing buffers, as the trackers do.
        let mut scratch = pyramids[0].clone();
        let t = Instant::now();
        for f in &frames {
            scratch.rebuild(&f.colour, &f.depth, &f.intrinsics, &config.pyramid_params());
        }
        let prepare = t.elapsed().as_secs_f64() * 1e3 / frames.len() as f64;
        let t = Instant::now();
        let mut iterations = 0;
        for pair in pyramids.windows(2) {
            let r = register(&pair[1], &pair[0], &Isometry3::identity(), &config).unwrap();
            iterations += r.iterations;
        }
        let solve = t.elapsed().as_secs_f64() * 1e3 / (frames.len() - 1) as f64;
        println!(
            "{method:?}: prepare {prepare:.1} ms/frame, register {solve:.1} ms/pair ({:.1} iterations), total {:.1} ms/frame",
            iterations as f64 / (frames.len() - 1) as f64,
            prepare + solve
        );
    }
    let trackers: Vec<Box<dyn Tracker>> = vec![
        Box::new(OdometryTracker::new(OdometryConfig::default()).unwrap()),
        Box::new(FrameToModelTracker::new(FrameToModelConfig::default()).unwrap()),
    ];
    for mut tracker in trackers {
        let t = Instant::now();
        for frame in &frames {
            tracker.track(frame).unwrap();
        }
        println!(
            "{}: {:.1} ms/frame end to end",
            tracker.name(),
            t.elapsed().as_secs_f64() * 1e3 / frames.len() as f64
        );
    }
}
