//! Fused attention: `softmax(q·kᵀ·scale)·v` in one CUDA kernel (`fused_attention.cu`) that never
//! writes the scores to global memory, for half-precision models on an NVIDIA GPU, and its plain
//! twin on the CPU.
//!
//! Why it exists: candle runs attention as two cuBLAS products and a softmax, so every head's
//! `(tokens × tokens)` scores go through global memory twice; at ViT-L's 1200 tokens that traffic
//! is the step's cost, and PyTorch's SDPA (flash attention in half precision) avoids it. The kernel
//! walks the keys in tiles of [`KEY_TILE`] with an online softmax, the products on tensor cores
//! (f16 or bf16 inputs, f32 accumulation), the probabilities rounded to the input type before
//! they multiply the values.
//!
//! The twin ([`scaled_dot_product`] on the CPU) runs the same tiles, the same online softmax and
//! the same roundings in plain loops, so the CPU test suite checks the algorithm; the GPU check
//! (`bench/gpu/check.sh` part 1, `tests/fused_attention.rs` with `VLEM_TEST_DEVICE=cuda`) checks
//! the kernel against the same references. The twin is a test path, not a fast one.
//!
//! The models use it only where [`enabled`] says so (`VLEM_FUSED_ATTENTION=1`, or
//! [`set_enabled`]): it stays opt-in until the GPU check has run the kernel and measured it
//! against the unfused path ([`unfused_scaled_dot_product`], the models' product otherwise).
//! Turned on, every attention it [`supports`] goes through it, on the CPU through the twin (slow:
//! that is for the tests, which run the models' path with it).

use std::sync::atomic::{AtomicU8, Ordering};

use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor, WithDType};

/// Keys per tile of the online softmax, the kernel's and the twin's.
pub const KEY_TILE: usize = 64;

/// The head widths the kernel is built for.
pub const HEAD_DIMS: [usize; 2] = [32, 64];

/// The most (batch × heads) rows one call takes.
pub const MAX_ROWS: usize = 65_535;

/// The environment switch that turns the fused attention on for the models (see [`enabled`]).
pub const ENABLE_ENV: &str = "VLEM_FUSED_ATTENTION";

/// The switch: 0 not read yet, 1 off, 2 on.
static SWITCH: AtomicU8 = AtomicU8::new(0);

/// Whether the models run their attention through [`scaled_dot_product`] where it [`supports`]
/// the inputs: as [`set_enabled`] last said, else `VLEM_FUSED_ATTENTION=1` (read once).
pub fn enabled() -> bool {
    match SWITCH.load(Ordering::Relaxed) {
        0 => {
            let on = std::env::var(ENABLE_ENV).is_ok_and(|v| v.trim() == "1");
            set_enabled(on);
            on
        }
        state => state == 2,
    }
}

/// Turns the fused attention on or off for the whole process (like cuBLAS's TF32 switch, one
/// setting for every model), over `VLEM_FUSED_ATTENTION`.
pub fn set_enabled(on: bool) {
    SWITCH.store(if on { 2 } else { 1 }, Ordering::Relaxed);
}

/// Whether [`scaled_dot_product`] takes these inputs: `q` `(batch, heads, queries, head_dim)`,
/// `k` and `v` `(batch, heads, keys, head_dim)` with the same batch and heads (no broadcast), a
/// head width of [`HEAD_DIMS`], at most [`MAX_ROWS`] batch × heads, at least one query and one
/// key, all three f16 or all three bf16, on one device.
pub fn supports(q: &Tensor, k: &Tensor, v: &Tensor) -> bool {
    let (Ok((b, h, nq, d)), Ok((kb, kh, nk, kd)), Ok(vdims)) = (q.dims4(), k.dims4(), v.dims4())
    else {
        return false;
    };
    let same_type = q.dtype() == k.dtype() && k.dtype() == v.dtype();
    let half = matches!(q.dtype(), DType::F16 | DType::BF16);
    let same_device = q.device().same_device(k.device()) && k.device().same_device(v.device());
    (kb, kh, kd) == (b, h, d)
        && vdims == (b, h, nk, d)
        && nq > 0
        && nk > 0
        // A grid row per (batch, head): CUDA's limit on a grid's second dimension.
        && b * h <= MAX_ROWS
        && HEAD_DIMS.contains(&d)
        && same_type
        && half
        && same_device
}

/// `softmax(q·kᵀ·scale)·v` for inputs [`supports`] takes, `(batch, heads, queries, head_dim)`
/// in the inputs' type: the fused kernel on a GPU, its plain twin on the CPU.
///
/// # Errors
/// Inputs [`supports`] refuses; the device's.
pub fn scaled_dot_product(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Result<Tensor> {
    if !supports(q, k, v) {
        candle_core::bail!(
            "fused attention takes f16 or bf16 (batch, heads, tokens, {HEAD_DIMS:?}) inputs of one \
             shape but the token counts, got q {:?} {:?}, k {:?} {:?}, v {:?} {:?}",
            q.dims(),
            q.dtype(),
            k.dims(),
            k.dtype(),
            v.dims(),
            v.dtype()
        );
    }
    let (batch, heads, queries, head_dim) = q.dims4()?;
    let rows = |t: &Tensor| -> Result<Tensor> {
        let (b, h, n, d) = t.dims4()?;
        t.contiguous()?.reshape((b * h, n, d))
    };
    let op = FusedAttention {
        scale: scale as f32,
    };
    rows(q)?
        .apply_op3_no_bwd(&rows(k)?, &rows(v)?, &op)?
        .reshape((batch, heads, queries, head_dim))
}

/// `softmax(q·kᵀ·scale)·v` as the models compute it without the kernel (two products and a
/// softmax; on the CPU their fast path), for benchmarks and tests beside [`scaled_dot_product`]:
/// `q` `(batch, heads, queries, head_dim)`, `k` and `v` `(batch, heads, keys, head_dim)`.
///
/// # Errors
/// Mismatched shapes; the device's.
pub fn unfused_scaled_dot_product(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
) -> Result<Tensor> {
    crate::attention::plain_scaled_dot_product(q, k, v, scale, crate::attention::Scores::Plain)
}

/// The custom op over `(rows, tokens, head_dim)` contiguous inputs.
struct FusedAttention {
    scale: f32,
}

/// `(rows, queries, keys, head_dim)` of contiguous inputs, or an error naming what is wrong.
fn dims(l1: &Layout, l2: &Layout, l3: &Layout) -> Result<(usize, usize, usize, usize)> {
    if !(l1.is_contiguous() && l2.is_contiguous() && l3.is_contiguous()) {
        candle_core::bail!("fused attention takes contiguous inputs");
    }
    let (rows, queries, head_dim) = l1.shape().dims3()?;
    let (_, keys, _) = l2.shape().dims3()?;
    Ok((rows, queries, keys, head_dim))
}

impl CustomOp3 for FusedAttention {
    fn name(&self) -> &'static str {
        "vlem-fused-attention"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let shape = dims(l1, l2, l3)?;
        let starts = (l1.start_offset(), l2.start_offset(), l3.start_offset());
        let out = match (s1, s2, s3) {
            (CpuStorage::F16(q), CpuStorage::F16(k), CpuStorage::F16(v)) => {
                CpuStorage::F16(twin((q, k, v), starts, shape, self.scale)?)
            }
            (CpuStorage::BF16(q), CpuStorage::BF16(k), CpuStorage::BF16(v)) => {
                CpuStorage::BF16(twin((q, k, v), starts, shape, self.scale)?)
            }
            _ => candle_core::bail!("fused attention takes f16 or bf16 inputs of one type"),
        };
        Ok((out, l1.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        use candle_core::backend::BackendStorage;

        let shape = dims(l1, l2, l3)?;
        let starts = (l1.start_offset(), l2.start_offset(), l3.start_offset());
        let out = match s1.dtype() {
            DType::F16 => cuda::launch::<half::f16>((s1, s2, s3), starts, shape, self.scale)?,
            DType::BF16 => cuda::launch::<half::bf16>((s1, s2, s3), starts, shape, self.scale)?,
            other => candle_core::bail!("fused attention takes f16 or bf16, got {other:?}"),
        };
        Ok((out, l1.shape().clone()))
    }
}

/// The kernel's algorithm in plain loops: per query, the keys in tiles of [`KEY_TILE`], each
/// tile's scores as f32 sums of products, the running maximum and sum in base 2, the
/// probabilities rounded to `T` before they weigh the values, the output accumulated in f32 and
/// rounded to `T` once.
fn twin<T: WithDType>(
    (q, k, v): (&[T], &[T], &[T]),
    (q_start, k_start, v_start): (usize, usize, usize),
    (rows, queries, keys, head_dim): (usize, usize, usize, usize),
    scale: f32,
) -> Result<Vec<T>> {
    let f = |x: T| x.to_f64() as f32;
    let slice = |values: &[T], start: usize, tokens: usize| -> Result<Vec<f32>> {
        match values.get(start..start + rows * tokens * head_dim) {
            Some(s) => Ok(s.iter().map(|&x| f(x)).collect()),
            None => candle_core::bail!("fused attention: an input is shorter than its layout"),
        }
    };
    let (q, k, v) = (
        slice(q, q_start, queries)?,
        slice(k, k_start, keys)?,
        slice(v, v_start, keys)?,
    );
    let scale_log2 = scale * std::f32::consts::LOG2_E;
    let mut out = Vec::with_capacity(rows * queries * head_dim);
    let mut scores = [0f32; KEY_TILE];
    let mut o = vec![0f32; head_dim];
    for row in 0..rows {
        let k = &k[row * keys * head_dim..(row + 1) * keys * head_dim];
        let v = &v[row * keys * head_dim..(row + 1) * keys * head_dim];
        for query in q[row * queries * head_dim..(row + 1) * queries * head_dim].chunks(head_dim) {
            let (mut m, mut l) = (f32::NEG_INFINITY, 0f32);
            o.fill(0.0);
            for first in (0..keys).step_by(KEY_TILE) {
                let tile = KEY_TILE.min(keys - first);
                for (j, s) in scores.iter_mut().take(tile).enumerate() {
                    let key = &k[(first + j) * head_dim..(first + j + 1) * head_dim];
                    *s = query.iter().zip(key).map(|(a, b)| a * b).sum::<f32>() * scale_log2;
                }
                let next = scores[..tile].iter().fold(m, |a, &s| a.max(s));
                let alpha = (m - next).exp2();
                let mut sum = 0f32;
                for x in &mut o {
                    *x *= alpha;
                }
                for (j, &s) in scores[..tile].iter().enumerate() {
                    let p = (s - next).exp2();
                    sum += p;
                    let rounded = f(T::from_f64(f64::from(p)));
                    let value = &v[(first + j) * head_dim..(first + j + 1) * head_dim];
                    for (x, &val) in o.iter_mut().zip(value) {
                        *x += rounded * val;
                    }
                }
                l = l * alpha + sum;
                m = next;
            }
            out.extend(o.iter().map(|&x| T::from_f64(f64::from(x / l))));
        }
    }
    Ok(out)
}

/// The kernel's launch: one block of 128 threads per 64 queries of a row.
#[cfg(feature = "cuda")]
mod cuda {
    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::driver::{DeviceRepr, LaunchConfig, PushKernelArg};
    use candle_core::cuda_backend::{CudaDType, WrapErr};
    use candle_core::{CudaStorage, Result};

    /// The kernels, compiled to PTX by the build script from `fused_attention.cu`.
    const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/fused_attention.ptx"));

    /// Queries per block (four warps of 16).
    const QUERIES_PER_BLOCK: usize = 64;

    /// The kernel's name for `T`.
    pub(super) trait KernelType: CudaDType + DeviceRepr {
        const NAME: &'static str;
    }
    impl KernelType for half::f16 {
        const NAME: &'static str = "f16";
    }
    impl KernelType for half::bf16 {
        const NAME: &'static str = "bf16";
    }

    /// Runs the kernel over `rows` rows of `queries` against `keys`; the output's storage.
    #[allow(
        unsafe_code,
        reason = "the kernel launch and its uninitialised output: the FFI into CUDA this module \
                  exists for, after the shape and alignment checks"
    )]
    pub(super) fn launch<T: KernelType>(
        (q, k, v): (&CudaStorage, &CudaStorage, &CudaStorage),
        (q_start, k_start, v_start): (usize, usize, usize),
        (rows, queries, keys, head_dim): (usize, usize, usize, usize),
        scale: f32,
    ) -> Result<CudaStorage> {
        // The kernel reads 16 bytes at a time: every row of every input starts 8 values apart.
        if [q_start, k_start, v_start].iter().any(|s| s % 8 != 0) {
            candle_core::bail!("fused attention needs inputs that start on a 16-byte boundary");
        }
        let too_big = |n: usize| i32::try_from(n).is_err();
        if too_big(queries) || too_big(keys) || rows > super::MAX_ROWS {
            candle_core::bail!("fused attention: {rows} rows of {queries} × {keys} is too large");
        }
        if PTX.is_empty() {
            candle_core::bail!(
                "fused attention: this build left the kernel out (CUDA_COMPUTE_CAP below 8.0 at \
                 build time); unset VLEM_FUSED_ATTENTION"
            );
        }
        let dev = q.device();
        let name = format!("fused_attention_{}_d{head_dim}", T::NAME);
        let func = dev.get_or_load_custom_func(&name, "vlem_fused_attention", PTX)?;
        let q = q.as_cuda_slice::<T>()?.slice(q_start..);
        let k = k.as_cuda_slice::<T>()?.slice(k_start..);
        let v = v.as_cuda_slice::<T>()?.slice(v_start..);
        let count = rows * queries * head_dim;
        // SAFETY: every element is written by the kernel (each query of each row, all columns).
        let out = unsafe { dev.alloc::<T>(count)? };
        let (queries, keys) = (queries as i32, keys as i32);
        let scale_log2 = scale * std::f32::consts::LOG2_E;
        let config = LaunchConfig {
            grid_dim: (
                queries.unsigned_abs().div_ceil(QUERIES_PER_BLOCK as u32),
                rows as u32,
                1,
            ),
            block_dim: (128, 1, 1),
            shared_mem_bytes: 0,
        };
        let mut builder = func.builder();
        builder.arg(&q);
        builder.arg(&k);
        builder.arg(&v);
        builder.arg(&out);
        builder.arg(&queries);
        builder.arg(&keys);
        builder.arg(&scale_log2);
        // SAFETY: the arguments match the kernel's signature (three inputs, the output, two
        // counts, the scale) and the slices hold `rows × tokens × head_dim` values each.
        unsafe { builder.launch(config) }.w()?;
        Ok(CudaStorage::wrap_cuda_slice(out, dev.clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_twin_refuses_what_the_kernel_does_not_take() -> Result<()> {
        let dev = candle_core::Device::Cpu;
        let t = |d: usize, dtype: DType| Tensor::zeros((1, 2, 5, d), dtype, &dev);
        let q = t(64, DType::F16)?;
        assert!(supports(&q, &q, &q));
        assert!(!supports(
            &t(48, DType::F16)?,
            &t(48, DType::F16)?,
            &t(48, DType::F16)?
        ));
        assert!(!supports(
            &t(64, DType::F32)?,
            &t(64, DType::F32)?,
            &t(64, DType::F32)?
        ));
        assert!(!supports(&q, &t(64, DType::BF16)?, &q));
        let one = Tensor::zeros((1, 1, 5, 64), DType::F16, &dev)?;
        assert!(!supports(&q, &one, &one), "broadcast keys");
        assert!(scaled_dot_product(&t(64, DType::F32)?, &q, &q, 1.0).is_err());
        Ok(())
    }
}
