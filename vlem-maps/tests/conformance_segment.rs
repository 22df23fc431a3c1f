//! The shared map contract, run against the segment map.
#![cfg(feature = "segment")]
#![allow(clippy::panic, reason = "tests")]

use vlem_core::EmbeddingMap;
use vlem_maps::segment::SegmentConfig;

fn segment_map(dim: usize, max_points: usize) -> Box<dyn EmbeddingMap> {
    let config = SegmentConfig {
        max_points,
        point_spacing: 0.02,
        ..SegmentConfig::default()
    };
    match config.build(Some(dim)) {
        Ok(map) => Box::new(map),
        Err(e) => panic!("valid config refused: {e}"),
    }
}

vlem_testkit::map_conformance!(segment_map);
