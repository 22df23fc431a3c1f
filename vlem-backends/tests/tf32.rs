#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! `tf32`, the key every candle model's section shares: refused where it cannot apply (the CPU,
//! half precision) with the reason, and on a GPU (`VLEM_TEST_DEVICE=cuda`, `bench/gpu/check.sh`
//! part 1) CLIP's f32 towers with TF32 products held to the same towers without.
//!
//! A test binary of its own: the switch is one per process (cuBLAS's, as PyTorch's), and the
//! golden tests that run beside each other in one binary would see it.
#![cfg(feature = "clip")]

mod common;

use std::path::Path;

use vlem_backends::clip::ClipModel;
use vlem_backends::{ComputeDevice, ModelDtype};
use vlem_core::{BuildContext, Registry, StageConfig};

#[test]
fn tf32_is_refused_on_the_cpu_and_with_half_precision() {
    let e = ComputeDevice::Cpu
        .open_for(ModelDtype::F32, Some(true))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("tf32 = true") && e.contains("device = \"cpu\""),
        "{e}"
    );
    // Checked before the device is opened: the same message in a build without CUDA.
    let e = ComputeDevice::Cuda(0)
        .open_for(ModelDtype::F16, Some(true))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("dtype = \"f16\"") && e.contains("half precision"),
        "{e}"
    );
    // Off, or unset, is fine anywhere.
    for tf32 in [None, Some(false)] {
        assert!(ComputeDevice::Cpu.open_for(ModelDtype::F32, tf32).is_ok());
    }
    // Through a section's key, with the stage named.
    let mut stage = StageConfig::named("clip");
    stage
        .params
        .insert("tf32".into(), toml::Value::Boolean(true));
    let tiny = Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/clip/tiny-gelu");
    stage.params.insert(
        "model_dir".into(),
        toml::Value::String(tiny.display().to_string()),
    );
    let err = Registry::global()
        .unwrap()
        .build_encoder(&stage, &BuildContext::default())
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(err.contains("clip") && err.contains("tf32 = true"), "{err}");
}

/// On a GPU: the tiny CLIP's text and image features with TF32 products against the same model
/// without (TF32 keeps 10 mantissa bits of each input, as f16 does: the same bound). On the CPU
/// there is nothing to switch, and the test says so.
#[test]
fn tf32_products_stay_close_to_f32_on_a_gpu() {
    let asked = common::compute_device();
    if asked == ComputeDevice::Cpu {
        println!("tf32 needs a GPU: run with VLEM_TEST_DEVICE=cuda (bench/gpu/check.sh part 1)");
        return;
    }
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/clip/tiny-gelu");
    let texts = ["a photo of a cat", "a red sofa", "the coffee machine"];
    let pixels: Vec<f32> = (0..4 * 3 * 32 * 32)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    let run = |tf32: bool| {
        let device = asked.open_for(ModelDtype::F32, Some(tf32)).unwrap();
        let model = ClipModel::load(&dir, &device, ModelDtype::F32).unwrap();
        let mut out = model.text_features(&texts).unwrap();
        out.extend(model.image_features(&pixels, 4).unwrap());
        out
    };
    let exact = run(false);
    let tf32 = run(true);
    let least = exact
        .iter()
        .zip(&tf32)
        .map(|(a, b)| common::least_row_cosine(b, a, a.len()))
        .fold(1.0, f32::min);
    run(false);
    println!("tf32 against f32 products: least cosine {least:.6}");
    let bound = common::half_precision_bound(ModelDtype::F16);
    assert!(least >= bound, "cosine {least} < {bound}");
}
