//! Small building blocks shared by SAM's image encoders and mask decoder, written to match
//! PyTorch's modules: exact (erf) GELU, LayerNorm over channels, convolutions with their batch
//! norm folded in.
//!
//! Why it exists: candle-transformers' `segment_anything` uses the tanh approximation of GELU in
//! the mask decoder and in TinyViT, where SAM and MobileSAM use the exact one; the difference
//! (up to ~5e-4 per activation) is visible in the masks, so this backend has its own layers.

use candle_core::{D, DType, Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

/// A linear layer with bias (PyTorch `nn.Linear`): weight `(out, in)`.
pub fn linear(vb: VarBuilder, in_dim: usize, out_dim: usize) -> Result<Linear> {
    candle_nn::linear(in_dim, out_dim, vb)
}

/// Applies a linear layer to a tensor of any rank (candle's `Linear` wants rank 2-4 with a
/// matching batch layout; this flattens the leading dimensions).
pub fn apply_linear(layer: &Linear, xs: &Tensor) -> Result<Tensor> {
    crate::attention::Project::project(layer, xs)
}

/// `nn.LayerNorm(dim, eps)` over the last dimension.
pub fn layer_norm(vb: VarBuilder, dim: usize, eps: f64) -> Result<LayerNorm> {
    candle_nn::layer_norm(dim, eps, vb)
}

/// SAM's `LayerNorm2d`: normalises each pixel over the channels of an `(N, C, H, W)` tensor.
#[derive(Debug, Clone)]
pub struct LayerNorm2d {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm2d {
    /// Loads `weight` and `bias` of `channels` values.
    pub fn new(vb: VarBuilder, channels: usize, eps: f64) -> Result<Self> {
        Ok(Self {
            // f32 whatever the model's type: see `forward`.
            weight: vb
                .get(channels, "weight")?
                .to_dtype(DType::F32)?
                .reshape((1, channels, 1, 1))?,
            bias: vb
                .get(channels, "bias")?
                .to_dtype(DType::F32)?
                .reshape((1, channels, 1, 1))?,
            eps,
        })
    }
}

impl Module for LayerNorm2d {
    /// In f32 whatever the input's type (and back): candle sums a half-precision tensor in half
    /// precision on the CPU and on CUDA, and means over 256 channels that way lose what a model
    /// in half keeps elsewhere (PyTorch's norms accumulate in f32 too).
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let dtype = xs.dtype();
        let xs = xs.to_dtype(DType::F32)?;
        let mean = xs.mean_keepdim(1)?;
        let centred = xs.broadcast_sub(&mean)?;
        let var = centred.sqr()?.mean_keepdim(1)?;
        centred
            .broadcast_div(&(var + self.eps)?.sqrt()?)?
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)?
            .to_dtype(dtype)
    }
}

/// Exact GELU (PyTorch's `nn.GELU()` default).
pub fn gelu(xs: &Tensor) -> Result<Tensor> {
    crate::kernels::gelu_erf(xs)
}

/// A PyTorch `Conv2d` + `BatchNorm2d` pair (TinyViT's `Conv2d_BN`, names `c.weight` and
/// `bn.{weight,bias,running_mean,running_var}`) folded into one convolution with bias, as
/// inference in eval mode computes it.
pub fn conv2d_bn(
    vb: VarBuilder,
    in_ch: usize,
    out_ch: usize,
    kernel: usize,
    cfg: Conv2dConfig,
) -> Result<Conv2d> {
    let groups = cfg.groups.max(1);
    let w = vb
        .pp("c")
        .get((out_ch, in_ch / groups, kernel, kernel), "weight")?;
    let bn = vb.pp("bn");
    let gamma = bn.get(out_ch, "weight")?;
    let beta = bn.get(out_ch, "bias")?;
    let mean = bn.get(out_ch, "running_mean")?;
    let var = bn.get(out_ch, "running_var")?;
    // BatchNorm2d's default eps.
    let scale = gamma.div(&(var + 1e-5)?.sqrt()?)?;
    let w = w.broadcast_mul(&scale.reshape((out_ch, 1, 1, 1))?)?;
    let b = beta.sub(&mean.mul(&scale)?)?;
    Ok(Conv2d::new(w, Some(b), cfg))
}

/// Softmax over the last dimension.
pub fn softmax_last(xs: &Tensor) -> Result<Tensor> {
    crate::kernels::softmax_last_dim(xs)
}

/// Concatenates along the last dimension.
pub fn cat_last(xs: &[&Tensor]) -> Result<Tensor> {
    Tensor::cat(xs, D::Minus1)
}
