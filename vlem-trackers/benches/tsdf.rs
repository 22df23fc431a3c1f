//! Timing of the TSDF volume on the committed ICL-NUIM living-room frames (640x480), at the
//! dataset poses: `cargo bench -p vlem-trackers --bench tsdf`.
//!
//! Prints milliseconds per call of `integrate`, `raycast` (at the pose just integrated, as
//! frame-to-model tracking does), `extract_mesh` and `extract_points`, with the block count and
//! memory of the final volume.
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
    let mut hits = 0.0;
    let mut volume = TsdfVolume::new(TsdfConfig::default()).expect("config");
    for round in 0..rounds {
        volume = TsdfVolume::new(TsdfConfig::default()).expect("config");
        for frame in &frames {
            let pose = frame.pose.expect("pose");
            integrate.time(|| volume.integrate(&frame.depth, &frame.colour, &k, &pose));
            let cast = raycast.time(|| volume.raycast(&k, &pose));
            hits += cast.hit_count() as f64 / (k.width * k.height) as f64;
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
