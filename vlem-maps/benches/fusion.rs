//! Benchmark of the point-cloud map's fusion step and of text queries (a bench binary, not a test).
//!
//! `cargo bench -p vlem-maps --bench fusion` fuses one real 640x480 frame (the living-room frame 1,
//! with 300 segments of random 11-d or 512-d embeddings) into maps of 100k and 1M points that lie
//! on the surfaces the frame sees (points of frame 0 in its pixel order, jittered by up to 3 mm), with
//! each association, without and with downsampling to the budget; beside each case, the memory
//! floor of its fusion, measured right after each run: reading and writing back the fused rows,
//! and writing the inserted rows into fresh memory. Then it times the fusion pass alone over
//! 1M x 512 rows in memory, beside its floor (`VLEM_BENCH_NO_PASS=1` skips it), and one text
//! query over 1M x 512 embeddings. It prints a table of medians (the floor ratio is the median of each run's ratio
//! to its own floor); BENCHMARKS.md records the numbers.
//!
//! One case at a time, e.g. for a profile: `VLEM_BENCH_DIMS=11 VLEM_BENCH_POINTS=1000000
//! VLEM_BENCH_ASSOCIATION=projective VLEM_BENCH_NO_QUERY=1` (each list comma-separated);
//! `VLEM_BENCH_PRECISION=f16` stores the map's embeddings as f16; `VLEM_BENCH_BUDGETS=none` (or
//! `map-size`) runs one of the two budgets. The scaling rows of BENCHMARKS.md:
//! `VLEM_BENCH_POINTS=100000,1000000,4000000 VLEM_BENCH_DIMS=11 VLEM_BENCH_ASSOCIATION=projective
//! VLEM_BENCH_BUDGETS=none`, with and without `VLEM_BENCH_PRECISION=f16`.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "bench binary"
)]

use std::path::Path;
use std::time::Instant;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use vlem_core::config::DatasetConfig;
use vlem_core::{
    EmbeddingMap, IntegrationStats, MapMetadata, MapSnapshot, Observation, PixelEmbeddings,
};
use vlem_maps::point_cloud::{Association, NAME, PointCloudConfig};
use vlem_maps::storage::Precision;

/// The dimension of the text query's embeddings (CLIP ViT-B/16).
const DIM: usize = 512;
const RUNS: usize = 5;

fn main() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/living-room");
    let mut source = vlem_datasets::open(&DatasetConfig::default(), &data).unwrap();
    let frame0 = source.frame(0).unwrap();
    let frame1 = source.frame(1).unwrap();
    let mut rng = StdRng::seed_from_u64(7);
    let surface = surface_points(&frame0);
    let precision = match std::env::var("VLEM_BENCH_PRECISION").as_deref() {
        Ok("f16") => Precision::F16,
        _ => Precision::F32,
    };
    println!(
        "threads: {}; embeddings stored as {precision:?}; frame 1 has {} valid depth pixels; frame 0 surface {} points",
        rayon::current_num_threads(),
        frame1.depth.valid_count(),
        surface.len()
    );
    println!(
        "| dim | map points | association | budget | median ms | min ms | fused | inserted | removed | floor ms (fused + new rows) | / floor | / fused-row floor | query ms |"
    );
    println!("|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let budgets: Vec<(&str, usize)> = match std::env::var("VLEM_BENCH_BUDGETS").as_deref() {
        Ok("none") => vec![("no downsampling", 4)],
        Ok("map-size") => vec![("at budget N = map size", 1)],
        _ => vec![("no downsampling", 4), ("at budget N = map size", 1)],
    };
    // 11-d: the colour-names encoder; 512-d: CLIP ViT-B/16.
    for dim in env_list("VLEM_BENCH_DIMS", &[11, DIM]) {
        let embeddings =
            region_embeddings(&mut rng, frame1.colour.width(), frame1.colour.height(), dim);
        for n in env_list("VLEM_BENCH_POINTS", &[100_000, 1_000_000]) {
            let snapshot = map_on_surface(&mut rng, &surface, n, dim);
            let associations = match std::env::var("VLEM_BENCH_ASSOCIATION").as_deref() {
                Ok("projective") => vec![Association::Projective],
                Ok("kd-tree") => vec![Association::KdTree],
                _ => vec![Association::Projective, Association::KdTree],
            };
            for association in associations {
                for &(label, budget_factor) in &budgets {
                    let config = PointCloudConfig {
                        max_points: budget_factor * n,
                        association,
                        precision,
                        ..PointCloudConfig::default()
                    };
                    let observation = Observation {
                        frame: &frame1,
                        pose: frame1.pose.as_ref().unwrap(),
                        embeddings: Some(&embeddings),
                    };
                    let (mut first, mut again) = (Vec::new(), Vec::new());
                    let (mut stats, mut again_stats) = (None, None);
                    let mut query_ms = 0.0;
                    // One map for the case, kept across its runs as a running pipeline keeps
                    // its map: a first, untimed frame sizes its per-frame buffers (the frame's
                    // points, the correspondences, the pixel grid), so that a timed frame costs
                    // what it costs a map that has been integrating rather than the first
                    // frame's allocations. Each run restores the same points into it.
                    let mut map = config.build(Some(dim)).unwrap();
                    let empty = MapSnapshot {
                        map_kind: NAME.into(),
                        dim,
                        positions: Vec::new(),
                        colours: Vec::new(),
                        embeddings: Vec::new(),
                        metadata: MapMetadata::default(),
                    };
                    for run in 0..=RUNS {
                        // The last run's table goes before the next copy is made, so that a
                        // 4M-point map at 512 dimensions and its copy need not fit at once.
                        map.restore(empty.clone()).unwrap();
                        map.restore(snapshot.clone()).unwrap();
                        // A map being built grows its tables by doubling, so a frame rarely
                        // reallocates them; a restored one holds exactly its points.
                        map.reserve(frame1.depth.valid_count());
                        let (ms, s) = timed_integrate(&mut map, &observation);
                        if run == 0 {
                            continue;
                        }
                        // This run's floor, measured right after it: on this VM the speed of
                        // memory, and above all what a fresh page costs, drift from one run to
                        // the next, so each run is set against its own floor. The new rows'
                        // part first, while memory is as the frame left it.
                        let new_rows = fresh_write_ms(s.inserted * dim);
                        if run == RUNS {
                            // One text query over the integrated map, as a user asks it.
                            let text = random_unit_rows(&mut rng, 1, dim);
                            let mut scores = Vec::new();
                            let t = Instant::now();
                            map.similarity(&text, &mut scores).unwrap();
                            query_ms = t.elapsed().as_secs_f64() * 1e3;
                        }
                        // Without downsampling, the same frame once more: the map now holds
                        // its points, so it fuses nearly all of them and grows by next to
                        // nothing, as a map does that sees a room it has mapped. No fresh
                        // pages, so this row is the fusion against the speed of memory alone.
                        let seen_again = (budget_factor > 1).then(|| {
                            let (ms, s) = timed_integrate(&mut map, &observation);
                            (ms, fresh_write_ms(s.inserted * dim), s)
                        });
                        // The fused rows' part once the map's table is gone, so that a 4M-point
                        // map at 512 dimensions and this pass's buffer need not fit at once.
                        map.restore(empty.clone()).unwrap();
                        first.push(Timed {
                            ms,
                            floor: Floor {
                                fused_rows: read_write_pass_ms(s.fused * dim),
                                new_rows,
                            },
                        });
                        if let Some((ms, new_rows, s)) = seen_again {
                            again.push(Timed {
                                ms,
                                floor: Floor {
                                    fused_rows: read_write_pass_ms(s.fused * dim),
                                    new_rows,
                                },
                            });
                            again_stats = Some(s);
                        }
                        stats = Some(s);
                    }
                    let case = format!("| {dim} | {n} | {association:?}");
                    print_row(&case, label, &first, &stats.unwrap(), query_ms);
                    if let Some(s) = again_stats {
                        print_row(&case, "the same frame again", &again, &s, query_ms);
                    }
                }
            }
        }
    }
    if std::env::var_os("VLEM_BENCH_NO_PASS").is_none() {
        fusion_pass_benchmark(&mut rng);
    }
    if std::env::var_os("VLEM_BENCH_NO_QUERY").is_none() {
        query_benchmark(&mut rng);
    }
}

/// The fusion pass alone, over 1M x 512 rows already in memory, beside the floor pass over the
/// same rows and the fusion as it was built before (blend, then `normalise`): whether the row
/// fusion runs at the speed of memory, without the frame's fresh pages and the rest of
/// `integrate` around it. Each round times the three in turn, so drift hits all three alike.
fn fusion_pass_benchmark(rng: &mut StdRng) {
    const ROUNDS: usize = 7;
    let (n, dim, map_weight) = (1_000_000, DIM, 0.5);
    let mut rows = random_unit_rows(rng, n, dim);
    let segments = random_unit_rows(rng, 300, dim);
    // Each row fuses with the segment its 32x32 block of a 640x480 frame would see.
    let segment_of = |i: usize| (i / 3000) % 300;
    let mut pass = |fuse: fn(&mut [f32], &[f32], f32)| {
        let t = Instant::now();
        rows.par_chunks_exact_mut(dim)
            .enumerate()
            .with_min_len(256)
            .for_each(|(i, row)| fuse(row, &segments[segment_of(i) * dim..][..dim], map_weight));
        t.elapsed().as_secs_f64() * 1e3
    };
    let (mut floor, mut before, mut now) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        floor.push(pass(|row, _, _| row.iter_mut().for_each(|x| *x *= 0.999_9)));
        before.push(pass(blend_then_normalise));
        now.push(pass(vlem_maps::storage::fuse_into));
    }
    let median = |v: &[f64]| {
        let mut v = v.to_vec();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let ratio = |v: &[f64]| median(&v.iter().zip(&floor).map(|(t, f)| t / f).collect::<Vec<_>>());
    println!(
        "fusion pass over {n} x {dim} rows in memory (median of {ROUNDS} rounds): floor {:.1} ms; blend then normalise (before) {:.1} ms, {:.2}x the floor; `fuse_into` {:.1} ms, {:.2}x",
        median(&floor),
        median(&before),
        ratio(&before),
        median(&now),
        ratio(&now)
    );
}

/// The row fusion as the library built it before `fuse_into`'s one-pass AVX2 build.
fn blend_then_normalise(map: &mut [f32], observed: &[f32], map_weight: f32) {
    for (m, p) in map.iter_mut().zip(observed) {
        *m = (1.0 - map_weight) * p + map_weight * *m;
    }
    if !vlem_core::embeddings::normalise(map) {
        map.copy_from_slice(observed);
    }
}

/// The comma-separated numbers in environment variable `name`, `default` where it is unset.
fn env_list(name: &str, default: &[usize]) -> Vec<usize> {
    std::env::var(name).map_or_else(
        |_| default.to_vec(),
        |v| v.split(',').map(|x| x.trim().parse().unwrap()).collect(),
    )
}

/// Integrates `observation` into `map`: the time in ms and the map's report.
fn timed_integrate(
    map: &mut impl EmbeddingMap,
    observation: &Observation<'_>,
) -> (f64, IntegrationStats) {
    let t = Instant::now();
    let stats = map.integrate(observation).unwrap();
    (t.elapsed().as_secs_f64() * 1e3, stats)
}

/// One timed frame and the floor measured right after it.
struct Timed {
    ms: f64,
    floor: Floor,
}

/// Prints the table row of the `runs` of one case (`case`: its first three columns).
fn print_row(case: &str, label: &str, runs: &[Timed], stats: &IntegrationStats, query_ms: f64) {
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let times = || runs.iter().map(|r| r.ms);
    let min = times().fold(f64::INFINITY, f64::min);
    let floor_fused = median(runs.iter().map(|r| r.floor.fused_rows).collect());
    let floor_new = median(runs.iter().map(|r| r.floor.new_rows).collect());
    // Each run against its own floor.
    let ratio = median(
        runs.iter()
            .map(|r| r.ms / (r.floor.fused_rows + r.floor.new_rows))
            .collect(),
    );
    let fused_ratio = median(runs.iter().map(|r| r.ms / r.floor.fused_rows).collect());
    println!(
        "{case} | {label} | {:.1} | {min:.1} | {} | {} | {} | {floor_fused:.1} + {floor_new:.1} | {ratio:.2} | {fused_ratio:.2} | {query_ms:.1} |",
        median(times().collect()),
        stats.fused,
        stats.inserted,
        stats.removed,
    );
}

/// One run's memory floor, in ms: the least any fusion of its rows can cost on this machine.
struct Floor {
    /// Reading and writing back every fused row once ([`read_write_pass_ms`]).
    fused_rows: f64,
    /// Writing the inserted rows into memory never touched before ([`fresh_write_ms`]).
    new_rows: f64,
}

/// The time of one parallel pass that reads and writes `values` floats in memory already
/// touched (each fused embedding is read and written back once), on as many threads as the
/// fusion uses; the median of three passes.
fn read_write_pass_ms(values: usize) -> f64 {
    let mut buffer = vec![1.0f32; values];
    let mut times: Vec<f64> = (0..3)
        .map(|_| {
            let t = Instant::now();
            buffer
                .par_chunks_mut(1 << 16)
                .for_each(|chunk| chunk.iter_mut().for_each(|x| *x *= 0.999_9));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    std::hint::black_box(&buffer);
    times.sort_by(f64::total_cmp);
    times[1]
}

/// The time of writing `values` floats, in parallel, into memory the process has never touched:
/// what a map's new rows cost at least. A growing map writes them past the end of its table, in
/// pages that each cost a fault on first touch, and on a VM whatever the host charges for backing
/// the page. At least 32 MiB is allocated so that the allocator maps fresh pages (glibc maps any
/// request that large) instead of handing back its heap.
fn fresh_write_ms(values: usize) -> f64 {
    let mut fresh: Vec<f32> = Vec::with_capacity(values.max((32 << 20) / 4 + 1024));
    let t = Instant::now();
    fresh.par_extend(rayon::iter::repeat_n(0.0f32, values));
    let ms = t.elapsed().as_secs_f64() * 1e3;
    std::hint::black_box(&fresh);
    ms
}

/// 300 segments (32x32-pixel blocks) with random unit 512-d embeddings, like SAM + CLIP output.
fn region_embeddings(rng: &mut StdRng, w: u32, h: u32, dim: usize) -> PixelEmbeddings {
    let blocks_x = w.div_ceil(32);
    let index = (0..w * h)
        .map(|i| (i % w) / 32 + (i / w) / 32 * blocks_x)
        .collect();
    let segments = (blocks_x * h.div_ceil(32)) as usize;
    let table = random_unit_rows(rng, segments, dim);
    PixelEmbeddings::from_regions(w, h, dim, index, table).unwrap()
}

fn random_unit_rows(rng: &mut StdRng, n: usize, dim: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n * dim)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    for row in v.chunks_exact_mut(dim) {
        vlem_core::embeddings::normalise(row);
    }
    v
}

/// The world points of every valid pixel of `frame`.
fn surface_points(frame: &vlem_core::Frame) -> Vec<[f32; 3]> {
    let k = &frame.intrinsics;
    let pose = frame.pose.unwrap();
    let mut out = Vec::new();
    for v in 0..k.height {
        for u in 0..k.width {
            if let Some(z) = frame.depth.get(u, v) {
                let p = pose * k.back_project(f64::from(u), f64::from(v), f64::from(z));
                out.push([p.x as f32, p.y as f32, p.z as f32]);
            }
        }
    }
    out
}

/// `n` points sampled from the surface with up to 3 mm jitter, random unit embeddings.
///
/// The points are stored in the order of the frame-0 pixels they were drawn from, the row-major
/// order in which a map inserts a frame's points; a shuffled table would make every fused row a
/// cache miss that no real map has.
fn map_on_surface(rng: &mut StdRng, surface: &[[f32; 3]], n: usize, dim: usize) -> MapSnapshot {
    let mut drawn: Vec<usize> = (0..n).map(|_| rng.random_range(0..surface.len())).collect();
    drawn.sort_unstable();
    let positions = drawn
        .into_iter()
        .map(|i| surface[i].map(|x| x + rng.random_range(-0.003f32..0.003)))
        .collect();
    MapSnapshot {
        map_kind: NAME.into(),
        dim,
        positions,
        colours: vec![[128, 128, 128]; n],
        embeddings: random_unit_rows(rng, n, dim),
        metadata: MapMetadata::default(),
    }
}

fn query_benchmark(rng: &mut StdRng) {
    let n = 1_000_000;
    let embeddings = random_unit_rows(rng, n, DIM);
    let text = random_unit_rows(rng, 1, DIM);
    let mut out = Vec::new();
    let mut times = Vec::new();
    for _ in 0..10 {
        let t = Instant::now();
        vlem_core::query::normalised_similarity(&embeddings, DIM, &text, &mut out).unwrap();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    let bytes = (n * DIM * 4) as f64;
    println!(
        "text query over {n} x {DIM} f32 ({:.0} MB): median {:.1} ms, min {:.1} ms ({:.1} GB/s)",
        bytes / 1e6,
        times[5],
        times[0],
        bytes / times[0] / 1e6
    );
}
