//! Opening a [`ComputeDevice`] for candle: the CPU always; a GPU only in a build with `cuda`, after
//! checking what the driver sees, so that every way it can fail is an error naming the device
//! asked for and what was found.

use super::ComputeDevice;
use crate::ModelDtype;
use crate::error::BackendError;

impl ComputeDevice {
    /// Opens the device for candle.
    ///
    /// # Errors
    /// [`BackendError::DeviceUnavailable`] when the build has no `cuda` feature, no NVIDIA driver
    /// or GPU answers, the index is past the last GPU, or the GPU's compute capability is not one
    /// the build's kernels run on.
    pub fn open(self) -> Result<candle_core::Device, BackendError> {
        match self {
            Self::Cpu => Ok(candle_core::Device::Cpu),
            Self::Cuda(index) => open_cuda(self, index),
        }
    }

    /// Opens the device for a model that computes in `dtype`, and applies its section's `tf32`
    /// key: `true` lets cuBLAS run f32 matrix products on TF32 tensor cores (10-bit mantissa
    /// inputs, f32 sums), `false` forbids it, unset leaves it as it is. Off unless asked, as in
    /// PyTorch; like PyTorch's `torch.backends.cuda.matmul.allow_tf32` it is one setting for the
    /// whole process, so the last model built with the key decides.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for `tf32 = true` on the CPU (nothing to apply it to) or
    /// with a half-precision `dtype` (whose products are not f32); as [`Self::open`].
    pub fn open_for(
        self,
        dtype: ModelDtype,
        tf32: Option<bool>,
    ) -> Result<candle_core::Device, BackendError> {
        if tf32 == Some(true) {
            if self == Self::Cpu {
                return Err(BackendError::InvalidParams(
                    "tf32 = true speeds up f32 matrix products on an NVIDIA GPU, and device = \
                     \"cpu\": remove the key or set device = \"cuda\""
                        .to_owned(),
                ));
            }
            if dtype != ModelDtype::F32 {
                return Err(BackendError::InvalidParams(format!(
                    "tf32 = true applies to f32 matrix products, and dtype = \"{dtype}\" computes \
                     in half precision already: remove one of the two"
                )));
            }
        }
        let device = self.open()?;
        if let Some(allow) = tf32 {
            set_tf32(allow);
        }
        Ok(device)
    }
}

/// cuBLAS's process-wide TF32 switch for f32 products (candle's).
#[cfg(feature = "cuda")]
fn set_tf32(allow: bool) {
    candle_core::cuda_backend::set_gemm_reduced_precision_f32(allow);
}

/// Without CUDA no product is a cuBLAS one: nothing to switch.
#[cfg(not(feature = "cuda"))]
fn set_tf32(_allow: bool) {}

#[cfg(not(feature = "cuda"))]
fn open_cuda(asked: ComputeDevice, _index: usize) -> Result<candle_core::Device, BackendError> {
    Err(asked.not_in_this_build())
}

#[cfg(feature = "cuda")]
fn open_cuda(asked: ComputeDevice, index: usize) -> Result<candle_core::Device, BackendError> {
    use candle_core::cuda::cudarc::driver::CudaContext;

    let unavailable = |found: String, hint: &str| BackendError::DeviceUnavailable {
        asked: asked.to_string(),
        found,
        hint: hint.to_owned(),
    };
    let count = CudaContext::device_count().map_err(|e| {
        unavailable(
            format!("the NVIDIA driver did not start ({e})"),
            "check `nvidia-smi`; a driver for CUDA 13.0 or newer is needed",
        )
    })?;
    let count = usize::try_from(count).unwrap_or(0);
    if index >= count {
        return Err(unavailable(
            match count {
                0 => "the driver sees no CUDA GPU".to_owned(),
                1 => "the driver sees 1 CUDA GPU, cuda:0".to_owned(),
                n => format!("the driver sees {n} CUDA GPUs, cuda:0 to cuda:{}", n - 1),
            },
            "set `device` to one of them, or `CUDA_VISIBLE_DEVICES` to make it visible",
        ));
    }
    let context = CudaContext::new(index)
        .map_err(|e| unavailable(format!("it did not open ({e})"), "check `nvidia-smi`"))?;
    let name = context.name().unwrap_or_else(|_| "the GPU".to_owned());
    if let (Ok((major, minor)), Some(built)) = (
        context.compute_capability(),
        super::kernels_compute_capability(),
    ) && let Some(reason) = super::capability_mismatch(built, major, minor)
    {
        return Err(unavailable(
            format!("it is {name}, compute capability {major}.{minor}, and {reason}"),
            &format!(
                "rebuild with CUDA_COMPUTE_CAP={major}{minor} (cargo then rebuilds candle's \
                 kernels)"
            ),
        ));
    }
    drop(context);
    candle_core::Device::new_cuda(index).map_err(|e| {
        unavailable(
            format!("{name} did not open in candle ({e})"),
            "check `nvidia-smi`",
        )
    })
}

#[cfg(all(test, not(feature = "cuda")))]
mod tests {
    use super::*;

    #[test]
    fn asking_for_a_gpu_without_the_cuda_feature_names_both() {
        let error = ComputeDevice::Cuda(1).open().err().map(|e| e.to_string());
        let error = error.unwrap_or_default();
        assert!(error.contains("cuda:1"), "{error}");
        assert!(error.contains("no CUDA support"), "{error}");
        assert!(error.contains("--features cuda"), "{error}");
    }
}
