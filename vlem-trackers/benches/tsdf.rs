//! Timing of the TSDF volume on the committed ICL-NUIM living-room frames (640x480), at the
//! dataset poses: `cargo bench -p vlem-trackers --bench tsdf`.
//!
//! Prints milliseconds per call of `integrate`, `raycast` (at the pose just integrated),
//! `raycast_near_depth` (the same cast with rays starting near the depth just fused, as
//! frame-to-model tracking casts), `extract_mesh` and `extract_points`, with the block count and
//! memory of the final volume, and how often the two casts agree.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "benchmark binary")]

use std::path::Path;
use std::time::Instant;

use vlem_core::Frame;
use vlem_core::config::DatasetConfig;
use vlem_trackers::tsdf::{RaycastOptions, TsdfConfig, TsdfVolume};

fn ms(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

/// CPU time of the whole process (all threads) in ms, from `/proc/self/stat` (10 ms ticks, so
/// only sums over many calls are meaningful); 0 where unavailable. Unlike wall time it does
/// not grow when other processes compete for the cores.
fn cpu_ms() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    let Some(rest) = stat.rsplit(')').next() else {
        return 0.0;
    };
    // After the command name: state is field 3, utime and stime are fields 14 and 15.
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields[11..13]
        .iter()
        .map(|f| f.parse::<f64>().unwrap_or(0.0))
        .sum();
    ticks * 10.0
}

/// Wall and CPU time of phases, summed over calls.
#[derive(Default)]
struct Timer {
    wall: Vec<f64>,
    cpu: f64,
}

impl Timer {
    fn time<T>(&mut self, f: impl FnOnce() -> T) -> T {
        let (t, c) = (Instant::now(), cpu_ms());
        let out = f();
        self.wall.push(ms(t));
        self.cpu += cpu_ms() - c;
        out
    }

    fn print(&mut self, name: &str) {
        let times = &mut self.wall;
        times.sort_by(f64::total_cmp);
        let n = times.len() as f64;
        let mean = times.iter().sum::<f64>() / n;
        let median = times[times.len() / 2];
        println!(
            "{name:<26} wall mean {mean:7.2} ms  median {median:7.2} ms   cpu {:7.2} ms/call  ({} calls)",
            self.cpu / n,
            times.len()
        );
    }
}

fn main() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/living-room");
    let mut source = vlem_datasets::open(&DatasetConfig::default(), &dir).expect("dataset");
    let frames: Vec<Frame> = (0..source.len())
        .map(|i| source.frame(i).expect("frame"))
        .collect();
    let k = frames[0].intrinsics;
    println!(
        "{} frames {}x{}, rayon threads {}",
        frames.len(),
        k.width,
        k.height,
        rayon::current_num_threads()
    );

    let rounds = 3;
    let mut integrate = Timer::default();
    let mut raycast = Timer::default();
    let mut raycast_normals = Timer::default();
    let mut raycast_near = Timer::default();
    let mut hits = 0.0;
    // Pixels where both casts hit, their depths within 0.1 mm / exactly equal, and pixels
    // where only one hits.
    let (mut both, mut close, mut equal, mut one) = (0_usize, 0_usize, 0_usize, 0_usize);
    let mut differences: Vec<f32> = Vec::new();
    let mut volume = TsdfVolume::new(TsdfConfig::default()).expect("config");
    for round in 0..rounds {
        volume = TsdfVolume::new(TsdfConfig::default()).expect("config");
        for frame in &frames {
            let pose = frame.pose.expect("pose");
            integrate.time(|| volume.integrate(&frame.depth, &frame.colour, &k, &pose));
            let cast = raycast.time(|| volume.raycast(&k, &pose));
            hits += cast.hit_count() as f64 / (k.width * k.height) as f64;
            let options = RaycastOptions::default();
            let near =
                raycast_near.time(|| volume.raycast_near_depth(&k, &pose, &options, &frame.depth));
            if round == 0 {
                for (a, b) in cast.depth.as_raw().iter().zip(near.depth.as_raw()) {
                    match (*a > 0.0, *b > 0.0) {
                        (true, true) => {
                            both += 1;
                            close += usize::from((a - b).abs() <= 1e-4);
                            equal += usize::from(a == b);
                            differences.push((a - b).abs());
                        }
                        (false, false) => {}
                        _ => one += 1,
                    }
                }
            }
            if round == 0 {
                let options = RaycastOptions {
                    normals: true,
                    ..RaycastOptions::default()
                };
                let cast = raycast_normals.time(|| volume.raycast_with(&k, &pose, &options));
                std::hint::black_box(cast);
            }
        }
    }
    integrate.print("integrate");
    raycast.print("raycast (depth + colour)");
    raycast_normals.print("raycast (+ normals)");
    raycast_near.print("raycast_near_depth");
    differences.sort_by(f32::total_cmp);
    let quantile = |q: f64| 1e3 * differences[((differences.len() - 1) as f64 * q) as usize];
    println!(
        "raycast_near_depth against raycast, depth difference where both hit: median {:.3} mm, \
         99th percentile {:.3} mm, 99.9th {:.3} mm, largest {:.1} mm",
        quantile(0.5),
        quantile(0.99),
        quantile(0.999),
        quantile(1.0)
    );
    println!(
        "raycast_near_depth against raycast: {:.3} % of the hits equal, {:.3} % within 0.1 mm, \
         {:.3} % of the pixels hit by one cast only",
        100.0 * equal as f64 / both as f64,
        100.0 * close as f64 / both as f64,
        100.0 * one as f64 / (frames.len() * (k.width * k.height) as usize) as f64,
    );
    println!(
        "raycast hit rate {:.1} %",
        100.0 * hits / (rounds * frames.len()) as f64
    );
    println!(
        "after {} frames: {} blocks, {:.1} MiB",
        volume.frame_count(),
        volume.block_count(),
        volume.memory_bytes() as f64 / (1024.0 * 1024.0)
    );

    let mut mesh_times = Timer::default();
    let mut point_times = Timer::default();
    let mut sizes = (0, 0, 0);
    for _ in 0..3 {
        let mesh = mesh_times.time(|| volume.extract_mesh());
        let points = point_times.time(|| volume.extract_points());
        sizes = (
            mesh.vertices.len(),
            mesh.triangles.len(),
            points.vertices.len(),
        );
    }
    mesh_times.print("extract_mesh");
    point_times.print("extract_points");
    println!(
        "mesh: {} vertices, {} triangles; points: {}",
        sizes.0, sizes.1, sizes.2
    );
}
