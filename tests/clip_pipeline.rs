//! The segment-embedding pipeline end to end: `configs/synthetic-clip.toml` (synthetic scene,
//! `graph` regions, the `clip` encoder on the tiny random-weight CLIP committed in
//! `vlem-backends/goldens/clip/`, a point-cloud map) built through the registry as the `vlem`
//! binary builds it, run on a few small frames. Checks that exactly the pixels inside a region
//! (with valid depth) become map points, that the map has the CLIP projection's dimension and
//! that a text query scores every point with a finite normalised cosine.
#![cfg(feature = "cli")]
#![cfg(all(feature = "clip", feature = "graph", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

// Link the crates whose stages the config names (registrations of unreferenced crates vanish).
use vlem_backends as _;
use vlem_maps as _;

mod common;
use vlem_trackers as _;

use std::path::PathBuf;

use vlem_core::pipeline::Pipeline;
use vlem_core::types::valid_depth;
use vlem_core::{BuildContext, Config, Registry};

/// The tiny CLIP folder of the goldens, relative to `configs/`.
const TINY_CLIP: &str = "../vlem-backends/goldens/clip/tiny-quick-gelu";

fn configs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("configs")
}

/// The shipped config, shrunk to `frames` frames of 160x120 (the region settings scaled along).
fn config(frames: usize) -> (Config, BuildContext) {
    let mut config = Config::from_file(&configs().join("synthetic-clip.toml")).unwrap();
    let synthetic = config.dataset.params["synthetic"].as_table_mut().unwrap();
    synthetic.insert("frames".into(), (frames as i64).into());
    synthetic.insert("width".into(), 160.into());
    synthetic.insert("height".into(), 120.into());
    let proposer = config.proposer.as_mut().unwrap();
    proposer.params.insert("min_size".into(), 50.into());
    proposer.params.insert("max_regions".into(), 8.into());
    let ctx = BuildContext {
        config_dir: configs(),
        embedding_dim: None,
    };
    (config, ctx)
}

#[test]
fn shipped_config_builds_every_stage_through_the_registry() {
    let config = Config::from_file(&configs().join("synthetic-clip.toml")).unwrap();
    assert_eq!(config.proposer.as_ref().unwrap().kind, "graph");
    assert_eq!(config.encoder.as_ref().unwrap().kind, "clip");
    let ctx = BuildContext {
        config_dir: configs(),
        embedding_dim: None,
    };
    let pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let encoder = pipeline.encoder().unwrap();
    assert_eq!((encoder.name(), encoder.dim()), ("clip", 16));
    assert!(encoder.needs_regions());
    assert_eq!(pipeline.map().unwrap().dim(), 16);
}

/// The real-time CPU config: every stage but the encoder builds with its keys, and the encoder
/// asks for the model folder it names (no CLIP weights ship with the repository), unless the
/// tiny test model is swapped in.
#[test]
fn realtime_cpu_config_builds_with_a_model_folder() {
    let mut config = Config::from_file(&configs().join("realtime-cpu-clip.toml")).unwrap();
    let ctx = BuildContext {
        config_dir: configs(),
        embedding_dim: None,
    };
    let registry = Registry::global().unwrap();
    registry
        .build_proposer(config.proposer.as_ref().unwrap(), &ctx)
        .unwrap();
    let err = registry
        .build_encoder(config.encoder.as_ref().unwrap(), &ctx)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("clip-vit-base-patch16"), "{err}");
    let encoder = config.encoder.as_mut().unwrap();
    encoder.params.insert("model_dir".into(), TINY_CLIP.into());
    let pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    assert_eq!(pipeline.encoder().unwrap().name(), "clip");
}

/// The real-time GPU config: in a build without `cuda` the encoder says so and how to get one;
/// on the CPU (its device key switched) it builds as it is.
#[test]
fn realtime_cuda_config_asks_for_the_gpu_it_names() {
    let (mut config, ctx) = common::gpu_config("realtime-cuda-clip.toml", TINY_CLIP);
    assert_eq!(config.tracker.kind, "frame-to-model");
    common::on_the_cpu(&mut config);
    let pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    assert_eq!(pipeline.encoder().unwrap().name(), "clip");
}

#[test]
fn one_frame_maps_exactly_the_pixels_inside_regions() {
    let (config, ctx) = config(1);
    let registry = Registry::global().unwrap();
    let proposer = registry
        .build_proposer(config.proposer.as_ref().unwrap(), &ctx)
        .unwrap();
    let encoder = registry
        .build_encoder(config.encoder.as_ref().unwrap(), &ctx)
        .unwrap();
    let mut source = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let frame = source.frame(0).unwrap();

    // What the stages make of the frame: the encoder embeds the union of the region masks.
    let regions = proposer.propose(&frame.colour).unwrap();
    assert!(!regions.is_empty());
    let embeddings = encoder.encode_frame(&frame, &regions).unwrap();
    let (w, h) = (frame.colour.width(), frame.colour.height());
    let (mut covered_with_depth, mut uncovered_with_depth) = (0usize, 0usize);
    for v in 0..h {
        for u in 0..w {
            let inside = regions.iter().any(|r| r.contains(u, v));
            assert_eq!(
                embeddings.has_embedding(u, v),
                inside,
                "pixel ({u}, {v}): embedded iff inside a region"
            );
            if frame.depth.get(u, v).and_then(valid_depth).is_some() {
                if inside {
                    covered_with_depth += 1;
                } else {
                    uncovered_with_depth += 1;
                }
            }
        }
    }
    // With max_regions the smaller segments get no region: the check below can tell.
    assert!(uncovered_with_depth > 0 && covered_with_depth > 0);

    // The pipeline: the first frame inserts one point per embedded pixel with depth, no more.
    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let mut source = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let report = pipeline.run(source.as_mut(), None, &|_| {}).unwrap();
    assert_eq!(report.frames_processed, 1);
    assert_eq!(pipeline.map().unwrap().len(), covered_with_depth);
}

#[test]
fn a_few_frames_give_a_map_that_text_queries_score() {
    let (config, ctx) = config(3);
    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let mut source = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let report = pipeline.run(source.as_mut(), None, &|_| {}).unwrap();
    assert_eq!(report.frames_processed, 3);
    assert!(report.stage_ms.contains_key("propose"));
    assert!(report.stage_ms.contains_key("encode"));

    let map = pipeline.map().unwrap();
    assert_eq!(map.dim(), 16, "the map takes the CLIP projection dimension");
    assert!(!map.is_empty());

    let encoder = pipeline.encoder().unwrap();
    let mut scores = Vec::new();
    let mut previous: Option<Vec<f32>> = None;
    for text in &config.query.texts {
        let query = encoder.encode_text(text).unwrap();
        assert_eq!(query.len(), 16);
        map.similarity(&query, &mut scores).unwrap();
        assert_eq!(scores.len(), map.len());
        assert!(
            scores
                .iter()
                .all(|s| s.is_finite() && (-1e-4..=1.0 + 1e-4).contains(s)),
            "{text}: scores must be finite normalised cosines, (cos + 1) / 2"
        );
        // Different queries rank the map differently.
        if let Some(p) = &previous {
            assert!(p.iter().zip(&scores).any(|(a, b)| (a - b).abs() > 1e-4));
        }
        previous = Some(scores.clone());
    }
}

/// The real-time SAM + CLIP GPU config: poses estimated, SAM ViT-B with the refinement, and on the
/// CPU (devices switched, the tiny CLIP) it gets as far as SAM's weights, which it names.
#[cfg(feature = "sam")]
#[test]
fn realtime_cuda_sam_clip_config_names_its_gpu_and_its_weights() {
    let (mut config, ctx) = common::gpu_config("realtime-cuda-sam-clip.toml", TINY_CLIP);
    assert_eq!(config.tracker.kind, "frame-to-model");
    let proposer = config.proposer.as_ref().unwrap();
    assert_eq!(proposer.params["variant"].as_str(), Some("vit-b"));
    assert_eq!(proposer.params["refine"].as_bool(), Some(true));
    common::on_the_cpu(&mut config);
    let err = Pipeline::from_config(&config, &ctx)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("sam_vit_b.safetensors"), "{err}");
}
