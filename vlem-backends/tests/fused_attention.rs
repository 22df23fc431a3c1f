#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The fused attention (`vlem_backends::fused_attention`) against attention in f32 on the same
//! half-precision inputs: on the CPU its plain twin (the kernel's tiles, online softmax and
//! roundings), on a GPU (`VLEM_TEST_DEVICE=cuda`, `bench/gpu/check.sh` part 1) the CUDA kernel
//! itself. Shapes cover partial query blocks and key tiles, one key, more keys than queries and
//! the reverse, both head widths and both half types; and a NARADIO trunk in f16 through the
//! models' path with the switch on and off.
#![cfg(any(
    feature = "clip",
    feature = "dinov3",
    feature = "naradio",
    feature = "sam"
))]

mod common;

use candle_core::{DType, Device, Tensor};
use vlem_backends::fused_attention::{
    HEAD_DIMS, KEY_TILE, scaled_dot_product, supports, unfused_scaled_dot_product,
};

/// Deterministic values in `[-amplitude, amplitude)` of `shape`, rounded to `dtype`.
fn values(
    shape: (usize, usize, usize, usize),
    amplitude: f32,
    seed: u64,
    dtype: DType,
    device: &Device,
) -> Tensor {
    let (a, b, c, d) = shape;
    let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15).wrapping_add(1);
    let data: Vec<f32> = (0..a * b * c * d)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * amplitude
        })
        .collect();
    Tensor::from_vec(data, shape, device)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// Attention in f32 over the same (rounded) inputs.
fn reference(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Tensor {
    let f = |t: &Tensor| t.to_dtype(DType::F32).unwrap();
    let logits = (f(q).matmul(&f(k).t().unwrap()).unwrap() * scale).unwrap();
    candle_nn_free_softmax(&logits).matmul(&f(v)).unwrap()
}

/// Softmax over the last dimension in f32 (the test's own, independent of the crate's kernels).
fn candle_nn_free_softmax(logits: &Tensor) -> Tensor {
    let max = logits.max_keepdim(3).unwrap();
    let e = logits.broadcast_sub(&max).unwrap().exp().unwrap();
    let sum = e.sum_keepdim(3).unwrap();
    e.broadcast_div(&sum).unwrap()
}

fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a.to_dtype(DType::F32).unwrap() - b.to_dtype(DType::F32).unwrap())
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[test]
fn fused_attention_matches_f32_attention_in_both_half_types() {
    let device = common::device();
    // (batch, heads, queries, keys, head_dim)
    let shapes = [
        (1, 2, 70, 70, 64),
        (2, 3, 130, 129, 32),
        (1, 1, 1, 1, 64),
        (1, 2, 64, 2 * KEY_TILE + 3, 64),
        (1, 1, 200, 17, 32),
        (3, 2, 197, 197, 64),
    ];
    for dtype in [DType::F16, DType::BF16] {
        // Outputs are within ±1: a few units of f16's and bf16's last place there (the twin is
        // within 3.3e-4 and 2.8e-3 on the CPU; the unfused path, which rounds the scores too,
        // 2.9e-3 and 2.0e-2). A wrong tile or rescaling is off by tenths.
        let bound = if dtype == DType::F16 { 2e-3 } else { 1.5e-2 };
        for (i, &(b, h, nq, nk, d)) in shapes.iter().enumerate() {
            let seed = 3 * i as u64;
            // Queries and keys of ±3: scores up to ±9·√d·scale, so the tiles' maxima differ and
            // the running rescaling matters.
            let q = values((b, h, nq, d), 3.0, seed, dtype, &device);
            let k = values((b, h, nk, d), 3.0, seed + 1, dtype, &device);
            let v = values((b, h, nk, d), 1.0, seed + 2, dtype, &device);
            assert!(supports(&q, &k, &v));
            let scale = (d as f64).powf(-0.5);
            let fused = scaled_dot_product(&q, &k, &v, scale).unwrap();
            assert_eq!(fused.dims(), &[b, h, nq, d]);
            assert_eq!(fused.dtype(), dtype);
            let want = reference(&q, &k, &v, scale);
            let diff = max_diff(&fused, &want);
            let unfused = unfused_scaled_dot_product(&q, &k, &v, scale).unwrap();
            let unfused_diff = max_diff(&unfused, &want);
            println!(
                "{dtype:?} {:?}: fused {diff:.2e}, unfused {unfused_diff:.2e} from f32",
                (b, h, nq, nk, d)
            );
            assert!(
                diff <= bound,
                "{dtype:?} {:?}: {diff} from f32 attention (bound {bound})",
                (b, h, nq, nk, d)
            );
        }
    }
}

#[test]
fn the_head_widths_are_the_kernels() {
    assert_eq!(HEAD_DIMS, [32, 64]);
    let device = Device::Cpu;
    let t = |d: usize| values((1, 1, 3, d), 1.0, 0, DType::F16, &device);
    for d in [16, 48, 80, 128] {
        assert!(!supports(&t(d), &t(d), &t(d)), "head width {d}");
        let e = scaled_dot_product(&t(d), &t(d), &t(d), 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("fused attention takes"), "{e}");
    }
}

/// The models' path: a NARADIO trunk (64-wide heads) in f16 with the fused attention turned on
/// gives the features it gives without, within half precision, and not bit for bit (so the
/// switch took the fused path).
#[cfg(feature = "naradio")]
#[test]
fn a_half_precision_trunk_gives_its_features_through_the_fused_attention() {
    use vlem_backends::ModelDtype;
    use vlem_backends::fused_attention::set_enabled;
    use vlem_backends::naradio::{LastBlock, RadioConfig, RadioModel};

    let device = common::device();
    let config = RadioConfig {
        format: "vlem-naradio-1".into(),
        patch_size: 16,
        embed_dim: 128,
        depth: 2,
        num_heads: 2,
        mlp_hidden: 256,
        qkv_bias: true,
        layer_scale: false,
        layer_norm_eps: 1e-6,
        final_norm: false,
        pos_grid: [8, 8],
        num_cls_tokens: 2,
        num_registers: 2,
        summary_idxs: vec![0, 1],
        adaptor: "siglip".into(),
        adaptor_token_slot: 1,
        adaptor_mlp: "v2".into(),
        adaptor_layer_norm_eps: 1e-5,
        feature_normalizer: false,
        input_mean: [0.5; 3],
        input_std: [0.25; 3],
    };
    let model = RadioModel::random(config, 64, 32, &device, ModelDtype::F16).unwrap();
    // 6 x 5 patches: 30 patch tokens and 4 prefix tokens, one partial key tile and query block.
    let x = values((1, 3, 80, 96), 1.0, 7, DType::F32, &device);
    let features = |fused: bool| {
        set_enabled(fused);
        let out = model.forward(&x, LastBlock::Plain).unwrap().features;
        set_enabled(false);
        out.to_dtype(DType::F32).unwrap().flatten_from(1).unwrap()
    };
    let (plain, fused) = (features(false), features(true));
    let plain_rows: Vec<f32> = plain.flatten_all().unwrap().to_vec1().unwrap();
    let fused_rows: Vec<f32> = fused.flatten_all().unwrap().to_vec1().unwrap();
    let least = common::least_row_cosine(&fused_rows, &plain_rows, 128);
    println!("NARADIO trunk f16, fused against unfused: least cosine {least:.6}");
    assert!(least >= 0.9995, "least cosine {least}");
    assert_ne!(plain_rows, fused_rows, "the switch changed nothing");
}
