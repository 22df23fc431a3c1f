//! The pieces of a ViT that every candle transformer backbone here is built from.
//!
//! Why it exists: DINOv3 (with its dino.txt heads) and RADIO (NARADIO) are both pre-norm ViTs
//! whose blocks differ only in details (RoPE or not, layer scale or not, plain or gated MLP);
//! writing the block once keeps the two backbones' maths in one place and one set of tests.
//! This module owns loading named tensors with checked shapes ([`Weights`]), the linear layer,
//! RoPE, fused-qkv multi-head attention, the MLP and the block.

use std::collections::HashMap;

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{LayerNorm, Module};

use crate::attention::Scores;
use crate::profile;

/// A transformer MLP activation, from `hidden_act` in `config.json`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// `gelu`: the exact GELU, `x · Φ(x)` (erf); the ViT-S/B/L checkpoints.
    Gelu,
    /// `gelu_new`, `gelu_pytorch_tanh`, `gelu_fast`: the tanh approximation of GELU.
    GeluTanh,
    /// `silu` (`swish`): `x · σ(x)`; the gated MLP of the "plus" checkpoints.
    Silu,
}

impl Activation {
    /// The activation named `name` in `transformers`' `ACT2FN`, where it is one of these.
    pub fn from_hf_name(name: &str) -> Option<Self> {
        match name {
            "gelu" => Some(Self::Gelu),
            "gelu_new" | "gelu_pytorch_tanh" | "gelu_fast" => Some(Self::GeluTanh),
            "silu" | "swish" => Some(Self::Silu),
            _ => None,
        }
    }

    pub(crate) fn apply(self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Self::Gelu => crate::kernels::gelu_erf(x),
            Self::GeluTanh => x.gelu(),
            Self::Silu => x.silu(),
        }
    }
}

/// Named tensors with checked shapes, converted to the model's dtype and put on its device: the
/// loading side of every module here.
pub(crate) struct Weights {
    tensors: HashMap<String, Tensor>,
    device: Device,
    dtype: DType,
}

impl Weights {
    /// `tensors` (on any device, in any float type), handed out on `device` in `dtype`.
    pub(crate) fn new(tensors: HashMap<String, Tensor>, device: &Device, dtype: DType) -> Self {
        Self {
            tensors,
            device: device.clone(),
            dtype,
        }
    }

    /// The device the tensors are handed out on.
    pub(crate) fn device(&self) -> &Device {
        &self.device
    }

    /// The type the tensors are handed out in: the model's.
    pub(crate) fn dtype(&self) -> DType {
        self.dtype
    }

    pub(crate) fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    /// The shape of tensor `name`, if there is one.
    pub(crate) fn dims(&self, name: &str) -> Option<Vec<usize>> {
        self.tensors.get(name).map(|t| t.dims().to_vec())
    }

    /// The tensor `name`, which must have `shape`.
    pub(crate) fn get(&self, name: &str, shape: &[usize]) -> Result<Tensor, String> {
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| format!("tensor {name} is missing"))?;
        if t.dims() != shape {
            return Err(format!(
                "tensor {name} has shape {:?}, expected {shape:?}",
                t.dims()
            ));
        }
        t.to_dtype(self.dtype)
            .and_then(|t| t.to_device(&self.device))
            .map_err(|e| format!("tensor {name}: {e}"))
    }

    pub(crate) fn linear(
        &self,
        prefix: &str,
        inputs: usize,
        outputs: usize,
        bias: bool,
    ) -> Result<Linear, String> {
        let weight = self.get(&format!("{prefix}.weight"), &[outputs, inputs])?;
        let bias = if bias {
            Some(self.get(&format!("{prefix}.bias"), &[outputs])?)
        } else {
            None
        };
        Linear::new(&weight, bias).map_err(|e| format!("{prefix}: {e}"))
    }

    pub(crate) fn layer_norm(
        &self,
        prefix: &str,
        width: usize,
        eps: f64,
    ) -> Result<LayerNorm, String> {
        Ok(LayerNorm::new(
            self.get(&format!("{prefix}.weight"), &[width])?,
            self.get(&format!("{prefix}.bias"), &[width])?,
            eps,
        ))
    }
}

/// `x · Wᵀ + b` with `Wᵀ` stored contiguous.
#[derive(Clone, Debug)]
pub(crate) struct Linear {
    weight_t: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    /// From a `(outputs, inputs)` weight as PyTorch stores it.
    pub(crate) fn new(weight: &Tensor, bias: Option<Tensor>) -> candle_core::Result<Self> {
        Ok(Self {
            weight_t: weight.t()?.contiguous()?,
            bias,
        })
    }

    /// The output width.
    #[cfg_attr(
        not(feature = "naradio"),
        allow(dead_code, reason = "used by naradio only")
    )]
    pub(crate) fn outputs(&self) -> candle_core::Result<usize> {
        self.weight_t.dim(1)
    }

    /// Over the last dimension of `x`, whatever its leading dimensions (flattened to one matrix
    /// product, which is what candle's CPU matmul is fastest at).
    pub(crate) fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut dims = x.dims().to_vec();
        let inputs = x.dim(D::Minus1)?;
        let rows = x.elem_count() / inputs.max(1);
        let y = x.reshape((rows, inputs))?.matmul(&self.weight_t)?;
        let y = match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        };
        if let Some(last) = dims.last_mut() {
            *last = self.weight_t.dim(1)?;
        }
        y.reshape(dims)
    }
}

/// The cosines and sines of 2-D RoPE for an `h × w` patch grid, `(h·w, head_dim)` each.
#[derive(Clone, Debug)]
pub(crate) struct Rope {
    cos: Tensor,
    sin: Tensor,
}

/// RoPE angles, row-major over the grid: `(h·w) × head_dim` values laid out as
/// `[y·f₀.., x·f₀.., y·f₀.., x·f₀..]`, each times 2π. Computed in f32 like `transformers`.
pub fn rope_angles(grid_h: usize, grid_w: usize, head_dim: usize, theta: f64) -> Vec<f32> {
    let quarter = head_dim / 4;
    let freqs: Vec<f32> = (0..quarter)
        .map(|k| {
            let exponent = (k as f32) * (4.0 / head_dim as f32);
            1.0 / (theta as f32).powf(exponent)
        })
        .collect();
    let coord = |i: usize, n: usize| 2.0 * ((i as f32 + 0.5) / n as f32) - 1.0;
    let two_pi = 2.0 * std::f32::consts::PI;
    let mut out = Vec::with_capacity(grid_h * grid_w * head_dim);
    for i in 0..grid_h {
        let y = coord(i, grid_h);
        for j in 0..grid_w {
            let x = coord(j, grid_w);
            for _ in 0..2 {
                out.extend(freqs.iter().map(|f| two_pi * y * f));
                out.extend(freqs.iter().map(|f| two_pi * x * f));
            }
        }
    }
    out
}

impl Rope {
    /// The tables in `dtype`, the model's (computed in f32 like the reference, then converted).
    pub(crate) fn new(
        (grid_h, grid_w): (usize, usize),
        head_dim: usize,
        theta: f64,
        device: &Device,
        dtype: DType,
    ) -> candle_core::Result<Self> {
        let angles = rope_angles(grid_h, grid_w, head_dim, theta);
        let cos: Vec<f32> = angles.iter().map(|a| a.cos()).collect();
        let sin: Vec<f32> = angles.iter().map(|a| a.sin()).collect();
        let table =
            |v: Vec<f32>| Tensor::from_vec(v, (grid_h * grid_w, head_dim), device)?.to_dtype(dtype);
        Ok(Self {
            cos: table(cos)?,
            sin: table(sin)?,
        })
    }

    /// Rotates the last `h·w` tokens of `x` (`(batch, heads, tokens, head_dim)`), leaving the
    /// prefix tokens (CLS, registers) as they are.
    fn apply(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let (_, _, tokens, head_dim) = x.dims4()?;
        let patches = self.cos.dim(0)?;
        let prefix = tokens.checked_sub(patches).ok_or_else(|| {
            candle_core::Error::Msg(format!(
                "RoPE for {patches} patches applied to {tokens} tokens"
            ))
        })?;
        let p = x.narrow(2, prefix, patches)?;
        let half = head_dim / 2;
        let rotated = Tensor::cat(
            &[
                &p.narrow(D::Minus1, half, half)?.neg()?,
                &p.narrow(D::Minus1, 0, half)?,
            ],
            D::Minus1,
        )?;
        let p = (p.broadcast_mul(&self.cos)? + rotated.broadcast_mul(&self.sin)?)?;
        if prefix == 0 {
            Ok(p)
        } else {
            Tensor::cat(&[&x.narrow(2, 0, prefix)?, &p], 2)
        }
    }
}

/// The ViTs' multi-head self-attention: the shared layer with the query, key and value
/// projections fused into one matrix product (optional RoPE, optional causal mask).
pub(crate) type Attention = crate::attention::Attention<Linear>;

impl crate::attention::Project for Linear {
    fn project(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        self.forward(x)
    }
}

impl crate::attention::Rotate for Rope {
    fn rotate(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        self.apply(x)
    }
}

/// An attention layer of `heads` heads with a fused `qkv` projection and an `out` projection.
pub(crate) fn fused_attention(qkv: Linear, out: Linear, heads: usize) -> Attention {
    Attention::new(crate::attention::Inputs::Fused(qkv), out, heads)
}

/// A transformer MLP: plain (`down(act(up x))`) or gated (`down(act(gate x) ⊙ up x)`).
#[derive(Clone, Debug)]
pub(crate) enum Mlp {
    Plain {
        up: Linear,
        down: Linear,
        act: Activation,
    },
    Gated {
        gate: Linear,
        up: Linear,
        down: Linear,
        act: Activation,
    },
}

impl Mlp {
    pub(crate) fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Self::Plain { up, down, act } => down.forward(&act.apply(&up.forward(x)?)?),
            Self::Gated {
                gate,
                up,
                down,
                act,
            } => down.forward(&(act.apply(&gate.forward(x)?)? * up.forward(x)?)?),
        }
    }
}

/// One pre-norm transformer block with optional per-channel layer scales:
/// `x += ls1 ⊙ attn(norm1 x)`, `x += ls2 ⊙ mlp(norm2 x)`.
#[derive(Clone, Debug)]
pub(crate) struct Block {
    pub(crate) norm1: LayerNorm,
    pub(crate) attention: Attention,
    pub(crate) scale1: Option<Tensor>,
    pub(crate) norm2: LayerNorm,
    pub(crate) mlp: Mlp,
    pub(crate) scale2: Option<Tensor>,
}

impl Block {
    pub(crate) fn forward(
        &self,
        x: &Tensor,
        rope: Option<&Rope>,
        mask: Option<&Tensor>,
    ) -> candle_core::Result<Tensor> {
        let scaled = |y: Tensor, s: &Option<Tensor>| match s {
            Some(s) => y.broadcast_mul(s),
            None => Ok(y),
        };
        let scores = mask.map_or(Scores::Plain, Scores::Bias);
        let rope = rope.map(|r| r as &dyn crate::attention::Rotate);
        let device = x.device();
        let normed = profile::timed("norm", device, || self.norm1.forward(x))?;
        let a = self.attention.forward(&normed, rope, scores)?;
        let x = (x + scaled(a, &self.scale1)?)?;
        let normed = profile::timed("norm", device, || self.norm2.forward(&x))?;
        let m = profile::timed("mlp", device, || self.mlp.forward(&normed))?;
        x + scaled(m, &self.scale2)?
    }
}
