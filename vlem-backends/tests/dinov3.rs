#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The DINOv3 backbone against `transformers`' DINOv3ViTModel: the goldens of
//! `goldens/dinov3/make_dinov3_goldens.py` (tiny random-weight models in the Hugging Face
//! layout), plus the behaviour around them (batching, grid shapes, missing files); the dino.txt
//! heads against Meta's code; CLIP's tokenizer against Meta's; and the `dinov3` encoder (its
//! goldens, parameters, file lookup and the shared conformance suite).
#![cfg(feature = "dinov3")]

mod common;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde_json::Value;
use vlem_backends::BackendError;
use vlem_backends::ModelDtype::{self, F32};
use vlem_backends::dinov3::clip_bpe::{self, ClipBpe};
use vlem_backends::dinov3::encoder::locate_files;
use vlem_backends::dinov3::{DinoTxtHeads, Dinov3Backbone, Dinov3Encoder, Dinov3EncoderConfig};
use vlem_core::{BuildContext, Encoder, RgbImage};

fn tolerance() -> f32 {
    common::tolerance(1e-4)
}

fn goldens_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/dinov3")
}

fn goldens() -> Value {
    let text = std::fs::read_to_string(goldens_dir().join("dinov3_goldens.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// The input of the goldens: x[c, y, x] = 2 sin(0.7 c + 0.31 y + 0.17 x + 0.013 x y), f64 then
/// f32, shape (1, 3, height, width).
fn pixels(height: usize, width: usize) -> Tensor {
    let mut v = Vec::with_capacity(3 * height * width);
    for c in 0..3 {
        for y in 0..height {
            for x in 0..width {
                let (c, y, x) = (c as f64, y as f64, x as f64);
                v.push((2.0 * (0.7 * c + 0.31 * y + 0.17 * x + 0.013 * x * y).sin()) as f32);
            }
        }
    }
    Tensor::from_vec(v, (1, 3, height, width), &common::device()).unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

#[test]
fn backbone_matches_transformers_goldens() {
    let g = goldens();
    let models = g["models"].as_object().unwrap();
    assert_eq!(models.len(), 2);
    for (name, model) in models {
        let backbone =
            Dinov3Backbone::load(&goldens_dir().join(name), &common::device(), F32).unwrap();
        let registers = model["num_register_tokens"].as_u64().unwrap() as usize;
        let hidden = model["hidden_size"].as_u64().unwrap() as usize;
        assert_eq!(backbone.config().num_register_tokens, registers);
        for case in model["cases"].as_array().unwrap() {
            let height = case["height"].as_u64().unwrap() as usize;
            let width = case["width"].as_u64().unwrap() as usize;
            let expected: Vec<f32> = case["last_hidden_state"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
                .collect();
            let out = backbone.forward(&pixels(height, width)).unwrap();
            let (gh, gw) = (height / 16, width / 16);
            assert_eq!((out.grid_height, out.grid_width), (gh, gw));
            assert_eq!(out.tokens.dims(), &[1, 1 + registers + gh * gw, hidden]);
            let got = flat(&out.tokens);
            let diff = max_abs_diff(&got, &expected);
            assert!(
                diff <= tolerance(),
                "{name} {height}x{width}: max |diff| {diff}"
            );
            // The three views cut the same tokens: CLS first, then registers, then patches in
            // row-major grid order.
            assert_eq!(flat(&out.cls().unwrap()), got[..hidden]);
            let regs = out.registers().unwrap();
            assert_eq!(regs.dims(), &[1, registers, hidden]);
            assert_eq!(flat(&regs), got[hidden..(1 + registers) * hidden]);
            let grid = out.patch_grid().unwrap();
            assert_eq!(grid.dims(), &[1, gh, gw, hidden]);
            let grid = flat(&grid);
            let last = (gh * gw - 1) * hidden;
            let offset = (1 + registers) * hidden;
            assert_eq!(grid[last..], got[offset + last..]);
            // Patch (row 1, column 0) is token 1 + registers + gw.
            assert_eq!(
                grid[gw * hidden..(gw + 1) * hidden],
                got[offset + gw * hidden..offset + (gw + 1) * hidden]
            );
        }
    }
}

#[test]
fn a_batch_equals_its_images_one_by_one() {
    let backbone =
        Dinov3Backbone::load(&goldens_dir().join("tiny"), &common::device(), F32).unwrap();
    let a = pixels(48, 80);
    let b = (pixels(48, 80) * -0.5).unwrap();
    let both = Tensor::cat(&[&a, &b], 0).unwrap();
    let out = backbone.forward(&both).unwrap();
    let one_a = flat(&backbone.forward(&a).unwrap().tokens);
    let one_b = flat(&backbone.forward(&b).unwrap().tokens);
    let batch = flat(&out.tokens);
    let half = batch.len() / 2;
    assert!(max_abs_diff(&batch[..half], &one_a) < common::tolerance(1e-5));
    assert!(max_abs_diff(&batch[half..], &one_b) < common::tolerance(1e-5));
    assert!(
        max_abs_diff(&one_a, &one_b) > 1e-2,
        "different images, same tokens"
    );
}

#[test]
fn sides_must_be_multiples_of_the_patch() {
    let backbone =
        Dinov3Backbone::load(&goldens_dir().join("tiny"), &common::device(), F32).unwrap();
    let e = backbone.forward(&pixels(40, 64)).unwrap_err().to_string();
    assert!(e.contains("40x64"), "{e}");
    let grey = Tensor::zeros((1, 1, 32, 32), candle_core::DType::F32, &common::device()).unwrap();
    assert!(backbone.forward(&grey).is_err());
}

#[test]
fn in_memory_tensor_names_load_too() {
    // transformers >= 5 names the layers `model.layer.N` in memory (the hub files say
    // `layer.N`): a file saved with those names must give the same model.
    let src = goldens_dir().join("tiny");
    let tensors =
        candle_core::safetensors::load(src.join("model.safetensors"), &Device::Cpu).unwrap();
    let renamed: HashMap<String, Tensor> = tensors
        .into_iter()
        .map(|(k, v)| {
            let k = match k.strip_prefix("layer.") {
                Some(rest) => format!("model.layer.{rest}"),
                None => k,
            };
            (k, v)
        })
        .collect();
    assert!(renamed.contains_key("model.layer.1.norm2.weight"));
    let dir = tempfile::tempdir().unwrap();
    candle_core::safetensors::save(&renamed, dir.path().join("model.safetensors")).unwrap();
    std::fs::copy(src.join("config.json"), dir.path().join("config.json")).unwrap();
    let a = Dinov3Backbone::load(&src, &common::device(), F32).unwrap();
    let b = Dinov3Backbone::load(dir.path(), &common::device(), F32).unwrap();
    let x = pixels(64, 64);
    assert_eq!(
        flat(&a.forward(&x).unwrap().tokens),
        flat(&b.forward(&x).unwrap().tokens)
    );
}

#[test]
fn weights_that_disagree_with_the_config_are_named() {
    let src = goldens_dir().join("tiny");
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        src.join("model.safetensors"),
        dir.path().join("model.safetensors"),
    )
    .unwrap();
    let config = std::fs::read_to_string(src.join("config.json"))
        .unwrap()
        .replace("\"num_hidden_layers\": 2", "\"num_hidden_layers\": 3");
    std::fs::write(dir.path().join("config.json"), config).unwrap();
    let e = Dinov3Backbone::load(dir.path(), &common::device(), F32).unwrap_err();
    assert!(matches!(e, BackendError::InvalidModelFile { .. }), "{e:?}");
    assert!(e.to_string().contains("layer.2"), "{e}");
}

#[test]
fn missing_files_are_named_with_the_way_to_get_them() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("config.json"), "{}").unwrap();
    let e = Dinov3Backbone::load(dir.path(), &common::device(), F32).unwrap_err();
    let BackendError::MissingModelFiles { missing, .. } = &e else {
        panic!("{e:?}");
    };
    assert_eq!(missing, &vec!["model.safetensors"]);
    let message = e.to_string();
    assert!(
        message.contains("facebook/dinov3-vitl16-pretrain-lvd1689m"),
        "{message}"
    );
}

/// A JSON array of token ids.
fn token_ids(v: &Value) -> Vec<u32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| u32::try_from(x.as_u64().unwrap()).unwrap())
        .collect()
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn tiny_dinotxt() -> (Dinov3Backbone, DinoTxtHeads, Value) {
    let g = goldens()["dinotxt"].clone();
    let backbone = Dinov3Backbone::load(
        &goldens_dir().join(g["backbone"].as_str().unwrap()),
        &common::device(),
        F32,
    )
    .unwrap();
    let heads = DinoTxtHeads::load_pth(
        &goldens_dir().join(g["checkpoint"].as_str().unwrap()),
        g["vision_heads"].as_u64().unwrap() as usize,
        Some(g["text_heads"].as_u64().unwrap() as usize),
        &common::device(),
        F32,
    )
    .unwrap();
    (backbone, heads, g)
}

#[test]
fn dinotxt_vision_head_matches_meta_goldens() {
    let (backbone, heads, g) = tiny_dinotxt();
    assert_eq!(heads.vision_blocks(), 2);
    assert_eq!(heads.embed_dim(), 2 * heads.patch_dim());
    for case in g["images"].as_array().unwrap() {
        let height = case["height"].as_u64().unwrap() as usize;
        let width = case["width"].as_u64().unwrap() as usize;
        let out = heads
            .vision(&backbone.forward(&pixels(height, width)).unwrap())
            .unwrap();
        let image = flat(&out.image_embedding);
        let diff = max_abs_diff(&image, &floats(&case["image_embedding"]));
        assert!(
            diff <= tolerance(),
            "{height}x{width} image: max |diff| {diff}"
        );
        let (gh, gw) = (height / 16, width / 16);
        assert_eq!(out.patch_grid.dims(), &[1, gh, gw, heads.patch_dim()]);
        let diff = max_abs_diff(&flat(&out.patch_grid), &floats(&case["patch_tokens"]));
        assert!(
            diff <= tolerance(),
            "{height}x{width} patches: max |diff| {diff}"
        );
    }
}

#[test]
fn dinotxt_text_tower_matches_meta_goldens() {
    let (_, heads, g) = tiny_dinotxt();
    assert_eq!(
        heads.context_length(),
        g["text_context"].as_u64().unwrap() as usize
    );
    let texts = g["texts"].as_array().unwrap();
    assert_eq!(texts.len(), 3);
    let mut embeddings = Vec::new();
    for case in texts {
        let expected = floats(&case["text_embedding"]);
        let ids = token_ids(&case["ids"]);
        let got = heads.text(&ids).unwrap();
        assert_eq!(got.len(), heads.embed_dim());
        let diff = max_abs_diff(&got, &expected);
        assert!(diff <= tolerance(), "{ids:?}: max |diff| {diff}");
        // The zero-padded sequence the reference runs gives the same embedding.
        let padded = token_ids(&case["padded_ids"]);
        assert_eq!(heads.text(&padded).unwrap(), got);
        embeddings.push(got);
    }
    assert!(max_abs_diff(&embeddings[0], &embeddings[1]) > 1e-2);
    let e = heads.text(&[3, 999]).unwrap_err().to_string();
    assert!(e.contains("999"), "{e}");
    assert!(heads.text(&[]).is_err());
}

// --- The tokenizer and the `dinov3` encoder --------------------------------------------------

/// The released BPE vocabulary, from the PyPI package `open_clip_torch` (installed with
/// `--no-deps` by the README's test command).
fn released_vocab() -> PathBuf {
    let dir = vlem_backends::model_files::python_package_dir("open_clip").unwrap_or_else(|e| {
        panic!(
            "the tokenizer test needs bpe_simple_vocab_16e6.txt.gz from the Python package \
             open_clip ({e}): python3 -m pip install --no-deps open_clip_torch==3.3.0"
        )
    });
    dir.join(clip_bpe::VOCAB_FILE)
}

#[test]
fn tokenizer_matches_the_reference() {
    let bpe = ClipBpe::load(&released_vocab()).unwrap();
    assert_eq!(bpe.vocab_size(), 49408);
    assert_eq!((bpe.start_id(), bpe.end_id()), (49406, 49407));
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/clip_bpe/clip_bpe_goldens.json"),
    )
    .unwrap();
    let g: Value = serde_json::from_str(&text).unwrap();
    let context = g["context_length"].as_u64().unwrap() as usize;
    let cases = g["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 20);
    for case in cases {
        let text = case["text"].as_str().unwrap();
        let expected = token_ids(&case["ids"]);
        assert_eq!(bpe.tokenize(text, context), expected, "{text:?}");
    }
}

fn encoder_goldens() -> Value {
    goldens()["dinotxt"]["encoder"].clone()
}

fn tiny_encoder_config() -> Dinov3EncoderConfig {
    let g = goldens()["dinotxt"].clone();
    Dinov3EncoderConfig {
        model_dir: Some(goldens_dir().join(g["backbone"].as_str().unwrap())),
        dinotxt_weights: Some(goldens_dir().join(g["checkpoint"].as_str().unwrap())),
        bpe_vocab: Some(goldens_dir().join(encoder_goldens()["bpe_vocab"].as_str().unwrap())),
        text_heads: Some(g["text_heads"].as_u64().unwrap() as usize),
        // The golden image is 64x48: this short side needs no resampling.
        short_side: 48,
        device: common::compute_device(),
        ..Dinov3EncoderConfig::default()
    }
}

fn tiny_encoder() -> Dinov3Encoder {
    Dinov3Encoder::from_config(tiny_encoder_config(), &BuildContext::default()).unwrap()
}

#[test]
fn encoder_text_matches_meta_goldens() {
    let encoder = tiny_encoder();
    for case in encoder_goldens()["prompts"].as_array().unwrap() {
        let text = case["text"].as_str().unwrap();
        let ids = token_ids(&case["ids"]);
        assert_eq!(encoder.tokenizer().tokenize(text, 16), ids, "{text:?}");
        let got = encoder.encode_text(text).unwrap();
        let diff = max_abs_diff(&got, &floats(&case["embedding"]));
        assert!(diff <= tolerance(), "{text:?}: max |diff| {diff}");
    }
}

/// The golden image: pixel (x, y) = (37x + 11y, 3x + 71y + 5, 13xy + 7) mod 256.
fn golden_image(width: u32, height: u32) -> RgbImage {
    let mut data = Vec::with_capacity((3 * width * height) as usize);
    for y in 0..height {
        for x in 0..width {
            data.push(((37 * x + 11 * y) % 256) as u8);
            data.push(((3 * x + 71 * y + 5) % 256) as u8);
            data.push(((13 * x * y + 7) % 256) as u8);
        }
    }
    RgbImage::new(width, height, data).unwrap()
}

#[test]
fn encoder_patch_grid_matches_meta_goldens() {
    let g = encoder_goldens()["image"].clone();
    let (width, height) = (
        g["width"].as_u64().unwrap() as u32,
        g["height"].as_u64().unwrap() as u32,
    );
    let encoder = tiny_encoder();
    assert_eq!(encoder.input_size(width, height), (width, height));
    let (gw, gh, grid) = encoder.patch_grid(&golden_image(width, height)).unwrap();
    assert_eq!(
        (u64::from(gw), u64::from(gh)),
        (
            g["grid_width"].as_u64().unwrap(),
            g["grid_height"].as_u64().unwrap()
        )
    );
    let diff = max_abs_diff(&grid, &floats(&g["patch_grid"]));
    assert!(diff <= tolerance(), "max |diff| {diff}");
    // The embeddings cover the frame; a pixel at a patch centre has that patch's embedding.
    let e = encoder
        .encode_image(&golden_image(width, height), &[])
        .unwrap();
    assert_eq!((e.width(), e.height(), e.dim()), (width, height, 32));
}

/// Half precision (`dtype = "f16" | "bf16"`): the backbone and both heads against Meta's f32
/// goldens, per patch embedding and per text embedding, as embeddings are compared (cosine).
#[test]
fn half_precision_encoder_agrees_with_the_f32_goldens() {
    let g = encoder_goldens();
    let image = &g["image"];
    let (width, height) = (
        image["width"].as_u64().unwrap() as u32,
        image["height"].as_u64().unwrap() as u32,
    );
    for dtype in [ModelDtype::F16, ModelDtype::Bf16] {
        let encoder = Dinov3Encoder::from_config(
            Dinov3EncoderConfig {
                dtype,
                ..tiny_encoder_config()
            },
            &BuildContext::default(),
        )
        .unwrap();
        let (_, _, grid) = encoder.patch_grid(&golden_image(width, height)).unwrap();
        let patches = common::least_row_cosine(&grid, &floats(&image["patch_grid"]), 32);
        let mut texts = 1.0f32;
        for case in g["prompts"].as_array().unwrap() {
            let got = encoder.encode_text(case["text"].as_str().unwrap()).unwrap();
            texts = texts.min(common::least_row_cosine(
                &got,
                &floats(&case["embedding"]),
                got.len(),
            ));
        }
        println!("{dtype:?}: least cosine, patches {patches:.6}, texts {texts:.6}");
        let bound = common::half_precision_bound(dtype);
        assert!(patches >= bound, "{dtype:?} patches: {patches} < {bound}");
        assert!(texts >= bound, "{dtype:?} texts: {texts} < {bound}");
    }
}

#[test]
fn encoder_resizes_to_the_short_side_keeping_the_aspect_ratio() {
    let config = Dinov3EncoderConfig {
        short_side: 32,
        ..tiny_encoder_config()
    };
    let encoder = Dinov3Encoder::from_config(config, &BuildContext::default()).unwrap();
    assert_eq!(encoder.input_size(64, 48), (48, 32));
    let (gw, gh, grid) = encoder.patch_grid(&golden_image(64, 48)).unwrap();
    assert_eq!((gw, gh, grid.len()), (3, 2, 3 * 2 * 32));
}

#[test]
fn encoder_parameters_are_checked() {
    let build = |config: Dinov3EncoderConfig| {
        Dinov3Encoder::from_config(config, &BuildContext::default())
            .unwrap_err()
            .to_string()
    };
    let err = build(Dinov3EncoderConfig {
        short_side: 40,
        ..tiny_encoder_config()
    });
    assert!(err.contains("multiple of the patch size 16"), "{err}");
    let err = build(Dinov3EncoderConfig {
        templates: vec!["a photo".to_owned()],
        ..tiny_encoder_config()
    });
    assert!(err.contains("{}"), "{err}");
    // The registry's parsing refuses unknown keys.
    let params: toml::Table = toml::from_str("short_sid = 448").unwrap();
    let err = vlem_backends::dinov3::encoder::build(&params, &BuildContext::default())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("short_sid"), "{err}");
}

#[test]
fn encoder_names_every_missing_file_and_where_to_get_it() {
    let dir = tempfile::tempdir().unwrap();
    let config = Dinov3EncoderConfig {
        model_dir: Some(dir.path().to_path_buf()),
        bpe_vocab: Some(released_vocab()),
        ..Dinov3EncoderConfig::default()
    };
    let e = Dinov3Encoder::from_config(config, &BuildContext::default()).unwrap_err();
    let BackendError::MissingModelFiles { missing, .. } = &e else {
        panic!("{e:?}");
    };
    assert_eq!(
        missing,
        &vec![
            "config.json",
            "model.safetensors",
            "dinov3_vitl16_dinotxt_vision_head_and_text_encoder-*.pth"
        ]
    );
    let message = e.to_string();
    assert!(message.contains("dinov3-downloads"), "{message}");
    assert!(message.contains("open_clip_torch"), "{message}");
    // A configured file that is not there is named as such.
    let config = Dinov3EncoderConfig {
        dinotxt_weights: Some(dir.path().join("nope.pth")),
        ..tiny_encoder_config()
    };
    let e = Dinov3Encoder::from_config(config, &BuildContext::default()).unwrap_err();
    assert!(e.to_string().contains("nope.pth"), "{e}");
}

#[test]
fn encoder_finds_its_files_in_the_model_folder() {
    // The layout the docs ask for: the backbone folder also holds the two dino.txt files.
    let dir = tempfile::tempdir().unwrap();
    let tiny = goldens_dir().join("tiny");
    for name in ["config.json", "model.safetensors"] {
        std::fs::copy(tiny.join(name), dir.path().join(name)).unwrap();
    }
    std::fs::copy(
        goldens_dir().join("tiny-dinotxt.pth"),
        dir.path()
            .join("dinov3_vitl16_dinotxt_vision_head_and_text_encoder-a442d8f5.pth"),
    )
    .unwrap();
    std::fs::copy(
        goldens_dir().join("tiny-bpe.txt.gz"),
        dir.path().join(clip_bpe::VOCAB_FILE),
    )
    .unwrap();
    let files = locate_files(Some(dir.path()), None, None).unwrap();
    assert_eq!(files.bpe_vocab, dir.path().join(clip_bpe::VOCAB_FILE));
    let config = Dinov3EncoderConfig {
        model_dir: Some(dir.path().to_path_buf()),
        text_heads: Some(3),
        ..Dinov3EncoderConfig::default()
    };
    let encoder = Dinov3Encoder::from_config(config, &BuildContext::default()).unwrap();
    assert_eq!(encoder.dim(), 32);
}

fn build_tiny() -> Box<dyn Encoder> {
    Box::new(tiny_encoder())
}

vlem_testkit::encoder_conformance!(build_tiny, text = "a chair");
