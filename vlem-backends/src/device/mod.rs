//! `device = "cpu" | "cuda" | "cuda:N"`: where a candle model runs, the one key that the
//! `[encoder]` and `[proposer]` sections of every candle backend share.
//!
//! Why it exists: the candle models are device-generic (their CPU fast paths in `kernels` and
//! SAM's fused decoder step aside, which fall back to candle's own ops on other devices), so the
//! choice of device is configuration, parsed and opened in one place. Opening a device is where
//! a user learns what is wrong with it: a build without the `cuda` feature, no NVIDIA driver, no
//! GPU with that index, or a GPU the build's kernels were not compiled for. Each is an error that
//! names the device asked for and what was found; nothing falls back to the CPU silently.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer};

use crate::error::BackendError;

mod dtype;
// Opening a device needs candle: every candle backend brings it, and `candle` alone does too.
mod memory;
#[cfg(feature = "candle")]
mod open;

pub use dtype::ModelDtype;
pub use memory::DeviceMemoryPeak;

/// How to get a build that can run on a GPU, for the messages that say this one cannot.
pub const CUDA_BUILD_HINT: &str = "build vlem with `--features cuda` (docs/gpu.md: \
     `source bench/gpu/cuda-toolchain.sh --link` first), or set `device = \"cpu\"`";

/// The device a model runs on: `"cpu"` (the default), `"cuda"` (the first GPU) or `"cuda:N"`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ComputeDevice {
    /// The CPU, with the crate's own vectorised kernels.
    #[default]
    Cpu,
    /// The NVIDIA GPU with this index (CUDA's device ordinal), through candle's CUDA backend.
    Cuda(usize),
}

impl FromStr for ComputeDevice {
    type Err = BackendError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let invalid = || {
            BackendError::InvalidParams(format!(
                "device = {text:?} is not a device; expected \"cpu\", \"cuda\" or \"cuda:N\" \
                 (N the GPU's index, from 0)"
            ))
        };
        match text.trim() {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            other => other
                .strip_prefix("cuda:")
                .and_then(|index| index.parse::<usize>().ok())
                .map(Self::Cuda)
                .ok_or_else(invalid),
        }
    }
}

impl fmt::Display for ComputeDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => f.write_str("cpu"),
            Self::Cuda(index) => write!(f, "cuda:{index}"),
        }
    }
}

impl<'de> Deserialize<'de> for ComputeDevice {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// The compute capability the build's CUDA kernels were compiled for (`CUDA_COMPUTE_CAP` when
/// candle's kernels were built, e.g. `90`), when it was set.
pub fn kernels_compute_capability() -> Option<&'static str> {
    option_env!("CUDA_COMPUTE_CAP")
}

impl ComputeDevice {
    /// The error for asking a build without the `cuda` feature for this device.
    pub fn not_in_this_build(self) -> BackendError {
        BackendError::DeviceUnavailable {
            asked: self.to_string(),
            found: "this build of vlem has no CUDA support (the `cuda` feature is off)".to_owned(),
            hint: CUDA_BUILD_HINT.to_owned(),
        }
    }

    /// The device named by the environment variable `name` (benchmarks' and tests' switch);
    /// [`ComputeDevice::Cpu`] when it is unset or empty.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] for a value that is not a device.
    pub fn from_env(name: &str) -> Result<Self, BackendError> {
        parse_env(name, Self::Cpu)
    }
}

/// The value of the environment variable `name`, parsed; `default` when it is unset or empty:
/// the benchmarks' and tests' switches of device and type.
fn parse_env<T: FromStr<Err = BackendError>>(name: &str, default: T) -> Result<T, BackendError> {
    match std::env::var(name) {
        Ok(text) if !text.trim().is_empty() => text.trim().parse().map_err(|e: BackendError| {
            BackendError::InvalidParams(format!("the environment variable {name}: {e}"))
        }),
        _ => Ok(default),
    }
}

/// Why kernels compiled for `built` (`CUDA_COMPUTE_CAP`, e.g. "90") do not run on a GPU of
/// compute capability `major.minor`, or `None` when they do. From 9.0 on, candle compiles for
/// the architecture-specific target (`sm_90a`), which runs on that capability only; below it the
/// PTX runs on that capability and every later one.
#[cfg_attr(
    not(feature = "cuda"),
    allow(
        dead_code,
        reason = "used only where a GPU can be opened, and by its test"
    )
)]
fn capability_mismatch(built: &str, major: i32, minor: i32) -> Option<String> {
    let built: i32 = built.trim().parse().ok()?;
    let device = major * 10 + minor;
    if built >= 90 && device != built {
        Some(format!(
            "this build's kernels were compiled for compute capability {}.{} only \
             (CUDA_COMPUTE_CAP={built})",
            built / 10,
            built % 10
        ))
    } else if device < built {
        Some(format!(
            "this build's kernels need compute capability {}.{} or later (CUDA_COMPUTE_CAP={built})",
            built / 10,
            built % 10
        ))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_and_print_back() {
        for (text, device) in [
            ("cpu", ComputeDevice::Cpu),
            ("cuda", ComputeDevice::Cuda(0)),
            ("cuda:0", ComputeDevice::Cuda(0)),
            ("cuda:3", ComputeDevice::Cuda(3)),
        ] {
            assert_eq!(text.parse::<ComputeDevice>().ok(), Some(device), "{text}");
        }
        assert_eq!(ComputeDevice::Cuda(2).to_string(), "cuda:2");
        assert_eq!(ComputeDevice::default(), ComputeDevice::Cpu);
        for bad in ["gpu", "cuda:", "cuda:-1", "cuda:x", "CUDA", "metal"] {
            let error = bad.parse::<ComputeDevice>().err().map(|e| e.to_string());
            assert!(
                error.as_deref().is_some_and(|e| e.contains("cuda:N")),
                "{bad}: {error:?}"
            );
        }
    }

    #[test]
    fn a_device_key_deserialises_from_toml() {
        #[derive(Deserialize)]
        struct Section {
            device: ComputeDevice,
        }
        let parsed: Section = toml::from_str("device = \"cuda:1\"").expect("valid");
        assert_eq!(parsed.device, ComputeDevice::Cuda(1));
        let error = toml::from_str::<Section>("device = \"tpu\"")
            .err()
            .map(|e| e.to_string());
        assert!(error.is_some_and(|e| e.contains("\"tpu\"")));
    }

    #[test]
    fn kernels_run_on_the_capabilities_they_were_compiled_for() {
        // sm_90a: Hopper only.
        assert_eq!(capability_mismatch("90", 9, 0), None);
        assert!(capability_mismatch("90", 8, 9).is_some());
        assert!(capability_mismatch("90", 10, 0).is_some());
        // sm_89 PTX: Ada and every later GPU, not Ampere.
        assert_eq!(capability_mismatch("89", 8, 9), None);
        assert_eq!(capability_mismatch("89", 9, 0), None);
        assert!(capability_mismatch("89", 8, 6).is_some());
        assert_eq!(capability_mismatch("not a number", 8, 6), None);
    }
}
