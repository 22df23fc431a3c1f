#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The `onnx` encoder on the tiny models of `goldens/onnx/` (written, with their goldens, by
//! `goldens/onnx/make_onnx_models.py` from torch modules: the goldens are torch's outputs).
//!
//! These tests need the ONNX Runtime library (`python3 -m pip install --no-deps onnxruntime==1.31.1`, found
//! through `python3`, or `ORT_DYLIB_PATH`); without it they FAIL with that hint, on purpose.
#![cfg(feature = "onnx")]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde::Deserialize;
use vlem_backends::onnx::{OnnxConfig, OnnxEncoder, OutputKind};
use vlem_core::{
    BuildContext, EmbeddingLayout, Encoder, PixelRect, Region, Registry, RgbImage, StageConfig,
};

/// Largest accepted difference of any component from torch.
const TOLERANCE: f32 = 1e-4;

#[derive(Deserialize)]
struct Goldens {
    dim: usize,
    global: ImageGoldens,
    patches: ImageGoldens,
    prompts: Vec<PromptGolden>,
    texts: Vec<TextGolden>,
}

#[derive(Deserialize)]
struct ImageGoldens {
    width: u32,
    height: u32,
    skip_tokens: Option<usize>,
    images: Vec<Vec<u8>>,
    input: Vec<f32>,
    output: OutputGolden,
    grid_output: Option<OutputGolden>,
}

#[derive(Deserialize)]
struct OutputGolden {
    shape: Vec<i64>,
    batch: Vec<f32>,
    alone: Vec<Vec<f32>>,
}

#[derive(Deserialize)]
struct PromptGolden {
    prompt: String,
    embedding: Vec<f32>,
}

#[derive(Deserialize)]
struct TextGolden {
    text: String,
    embedding: Vec<f32>,
}

fn goldens() -> &'static Goldens {
    static GOLDENS: OnceLock<Goldens> = OnceLock::new();
    GOLDENS
        .get_or_init(|| serde_json::from_str(include_str!("../goldens/onnx/goldens.json")).unwrap())
}

fn models_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/onnx")
}

fn ctx() -> BuildContext {
    BuildContext {
        config_dir: models_dir(),
        ..BuildContext::default()
    }
}

const TEXT: &str = r#"
[text]
model = "text.onnx"
tokenizer = "tokenizer.json"
max_length = 8
templates = ["a photo of a {}", "{}"]
"#;

const GLOBAL: &str = r#"
[image]
model = "image_global.onnx"
output_kind = "global"
size = 32
"#;

const PATCHES: &str = r#"
[image]
model = "image_patches.onnx"
output_kind = "patch-grid"
patch_size = 8
skip_tokens = 2
"#;

const PATCHES_NHWC: &str = r#"
[image]
model = "image_patches_nhwc.onnx"
output_kind = "patch-grid"
width = 48
height = 32
patch_size = 8
"#;

fn try_build(config: &str) -> Result<OnnxEncoder, String> {
    let config: OnnxConfig = toml::from_str(config).map_err(|e| e.to_string())?;
    OnnxEncoder::from_config(config, &ctx()).map_err(|e| e.to_string())
}

fn build(config: &str) -> OnnxEncoder {
    try_build(config).unwrap_or_else(|e| panic!("cannot build the onnx encoder: {e}"))
}

/// The error of building `config` through the registry (as `vlem` does), as text.
fn registry_error(config: &str) -> String {
    let params: toml::Table = toml::from_str(config).unwrap();
    let stage = StageConfig {
        kind: "onnx".to_owned(),
        params,
    };
    match Registry::global().unwrap().build_encoder(&stage, &ctx()) {
        Ok(_) => panic!("built an encoder from a bad config:\n{config}"),
        Err(e) => e.to_string(),
    }
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn assert_close(actual: &[f32], expected: &[f32], what: &str) {
    let diff = max_abs_diff(actual, expected);
    assert!(diff <= TOLERANCE, "{what}: differs from torch by {diff}");
}

fn image(g: &ImageGoldens, i: usize) -> RgbImage {
    RgbImage::new(g.width, g.height, g.images[i].clone()).unwrap()
}

fn unit(v: &[f32]) -> Vec<f32> {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    v.iter().map(|x| x / n).collect()
}

/// Runs the image model on the golden inputs, as one batch and one image at a time.
fn check_image_model(encoder: &OnnxEncoder, g: &ImageGoldens, out: &OutputGolden, what: &str) {
    let n = g.images.len();
    assert!(n >= 3, "the goldens hold a batch of several images");
    let batch = encoder.run_image_model(&g.input, n).unwrap();
    assert_eq!(batch.shape, out.shape, "{what}: output shape");
    assert_close(&batch.data, &out.batch, &format!("{what}, batch of {n}"));
    let per_image = g.input.len() / n;
    for (i, alone) in out.alone.iter().enumerate() {
        let input = &g.input[i * per_image..(i + 1) * per_image];
        let one = encoder.run_image_model(input, 1).unwrap();
        assert_eq!(one.shape[0], 1);
        assert_close(&one.data, alone, &format!("{what}, image {i} alone"));
    }
}

#[test]
fn global_image_model_matches_torch_alone_and_in_a_batch() {
    let g = goldens();
    let encoder = build(GLOBAL);
    assert_eq!(encoder.output_kind(), OutputKind::Global);
    assert_eq!(encoder.dim(), g.dim);
    assert!(encoder.needs_regions());
    check_image_model(&encoder, &g.global, &g.global.output, "global tower");
}

#[test]
fn patch_image_models_match_torch_alone_and_in_a_batch() {
    let g = goldens();
    let tokens = build(PATCHES);
    assert_eq!(tokens.output_kind(), OutputKind::PatchGrid);
    assert!(!tokens.needs_regions());
    // The size comes from the model's static input shape: 48 wide, 32 high.
    assert_eq!(tokens.input_size(), (48, 32));
    check_image_model(&tokens, &g.patches, &g.patches.output, "token output");
    let grid = build(PATCHES_NHWC);
    let grid_golden = g.patches.grid_output.as_ref().unwrap();
    check_image_model(&grid, &g.patches, grid_golden, "grid output");
}

#[test]
fn preprocessing_matches_the_python_reference() {
    let g = goldens();
    for (config, golden) in [(GLOBAL, &g.global), (PATCHES, &g.patches)] {
        let encoder = build(config);
        let per_image = golden.input.len() / golden.images.len();
        for i in 0..golden.images.len() {
            let input = encoder.preprocess(&image(golden, i)).unwrap();
            let expected = &golden.input[i * per_image..(i + 1) * per_image];
            // The same f32 operations in the same order: equal up to the decimal round trip.
            let diff = max_abs_diff(&input, expected);
            assert!(diff <= 1e-6, "image {i}: preprocessing differs by {diff}");
        }
    }
}

#[test]
fn patch_grid_encoding_is_the_torch_grid_without_the_leading_tokens() {
    let g = goldens();
    let p = &g.patches;
    let skip = p.skip_tokens.unwrap();
    let grid_golden = p.grid_output.as_ref().unwrap();
    for config in [PATCHES, PATCHES_NHWC] {
        let encoder = build(config);
        for i in 0..p.images.len() {
            let e = encoder.encode_image(&image(p, i), &[]).unwrap();
            assert_eq!((e.width(), e.height(), e.dim()), (48, 32, g.dim));
            let EmbeddingLayout::PatchGrid {
                grid_width,
                grid_height,
                data,
            } = e.layout()
            else {
                panic!("not a patch grid");
            };
            assert_eq!((*grid_width, *grid_height), (6, 4));
            assert_close(data, &p.output.alone[i][skip * g.dim..], "grid from tokens");
            assert_close(data, &grid_golden.alone[i], "grid from the h x w output");
        }
    }
}

#[test]
fn patch_grid_resamples_frames_of_another_size() {
    let g = goldens();
    let encoder = build(PATCHES);
    let frame = vlem_testkit::images::gradient(96, 64);
    let e = encoder.encode_image(&frame, &[]).unwrap();
    assert_eq!((e.width(), e.height()), (96, 64));
    let EmbeddingLayout::PatchGrid { data, .. } = e.layout() else {
        panic!("not a patch grid");
    };
    // The model saw the frame shrunk to 48 x 32: the same as encoding that image directly.
    let small = encoder.preprocess(&frame).unwrap();
    let direct = encoder.run_image_model(&small, 1).unwrap();
    let skip = g.patches.skip_tokens.unwrap();
    assert_close(data, &direct.data[skip * g.dim..], "resampled frame");
}

#[test]
fn global_encoding_of_a_whole_frame_region_is_the_normalised_torch_embedding() {
    let g = goldens();
    let encoder = build(GLOBAL);
    let (w, h) = (g.global.width, g.global.height);
    let whole = Region {
        bbox: PixelRect {
            x: 0,
            y: 0,
            width: w,
            height: h,
        },
        mask: vec![true; (w * h) as usize],
    };
    // A second, smaller region wins the pixels it covers.
    let corner = Region {
        bbox: PixelRect {
            x: 0,
            y: 0,
            width: 8,
            height: 8,
        },
        mask: vec![true; 64],
    };
    for i in 0..g.global.images.len() {
        let img = image(&g.global, i);
        let e = encoder
            .encode_image(&img, &[whole.clone(), corner.clone()])
            .unwrap();
        let expected = unit(&g.global.output.alone[i]);
        assert_close(
            e.region_row(20, 20).unwrap(),
            &expected,
            "whole-frame region",
        );
        let small = e.region_row(3, 3).unwrap();
        assert!(
            max_abs_diff(small, &expected) > 1e-3,
            "the corner region got the whole frame's embedding"
        );
    }
    // No regions: no pixel has an embedding.
    let e = encoder.encode_image(&image(&g.global, 0), &[]).unwrap();
    assert!(!e.has_embedding(0, 0));
}

#[test]
fn global_batches_of_any_size_give_the_same_embeddings() {
    let g = goldens();
    let img = image(&g.global, 1);
    let regions = vlem_testkit::images::rectangular_regions(32, 32);
    let one = build(&format!("{GLOBAL}batch = 1\n"));
    let many = build(GLOBAL);
    let (a, b) = (
        one.encode_image(&img, &regions).unwrap(),
        many.encode_image(&img, &regions).unwrap(),
    );
    for (u, v) in [(2, 2), (10, 10), (20, 20)] {
        assert_close(
            a.region_row(u, v).unwrap(),
            b.region_row(u, v).unwrap(),
            "batch 1 against batch 16",
        );
    }
}

#[test]
fn text_prompts_in_one_padded_batch_match_torch_alone() {
    let g = goldens();
    for padding in ["max-length", "longest"] {
        let encoder = build(&format!("{GLOBAL}{TEXT}padding = \"{padding}\"\n"));
        let prompts: Vec<&str> = g.prompts.iter().map(|p| p.prompt.as_str()).collect();
        let batch = encoder.embed_prompts(&prompts).unwrap();
        for (p, e) in g.prompts.iter().zip(&batch) {
            assert_close(
                e,
                &p.embedding,
                &format!("{padding}: prompt {:?}", p.prompt),
            );
            let alone = encoder.embed_prompts(&[p.prompt.as_str()]).unwrap();
            assert_close(
                &alone[0],
                &p.embedding,
                &format!("{padding}: {:?} alone", p.prompt),
            );
        }
    }
}

#[test]
fn text_embeddings_average_the_templates_like_the_reference() {
    let g = goldens();
    let encoder = build(&format!("{GLOBAL}{TEXT}"));
    assert!(encoder.has_text());
    for t in &g.texts {
        let e = encoder.encode_text(&t.text).unwrap();
        assert_close(&e, &t.embedding, &format!("text {:?}", t.text));
    }
    let texts: Vec<&str> = g.texts.iter().map(|t| t.text.as_str()).collect();
    for (e, t) in encoder.embed_texts(&texts).unwrap().iter().zip(&g.texts) {
        assert_close(e, &t.embedding, &format!("text {:?} in a batch", t.text));
    }
}

#[test]
fn without_a_text_model_text_is_unsupported() {
    let encoder = build(PATCHES);
    assert!(!encoder.has_text());
    let err = encoder.encode_text("chair").unwrap_err();
    assert!(
        matches!(err, vlem_core::CoreError::Unsupported { .. }),
        "{err}"
    );
}

#[test]
fn the_registry_builds_it_from_toml() {
    let params: toml::Table = toml::from_str(&format!("{PATCHES}{TEXT}")).unwrap();
    let stage = StageConfig {
        kind: "onnx".to_owned(),
        params,
    };
    let encoder = Registry::global()
        .unwrap()
        .build_encoder(&stage, &ctx())
        .unwrap();
    assert_eq!(encoder.name(), "onnx");
    assert_eq!(encoder.dim(), goldens().dim);
}

#[test]
fn a_missing_model_file_is_named() {
    let message = registry_error("[image]\nmodel = \"nope.onnx\"\noutput_kind = \"global\"\n");
    let path = models_dir().join("nope.onnx");
    assert!(
        message.contains(&format!("model file {}: no such file", path.display())),
        "{message}"
    );
    let message = registry_error(&format!(
        "{GLOBAL}[text]\nmodel = \"text.onnx\"\ntokenizer = \"missing.json\"\n"
    ));
    let path = models_dir().join("missing.json");
    assert!(
        message.contains(&format!("model file {}: no such file", path.display())),
        "{message}"
    );
}

#[test]
fn a_missing_library_is_named_with_the_setup_command() {
    let dir = tempfile::tempdir().unwrap();
    let library = dir.path().join("libonnxruntime.so.9.9.9");
    let message = registry_error(&format!(
        "library = {:?}\n{GLOBAL}",
        library.to_str().unwrap()
    ));
    assert!(
        message.contains(&format!(
            "cannot load the ONNX Runtime shared library {} (from [encoder] library): no such file",
            library.display()
        )),
        "{message}"
    );
    assert!(
        message.contains("python3 -m pip install --no-deps onnxruntime==1.31.1"),
        "{message}"
    );
}

#[test]
fn a_second_different_library_is_refused() {
    // Loads the library first (whichever test runs first), then asks for another file.
    let _ = build(GLOBAL);
    let loaded = vlem_backends::onnx::runtime::loaded_library().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let other = dir.path().join("libonnxruntime.so");
    std::fs::write(&other, b"not a library").unwrap();
    let message = registry_error(&format!(
        "library = {:?}\n{GLOBAL}",
        other.to_str().unwrap()
    ));
    assert!(
        message.contains(&format!(
            "this process has loaded the ONNX Runtime library {} and cannot load a second one, {}",
            loaded.display(),
            other.display()
        )),
        "{message}"
    );
    // The loaded library itself, named explicitly, is fine.
    let again = build(&format!(
        "library = {:?}\n{GLOBAL}",
        loaded.to_str().unwrap()
    ));
    assert_eq!(again.dim(), goldens().dim);
}

#[test]
fn bad_configs_say_what_is_wrong() {
    let cases: [(String, &str); 9] = [
        (
            format!("{GLOBAL}sise = 3\n"),
            "[encoder] kind = \"onnx\": unknown field `sise`",
        ),
        (
            "[image]\nmodel = \"image_global.onnx\"\noutput_kind = \"tokens\"\n".to_owned(),
            "unknown variant `tokens`",
        ),
        (
            format!("{GLOBAL}patch_size = 8\n"),
            "patch_size applies to output_kind = \"patch-grid\" only",
        ),
        (
            "[image]\nmodel = \"image_patches.onnx\"\noutput_kind = \"patch-grid\"\n".to_owned(),
            "needs patch_size",
        ),
        (
            format!("{PATCHES}background = \"random\"\n"),
            "background applies to output_kind = \"global\" only",
        ),
        (
            "[image]\nmodel = \"image_global.onnx\"\noutput_kind = \"global\"\nsize = 64\n"
                .to_owned(),
            "is 32 wide and 32 high, the config says 64 x 64",
        ),
        (
            format!("dim = 16\n{GLOBAL}"),
            "the output has dimension 8, the config says dim = 16",
        ),
        (
            "[image]\nmodel = \"image_patches.onnx\"\noutput_kind = \"patch-grid\"\n\
             patch_size = 8\n"
                .to_owned(),
            "has 26 tokens, but 0 skipped tokens and a 6 x 4 grid of 8-pixel patches make 24",
        ),
        (
            format!(
                "{GLOBAL}[text]\nmodel = \"text.onnx\"\ntokenizer = \"tokenizer.json\"\ntemplates = [\"a photo\"]\n"
            ),
            "\"a photo\" has none",
        ),
    ];
    for (config, expected) in cases {
        let message = registry_error(&config);
        assert!(message.contains(expected), "{config}\n=> {message}");
    }
    // Errors found in a model name its file.
    let message = registry_error(&format!("dim = 16\n{GLOBAL}"));
    let path = models_dir().join("image_global.onnx");
    assert!(message.contains(&path.display().to_string()), "{message}");
}

fn build_global() -> Box<dyn Encoder> {
    Box::new(build(&format!("{GLOBAL}{TEXT}")))
}

fn build_patch_grid() -> Box<dyn Encoder> {
    Box::new(build(PATCHES))
}

/// The conformance suite on the `global` kind (a region encoder with a text tower).
mod global {
    use super::*;
    vlem_testkit::encoder_conformance!(build_global, text = "red chair");
}

/// The conformance suite on the `patch-grid` kind (no text tower).
mod patch_grid {
    use super::*;
    vlem_testkit::encoder_conformance!(build_patch_grid);
}
