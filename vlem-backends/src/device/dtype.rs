//! `dtype = "f32" | "f16" | "bf16"`: the floating-point type a candle model computes in.
//!
//! Why it exists: on a GPU, half precision halves the weights' and activations' memory traffic,
//! and every peer runs its models that way; on the CPU, f32 is what the crate's fused kernels
//! speed up (half precision runs through candle's own ops there, correct but slower). One key,
//! parsed in one place, for every candle model's section. Inputs and outputs stay f32: the model
//! converts at its edges.

use serde::{Deserialize, Serialize};

use crate::error::BackendError;

/// The floating-point type of a candle model's weights and activations.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelDtype {
    /// 32-bit floats, the default: the reference's precision.
    #[default]
    F32,
    /// IEEE half precision (10-bit mantissa).
    F16,
    /// bfloat16 (8-bit mantissa, f32's range).
    Bf16,
}

impl std::str::FromStr for ModelDtype {
    type Err = BackendError;

    /// The names the `dtype` key takes, read by the key's own deserialiser (one list of names).
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        use serde::de::IntoDeserializer;
        Self::deserialize(text.into_deserializer()).map_err(|e: serde::de::value::Error| {
            BackendError::InvalidParams(format!("dtype = {text:?}: {e}"))
        })
    }
}

impl std::fmt::Display for ModelDtype {
    /// The name the `dtype` key takes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::F16 => "f16",
            Self::Bf16 => "bf16",
        })
    }
}

impl ModelDtype {
    /// The type named by the environment variable `name` (`f32`, `f16` or `bf16`), f32 when it
    /// is unset or empty: how the benchmarks are told the type to time.
    ///
    /// # Errors
    /// [`BackendError::InvalidParams`] naming the variable when it holds another word.
    pub fn from_env(name: &str) -> Result<Self, BackendError> {
        super::parse_env(name, Self::F32)
    }

    /// The candle type.
    #[cfg(feature = "candle")]
    pub fn candle(self) -> candle_core::DType {
        match self {
            Self::F32 => candle_core::DType::F32,
            Self::F16 => candle_core::DType::F16,
            Self::Bf16 => candle_core::DType::BF16,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, reason = "tests")]
mod tests {
    use super::*;

    #[test]
    fn the_key_reads_the_three_names_and_refuses_others() {
        #[derive(Deserialize)]
        struct Section {
            dtype: ModelDtype,
        }
        let parse =
            |v: &str| toml::from_str::<Section>(&format!("dtype = \"{v}\"")).map(|s| s.dtype);
        assert_eq!(parse("f32").unwrap(), ModelDtype::F32);
        assert_eq!(parse("f16").unwrap(), ModelDtype::F16);
        assert_eq!(parse("bf16").unwrap(), ModelDtype::Bf16);
        let err = parse("fp16").unwrap_err().to_string();
        assert!(err.contains("f32") && err.contains("bf16"), "{err}");
        // The environment's switch reads the same names.
        assert_eq!("bf16".parse::<ModelDtype>().unwrap(), ModelDtype::Bf16);
        let err = "fp16".parse::<ModelDtype>().unwrap_err().to_string();
        assert!(err.contains("fp16") && err.contains("f16"), "{err}");
    }
}
