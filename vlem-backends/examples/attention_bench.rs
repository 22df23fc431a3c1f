//! The attention step alone, fused against unfused: milliseconds per call of
//! `softmax(q·kᵀ·scale)·v` at the models' shapes (`vlem_backends::fused_attention`), in f16 and
//! bf16 with the fused kernel and without, and in f32 without (the models' default). One JSON
//! line per shape and type, the same shapes and fields as `bench/attention/sdpa_bench.py` prints
//! for PyTorch's `scaled_dot_product_attention`, so the two can be read side by side.
//!
//! ```text
//! VLEM_BENCH_DEVICE=cuda target/release/examples/attention_bench [iterations]
//! ```
//! On the CPU the fused side is the kernel's plain twin (a test path, not a fast one).

use std::time::Instant;

use anyhow::Result;
use candle_core::{DType, Device, Tensor};
use vlem_backends::fused_attention::{scaled_dot_product, supports, unfused_scaled_dot_product};

/// (name, batch, heads, tokens, head_dim): the models' attention at their benchmarks' inputs.
const SHAPES: [(&str, usize, usize, usize, usize); 5] = [
    ("clip-b16-batch32", 32, 12, 197, 64),
    ("naradio-b16-640x480", 1, 12, 1208, 64),
    ("naradio-l16-640x480", 1, 16, 1208, 64),
    ("dinov3-l16-448", 1, 16, 789, 64),
    ("tokens-4096", 1, 16, 4096, 64),
];

/// Milliseconds per call of `f`, the device synchronised, after one call to warm up.
fn time(device: &Device, iterations: usize, f: impl Fn() -> Result<Tensor>) -> Result<f64> {
    f()?;
    device.synchronize()?;
    let start = Instant::now();
    for _ in 0..iterations {
        f()?;
    }
    device.synchronize()?;
    Ok(start.elapsed().as_secs_f64() * 1e3 / iterations as f64)
}

fn main() -> Result<()> {
    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    let iterations: usize = std::env::args().nth(1).map_or(Ok(20), |s| s.parse())?;
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    let device_name = if device.is_cuda() { "cuda" } else { "cpu" };
    for (name, batch, heads, tokens, head_dim) in SHAPES {
        let shape = (batch, heads, tokens, head_dim);
        let q = Tensor::randn(0f32, 1.0, shape, &device)?;
        let k = Tensor::randn(0f32, 1.0, shape, &device)?;
        let v = Tensor::randn(0f32, 1.0, shape, &device)?;
        let scale = (head_dim as f64).powf(-0.5);
        for dtype in [DType::F32, DType::F16, DType::BF16] {
            let (q, k, v) = (q.to_dtype(dtype)?, k.to_dtype(dtype)?, v.to_dtype(dtype)?);
            let unfused = time(&device, iterations, || {
                Ok(unfused_scaled_dot_product(&q, &k, &v, scale)?)
            })?;
            let fused = if supports(&q, &k, &v) && (device.is_cuda() || tokens <= 1208) {
                Some(time(&device, iterations.min(3), || {
                    Ok(scaled_dot_product(&q, &k, &v, scale)?)
                })?)
            } else {
                None
            };
            let fused_json = fused.map_or("null".to_owned(), |ms| format!("{ms:.4}"));
            let ratio = fused.map_or("null".to_owned(), |ms| format!("{:.2}", unfused / ms));
            println!(
                "{{\"impl\": \"vlem\", \"shape\": \"{name}\", \"batch\": {batch}, \"heads\": \
                 {heads}, \"tokens\": {tokens}, \"head_dim\": {head_dim}, \"device\": \
                 \"{device_name}\", \"dtype\": \"{}\", \"unfused_ms\": {unfused:.4}, \
                 \"fused_ms\": {fused_json}, \"unfused_over_fused\": {ratio}}}",
                dtype.as_str()
            );
        }
    }
    Ok(())
}
