//! `[dataset.synthetic]`: the settings of the generated scene, owned by its reader.

use serde::{Deserialize, Serialize};
use vlem_core::config::DatasetConfig;

use super::SYNTHETIC;
use crate::error::{DatasetError, Result};

/// Depth noise of the synthetic scene.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum SyntheticNoise {
    /// Exact depth (default).
    #[default]
    None,
    /// Kinect-like: axial noise σ(z) = 0.0012 + 0.0019 (z − 0.4)² m, disparity quantisation, no
    /// depth before 0.4 m or beyond 8 m, and dropout at grazing angles.
    Kinect,
}

/// `[dataset.synthetic]`: the procedural labelled RGB-D scene of `kind = "synthetic"`.
///
/// Plain data; [`SyntheticScene::new`](super::SyntheticScene::new) validates it (and names the
/// key of a bad value). Everything the scene holds, and its camera path, follows from these values
/// alone.
///
/// ```toml
/// [dataset]
/// kind = "synthetic"
///
/// [dataset.synthetic]
/// seed = 7
/// frames = 450
/// ```
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SyntheticConfig {
    /// Seed of the furniture, textures, camera path and noise; default 0.
    #[serde(default)]
    pub seed: u64,
    /// Number of frames; default 450 (15 s at 30 Hz: one full orbit of the room, which takes
    /// 380–440 frames).
    #[serde(default = "default_synthetic_frames")]
    pub frames: usize,
    /// Image width in pixels; default 640 (fx = fy = 525 · width / 640).
    #[serde(default = "default_synthetic_width")]
    pub width: u32,
    /// Image height in pixels; default 480.
    #[serde(default = "default_synthetic_height")]
    pub height: u32,
    /// Depth noise model; default `none` (exact depth).
    #[serde(default)]
    pub noise: SyntheticNoise,
    /// Room size in metres: x extent, y extent, height; default `[5.5, 4.5, 2.7]`.
    #[serde(default = "default_synthetic_room")]
    pub room: [f64; 3],
    /// How many pieces of furniture and wall items to try to place; default 18 (fewer fit in a
    /// small room; pilasters and small props on top of furniture come in addition, and pieces the
    /// camera path would not see are dropped).
    #[serde(default = "default_synthetic_objects")]
    pub objects: usize,
}

fn default_synthetic_frames() -> usize {
    450
}

fn default_synthetic_width() -> u32 {
    640
}

fn default_synthetic_height() -> u32 {
    480
}

fn default_synthetic_room() -> [f64; 3] {
    [5.5, 4.5, 2.7]
}

fn default_synthetic_objects() -> usize {
    18
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            frames: default_synthetic_frames(),
            width: default_synthetic_width(),
            height: default_synthetic_height(),
            noise: SyntheticNoise::None,
            room: default_synthetic_room(),
            objects: default_synthetic_objects(),
        }
    }
}

impl SyntheticConfig {
    /// The `[dataset]` config of this scene: `kind = "synthetic"` with these settings.
    ///
    /// # Errors
    /// [`DatasetError::InvalidSettings`] if the settings have no TOML form (never for finite
    /// values).
    pub fn dataset_config(&self) -> Result<DatasetConfig> {
        DatasetConfig::named(SYNTHETIC)
            .with_param("synthetic", self)
            .map_err(|e| DatasetError::InvalidSettings {
                reader: SYNTHETIC.to_owned(),
                message: e.to_string(),
            })
    }
}

/// `[dataset]` keys of the synthetic reader, besides the shared ones.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SyntheticSettings {
    /// `[dataset.synthetic]`.
    #[serde(default)]
    pub(super) synthetic: SyntheticConfig,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_section_parses_with_defaults_and_refuses_unknown_keys() {
        let config: vlem_core::Config = toml::from_str(
            "[dataset]\nkind = \"synthetic\"\n[dataset.synthetic]\nseed = 3\nnoise = \"kinect\"\n",
        )
        .unwrap();
        let settings: SyntheticSettings =
            crate::sequence::reader_settings(SYNTHETIC, &config.dataset).unwrap();
        let s = settings.synthetic;
        assert_eq!(s.seed, 3);
        assert_eq!(s.noise, SyntheticNoise::Kinect);
        assert_eq!((s.frames, s.width, s.height), (450, 640, 480));
        assert_eq!(s.room, [5.5, 4.5, 2.7]);
        let round_trip: SyntheticSettings =
            crate::sequence::reader_settings(SYNTHETIC, &s.dataset_config().unwrap()).unwrap();
        assert_eq!(round_trip.synthetic, s);

        let config: vlem_core::Config =
            toml::from_str("[dataset.synthetic]\nfrmaes = 3\n").unwrap();
        let err = crate::sequence::reader_settings::<SyntheticSettings>(SYNTHETIC, &config.dataset)
            .unwrap_err()
            .to_string();
        assert!(err.contains("unknown field `frmaes`"), "{err}");
    }
}
