//! Deterministic synthetic weights for SAM networks, for tests and benchmarks.
//!
//! Why it exists: no pretrained SAM weights can be downloaded where this project is built and
//! tested, and the mask decoder alone is 16 MB, too big to commit. Instead every tensor is a pure
//! function of its name and shape, computed identically here and by the golden script
//! `vlem-backends/goldens/sam/make_sam_goldens.py`, which fills the reference PyTorch model with
//! it. The values are plausible for a network (fan-in scaled weights, norm gains near 1), so the
//! activations stay in a realistic range.
//!
//! The rule, for a tensor `name` with `shape`: `h = fnv1a64(name)`; element `i` (row-major) takes
//! `u_i = (splitmix64_mix(h + i + 0x9E3779B97F4A7C15) >> 40) * 2^-23 - 1` in `[-1, 1)` (exact in
//! f32), and the value is, in f32 arithmetic:
//! - `positional_encoding_gaussian_matrix`: `u_i`;
//! - one-dimensional `weight` or `running_var` (norm gains, batch-norm variances): `0.1 * u_i + 1`;
//! - other one-dimensional tensors (biases, batch-norm means): `0.1 * u_i`;
//! - the rest: `s * u_i` with `s = f32(1 / sqrt(fan_in))`, `fan_in` the product of all dimensions
//!   but the first.

use std::sync::{Arc, Mutex, PoisonError};

use candle_core::{DType, Device, Result, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder};

use super::amg::splitmix64_mix;

/// FNV-1a, 64 bits.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// The values of the synthetic tensor `name` of `shape` (see the [module docs](self)).
pub fn synthetic_values(name: &str, shape: &[usize]) -> Vec<f32> {
    let h = fnv1a64(name.as_bytes());
    let n: usize = shape.iter().product();
    let leaf = name.rsplit('.').next().unwrap_or(name);
    let (scale, offset) = if leaf == "positional_encoding_gaussian_matrix" {
        (1.0f32, 0.0f32)
    } else if shape.len() == 1 {
        if leaf == "weight" || leaf == "running_var" {
            (0.1, 1.0)
        } else {
            (0.1, 0.0)
        }
    } else {
        let fan_in: usize = shape.iter().skip(1).product();
        ((1.0 / (fan_in.max(1) as f64).sqrt()) as f32, 0.0)
    };
    (0..n as u64)
        .map(|i| {
            let z = splitmix64_mix(h.wrapping_add(i).wrapping_add(0x9E37_79B9_7F4A_7C15));
            let u = (z >> 40) as f32 * (1.0 / 8_388_608.0) - 1.0;
            scale * u + offset
        })
        .collect()
}

/// A var-builder backend that makes every requested tensor with [`synthetic_values`] and
/// records what was requested (name and shape), so that a test can compare the set with the
/// reference's state dict.
#[derive(Clone, Debug, Default)]
pub struct SyntheticWeights {
    requested: Arc<Mutex<RequestLog>>,
}

/// Requested tensors: name and shape, in request order.
type RequestLog = Vec<(String, Vec<usize>)>;

impl SyntheticWeights {
    /// A new backend with an empty request log.
    pub fn new() -> Self {
        Self::default()
    }

    /// A var builder (f32) over a clone of this backend (sharing its log).
    pub fn var_builder(&self, device: &Device) -> VarBuilder<'static> {
        self.var_builder_in(device, DType::F32)
    }

    /// A var builder handing out the tensors in `dtype` (the values are made in f32 and
    /// converted, so each type holds the f32 weights as closely as it can).
    pub fn var_builder_in(&self, device: &Device, dtype: DType) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), dtype, device.clone())
    }

    /// Every tensor requested so far, in request order.
    pub fn requested(&self) -> Vec<(String, Vec<usize>)> {
        self.requested
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

impl SimpleBackend for SyntheticWeights {
    fn get(&self, s: Shape, name: &str, _h: Init, dtype: DType, dev: &Device) -> Result<Tensor> {
        let dims = s.dims().to_vec();
        self.requested
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push((name.to_owned(), dims.clone()));
        Tensor::from_vec(synthetic_values(name, &dims), s, dev)?.to_dtype(dtype)
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> Result<Tensor> {
        candle_core::bail!("synthetic weights need a shape: {name} was requested without one")
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_follow_the_documented_rule() {
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
        let w = synthetic_values("x.weight", &[4, 9]);
        assert_eq!(w.len(), 36);
        assert!(w.iter().all(|v| v.abs() <= 1.0 / 3.0));
        let g = synthetic_values("norm.weight", &[8]);
        assert!(g.iter().all(|v| (0.9..=1.1).contains(v)));
        let b = synthetic_values("norm.bias", &[8]);
        assert!(b.iter().all(|v| v.abs() <= 0.1));
        assert_ne!(synthetic_values("a.bias", &[8]), b);
        assert_eq!(synthetic_values("norm.bias", &[8]), b);
    }
}
