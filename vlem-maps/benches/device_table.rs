//! Benchmark of the maps' device table (`[map] device`) beside the host table, on the same rows:
//! fusing one 640×480 frame's region embeddings into a map, appending a frame's new rows, and a
//! text query of one and of eight texts (bench binary, not a test).
//!
//! `cargo bench -p vlem-maps --features candle --bench device_table` runs on candle's CPU device;
//! with `--features cuda` and `VLEM_BENCH_DEVICE=cuda` on a GPU (what `bench/gpu/check.sh` part 5
//! runs). The map holds `VLEM_BENCH_POINTS` rows (default 1,000,000) of 512-d unit embeddings in
//! `VLEM_BENCH_PRECISION` (default `f16`, the GPU configs' setting); the frame has 300 segments and
//! fuses `VLEM_BENCH_FUSED` map rows (default 250,000, about what a 640×480 frame matches in a
//! dense map) and appends 50,000. Times are medians of 10 runs, each ended by a device
//! synchronisation, with the host table's time for the same operation beside them.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "bench binary"
)]

use std::time::Instant;

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use vlem_backends::ComputeDevice;
use vlem_core::PixelEmbeddings;
use vlem_maps::storage::{DeviceTable, EmbeddingStore, FrameTable, Lookups, Precision, fuse_into};

const DIM: usize = 512;
const RUNS: usize = 10;
const SEGMENTS: usize = 300;
const APPENDED: usize = 50_000;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.replace('_', "").parse().ok())
        .unwrap_or(default)
}

fn unit_rows(rng: &mut StdRng, rows: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..rows * DIM)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    v.chunks_exact_mut(DIM).for_each(|r| {
        vlem_core::embeddings::normalise(r);
    });
    v
}

fn median_ms(mut run: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..RUNS)
        .map(|_| {
            let start = Instant::now();
            run();
            start.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[RUNS / 2]
}

fn main() {
    let points = env_usize("VLEM_BENCH_POINTS", 1_000_000);
    let fused = env_usize("VLEM_BENCH_FUSED", 250_000).min(points);
    let precision = match std::env::var("VLEM_BENCH_PRECISION").as_deref() {
        Ok("f32") => Precision::F32,
        _ => Precision::F16,
    };
    let asked = ComputeDevice::from_env("VLEM_BENCH_DEVICE").unwrap();
    let device = asked.open().unwrap();
    let sync = || device.synchronize().unwrap();
    let mut rng = StdRng::seed_from_u64(11);
    println!(
        "device {asked}; {points} rows × {DIM} in {precision:?}; a 640x480 frame of {SEGMENTS} \
         segments fusing {fused} rows and appending {APPENDED}; median of {RUNS} runs"
    );

    let rows = unit_rows(&mut rng, points);
    let mut host = EmbeddingStore::from_f32(DIM, precision, rows.clone());
    let mut table = DeviceTable::new(&device, DIM, precision, points + APPENDED).unwrap();
    table.replace(&rows).unwrap();
    drop(rows);
    sync();

    // The frame: a segment per pixel, and which map rows fuse with which pixel.
    let (w, h) = (640u32, 480u32);
    let index: Vec<u32> = (0..w * h)
        .map(|_| rng.random_range(0..SEGMENTS as u32))
        .collect();
    let segment_table = unit_rows(&mut rng, SEGMENTS);
    let embeddings =
        PixelEmbeddings::from_regions(w, h, DIM, index.clone(), segment_table.clone()).unwrap();
    let mut map_rows: Vec<u32> = (0..points as u32).collect();
    map_rows.shuffle(&mut rng);
    map_rows.truncate(fused);
    let pixels: Vec<u32> = (0..fused).map(|_| rng.random_range(0..w * h)).collect();

    let fuse_device = median_ms(|| {
        let frame = FrameTable::upload(&embeddings, &table).unwrap();
        let mut lookups = Lookups::default();
        frame.lookups(&mut lookups);
        for &p in &pixels {
            frame.push(p, &mut lookups);
        }
        table.fuse(&frame, &map_rows, &lookups, 0.5).unwrap();
        sync();
    });
    // The host table's fusion of the same rows, as the point-cloud map runs it (one parallel
    // pass over the table, the rows without a match skipped).
    let mut pixel_of_row = vec![u32::MAX; points];
    for (&r, &p) in map_rows.iter().zip(&pixels) {
        pixel_of_row[r as usize] = p;
    }
    let fuse_host = median_ms(|| {
        host.par_update_rows_from(0, |i, row| {
            let p = pixel_of_row[i];
            if p == u32::MAX {
                return false;
            }
            let s = index[p as usize] as usize;
            fuse_into(row, &segment_table[s * DIM..(s + 1) * DIM], 0.5);
            true
        });
    });
    println!("fuse one frame: device {fuse_device:.2} ms, host {fuse_host:.2} ms");

    let append_device = median_ms(|| {
        let frame = FrameTable::upload(&embeddings, &table).unwrap();
        let mut lookups = Lookups::default();
        frame.lookups(&mut lookups);
        for &p in &pixels[..APPENDED.min(pixels.len())] {
            frame.push(p, &mut lookups);
        }
        table.append(&frame, &lookups).unwrap();
        sync();
        table.truncate(points);
    });
    println!("append {APPENDED} rows: device {append_device:.2} ms");

    for texts in [1usize, 8] {
        let queries = unit_rows(&mut rng, texts);
        let queries: Vec<&[f32]> = queries.chunks_exact(DIM).collect();
        let mut out = Vec::new();
        let device_ms = median_ms(|| {
            table.similarity_many(&queries, &mut out).unwrap();
        });
        let host_ms = median_ms(|| {
            host.similarity_many(&queries, &mut out).unwrap();
        });
        println!(
            "query of {texts} text(s), scores on the host: device {device_ms:.2} ms, host {host_ms:.2} ms"
        );
    }
}
