//! The patch-embedding pipeline end to end, for each patch encoder: `configs/synthetic-dinov3.toml`
//! (the `dinov3` encoder on the tiny random-weight DINOv3 + dino.txt committed in
//! `vlem-backends/goldens/dinov3/`) and `configs/synthetic-naradio.toml` (the `naradio` encoder on
//! the tiny RADIO + SigLIP text tower in `vlem-backends/goldens/naradio/`), each on the synthetic
//! scene with a point-cloud map, built through the registry as the `vlem` binary builds it.
//! Checks that every pixel with depth becomes a map point (a patch encoder embeds the whole
//! frame), that the map has the patch embedding's dimension and that text queries score every
//! point with a finite normalised cosine.
#![cfg(feature = "cli")]
#![cfg(all(feature = "point-cloud", any(feature = "dinov3", feature = "naradio")))]
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
use vlem_core::{BuildContext, Config};

fn configs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("configs")
}

/// The shipped config `name`, shrunk to `frames` frames of 160x120 (the short side along).
fn config(name: &str, frames: usize) -> (Config, BuildContext) {
    let mut config = Config::from_file(&configs().join(name)).unwrap();
    let synthetic = config.dataset.params["synthetic"].as_table_mut().unwrap();
    synthetic.insert("frames".into(), (frames as i64).into());
    synthetic.insert("width".into(), 160.into());
    synthetic.insert("height".into(), 120.into());
    let encoder = config.encoder.as_mut().unwrap();
    encoder.params.insert("short_side".into(), 112.into());
    let ctx = BuildContext {
        config_dir: configs(),
        embedding_dim: None,
    };
    (config, ctx)
}

#[cfg(feature = "dinov3")]
#[test]
fn dinov3_maps_every_pixel_with_depth_and_queries_score_them() {
    check("synthetic-dinov3.toml", "dinov3", 32);
}

#[cfg(feature = "naradio")]
#[test]
fn naradio_maps_every_pixel_with_depth_and_queries_score_them() {
    check("synthetic-naradio.toml", "naradio", 40);
}

/// A `[proposer]` beside a patch encoder is not built or run: a warning says so, in the pipeline
/// and in each run's report (and so in `stats.json`), instead of nothing.
#[cfg(all(feature = "naradio", feature = "graph"))]
#[test]
fn an_unused_proposer_is_a_warning() {
    let (mut config, ctx) = config("synthetic-naradio.toml", 1);
    config.proposer = Some(vlem_core::StageConfig::named("graph"));
    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let expected = "[proposer] kind = \"graph\" is not used: the encoder `naradio` embeds the \
                    whole frame, not regions";
    assert_eq!(pipeline.warnings(), [expected.to_owned()]);
    let mut source = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let report = pipeline.run(source.as_mut(), None, &|_| {}).unwrap();
    assert_eq!(report.warnings.first().map(String::as_str), Some(expected));
    // Without the section, nothing to say.
    config.proposer = None;
    assert!(
        Pipeline::from_config(&config, &ctx)
            .unwrap()
            .warnings()
            .is_empty()
    );
}

/// Runs config `name` (encoder `encoder` of dimension `dim`) and checks the map and the queries.
fn check(name: &str, encoder_name: &str, dim: usize) {
    let (config, ctx) = config(name, 2);
    let mut source = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let frame = source.frame(0).unwrap();
    let (w, h) = (frame.colour.width(), frame.colour.height());
    let with_depth = (0..h)
        .flat_map(|v| (0..w).map(move |u| (u, v)))
        .filter(|&(u, v)| frame.depth.get(u, v).and_then(valid_depth).is_some())
        .count();
    assert!(with_depth > 0);

    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let encoder = pipeline.encoder().unwrap();
    assert_eq!((encoder.name(), encoder.dim()), (encoder_name, dim));
    assert!(!encoder.needs_regions());

    // One frame: one point per pixel with depth.
    let mut one = vlem_datasets::open(&config.dataset, &ctx.config_dir).unwrap();
    let mut first = Pipeline::from_config(&config, &ctx).unwrap();
    let report = first.run(one.as_mut(), Some(1), &|_| {}).unwrap();
    assert_eq!(report.frames_processed, 1);
    assert_eq!(first.map().unwrap().len(), with_depth);

    let report = pipeline.run(source.as_mut(), None, &|_| {}).unwrap();
    assert_eq!(report.frames_processed, 2);
    assert!(report.stage_ms.contains_key("encode"));
    let map = pipeline.map().unwrap();
    assert_eq!(map.dim(), dim);
    let encoder = pipeline.encoder().unwrap();
    let mut scores = Vec::new();
    let mut previous: Option<Vec<f32>> = None;
    for text in &config.query.texts {
        let query = encoder.encode_text(text).unwrap();
        assert_eq!(query.len(), dim);
        map.similarity(&query, &mut scores).unwrap();
        assert_eq!(scores.len(), map.len());
        assert!(
            scores
                .iter()
                .all(|s| s.is_finite() && (-1e-4..=1.0 + 1e-4).contains(s)),
            "{text}: scores must be finite normalised cosines"
        );
        if let Some(p) = &previous {
            assert!(p.iter().zip(&scores).any(|(a, b)| (a - b).abs() > 1e-4));
        }
        previous = Some(scores.clone());
    }
}

/// The real-time CPU configs of the patch encoders: the map builds, the encoder asks for the
/// full-size model folder it names (none ships with the repository), and with the tiny test model
/// swapped in the whole pipeline builds with the config's own keys.
fn check_realtime_config(name: &str, tiny: &[(&str, toml::Value)]) {
    let mut config = Config::from_file(&configs().join(name)).unwrap();
    let ctx = BuildContext {
        config_dir: configs(),
        embedding_dim: None,
    };
    assert_eq!(config.pipeline.mode, vlem_core::config::Mode::RealTime);
    let err = Pipeline::from_config(&config, &ctx)
        .err()
        .unwrap()
        .to_string();
    let named = config.encoder.as_ref().unwrap().params["model_dir"]
        .as_str()
        .unwrap()
        .to_owned();
    assert!(err.contains(named.trim_start_matches("../")), "{err}");
    let encoder = config.encoder.as_mut().unwrap();
    for (key, value) in tiny {
        encoder.params.insert((*key).into(), value.clone());
    }
    Pipeline::from_config(&config, &ctx).unwrap();
}

#[cfg(all(feature = "naradio", feature = "voxel"))]
#[test]
fn realtime_cpu_naradio_config_builds_with_a_model_folder() {
    check_realtime_config(
        "realtime-cpu-naradio.toml",
        &[("model_dir", "../vlem-backends/goldens/naradio/tiny".into())],
    );
}

#[cfg(all(feature = "dinov3", feature = "voxel"))]
#[test]
fn realtime_cpu_dinov3_config_builds_with_a_model_folder() {
    let tiny = "../vlem-backends/goldens/dinov3";
    check_realtime_config(
        "realtime-cpu-dinov3.toml",
        &[
            ("model_dir", format!("{tiny}/tiny").into()),
            ("dinotxt_weights", format!("{tiny}/tiny-dinotxt.pth").into()),
            ("bpe_vocab", format!("{tiny}/tiny-bpe.txt.gz").into()),
            ("text_heads", 3.into()),
        ],
    );
}

/// The real-time NARADIO GPU config: its poses are estimated, a build without `cuda` says what
/// was asked for, and on the CPU (its device key switched, the tiny model) it builds as it is.
#[cfg(all(feature = "naradio", feature = "point-cloud"))]
#[test]
fn realtime_cuda_naradio_config_asks_for_the_gpu_it_names() {
    let (mut config, ctx) = common::gpu_config(
        "realtime-cuda-naradio.toml",
        "../vlem-backends/goldens/naradio/tiny",
    );
    assert_eq!(config.tracker.kind, "frame-to-model");
    assert_eq!(config.pipeline.mode, vlem_core::config::Mode::RealTime);
    common::on_the_cpu(&mut config);
    let pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    assert_eq!(pipeline.tracker().name(), "frame-to-model");
}
