#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! Inputs that once crashed (or could crash) a vlem-core parser, kept as tests; found with the
//! fuzz targets of `fuzz/` (see fuzz/README.md).

use std::path::Path;
use std::time::Duration;

use vlem_core::config::Mode;
use vlem_core::mapfile::map_file_from_bytes;
use vlem_core::{Config, CoreError};

/// `[pipeline] frame_rate = 1e-300` (the `config_toml` seed `extreme_pipeline.toml`) made the
/// frame period 1e300 s, and `Duration::from_secs_f64` panicked on it when the pipeline started,
/// in either mode.
#[test]
fn config_toml_frame_rate_too_small_for_a_duration() {
    let text = "[pipeline]\nmode = \"real-time\"\nframe_rate = 1e-300\nqueue_capacity = 0\n";
    let mut config = Config::from_toml(text).unwrap().pipeline;
    assert_eq!(config.frame_period(), Duration::MAX);
    let err = config.validate().unwrap_err().to_string();
    assert!(err.contains("queue_capacity must be at least 1"), "{err}");
    config.queue_capacity = 1;
    let err = config.validate().unwrap_err().to_string();
    assert!(
        err.contains("frame_rate must be a positive number"),
        "{err}"
    );
    assert!(err.contains("1e-300"), "{err}");

    // Offline runs do not pace frames: the rate is not checked, and its period never panics.
    for rate in [1e-300, 1e-20, 0.0, -1.0, f64::NAN, f64::INFINITY] {
        config.frame_rate = rate;
        let _ = config.frame_period();
        config.mode = Mode::Offline;
        config.validate().unwrap();
        config.mode = Mode::RealTime;
        assert!(config.validate().is_err(), "{rate}");
    }
    config.frame_rate = 30.0;
    assert_eq!(config.frame_period(), Duration::from_secs_f64(1.0 / 30.0));
}

/// A header whose point count makes the expected file length overflow `usize`
/// (15 · 1229782938247303441 = `usize::MAX` bytes of positions and colours); with a valid CRC.
#[test]
fn map_file_point_count_overflowing_the_length() {
    let header = br#"{"map_kind":"x","points":1229782938247303441,"dim":0,"embedding_type":"f32","metadata":{"frames_integrated":0,"vlem_version":""}}"#;
    let mut bytes = b"VLEMMAP\0".to_vec();
    bytes.extend_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&u32::try_from(header.len()).unwrap().to_le_bytes());
    bytes.extend_from_slice(header);
    let crc = crc32fast_hash(&bytes);
    bytes.extend_from_slice(&crc.to_le_bytes());
    let err = map_file_from_bytes(&bytes, Path::new("map.vlem")).unwrap_err();
    assert!(matches!(err, CoreError::MapFile { .. }), "{err}");
}

/// CRC-32 (IEEE), bit by bit: the test needs no dependency for it.
fn crc32fast_hash(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
