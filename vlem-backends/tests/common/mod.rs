//! What the candle backends' golden tests share: the device they run on.
//!
//! The tests run on the CPU. `VLEM_TEST_DEVICE=cuda` (or `cuda:N`; set by `bench/gpu/check.sh`)
//! runs the same goldens on a GPU of a build with feature `cuda`, where kernels sum in other
//! orders: tolerances then widen to 1e-3 (the bar for f32 on a GPU).

#![allow(
    dead_code,
    reason = "each test binary includes this module and uses part of it"
)]

use std::sync::OnceLock;

use candle_core::Device;
use vlem_backends::ComputeDevice;

/// The environment variable naming the device the goldens run on.
pub const DEVICE_ENV: &str = "VLEM_TEST_DEVICE";

/// The configured device (`"cpu"` when unset), as a config's `device` key spells it.
pub fn compute_device() -> ComputeDevice {
    static DEVICE: OnceLock<ComputeDevice> = OnceLock::new();
    *DEVICE.get_or_init(|| ComputeDevice::from_env(DEVICE_ENV).unwrap_or_else(|e| panic!("{e}")))
}

/// The device the goldens run on, opened.
pub fn device() -> Device {
    compute_device()
        .open()
        .unwrap_or_else(|e| panic!("{DEVICE_ENV}: {e}"))
}

/// The `device = "…"` line for a test's encoder or proposer section.
pub fn device_line() -> String {
    format!("device = \"{}\"", compute_device())
}

/// `cpu`, the tolerance of a comparison on the CPU; at least 1e-3 on a GPU.
pub fn tolerance(cpu: f32) -> f32 {
    if compute_device() == ComputeDevice::Cpu {
        cpu
    } else {
        cpu.max(1e-3)
    }
}

/// The least cosine between matching rows of `dim` values of `got` and `want` (row-major, the
/// same length): how half-precision embeddings are held to their f32 goldens. A row with a value
/// that is not finite counts as -1 (`f32::min` alone would skip a NaN).
pub fn least_row_cosine(got: &[f32], want: &[f32], dim: usize) -> f32 {
    assert_eq!(got.len(), want.len(), "rows of different lengths");
    assert!(
        dim > 0 && got.len().is_multiple_of(dim),
        "{} values in rows of {dim}",
        got.len()
    );
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
    got.chunks(dim)
        .zip(want.chunks(dim))
        .map(|(g, w)| {
            let dot: f32 = g.iter().zip(w).map(|(a, b)| a * b).sum();
            let cosine = dot / (norm(g) * norm(w)).max(f32::MIN_POSITIVE);
            if cosine.is_finite() { cosine } else { -1.0 }
        })
        .fold(1.0, f32::min)
}

/// The least cosine a model in half precision must keep to its f32 goldens, per embedding: f16
/// keeps 11 significant bits, bf16 8.
pub fn half_precision_bound(dtype: vlem_backends::ModelDtype) -> f32 {
    match dtype {
        vlem_backends::ModelDtype::F32 => 0.99999,
        vlem_backends::ModelDtype::F16 => 0.9995,
        vlem_backends::ModelDtype::Bf16 => 0.995,
    }
}
