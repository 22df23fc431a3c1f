#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! NARADIO against its reference code: the goldens of `goldens/naradio/make_goldens.py` (NVlabs
//! RADIO's own loader and forward, RayFronts' own `NARadioEncoder`, open_clip's own tokenizer and
//! text tower, on a tiny random model in the hub layout converted by `convert_radio.py`), a
//! hand-computed NACLIP attention, the encoder conformance suite on the tiny model, and the
//! missing-model error.
#![cfg(feature = "naradio")]

mod common;

use std::path::{Path, PathBuf};

use candle_core::Tensor;
use serde_json::Value;
use vlem_backends::BackendError;
use vlem_backends::ModelDtype::{self, F32};
use vlem_backends::naradio::{
    GaussianGrid, LastBlock, NaradioEncoder, NaradioEncoderConfig, RadioModel, SiglipText,
    gaussian_prior,
};
use vlem_core::{BuildContext, Encoder, RgbImage};

fn tolerance() -> f32 {
    common::tolerance(1e-4)
}

fn goldens_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/naradio")
}

fn tiny_dir() -> PathBuf {
    goldens_dir().join("tiny")
}

fn goldens() -> Value {
    let text = std::fs::read_to_string(goldens_dir().join("naradio_goldens.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// The goldens' input, in [0, 1]: 0.5 + 0.45 sin(0.7 c + 0.31 y + 0.17 x + 0.013 x y).
fn pixels(height: usize, width: usize) -> Tensor {
    let mut v = Vec::with_capacity(3 * height * width);
    for c in 0..3 {
        for y in 0..height {
            for x in 0..width {
                let (c, y, x) = (c as f64, y as f64, x as f64);
                v.push((0.5 + 0.45 * (0.7 * c + 0.31 * y + 0.17 * x + 0.013 * x * y).sin()) as f32);
            }
        }
    }
    Tensor::from_vec(v, (1, 3, height, width), &common::device()).unwrap()
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

/// The strings of a golden list.
fn strs(v: &Value) -> Vec<&str> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap())
        .collect()
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn assert_close(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let diff = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    let scale = want.iter().map(|x| x.abs()).fold(0.0, f32::max);
    assert!(scale > 1e-3, "{what}: the golden is all zeros");
    assert!(
        diff <= tolerance(),
        "{what}: max |diff| {diff} > {}",
        tolerance()
    );
}

/// `(batch, channels, h, w)` row-major -> `(h·w, channels)` row-major, as RayFronts returns its
/// feature maps `(1, C, h, w)`.
fn chw_to_tokens(v: &[f32], channels: usize) -> Vec<f32> {
    let n = v.len() / channels;
    let mut out = vec![0.0; v.len()];
    for c in 0..channels {
        for t in 0..n {
            out[t * channels + c] = v[c * n + t];
        }
    }
    out
}

fn usize_of(v: &Value) -> usize {
    v.as_u64().unwrap() as usize
}

#[test]
fn trunk_matches_radio() {
    let g = goldens();
    let model = RadioModel::load(&tiny_dir(), &common::device(), F32).unwrap();
    for case in g["trunk"].as_array().unwrap() {
        let (h, w) = (usize_of(&case["height"]), usize_of(&case["width"]));
        let x = model.condition(&pixels(h, w)).unwrap();
        let out = model.forward(&x, LastBlock::Plain).unwrap();
        let what = format!("{h}x{w}");
        assert_close(
            &format!("{what} summary"),
            &flat(&out.summary),
            &floats(&case["summary"]),
        );
        assert_close(
            &format!("{what} features"),
            &flat(&out.features),
            &floats(&case["features"]),
        );
    }
}

#[test]
fn naradio_matches_rayfronts() {
    let g = goldens();
    let std = g["gauss_std"].as_f64().unwrap();
    let model = RadioModel::load(&tiny_dir(), &common::device(), F32).unwrap();
    let embed = model.config().embed_dim;
    let dim = model.adaptor_dim().unwrap();
    for case in g["naradio"].as_array().unwrap() {
        let (h, w) = (usize_of(&case["height"]), usize_of(&case["width"]));
        let x = model.condition(&pixels(h, w)).unwrap();
        for (grid, suffix) in [
            (GaussianGrid::Rayfronts, ""),
            (GaussianGrid::Image, "_image_grid"),
        ] {
            let what = format!("{h}x{w} {grid:?}");
            let last = LastBlock::Naclip {
                std,
                grid,
                reduced: false,
            };
            let out = model.forward(&x, last).unwrap();
            let want = chw_to_tokens(&floats(&case[format!("features{suffix}")]), embed);
            assert_close(&format!("{what} features"), &flat(&out.features), &want);
            let lang = model.adapt(&out.features).unwrap();
            let want = chw_to_tokens(&floats(&case[format!("lang{suffix}")]), dim);
            assert_close(&format!("{what} lang"), &flat(&lang), &want);
            let prefix = model.config().num_cls_tokens + model.config().num_registers;
            let prior = gaussian_prior(h / 16, w / 16, std, grid, prefix);
            assert_close(
                &format!("{what} prior"),
                &prior,
                &floats(&case[format!("prior{suffix}")]),
            );
            if grid == GaussianGrid::Rayfronts {
                let global = model
                    .adapt(&model.adaptor_summary(&out.summary).unwrap())
                    .unwrap();
                assert_close(
                    &format!("{what} global"),
                    &flat(&global),
                    &floats(&case["global"]),
                );
            }
        }
    }
}

/// Half precision (`dtype = "f16" | "bf16"`): the trunk with the NACLIP block and the adaptor
/// against RayFronts' f32 goldens per patch (cosine), the global embedding, and the label
/// embeddings through the encoder's key (trunk, adaptor and text tower in the same type).
#[test]
fn half_precision_agrees_with_the_f32_goldens() {
    let g = goldens();
    let std = g["gauss_std"].as_f64().unwrap();
    let labels = strs(&g["text"]["labels"]);
    for dtype in [ModelDtype::F16, ModelDtype::Bf16] {
        let model = RadioModel::load(&tiny_dir(), &common::device(), dtype).unwrap();
        let dim = model.adaptor_dim().unwrap();
        let mut least = 1.0f32;
        for case in g["naradio"].as_array().unwrap() {
            let (h, w) = (usize_of(&case["height"]), usize_of(&case["width"]));
            let x = model.condition(&pixels(h, w)).unwrap();
            let last = LastBlock::Naclip {
                std,
                grid: GaussianGrid::Rayfronts,
                reduced: false,
            };
            let out = model.forward(&x, last).unwrap();
            assert_eq!(out.features.dtype(), dtype.candle());
            let lang = model.adapt(&out.features).unwrap();
            let want = chw_to_tokens(&floats(&case["lang"]), dim);
            least = least.min(common::least_row_cosine(&flat32(&lang), &want, dim));
            let global = model
                .adapt(&model.adaptor_summary(&out.summary).unwrap())
                .unwrap();
            least = least.min(common::least_row_cosine(
                &flat32(&global),
                &floats(&case["global"]),
                dim,
            ));
        }
        let encoder = NaradioEncoder::from_config(
            NaradioEncoderConfig {
                dtype,
                ..tiny_encoder_config()
            },
            &BuildContext::default(),
        )
        .unwrap();
        let got = encoder.label_embeddings(&labels).unwrap().concat();
        let texts = common::least_row_cosine(&got, &floats(&g["text"]["label_embeddings"]), dim);
        // The encoder's own image path, against the f32 encoder's.
        let image = RgbImage::new(
            64,
            48,
            (0..64 * 48 * 3).map(|i| (i * 37 % 251) as u8).collect(),
        )
        .unwrap();
        let (_, _, half) = encoder.patch_grid(&image).unwrap();
        let (_, _, full) = tiny_encoder().patch_grid(&image).unwrap();
        least = least.min(common::least_row_cosine(&half, &full, dim));
        println!("{dtype:?}: least cosine, patches and global {least:.6}, labels {texts:.6}");
        let bound = common::half_precision_bound(dtype);
        assert!(least >= bound, "{dtype:?} image: {least} < {bound}");
        assert!(texts >= bound, "{dtype:?} labels: {texts} < {bound}");
    }
}

/// A tensor of any float type as f32 values.
fn flat32(t: &Tensor) -> Vec<f32> {
    flat(&t.to_dtype(candle_core::DType::F32).unwrap())
}

#[test]
fn the_two_prior_layouts_differ_only_for_non_square_grids() {
    let square_a = gaussian_prior(3, 3, 1.5, GaussianGrid::Rayfronts, 2);
    let square_b = gaussian_prior(3, 3, 1.5, GaussianGrid::Image, 2);
    assert_eq!(square_a, square_b);
    let wide_a = gaussian_prior(2, 3, 1.5, GaussianGrid::Rayfronts, 0);
    let wide_b = gaussian_prior(2, 3, 1.5, GaussianGrid::Image, 0);
    assert_ne!(wide_a, wide_b);
    // Image layout, 2 rows x 3 cols: patch 0 (0,0) and patch 3 (1,0) are vertical neighbours.
    let g = |d2: f64| (-d2 / (2.0 * 1.5 * 1.5)).exp() as f32;
    assert!((wide_b[3] - g(1.0)).abs() < 1e-7);
    // RayFronts reads the 6 tokens as 3 rows x 2 cols: token 3 is (1,1), diagonal from (0,0).
    assert!((wide_a[3] - g(2.0)).abs() < 1e-7);
}

/// NACLIP attention by hand on a 2x2 grid with one prefix token, one head of width 2:
/// q is ignored, logits = k·kᵀ/√2 + prior, the output is the softmax-weighted v.
#[test]
fn naclip_attention_by_hand() {
    let std = 1.0f64;
    let prior = gaussian_prior(2, 2, std, GaussianGrid::Image, 1);
    // Prefix row and column are zero; the diagonal is exp(0) = 1; edge neighbours exp(-1/2);
    // the diagonal neighbour exp(-1).
    let e1 = (-0.5f64).exp() as f32;
    let e2 = (-1.0f64).exp() as f32;
    #[rustfmt::skip]
    let want = [
        0.0, 0.0, 0.0, 0.0, 0.0,
        0.0, 1.0, e1, e1, e2,
        0.0, e1, 1.0, e2, e1,
        0.0, e1, e2, 1.0, e1,
        0.0, e2, e1, e1, 1.0,
    ];
    for (a, b) in prior.iter().zip(want) {
        assert!((a - b).abs() < 1e-7, "{prior:?}");
    }
    // Width 2, one head. x = the keys (k = I x); q = an arbitrary map (must not matter);
    // v = M x + b; identity output projection.
    let x = [
        [1.0f64, 0.0],
        [0.0, 1.0],
        [1.0, 1.0],
        [0.0, 0.0],
        [2.0, 0.0],
    ];
    let m = [[1.0f64, 2.0], [-1.0, 0.5]];
    let b = [0.1f64, -0.2];
    #[rustfmt::skip]
    let weight = [
        9.0f32, -9.0, 3.0, 1.0, // q
        1.0, 0.0, 0.0, 1.0,     // k
        1.0, 2.0, -1.0, 0.5,    // v
    ];
    let bias = [0.7f32, -0.3, 0.0, 0.0, 0.1, -0.2];
    let v: Vec<[f64; 2]> = x
        .iter()
        .map(|r| {
            [
                m[0][0] * r[0] + m[0][1] * r[1] + b[0],
                m[1][0] * r[0] + m[1][1] * r[1] + b[1],
            ]
        })
        .collect();
    let mut expected = Vec::new();
    for i in 0..5 {
        let logits: Vec<f64> = (0..5)
            .map(|j| {
                let kk = x[i][0] * x[j][0] + x[i][1] * x[j][1];
                kk / 2f64.sqrt() + f64::from(want[i * 5 + j])
            })
            .collect();
        let top = logits.iter().copied().fold(f64::MIN, f64::max);
        let ex: Vec<f64> = logits.iter().map(|l| (l - top).exp()).collect();
        let s: f64 = ex.iter().sum();
        let mut row = [0.0f64; 2];
        for (e, vj) in ex.iter().zip(&v) {
            row[0] += e / s * vj[0];
            row[1] += e / s * vj[1];
        }
        expected.extend(row.map(|r| r as f32));
    }
    let xs: Vec<f32> = x.iter().flatten().map(|&v| v as f32).collect();
    let got =
        vlem_backends::naradio::model::naclip_attention_for_test(&weight, &bias, &xs, 2, 1, &prior);
    for (a, b) in got.iter().zip(&expected) {
        assert!(
            (a - b).abs() < common::tolerance(1e-5),
            "{got:?} vs {expected:?}"
        );
    }
    // Changing q changes nothing.
    let mut other = weight;
    other[0] = -4.0;
    let again =
        vlem_backends::naradio::model::naclip_attention_for_test(&other, &bias, &xs, 2, 1, &prior);
    assert_eq!(got, again);
}

#[test]
fn text_matches_open_clip() {
    let g = goldens();
    let text = SiglipText::load(&tiny_dir().join("text"), &common::device(), F32).unwrap();
    let prompts = strs(&g["text"]["prompts"]);
    let ids = text.token_ids(&prompts).unwrap();
    let want: Vec<Vec<u32>> = g["text"]["ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as u32)
                .collect()
        })
        .collect();
    assert_eq!(ids, want);
    let emb: Vec<f32> = text.embed(&prompts).unwrap().concat();
    assert_close("text embeddings", &emb, &floats(&g["text"]["embeddings"]));
}

fn tiny_encoder_config() -> NaradioEncoderConfig {
    NaradioEncoderConfig {
        model_dir: Some(tiny_dir()),
        short_side: 64,
        gauss_std: goldens()["gauss_std"].as_f64().unwrap(),
        device: common::compute_device(),
        ..NaradioEncoderConfig::default()
    }
}

fn tiny_encoder() -> NaradioEncoder {
    NaradioEncoder::from_config(tiny_encoder_config(), &BuildContext::default()).unwrap()
}

#[test]
fn label_embeddings_match_rayfronts() {
    let g = goldens();
    let enc = tiny_encoder();
    let labels = strs(&g["text"]["labels"]);
    let got: Vec<f32> = enc.label_embeddings(&labels).unwrap().concat();
    assert_close(
        "label embeddings",
        &got,
        &floats(&g["text"]["label_embeddings"]),
    );
}

/// A query asked again comes from the cache: the same unit vector as the first time, which is
/// the normalised template mean of `label_embeddings`.
#[test]
fn repeated_queries_give_the_same_embedding() {
    let enc = tiny_encoder();
    let first = enc.encode_text("red sofa").unwrap();
    let again = enc.encode_text("red sofa").unwrap();
    assert_eq!(first, again);
    let mean = enc.label_embeddings(&["red sofa"]).unwrap().concat();
    let n = mean.iter().map(|v| v * v).sum::<f32>().sqrt();
    let unit: Vec<f32> = mean.iter().map(|v| v / n).collect();
    assert_close("cached query", &again, &unit);
    assert_ne!(enc.encode_text("blue chair").unwrap(), first);
}

/// The encoder on a 64 x 64 image whose pixels are the goldens' input rounded to 8 bits: the
/// patch grid is the golden's up to that rounding.
#[test]
fn encoder_patch_grid_is_the_models() {
    let g = goldens();
    let enc = tiny_encoder();
    let x = pixels(64, 64);
    let v = flat(&x);
    let n = 64 * 64;
    let mut rgb = Vec::with_capacity(3 * n);
    for i in 0..n {
        for c in 0..3 {
            rgb.push((v[c * n + i] * 255.0).round() as u8);
        }
    }
    let image = RgbImage::new(64, 64, rgb.clone()).unwrap();
    let (gw, gh, data) = enc.patch_grid(&image).unwrap();
    assert_eq!((gw, gh), (4, 4));
    // The same through the model on the 8-bit pixels.
    let q: Vec<f32> = (0..3)
        .flat_map(|c| (0..n).map(move |i| (c, i)))
        .map(|(c, i)| f32::from(rgb[i * 3 + c]) / 255.0)
        .collect();
    let model = enc.model();
    let x8 = model
        .condition(&Tensor::from_vec(q, (1, 3, 64, 64), &common::device()).unwrap())
        .unwrap();
    let last = LastBlock::Naclip {
        std: g["gauss_std"].as_f64().unwrap(),
        grid: GaussianGrid::Rayfronts,
        reduced: false,
    };
    let out = model.forward(&x8, last).unwrap();
    let want = flat(&model.adapt(&out.features).unwrap());
    assert_close("encoder grid", &data, &want);
    let e = enc.encode_image(&image, &[]).unwrap();
    assert_eq!((e.width(), e.height(), e.dim()), (64, 64, enc.dim()));
}

#[test]
fn input_keeps_the_aspect_ratio() {
    let mut enc_cfg = NaradioEncoderConfig {
        model_dir: Some(tiny_dir()),
        ..NaradioEncoderConfig::default()
    };
    let enc = NaradioEncoder::from_config(enc_cfg.clone(), &BuildContext::default()).unwrap();
    assert_eq!(enc.input_size(640, 480), (640, 480));
    assert_eq!(enc.input_size(1280, 960), (640, 480));
    enc_cfg.short_side = 40;
    let err = NaradioEncoder::from_config(enc_cfg, &BuildContext::default()).unwrap_err();
    assert!(err.to_string().contains("multiple"), "{err}");
}

#[test]
fn missing_files_are_named_with_the_way_to_get_them() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("config.json"), "{}").unwrap();
    let config = NaradioEncoderConfig {
        model_dir: Some(dir.path().to_path_buf()),
        ..NaradioEncoderConfig::default()
    };
    let err = NaradioEncoder::from_config(config, &BuildContext::default()).unwrap_err();
    match &err {
        BackendError::MissingModelFiles { missing, .. } => {
            assert_eq!(
                missing,
                &vec![
                    "radio.safetensors",
                    "text/config.json",
                    "text/model.safetensors",
                    "text/tokenizer.json"
                ]
            );
        }
        other => panic!("{other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("convert_radio.py") && msg.contains("nvidia/RADIO"),
        "{msg}"
    );
}

fn build_tiny() -> Box<dyn Encoder> {
    Box::new(tiny_encoder())
}

vlem_testkit::encoder_conformance!(build_tiny, text = "red sofa");
