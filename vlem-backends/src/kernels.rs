//! CPU kernels for the places where a chain of candle ops costs more than its arithmetic: a matrix
//! product into a caller's buffer, and the exact GELU in one vectorisable pass.
//!
//! Why it exists: on the CPU every candle op allocates its output and makes one pass over memory,
//! so a chain of cheap element-wise ops over large intermediates (SAM's mask decoder upscales each
//! prompt to 4-8 MB tensors) is bound by allocation, page faults and memory traffic, and candle's
//! exact GELU calls the scalar `erf` of `libm` per element. A fused loop over a cache-sized band
//! with these two kernels does the same arithmetic without that. The callers keep the candle op
//! chain for other devices and test the fused loop against it.
//!
//! `unsafe` lives here alone (the workspace denies it elsewhere): [`matmul`] calls the `gemm`
//! crate, candle's own CPU matrix product, whose entry point takes raw pointers and strides. The
//! wrapper checks every length before the call, so the pointers always cover the matrices.

/// `out = lhs · rhs` for row-major `lhs` (`m × k`), `rhs` (`k × n`) and `out` (`m × n`), on the
/// calling thread (callers parallelise over independent products).
///
/// # Panics
/// When a slice is shorter than its matrix: a caller's size bug, never a user input.
#[allow(
    unsafe_code,
    reason = "the one call into gemm's raw-pointer API, after its length checks"
)]
pub fn matmul(lhs: &[f32], rhs: &[f32], out: &mut [f32], (m, k, n): (usize, usize, usize)) {
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
    // SAFETY: the assert above makes `lhs`, `rhs` and `out` cover `m*k`, `k*n` and `m*n`
    // elements, which is every offset `gemm` forms from these row-major strides (row stride the
    // column count, column stride 1); `out` is a unique borrow, so it aliases neither input.
    // `read_dst = false` means `out` is only written (alpha is ignored), `beta = 1` is the plain
    // product, and the conjugation flags are no-ops for reals.
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
            1,
            stride(n),
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
    for x in xs {
        *x = 0.5 * *x * (1.0 + erf(*x * std::f32::consts::FRAC_1_SQRT_2));
    }
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
