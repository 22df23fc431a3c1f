//! The `[map]` parameters every map has (`dim`, `max_depth`, `pixel_stride`, `precision`,
//! `device`), their
//! defaults and their validation, and [`map_config!`](crate::map_config) that declares a map's
//! config with them.
//!
//! Why a macro and not a nested struct: configs are read with `#[serde(deny_unknown_fields)]` so
//! that a misspelt key is an error, and serde cannot combine that with `#[serde(flatten)]`. The
//! macro writes the shared fields into each config instead, once, so the configs stay flat
//! (`PointCloudConfig { precision, ..Default::default() }`, `[map] max_depth = 4`), unknown keys
//! are still refused, and the docs, defaults and checks of the shared fields exist only here.

use vlem_backends::ComputeDevice;
use vlem_core::CoreError;

use super::checks::{count_in, number_in, positive_metres, resolve_dim};
use crate::storage::Precision;

/// Default [`MapCommon::max_depth`] in metres.
pub const DEFAULT_MAX_DEPTH: f32 = 10.0;

/// Default [`MapCommon::pixel_stride`]: every pixel.
pub const DEFAULT_PIXEL_STRIDE: u32 = 1;

/// The parameters every map shares, as read from its config.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapCommon {
    /// Embedding dimension; `None` takes the encoder's (0 without an encoder).
    pub dim: Option<usize>,
    /// Depth beyond this (metres) is not integrated.
    pub max_depth: f32,
    /// Use every n-th pixel in both directions.
    pub pixel_stride: u32,
    /// Embedding storage.
    pub precision: Precision,
    /// Where the embedding table lives.
    pub device: ComputeDevice,
}

impl Default for MapCommon {
    fn default() -> Self {
        Self {
            dim: None,
            max_depth: DEFAULT_MAX_DEPTH,
            pixel_stride: DEFAULT_PIXEL_STRIDE,
            precision: Precision::default(),
            device: ComputeDevice::Cpu,
        }
    }
}

impl MapCommon {
    /// Checks the shared parameters of map `map` and returns its embedding dimension for an
    /// encoder of `encoder_dim` (`None` without an encoder): `dim` if set (it must equal the
    /// encoder's), else the encoder's, else 0.
    ///
    /// # Errors
    /// [`MapError::InvalidParameter`](crate::MapError::InvalidParameter) (wrapped as a stage
    /// error) for a `max_depth` that is not a positive number, a `pixel_stride` of 0, or a `dim`
    /// that disagrees with the encoder.
    /// A `device` other than `"cpu"` is refused with [`CoreError::Unsupported`]: maps that keep
    /// their table on a device check with [`MapCommon::validate_for_device`] instead.
    pub fn validate(&self, map: &str, encoder_dim: Option<usize>) -> Result<usize, CoreError> {
        if self.device != ComputeDevice::Cpu {
            return Err(CoreError::Unsupported {
                implementation: format!("the {map} map"),
                capability: "`device` other than \"cpu\" (the point-cloud and voxel maps keep \
                             their embeddings on a GPU)",
            });
        }
        self.validate_for_device(map, encoder_dim)
    }

    /// [`MapCommon::validate`] for a map that honours `device` (opening the device is the map's
    /// build step).
    ///
    /// # Errors
    /// As [`MapCommon::validate`], without the device check.
    pub fn validate_for_device(
        &self,
        map: &str,
        encoder_dim: Option<usize>,
    ) -> Result<usize, CoreError> {
        positive_metres(map, "max_depth", self.max_depth)?;
        // No RGB-D sensor measures farther; a larger bound is a unit mistake.
        number_in(map, "max_depth", self.max_depth, (0.0, 1000.0), "m")?;
        // Past 64 a map keeps a pixel in 4096 and is a map of nothing.
        count_in(
            map,
            "pixel_stride",
            usize::try_from(self.pixel_stride).unwrap_or(usize::MAX),
            (1, 64),
            "pixels",
        )?;
        resolve_dim(map, self.dim, encoder_dim)
    }
}

/// Declares a map's `[map]` config: a struct with the shared fields of [`MapCommon`] (`dim`,
/// `max_depth`, `pixel_stride`, `precision`, `device`, documented and defaulted here) and the map's own
/// fields, each with its default after `=`:
///
/// ```
/// vlem_maps::map_config! {
///     /// `[map] kind = "my-map"` parameters.
///     pub struct MyMapConfig {
///         /// Element budget; default 1000.
///         pub max_elements: usize = 1000,
///     }
/// }
/// let config: MyMapConfig = toml::from_str("max_elements = 5\nmax_depth = 4.0").unwrap();
/// assert_eq!((config.max_elements, config.max_depth, config.pixel_stride), (5, 4.0, 1));
/// assert!(toml::from_str::<MyMapConfig>("max_elemnts = 5").is_err());
/// assert_eq!(config.common().validate("my-map", Some(3)).unwrap(), 3);
/// ```
///
/// The struct derives `Clone`, `Debug`, `PartialEq`, `Default` (from the given defaults) and
/// serde's `Deserialize` with `deny_unknown_fields` (a missing key takes its default), so the
/// crate using the macro needs `serde` as a dependency. `common()` returns the shared fields as a
/// [`MapCommon`], whose [`MapCommon::validate`] checks them.
#[macro_export]
macro_rules! map_config {
    (
        $(#[$meta:meta])*
        $vis:vis struct $name:ident {
            $(
                $(#[$field_meta:meta])*
                $field_vis:vis $field:ident : $ty:ty = $default:expr
            ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Debug, PartialEq, serde::Deserialize)]
        #[serde(default, deny_unknown_fields)]
        $vis struct $name {
            /// Embedding dimension; defaults to the encoder's (0 without an encoder). If set, it
            /// must equal the encoder's.
            pub dim: Option<usize>,
            $(
                $(#[$field_meta])*
                $field_vis $field: $ty,
            )*
            /// Depth beyond this (metres) is not integrated; default 10.
            pub max_depth: f32,
            /// Use every n-th pixel in both directions; default 1 (every pixel, as in the paper).
            pub pixel_stride: u32,
            /// Embedding storage, `"f32"` (default) or `"f16"` (half the bytes, same query
            /// ranking).
            pub precision: $crate::storage::Precision,
            /// Where the embedding table lives: `"cpu"` (default), `"cuda"` or `"cuda:N"` (the
            /// point-cloud and voxel maps, in a build with the `cuda` feature).
            pub device: $crate::__private::ComputeDevice,
        }

        impl ::core::default::Default for $name {
            fn default() -> Self {
                let common = $crate::kit::MapCommon::default();
                Self {
                    dim: common.dim,
                    $($field: $default,)*
                    max_depth: common.max_depth,
                    pixel_stride: common.pixel_stride,
                    precision: common.precision,
                    device: common.device,
                }
            }
        }

        impl $name {
            /// The parameters every map shares.
            pub fn common(&self) -> $crate::kit::MapCommon {
                $crate::kit::MapCommon {
                    dim: self.dim,
                    max_depth: self.max_depth,
                    pixel_stride: self.pixel_stride,
                    precision: self.precision,
                    device: self.device,
                }
            }
        }
    };
}
