//! CPU kernels for the places where candle's CPU ops cost more than their arithmetic: a matrix
//! product into a caller's buffer, `exp` and the exact GELU in vectorisable loops, and the models'
//! activations and softmax as candle ops that use them on the CPU.
//!
//! Why it exists: on the CPU every candle op allocates its output and makes one pass over memory,
//! so a chain of cheap element-wise ops over large intermediates (SAM's mask decoder upscales each
//! prompt to 4-8 MB tensors) is bound by allocation, page faults and memory traffic; and candle
//! computes `exp` and the exact GELU's `erf` with scalar library calls on one thread (together
//! ~18 % of a NARADIO frame). Fused loops over cache-sized bands use [`matmul`] and [`erf`]; the
//! models' GELU, quick GELU and softmax go through [`gelu_erf`], [`quick_gelu`] and
//! [`softmax_last_dim`], which run these loops on both cores for CPU tensors (half precision
//! through f32, as PyTorch accumulates) and are candle's own ops on every other device (so model
//! code stays device-generic).
//!
//! The element-wise loops are written once, in plain Rust, and built twice: for baseline x86-64
//! and for AVX2 with FMA, picked at run time (module `wide`, bit-identical results).
//!
//! `unsafe` here (the workspace denies it elsewhere; the crate's only other place is the two
//! `mallopt` calls of `allocator.rs`): [`matmul`] calls the `gemm` crate, candle's own CPU matrix
//! product, whose entry point takes raw pointers and strides. The wrapper checks every length
//! before the call, so the pointers always cover the matrices. And `wide` calls the AVX2 build of
//! a loop only after asking the CPU whether it has AVX2 and FMA.

/// `out = lhs · rhs` for row-major `lhs` (`m × k`), `rhs` (`k × n`) and `out` (`m × n`), on the
/// calling thread (callers parallelise over independent products).
///
/// # Panics
/// When a slice is shorter than its matrix: a caller's size bug, never a user input.
pub fn matmul(lhs: &[f32], rhs: &[f32], out: &mut [f32], (m, k, n): (usize, usize, usize)) {
    product(lhs, (rhs, false), out, (m, k, n));
}

/// `out = lhs · rhsᵀ` for row-major `lhs` (`m × k`), `rhs` (`n × k`) and `out` (`m × n`), on the
/// calling thread: queries against keys, the keys read in place (the product packs its operands
/// anyway, so the transpose costs nothing).
///
/// # Panics
/// As [`matmul`].
pub fn matmul_by_transpose(
    lhs: &[f32],
    rhs: &[f32],
    out: &mut [f32],
    (m, k, n): (usize, usize, usize),
) {
    product(lhs, (rhs, true), out, (m, k, n));
}

/// [`matmul`], or [`matmul_by_transpose`] where `rhs.1`.
#[allow(
    unsafe_code,
    reason = "the one call into gemm's raw-pointer API, after its length checks"
)]
fn product(
    lhs: &[f32],
    (rhs, transposed): (&[f32], bool),
    out: &mut [f32],
    (m, k, n): (usize, usize, usize),
) {
    assert!(
        lhs.len() >= m * k && rhs.len() >= k * n && out.len() >= m * n,
        "matmul: slices of {}, {} and {} values for a {m}x{k} by {k}x{n} product",
        lhs.len(),
        rhs.len(),
        out.len()
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        out[..m * n].fill(0.0);
        return;
    }
    let stride = |v: usize| isize::try_from(v).unwrap_or(isize::MAX);
    // Element (row, column) of `rhs` as a `k × n` matrix: `row · n + column` in place, `column
    // · k + row` when it holds the transpose.
    let (rhs_column_stride, rhs_row_stride) = if transposed {
        (stride(k), 1)
    } else {
        (1, stride(n))
    };
    // SAFETY: the assert above makes `lhs`, `rhs` and `out` cover `m*k`, `k*n` and `m*n`
    // elements, which is every offset `gemm` forms from these strides (a `k × n` matrix stored
    // row-major or, transposed, as `n × k` row-major: the largest offset is `k*n - 1` either
    // way); `out` is a unique borrow, so it aliases neither input. `read_dst = false` means
    // `out` is only written (alpha is ignored), `beta = 1` is the plain product, and the
    // conjugation flags are no-ops for reals.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            stride(n),
            false,
            lhs.as_ptr(),
            1,
            stride(k),
            rhs.as_ptr(),
            rhs_column_stride,
            rhs_row_stride,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// `erf(x)` in f32 as a rational function of `x²` on `[-4, 4]` (outside, `erf` is ±1 to f32
/// precision), with no branch and no call, so loops over it vectorise. Absolute error below 5e-7
/// against the exact function (the test measures it; most of it is f32 rounding near ±1), where
/// `libm`'s `erff`, which candle calls, is within an ulp.
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    // Minimax coefficients of the numerator (x times a degree-6 polynomial in x²) and the
    // denominator (degree 4 in x²), highest power first.
    const P: [f32; 7] = [
        -2.726_142_3e-10,
        2.770_681_4e-8,
        -2.101_024e-6,
        -5.692_506_4e-5,
        -7.349_906_3e-4,
        -2.9546e-3,
        -1.609_603_3e-2,
    ];
    const Q: [f32; 5] = [
        -1.456_607_2e-5,
        -2.133_740_6e-4,
        -1.682_827e-3,
        -7.373_329e-3,
        -1.426_474e-2,
    ];
    // Plain multiply-adds: `mul_add` is a library call on CPUs built for without FMA.
    let x = x.clamp(-4.0, 4.0);
    let x2 = x * x;
    let mut p = P[0];
    for c in &P[1..] {
        p = p * x2 + c;
    }
    let mut q = Q[0];
    for c in &Q[1..] {
        q = q * x2 + c;
    }
    x * p / q
}

/// PyTorch's exact GELU, `x/2 · (1 + erf(x/√2))`, in place.
pub fn gelu_erf_in_place(xs: &mut [f32]) {
    wide::gelu_erf_in_place(xs);
}

#[inline(always)]
fn gelu_erf_plain(xs: &mut [f32]) {
    for x in xs {
        *x = 0.5 * *x * (1.0 + erf(*x * std::f32::consts::FRAC_1_SQRT_2));
    }
}

/// LayerNorm of one row in place, as candle and PyTorch compute it: the mean, the centred values,
/// the mean of their squares, division by `√(var + eps)`, then `weight` and `bias`.
pub fn layer_norm_in_place(row: &mut [f32], weight: &[f32], bias: &[f32], eps: f32) {
    let n = row.len().max(1) as f32;
    let mean = row.iter().sum::<f32>() / n;
    let mut var = 0.0f32;
    for v in row.iter_mut() {
        *v -= mean;
        var += *v * *v;
    }
    let root = (var / n + eps).sqrt();
    for ((v, w), b) in row.iter_mut().zip(weight).zip(bias) {
        *v = *v / root * w + b;
    }
}

/// `eˣ` in f32 without a call, so loops over it vectorise: `x = n·ln 2 + r` with `|r| ≤ ln 2 / 2`,
/// `eʳ` by its degree-7 Taylor polynomial (truncation below 2e-9 relative), `2ⁿ` built in the
/// exponent bits. Relative error within a few ulp (the test measures it); inputs are clamped to
/// `[-87.3, 88]`, so results stay normal numbers (`e^-87.3` ≈ 1.2e-38 instead of smaller
/// values or 0: below f32's precision of anything it is added to), `+∞` is never returned.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    // ln 2 split in a part with few mantissa bits (exact products with n) and the rest.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 · 2²³: adding and subtracting it rounds to the nearest integer.
    const ROUND: f32 = 12_582_912.0;
    // Compare-and-select rather than `clamp`: the same values, a NaN passes through as NaN, and
    // each is one vector instruction (`clamp`'s and `max`'s NaN rules cost a compare and blend).
    let x = if x < -87.3 { -87.3 } else { x };
    let x = if x > 88.0 { 88.0 } else { x };
    let rounded = x * std::f32::consts::LOG2_E + ROUND;
    let n = rounded - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let mut p = 1.0 / 5040.0;
    for c in [
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ] {
        p = p * r + c;
    }
    // 2ⁿ from `rounded`'s bits, where the integer `n` sits in the low mantissa bits (`rounded` =
    // 1.5 · 2²³ + n, and 2²³ ≤ rounded < 2²⁴ has a spacing of 1): integer arithmetic on the
    // bits instead of `n as i32`, whose saturating conversion does not vectorise well.
    let biased = rounded
        .to_bits()
        .wrapping_sub(ROUND.to_bits())
        .wrapping_add(127);
    p * f32::from_bits(biased << 23)
}

/// CLIP's quick GELU, `x · σ(1.702 x)`, in place.
pub fn quick_gelu_in_place(xs: &mut [f32]) {
    wide::quick_gelu_in_place(xs);
}

#[inline(always)]
fn quick_gelu_plain(xs: &mut [f32]) {
    for x in xs {
        *x /= 1.0 + exp(-1.702 * *x);
    }
}

/// Softmax of each run of `len` consecutive values, in place.
pub fn softmax_runs(values: &mut [f32], len: usize) {
    wide::softmax_runs(values, len);
}

#[inline(always)]
fn softmax_runs_plain(values: &mut [f32], len: usize) {
    if len == 0 {
        return;
    }
    for run in values.chunks_exact_mut(len) {
        let max = max_lanes(run);
        // Separate loops: a running sum in the `exp` loop would keep it from vectorising.
        for v in run.iter_mut() {
            *v = exp(*v - max);
        }
        let inv = 1.0 / sum_lanes(run);
        for v in run.iter_mut() {
            *v *= inv;
        }
    }
}

/// The sum of `values` in eight interleaved partial sums, which vectorise (a single running sum
/// is one dependent add per element).
#[inline(always)]
pub fn sum_lanes(values: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let chunks = values.chunks_exact(8);
    let rest: f32 = chunks.remainder().iter().sum();
    for chunk in chunks {
        for (l, v) in lanes.iter_mut().zip(chunk) {
            *l += v;
        }
    }
    lanes.iter().sum::<f32>() + rest
}

/// The largest of `values` (`-∞` for none) in eight interleaved lanes, like [`sum_lanes`].
#[inline(always)]
pub fn max_lanes(values: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; 8];
    let chunks = values.chunks_exact(8);
    let rest = chunks
        .remainder()
        .iter()
        .fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    for chunk in chunks {
        for (l, &v) in lanes.iter_mut().zip(chunk) {
            *l = if v > *l { v } else { *l };
        }
    }
    lanes.iter().fold(rest, |m, &v| m.max(v))
}

/// The loops above compiled a second time for AVX2 and FMA, chosen at run time where the CPU has
/// them, else the plain build (the crate is built for baseline x86-64, whose SSE2 vectors hold
/// four floats, not eight).
///
/// Why: on a CPU without AVX-512, where the matrix products are slowest relative to PyTorch
/// (BENCHMARKS.md, "The same table on a CPU without AVX-512"), the softmax of NARADIO B/16's
/// attention scores took ~65 of a layer's 159 ms of attention at one thread. The wide build runs
/// the same operations in the same order on wider vectors (Rust never contracts `a * b + c` into
/// an FMA on its own, and the sums and maxima keep their eight explicit lanes), so its results
/// are the plain build's, bit for bit (the tests compare them).
mod wide {
    #[cfg(target_arch = "x86_64")]
    pub(super) fn has_avx2() -> bool {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }

    /// One wide twin per loop: `$name` calls `$plain` compiled with AVX2 and FMA where the CPU
    /// has both, the plain build elsewhere.
    macro_rules! twin {
        ($name:ident, $plain:path, ($($arg:ident: $ty:ty),*)) => {
            pub(super) fn $name($($arg: $ty),*) {
                #[cfg(target_arch = "x86_64")]
                {
                    #[target_feature(enable = "avx2,fma")]
                    fn avx2($($arg: $ty),*) {
                        $plain($($arg),*)
                    }
                    if has_avx2() {
                        #[allow(
                            unsafe_code,
                            reason = "calling the AVX2 build of a loop, after checking that the \
                                      CPU has AVX2 and FMA"
                        )]
                        // SAFETY: `has_avx2` checked the features `avx2` was compiled for.
                        unsafe {
                            avx2($($arg),*)
                        };
                        return;
                    }
                }
                $plain($($arg),*)
            }
        };
    }

    twin!(gelu_erf_in_place, super::gelu_erf_plain, (xs: &mut [f32]));
    twin!(quick_gelu_in_place, super::quick_gelu_plain, (xs: &mut [f32]));
    twin!(softmax_runs, super::softmax_runs_plain, (values: &mut [f32], len: usize));
}

/// Elements per parallel task of the element-wise ops: large enough that a task's work dwarfs
/// rayon's overhead, small enough that both cores get work on a ViT's activations.
const TASK: usize = 1 << 15;

/// An f32 element-wise op, or a softmax over the last dimension, on a CPU tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum CpuOp {
    GeluErf,
    QuickGelu,
    SoftmaxLastDim,
}

impl candle_core::CustomOp1 for CpuOp {
    fn name(&self) -> &'static str {
        match self {
            CpuOp::GeluErf => "vlem-gelu-erf",
            CpuOp::QuickGelu => "vlem-quick-gelu",
            CpuOp::SoftmaxLastDim => "vlem-softmax-last-dim",
        }
    }

    fn cpu_fwd(
        &self,
        storage: &candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
        use rayon::prelude::*;
        let (candle_core::CpuStorage::F32(values), Some((start, end))) =
            (storage, layout.contiguous_offsets())
        else {
            return Err(candle_core::Error::Msg(format!(
                "{} takes a contiguous f32 tensor",
                self.name()
            )));
        };
        let mut out = values[start..end].to_vec();
        match self {
            CpuOp::GeluErf => out.par_chunks_mut(TASK).for_each(gelu_erf_in_place),
            CpuOp::QuickGelu => out.par_chunks_mut(TASK).for_each(quick_gelu_in_place),
            CpuOp::SoftmaxLastDim => {
                let len = layout.dims().last().copied().unwrap_or(1).max(1);
                let rows = (TASK / len).max(1);
                out.par_chunks_mut(rows * len)
                    .for_each(|chunk| softmax_runs(chunk, len));
            }
        }
        Ok((candle_core::CpuStorage::F32(out), layout.shape().clone()))
    }
}

/// Runs `op` on a CPU tensor, `fallback` (candle's own op) on other devices. Half-precision CPU
/// tensors go through f32 and back: candle's CPU softmax sums in the tensor's type, and 4096
/// exponentials summed in f16 lose the precision a model in half keeps elsewhere (on CUDA,
/// candle's softmax accumulates in f32 itself).
fn on_cpu_or(
    x: &candle_core::Tensor,
    op: CpuOp,
    fallback: impl FnOnce(&candle_core::Tensor) -> candle_core::Result<candle_core::Tensor>,
) -> candle_core::Result<candle_core::Tensor> {
    use candle_core::DType;
    match x.dtype() {
        DType::F32 if x.device().is_cpu() => x.contiguous()?.apply_op1_no_bwd(&op),
        half @ (DType::F16 | DType::BF16) if x.device().is_cpu() => x
            .to_dtype(DType::F32)?
            .apply_op1_no_bwd(&op)?
            .to_dtype(half),
        _ => fallback(x),
    }
}

/// The exact GELU (PyTorch's `nn.GELU()`, candle's `gelu_erf`).
///
/// # Errors
/// Candle's, on other devices.
pub fn gelu_erf(x: &candle_core::Tensor) -> candle_core::Result<candle_core::Tensor> {
    on_cpu_or(x, CpuOp::GeluErf, |x| x.gelu_erf())
}

/// CLIP's quick GELU, `x · σ(1.702 x)`.
///
/// # Errors
/// Candle's, on other devices.
pub fn quick_gelu(x: &candle_core::Tensor) -> candle_core::Result<candle_core::Tensor> {
    on_cpu_or(x, CpuOp::QuickGelu, |x| {
        x * candle_nn::ops::sigmoid(&(x * 1.702)?)?
    })
}

/// Softmax over the last dimension (candle-nn's `softmax_last_dim`).
///
/// # Errors
/// Candle's, on other devices.
pub fn softmax_last_dim(x: &candle_core::Tensor) -> candle_core::Result<candle_core::Tensor> {
    on_cpu_or(x, CpuOp::SoftmaxLastDim, candle_nn::ops::softmax_last_dim)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `erf` in f64 by its Maclaurin series (|x| ≤ 3) or continued fraction of `erfc` (beyond),
    /// accurate to ~1e-13: a reference independent of the rational approximation.
    fn erf_reference(x: f64) -> f64 {
        if x.abs() <= 3.0 {
            let mut term = x;
            let mut sum = x;
            for n in 1..200 {
                term *= -x * x / n as f64;
                sum += term / (2 * n + 1) as f64;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc(x) = exp(-x²)/√π · 1/(x + 1/2/(x + 1/(x + 3/2/(x + ...)))).
            let a = x.abs();
            let mut f = 0.0;
            for n in (1..60).rev() {
                f = (n as f64 / 2.0) / (a + f);
            }
            let erfc = (-a * a).exp() / std::f64::consts::PI.sqrt() / (a + f);
            (1.0 - erfc).copysign(x)
        }
    }

    #[test]
    fn erf_is_within_5e7_of_the_exact_function() {
        let mut worst = 0.0f64;
        for i in -80_000..=80_000 {
            let x = i as f32 * 1e-4;
            let err = (f64::from(erf(x)) - erf_reference(f64::from(x))).abs();
            worst = worst.max(err);
        }
        assert!(worst < 5e-7, "max error {worst:e}");
        assert_eq!(erf(0.0), 0.0);
        assert_eq!(erf(-1.5), -erf(1.5));
        assert!((erf(100.0) - 1.0).abs() < 5e-7 && (erf(-1e30) + 1.0).abs() < 5e-7);
    }

    #[test]
    fn gelu_matches_the_plain_formula() {
        let mut xs: Vec<f32> = (-500..=500).map(|i| i as f32 * 0.013).collect();
        let expected: Vec<f64> = xs
            .iter()
            .map(|&x| {
                let x = f64::from(x);
                0.5 * x * (1.0 + erf_reference(x / std::f64::consts::SQRT_2))
            })
            .collect();
        gelu_erf_in_place(&mut xs);
        for (got, want) in xs.iter().zip(&expected) {
            assert!((f64::from(*got) - want).abs() < 1e-6, "{got} vs {want}");
        }
    }

    #[test]
    fn exp_is_within_a_few_ulp() {
        let mut worst = 0.0f64;
        for i in -87_000..=87_900 {
            let x = i as f32 * 1e-3 + 0.000_37;
            let want = f64::from(x).exp();
            worst = worst.max((f64::from(exp(x)) - want).abs() / want);
        }
        assert!(worst < 4e-7, "max relative error {worst:e}");
        assert_eq!(exp(0.0), 1.0);
        assert!(exp(-1000.0) > 0.0 && exp(-1000.0) < 2e-38);
        assert!(exp(f32::NEG_INFINITY) < 2e-38 && exp(1000.0).is_finite());
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn exp_gives_the_bits_of_its_clamp_and_cast_form() {
        // The form `exp` had before its compare-and-select and its 2ⁿ from bits (both chosen
        // for speed): the same value for every input.
        fn clamp_and_cast(x: f32) -> f32 {
            let x = x.clamp(-87.3, 88.0);
            let n = (x * std::f32::consts::LOG2_E + 12_582_912.0) - 12_582_912.0;
            let r = (x - n * 0.693_359_4) - n * -2.121_944_4e-4;
            let mut p = 1.0 / 5040.0;
            for c in [
                1.0 / 720.0,
                1.0 / 120.0,
                1.0 / 24.0,
                1.0 / 6.0,
                0.5,
                1.0,
                1.0,
            ] {
                p = p * r + c;
            }
            p * f32::from_bits(((n as i32 + 127) as u32) << 23)
        }
        let edges = [
            f32::NEG_INFINITY,
            f32::INFINITY,
            -1e30,
            1e30,
            -87.31,
            -87.3,
            87.99,
            88.0,
        ];
        for x in (-1_000_000..1_000_000)
            .map(|i| i as f32 * 1e-4)
            .chain(edges)
        {
            assert_eq!(exp(x).to_bits(), clamp_and_cast(x).to_bits(), "{x}");
        }
    }

    #[test]
    fn tensor_ops_match_candles_own() -> candle_core::Result<()> {
        use candle_core::{Device, Tensor};
        let values: Vec<f32> = (0..3 * 70_001)
            .map(|i| ((i * 37) % 1001) as f32 * 0.013 - 6.5)
            .collect();
        let x = Tensor::from_vec(values, (3, 70_001), &Device::Cpu)?;
        let max_diff = |a: &Tensor, b: &Tensor| -> candle_core::Result<f32> {
            (a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()
        };
        assert!(max_diff(&gelu_erf(&x)?, &x.gelu_erf()?)? < 2e-6);
        let quick = (&x * candle_nn::ops::sigmoid(&(&x * 1.702)?)?)?;
        assert!(max_diff(&quick_gelu(&x)?, &quick)? < 2e-6);
        // Rows of several lengths, one longer than a task; a transposed (strided) input.
        for len in [1, 7, 197, 40_000] {
            let y = x.flatten_all()?.narrow(0, 0, 4 * len)?.reshape((4, len))?;
            let want = candle_nn::ops::softmax_last_dim(&y)?;
            assert!(max_diff(&softmax_last_dim(&y)?, &want)? < 1e-6, "len {len}");
        }
        let t = x.narrow(1, 0, 500)?.t()?;
        let want = candle_nn::ops::softmax_last_dim(&t.contiguous()?)?;
        assert!(max_diff(&softmax_last_dim(&t)?, &want)? < 1e-6);
        Ok(())
    }

    #[test]
    fn the_wide_loops_give_the_plain_loops_bits() {
        // Odd lengths (a remainder after the vectors), extremes that the clamps cut, and rows
        // of several lengths for the softmax.
        let values: Vec<f32> = (0..10_007)
            .map(|i| ((i * 7919) % 20_011) as f32 * 0.0011 - 11.0)
            .chain([0.0, -0.0, 1e30, -1e30, 88.5, -90.0, f32::MIN_POSITIVE])
            .collect();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
        let (mut wide, mut plain) = (values.clone(), values.clone());
        gelu_erf_in_place(&mut wide);
        gelu_erf_plain(&mut plain);
        assert_eq!(bits(&wide), bits(&plain), "gelu");
        let (mut wide, mut plain) = (values.clone(), values.clone());
        quick_gelu_in_place(&mut wide);
        quick_gelu_plain(&mut plain);
        assert_eq!(bits(&wide), bits(&plain), "quick gelu");
        for len in [1, 3, 8, 197, 1208, 10_014] {
            let n = values.len() / len * len;
            let (mut wide, mut plain) = (values[..n].to_vec(), values[..n].to_vec());
            softmax_runs(&mut wide, len);
            softmax_runs_plain(&mut plain, len);
            assert_eq!(bits(&wide), bits(&plain), "softmax of runs of {len}");
        }
        #[cfg(target_arch = "x86_64")]
        if !wide::has_avx2() {
            eprintln!("this CPU has no AVX2 and FMA: both sides ran the plain loops");
        }
    }

    #[test]
    fn matmul_matches_the_plain_triple_loop() {
        for (m, k, n) in [
            (1, 1, 1),
            (3, 5, 7),
            (37, 64, 19),
            (130, 256, 33),
            (4, 0, 3),
        ] {
            let lhs: Vec<f32> = (0..m * k).map(|i| ((i * 7) % 13) as f32 - 6.0).collect();
            let rhs: Vec<f32> = (0..k * n)
                .map(|i| ((i * 5) % 11) as f32 * 0.5 - 2.0)
                .collect();
            let mut out = vec![f32::NAN; m * n];
            matmul(&lhs, &rhs, &mut out, (m, k, n));
            for i in 0..m {
                for j in 0..n {
                    let want: f32 = (0..k).map(|p| lhs[i * k + p] * rhs[p * n + j]).sum();
                    assert!(
                        (out[i * n + j] - want).abs() < 1e-3,
                        "({i},{j}) of {m}x{k}x{n}"
                    );
                }
            }
        }
    }
}
