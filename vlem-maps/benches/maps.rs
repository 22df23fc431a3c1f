//! The three maps side by side on one sequence: integration and query time per frame, points and
//! bytes per point, in f32 and f16 (`cargo bench -p vlem-maps --bench maps`).
//!
//! Frames: the shared 150-frame living-room sequence (`../shared/data/icl-livingroom1`), or the
//! committed 30 frames when it is absent; `VLEM_BENCH_FRAMES=N` uses the first N. Embeddings: 512-d,
//! 300 segments per frame (32x32-pixel blocks) with random unit rows that stay fixed per block over
//! the sequence, the layout and size a SAM + CLIP encoder produces; and for the voxel map also a
//! 30x40 grid of 512-d patch embeddings (NARADIO's output shape), interpolated per pixel. Poses: the
//! dataset's. Each map runs with its defaults and a budget of 1M points (voxels, cells).
//! `VLEM_BENCH_MAPS=voxel` runs only the named maps.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "bench binary"
)]

mod common;

use std::time::Instant;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use vlem_core::{BuildContext, Observation, PixelEmbeddings, Registry, StageConfig};

const DIM: usize = 512;

fn main() {
    // Keep the map implementations linked (their registrations live in this crate).
    let _ = (
        vlem_maps::point_cloud::NAME,
        vlem_maps::voxel::NAME,
        vlem_maps::segment::NAME,
    );
    let (data, mut source, frames) = common::sequence();
    let frames: Vec<_> = (0..frames).map(|i| source.frame(i).unwrap()).collect();
    let (w, h) = (frames[0].colour.width(), frames[0].colour.height());
    let embeddings = block_embeddings(w, h);
    let mut text = vec![0.0f32; DIM];
    text[0] = 1.0;
    println!(
        "{} frames of {}, {DIM}-d embeddings, {} threads",
        frames.len(),
        data.display(),
        rayon::current_num_threads()
    );
    println!(
        "| map | embeddings | precision | integrate ms/frame (mean) | query ms | points | bytes | bytes/point |"
    );
    println!("|---|---|---|---:|---:|---:|---:|---:|");
    let only = std::env::var("VLEM_BENCH_MAPS").ok();
    let patches = patch_embeddings(w, h);
    let cases = [
        ("point-cloud", "segments", &embeddings),
        ("voxel", "segments", &embeddings),
        ("segment", "segments", &embeddings),
        ("voxel", "30x40 patches", &patches),
    ];
    for (kind, layout, embeddings) in cases {
        if only
            .as_deref()
            .is_some_and(|o| !o.split(',').any(|k| k == kind))
        {
            continue;
        }
        for precision in ["f32", "f16"] {
            let mut params = toml::Table::new();
            params.insert("precision".into(), precision.into());
            let budget_key = if kind == "voxel" {
                "max_voxels"
            } else {
                "max_points"
            };
            params.insert(budget_key.into(), toml::Value::Integer(1_000_000));
            let ctx = BuildContext {
                embedding_dim: Some(DIM),
                ..BuildContext::default()
            };
            let stage = StageConfig {
                kind: kind.into(),
                params,
            };
            let mut map = Registry::global().unwrap().build_map(&stage, &ctx).unwrap();
            let start = Instant::now();
            for frame in &frames {
                map.integrate(&Observation {
                    frame,
                    pose: frame.pose.as_ref().unwrap(),
                    embeddings: Some(embeddings),
                })
                .unwrap();
            }
            let per_frame = start.elapsed().as_secs_f64() * 1e3 / frames.len() as f64;
            let mut scores = Vec::new();
            let t = Instant::now();
            map.similarity(&text, &mut scores).unwrap();
            let query = t.elapsed().as_secs_f64() * 1e3;
            let (n, bytes) = (map.len(), map.memory_bytes());
            println!(
                "| {kind} | {layout} | {precision} | {per_frame:.0} | {query:.1} | {n} | {bytes} | {:.0} |",
                bytes as f64 / n.max(1) as f64
            );
        }
    }
}

/// A 30x40 grid of random patch embeddings (NARADIO's and dinov3's output shape at 640x480: 16-pixel
/// patches), fixed over the sequence; maps interpolate it per pixel.
fn patch_embeddings(w: u32, h: u32) -> PixelEmbeddings {
    let mut rng = StdRng::seed_from_u64(12);
    let (gw, gh) = (40u32, 30u32);
    let data = (0..(gw * gh) as usize * DIM)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    PixelEmbeddings::from_patch_grid(w, h, DIM, gw, gh, data).unwrap()
}

/// 32x32-pixel blocks, each with a fixed random unit embedding.
fn block_embeddings(w: u32, h: u32) -> PixelEmbeddings {
    let mut rng = StdRng::seed_from_u64(11);
    let blocks_x = w.div_ceil(32);
    let segments = (blocks_x * h.div_ceil(32)) as usize;
    let index = (0..w * h)
        .map(|i| (i % w) / 32 + (i / w) / 32 * blocks_x)
        .collect();
    let table = (0..segments * DIM)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    PixelEmbeddings::from_regions(w, h, DIM, index, table).unwrap()
}
