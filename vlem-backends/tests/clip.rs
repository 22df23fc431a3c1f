#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The CLIP towers and the `clip` encoder on the two tiny random-weight models committed in
//! `goldens/clip/` (Hugging Face layout, written by `goldens/clip/make_clip_goldens.py` with
//! `transformers`): token ids, image and text features against `transformers` to 1e-4, the
//! encoder's region layout, templates, parameters and errors, and the shared conformance suite.
//! Run in release (`cargo test --release`): candle in a debug build is many times slower.
#![cfg(feature = "clip")]

mod common;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde::Deserialize;
use vlem_backends::ModelDtype;
use vlem_backends::clip::model::Activation;
use vlem_backends::clip::{ClipEncoder, ClipEncoderConfig, ClipModel};
use vlem_backends::region_crops::{self, Background, CLIP_MEAN, CLIP_STD};
use vlem_core::{BuildContext, Encoder, PixelRect, Region, Registry, RgbImage, StageConfig};

/// The goldens written by `goldens/clip/make_clip_goldens.py`.
const GOLDENS: &str = include_str!("../goldens/clip/clip_goldens.json");

/// Largest accepted difference of any component from `transformers`.
fn tolerance() -> f32 {
    common::tolerance(1e-4)
}

#[derive(Deserialize)]
struct Goldens {
    pixels: PixelSpec,
    models: std::collections::BTreeMap<String, ModelGoldens>,
}

#[derive(Deserialize)]
struct PixelSpec {
    shape: [usize; 4],
}

#[derive(Deserialize)]
struct ModelGoldens {
    hidden_act: String,
    eos_token_id_in_config: i64,
    projection_dim: usize,
    image_mean: [f32; 3],
    image_std: [f32; 3],
    texts: Vec<TextGolden>,
    images: Vec<Vec<f32>>,
}

#[derive(Deserialize)]
struct TextGolden {
    text: String,
    ids: Vec<u32>,
    features: Vec<f32>,
}

fn goldens() -> &'static Goldens {
    static G: OnceLock<Goldens> = OnceLock::new();
    G.get_or_init(|| serde_json::from_str(GOLDENS).unwrap())
}

fn goldens_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/clip")
}

fn model_dir(name: &str) -> PathBuf {
    goldens_dir().join(name)
}

/// The pixels of the goldens, from the script's formula (f64, rounded to f32 as torch does).
fn golden_pixels() -> Vec<f32> {
    let [images, channels, size, _] = goldens().pixels.shape;
    let mut out = Vec::with_capacity(images * channels * size * size);
    for b in 0..images {
        for c in 0..channels {
            for y in 0..size {
                for x in 0..size {
                    let (b, c, y, x) = (b as f64, c as f64, y as f64, x as f64);
                    let v = (0.37 * (y + 1.0) * (c + 1.0) + 0.11 * x * (b + 1.0) + b).sin() * 1.5
                        + 0.1 * c;
                    out.push(v as f32);
                }
            }
        }
    }
    out
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn normalised(v: &[f32]) -> Vec<f32> {
    let n = dot(v, v).sqrt();
    v.iter().map(|x| x / n).collect()
}

/// Checks one model against its goldens and returns the worst error seen.
fn check_model(name: &str) -> f32 {
    let g = &goldens().models[name];
    let model = ClipModel::load(&model_dir(name), &common::device(), ModelDtype::F32).unwrap();
    let config = model.config();
    assert_eq!(model.projection_dim(), g.projection_dim);
    assert_eq!(config.text.eos_token_id, g.eos_token_id_in_config);
    let act = Activation::from_hf_name(&g.hidden_act).unwrap();
    assert_eq!(config.text.hidden_act, act);
    assert_eq!(config.vision.hidden_act, act);

    let mut worst = 0.0f32;
    // Token ids: the tokenizers crate reading tokenizer.json gives transformers' ids.
    for t in &g.texts {
        assert_eq!(
            model.tokenize(&t.text).unwrap(),
            t.ids,
            "ids of {:?}",
            t.text
        );
        assert!(t.ids.len() <= config.text.max_position_embeddings);
    }
    // Text features, one padded batch, then each text alone.
    let texts: Vec<&str> = g.texts.iter().map(|t| t.text.as_str()).collect();
    let batch = model.text_features(&texts).unwrap();
    for (t, e) in g.texts.iter().zip(&batch) {
        let err = max_abs_diff(e, &t.features);
        println!("{name}: text max abs error {err:.2e}  {:?}", t.text);
        worst = worst.max(err);
        let alone = model.text_features(&[&t.text]).unwrap().pop().unwrap();
        worst = worst.max(max_abs_diff(&alone, &t.features));
    }
    // Image features, the batch, then each image alone.
    let pixels = golden_pixels();
    let images = g.images.len();
    let features = model.image_features(&pixels, images).unwrap();
    let per_image = pixels.len() / images;
    for (i, (e, want)) in features.iter().zip(&g.images).enumerate() {
        let err = max_abs_diff(e, want);
        println!("{name}: image {i} max abs error {err:.2e}");
        worst = worst.max(err);
        let alone = model
            .image_features(&pixels[i * per_image..(i + 1) * per_image], 1)
            .unwrap()
            .pop()
            .unwrap();
        worst = worst.max(max_abs_diff(&alone, want));
    }
    println!("{name}: worst max abs error {worst:.2e}");
    worst
}

#[test]
fn quick_gelu_model_with_legacy_eos_matches_transformers() {
    let worst = check_model("tiny-quick-gelu");
    assert!(worst <= tolerance(), "worst error {worst:e}");
}

#[test]
fn gelu_model_with_real_eos_matches_transformers() {
    let worst = check_model("tiny-gelu");
    assert!(worst <= tolerance(), "worst error {worst:e}");
}

#[test]
fn goldens_exercise_truncation_and_the_end_token() {
    let g = &goldens().models["tiny-gelu"];
    let model =
        ClipModel::load(&model_dir("tiny-gelu"), &common::device(), ModelDtype::F32).unwrap();
    let max = model.config().text.max_position_embeddings;
    let long = g.texts.iter().map(|t| t.ids.len()).max().unwrap();
    assert_eq!(
        long, max,
        "the long golden text must be truncated to the positions"
    );
    let eos = *g.texts[0].ids.last().unwrap();
    assert!(g.texts.iter().all(|t| *t.ids.last().unwrap() == eos));
    // The empty text is the start and end tokens only.
    let empty = g.texts.iter().find(|t| t.text.is_empty()).unwrap();
    assert_eq!(empty.ids.len(), 2);
}

#[test]
fn image_features_refuse_a_wrong_pixel_count() {
    let model =
        ClipModel::load(&model_dir("tiny-gelu"), &common::device(), ModelDtype::F32).unwrap();
    let err = model.image_features(&[0.0; 10], 1).unwrap_err().to_string();
    assert!(err.contains("10 values for 1 image(s) of 3x32x32"), "{err}");
    assert!(model.image_features(&[], 0).unwrap().is_empty());
}

/// The least cosine similarity between `model`'s embeddings and the f32 goldens (texts in one
/// batch, images in one batch).
fn least_cosine_to_goldens(name: &str, model: &ClipModel) -> f32 {
    let g = &goldens().models[name];
    let texts: Vec<&str> = g.texts.iter().map(|t| t.text.as_str()).collect();
    let text = model.text_features(&texts).unwrap();
    let pixels = golden_pixels();
    let images = model.image_features(&pixels, g.images.len()).unwrap();
    let pairs = text
        .iter()
        .zip(g.texts.iter().map(|t| &t.features))
        .chain(images.iter().zip(&g.images));
    pairs
        .map(|(e, want)| common::least_row_cosine(e, want, e.len()))
        .fold(1.0, f32::min)
}

/// Half precision: both towers in f16 and bf16 against the f32 goldens of transformers, as
/// embeddings are compared (cosine). f16 keeps 11 significant bits, bf16 8: the bounds say so.
#[test]
fn half_precision_models_agree_with_the_f32_goldens() {
    for name in ["tiny-quick-gelu", "tiny-gelu"] {
        for dtype in [ModelDtype::F16, ModelDtype::Bf16] {
            let bound = common::half_precision_bound(dtype);
            let model = ClipModel::load(&model_dir(name), &common::device(), dtype).unwrap();
            let least = least_cosine_to_goldens(name, &model);
            println!("{name} {dtype:?}: least cosine to the f32 goldens {least:.6}");
            assert!(least >= bound, "{name} {dtype:?}: cosine {least} < {bound}");
        }
        let f32_model = ClipModel::load(&model_dir(name), &common::device(), ModelDtype::F32);
        let f32_bound = common::half_precision_bound(ModelDtype::F32);
        assert!(least_cosine_to_goldens(name, &f32_model.unwrap()) > f32_bound);
    }
    // Through the encoder's config key.
    let half = encoder_with("tiny-gelu", "dtype = \"f16\"");
    let text = half.encode_text("a photo of a cat").unwrap();
    assert!((dot(&text, &text) - 1.0).abs() < 1e-5);
}

fn encoder_with(name: &str, extra: &str) -> ClipEncoder {
    let params: toml::Table = toml::from_str(&format!(
        "model_dir = \"{name}\"\n{}\n{extra}",
        common::device_line()
    ))
    .unwrap();
    let config: ClipEncoderConfig =
        vlem_core::parse_params(vlem_core::StageKind::Encoder, "clip", &params).unwrap();
    let ctx = BuildContext {
        config_dir: goldens_dir(),
        ..BuildContext::default()
    };
    ClipEncoder::from_config(config, &ctx).unwrap()
}

fn encoder() -> &'static ClipEncoder {
    static E: OnceLock<ClipEncoder> = OnceLock::new();
    E.get_or_init(|| encoder_with("tiny-quick-gelu", ""))
}

#[test]
fn encoder_reads_the_preprocessor_normalisation_and_image_size() {
    let quick = encoder();
    assert_eq!(quick.crop_spec().size, 32);
    assert_eq!(quick.crop_spec().mean, CLIP_MEAN);
    assert_eq!(quick.crop_spec().std, CLIP_STD);
    assert_eq!(quick.crop_spec().background, Background::None);
    assert_eq!(quick.batch_size(), 16);
    assert_eq!(quick.dim(), 16);
    assert!(quick.needs_regions());

    let gelu = encoder_with("tiny-gelu", "background = \"mean-segment\"\nbatch_size = 3");
    let g = &goldens().models["tiny-gelu"];
    assert_eq!(gelu.crop_spec().mean, g.image_mean);
    assert_eq!(gelu.crop_spec().std, g.image_std);
    assert_eq!(gelu.crop_spec().mean, [0.5; 3]);
    assert_eq!(gelu.crop_spec().background, Background::MeanSegment);
    assert_eq!(gelu.batch_size(), 3);

    // Without preprocessor_config.json: CLIP's values.
    let dir = tempfile::tempdir().unwrap();
    for f in ["config.json", "model.safetensors", "tokenizer.json"] {
        std::fs::copy(model_dir("tiny-gelu").join(f), dir.path().join(f)).unwrap();
    }
    let config = ClipEncoderConfig {
        model_dir: Some(dir.path().to_path_buf()),
        ..ClipEncoderConfig::default()
    };
    let bare = ClipEncoder::from_config(config, &BuildContext::default()).unwrap();
    assert_eq!(bare.crop_spec().mean, CLIP_MEAN);
    assert_eq!(bare.crop_spec().std, CLIP_STD);
}

#[test]
fn text_embedding_is_the_normalised_projection_and_templates_average() {
    let plain = encoder();
    let raw = plain
        .model()
        .text_features(&["chair"])
        .unwrap()
        .pop()
        .unwrap();
    let e = plain.encode_text("chair").unwrap();
    assert!(max_abs_diff(&e, &normalised(&raw)) < 1e-6);

    let templated = encoder_with(
        "tiny-quick-gelu",
        "templates = [\"a photo of a {}.\", \"a picture of the {}\"]",
    );
    let prompts = templated
        .model()
        .text_features(&["a photo of a chair.", "a picture of the chair"])
        .unwrap();
    let mean: Vec<f32> = normalised(&prompts[0])
        .iter()
        .zip(normalised(&prompts[1]))
        .map(|(a, b)| a + b)
        .collect();
    let want = normalised(&mean);
    let got = templated.encode_text("chair").unwrap();
    assert!(max_abs_diff(&got, &want) < 1e-6);
    // The ensemble differs from either prompt alone and from the raw query.
    assert!(max_abs_diff(&got, &e) > 1e-3);
    assert!(max_abs_diff(&got, &normalised(&prompts[0])) > 1e-3);
    // Several texts at once give what each gives alone.
    let both = templated.embed_texts(&["chair", "lamp"]).unwrap();
    assert!(max_abs_diff(&both[0], &got) < common::tolerance(1e-5));
    assert!(
        max_abs_diff(&both[1], &templated.encode_text("lamp").unwrap()) < common::tolerance(1e-5)
    );
}

/// A 40x30 image with a left and right half of different colours and some texture.
fn test_image() -> RgbImage {
    let (w, h) = (40u32, 30u32);
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            let base: [u8; 3] = if x < w / 2 {
                [200, 40, 30]
            } else {
                [30, 60, 210]
            };
            let t = ((x * 7 + y * 13) % 32) as u8;
            data.extend(base.iter().map(|c| c.saturating_add(t)));
        }
    }
    RgbImage::new(w, h, data).unwrap()
}

fn rect_region(x: u32, y: u32, width: u32, height: u32) -> Region {
    Region {
        bbox: PixelRect {
            x,
            y,
            width,
            height,
        },
        mask: vec![true; (width * height) as usize],
    }
}

#[test]
fn regions_get_their_crop_embedding_and_the_smaller_region_wins() {
    let enc = encoder();
    let image = test_image();
    // The whole left half, and a small box inside it; the right half has no region.
    let regions = vec![rect_region(0, 0, 20, 30), rect_region(5, 5, 6, 6)];
    let e = enc.encode_image(&image, &regions).unwrap();
    assert_eq!((e.width(), e.height(), e.dim()), (40, 30, 16));

    // Expected rows: the crops through the model, normalised.
    let pixels = region_crops::crop_batch(&image, &regions, enc.crop_spec()).unwrap();
    let raw = enc.model().image_features(&pixels, 2).unwrap();
    let (big, small) = (normalised(&raw[0]), normalised(&raw[1]));
    assert!(max_abs_diff(&big, &small) > 1e-3, "two crops embed alike");

    let mut out = vec![0.0; 16];
    assert!(e.embedding_at(1, 1, &mut out));
    assert!(max_abs_diff(&out, &big) < common::tolerance(1e-5));
    assert!(e.embedding_at(7, 7, &mut out), "inside both: the small one");
    assert!(max_abs_diff(&out, &small) < common::tolerance(1e-5));
    assert!(!e.has_embedding(30, 10), "outside every region");
}

#[test]
fn batch_size_does_not_change_the_embeddings() {
    let image = test_image();
    let regions: Vec<Region> = (0..5)
        .map(|k| rect_region(k * 6, k * 3, 9 + k, 10))
        .collect();
    for background in ["none", "random"] {
        let one = encoder_with(
            "tiny-quick-gelu",
            &format!("batch_size = 1\nbackground = \"{background}\"\nseed = 7"),
        );
        let many = encoder_with(
            "tiny-quick-gelu",
            &format!("batch_size = 2\nbackground = \"{background}\"\nseed = 7"),
        );
        let pixels = region_crops::crop_batch(&image, &regions, one.crop_spec()).unwrap();
        let a = one.embed_crops(&pixels, regions.len()).unwrap();
        let b = many.embed_crops(&pixels, regions.len()).unwrap();
        assert_eq!(a.len(), 5 * 16);
        assert!(
            max_abs_diff(&a, &b) < common::tolerance(1e-5),
            "{background}"
        );
        let ea = one.encode_image(&image, &regions).unwrap();
        let eb = many.encode_image(&image, &regions).unwrap();
        let (mut x, mut y) = (vec![0.0; 16], vec![0.0; 16]);
        for (u, v) in [(1, 1), (10, 5), (30, 14), (39, 29)] {
            assert_eq!(ea.embedding_at(u, v, &mut x), eb.embedding_at(u, v, &mut y));
            assert!(max_abs_diff(&x, &y) < common::tolerance(1e-5));
        }
    }
}

#[test]
fn background_strategy_changes_what_a_masked_region_embeds() {
    let image = test_image();
    // A diagonal mask over the whole image: its background differs between strategies.
    let mut region = rect_region(0, 0, 40, 30);
    for (i, m) in region.mask.iter_mut().enumerate() {
        let (x, y) = (i % 40, i / 40);
        *m = x * 3 > y * 4;
    }
    let none = encoder_with("tiny-quick-gelu", "");
    let magenta = encoder_with("tiny-quick-gelu", "background = \"static\"");
    let a = none
        .encode_image(&image, std::slice::from_ref(&region))
        .unwrap();
    let b = magenta
        .encode_image(&image, std::slice::from_ref(&region))
        .unwrap();
    let (mut x, mut y) = (vec![0.0; 16], vec![0.0; 16]);
    assert!(a.embedding_at(39, 0, &mut x) && b.embedding_at(39, 0, &mut y));
    assert!(max_abs_diff(&x, &y) > 1e-4);
    assert!(!a.has_embedding(0, 29), "outside the mask");
}

#[test]
fn no_regions_embed_nothing() {
    let image = test_image();
    let e = encoder().encode_image(&image, &[]).unwrap();
    assert_eq!((e.width(), e.height(), e.dim()), (40, 30, 16));
    assert!((0..30).all(|v| (0..40).all(|u| !e.has_embedding(u, v))));
}

#[test]
fn a_region_outside_the_image_is_an_error_not_a_panic() {
    let err = encoder()
        .encode_image(&test_image(), &[rect_region(35, 0, 10, 10)])
        .unwrap_err()
        .to_string();
    assert!(err.starts_with("encoder `clip`"), "{err}");
}

fn ctx() -> BuildContext {
    BuildContext {
        config_dir: goldens_dir(),
        ..BuildContext::default()
    }
}

fn build_through_registry(params: &str) -> vlem_core::Result<Box<dyn Encoder>> {
    let stage: StageConfig = toml::from_str(&format!("kind = \"clip\"\n{params}")).unwrap();
    Registry::global().unwrap().build_encoder(&stage, &ctx())
}

#[test]
fn registry_builds_clip_and_refuses_bad_parameters() {
    let e = build_through_registry("model_dir = \"tiny-gelu\"").unwrap();
    assert_eq!((e.name(), e.dim()), ("clip", 16));

    let message = |params: &str| match build_through_registry(params) {
        Ok(_) => panic!("{params} was accepted"),
        Err(e) => e.to_string(),
    };
    let m = message("model_dir = \"tiny-gelu\"\nbatch_sise = 4");
    assert!(m.contains("batch_sise"), "{m}");
    for (batch, got) in [
        ("0", "got 0"),
        ("18014398509481984", "got 18014398509481984"),
    ] {
        let m = message(&format!("model_dir = \"tiny-gelu\"\nbatch_size = {batch}"));
        assert!(
            m.contains("batch_size must lie in 1–1024 crops") && m.contains(got),
            "{m}"
        );
    }
    let m = message("model_dir = \"tiny-gelu\"\ntemplates = [\"a photo\"]");
    assert!(m.contains("needs a {}"), "{m}");
    let m = message("model_dir = \"tiny-gelu\"\ntemplates = []");
    assert!(m.contains("at least one template"), "{m}");
    let m = message("model_dir = \"tiny-gelu\"\nbackground = \"blurred\"");
    assert!(m.contains("blurred"), "{m}");
    let m = message("model_dir = \"tiny-gelu\"\ndevice = \"gpu\"");
    assert!(m.contains("\"gpu\"") && m.contains("cuda:N"), "{m}");
}

#[cfg(not(feature = "cuda"))]
#[test]
fn asking_for_a_gpu_in_a_build_without_cuda_says_how_to_get_one() {
    let m = match build_through_registry("model_dir = \"tiny-gelu\"\ndevice = \"cuda:1\"") {
        Ok(_) => panic!("a GPU was opened without the cuda feature"),
        Err(e) => e.to_string(),
    };
    assert!(m.starts_with("encoder `clip`"), "{m}");
    assert!(m.contains("device = \"cuda:1\" was asked for"), "{m}");
    assert!(
        m.contains("no CUDA support") && m.contains("--features cuda"),
        "{m}"
    );
}

#[test]
fn missing_weights_name_the_file_and_how_to_get_them() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        model_dir("tiny-gelu").join("config.json"),
        dir.path().join("config.json"),
    )
    .unwrap();
    std::fs::copy(
        model_dir("tiny-gelu").join("tokenizer.json"),
        dir.path().join("tokenizer.json"),
    )
    .unwrap();
    let params = format!("model_dir = {:?}", dir.path().display().to_string());
    let m = match build_through_registry(&params) {
        Ok(_) => panic!("built without weights"),
        Err(e) => e.to_string(),
    };
    assert!(m.starts_with("encoder `clip`"), "{m}");
    assert!(m.contains("lacks model.safetensors;"), "{m}");
    assert!(m.contains(&dir.path().display().to_string()), "{m}");
    assert!(m.contains("(from [encoder] model_dir)"), "{m}");
    assert!(
        m.contains(
            "huggingface-cli download openai/clip-vit-base-patch16 config.json \
             model.safetensors tokenizer.json"
        ),
        "{m}"
    );

    // Only the PyTorch weights: the conversion line.
    std::fs::write(dir.path().join("pytorch_model.bin"), b"").unwrap();
    let m = match build_through_registry(&params) {
        Ok(_) => panic!("built without safetensors"),
        Err(e) => e.to_string(),
    };
    assert!(
        m.contains("CLIPModel.from_pretrained(d).save_pretrained(d)"),
        "{m}"
    );
}

#[test]
fn weights_that_disagree_with_the_config_are_an_invalid_model_file() {
    let dir = tempfile::tempdir().unwrap();
    for f in ["model.safetensors", "tokenizer.json"] {
        std::fs::copy(model_dir("tiny-gelu").join(f), dir.path().join(f)).unwrap();
    }
    // The gelu model has one layer per tower; claim two.
    let config = std::fs::read_to_string(model_dir("tiny-gelu").join("config.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&config).unwrap();
    json["vision_config"]["num_hidden_layers"] = 2.into();
    std::fs::write(dir.path().join("config.json"), json.to_string()).unwrap();
    let err = ClipModel::load(dir.path(), &common::device(), ModelDtype::F32)
        .unwrap_err()
        .to_string();
    assert!(err.contains("model.safetensors"), "{err}");
    assert!(err.contains("do not match config.json"), "{err}");
}

fn build_tiny() -> Box<dyn Encoder> {
    let config = ClipEncoderConfig {
        model_dir: Some(model_dir("tiny-quick-gelu")),
        ..ClipEncoderConfig::default()
    };
    Box::new(ClipEncoder::from_config(config, &BuildContext::default()).unwrap())
}

vlem_testkit::encoder_conformance!(build_tiny, text = "a photo of a chair.");
