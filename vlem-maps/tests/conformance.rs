//! The shared map contract, run against the point-cloud map.
#![cfg(feature = "point-cloud")]
#![allow(clippy::panic, reason = "tests")]

use vlem_core::EmbeddingMap;
use vlem_maps::point_cloud::PointCloudConfig;

fn point_cloud(dim: usize, max_points: usize) -> Box<dyn EmbeddingMap> {
    let config = PointCloudConfig {
        max_points,
        ..PointCloudConfig::default()
    };
    match config.build(Some(dim)) {
        Ok(map) => Box::new(map),
        Err(e) => panic!("valid config refused: {e}"),
    }
}

vlem_testkit::map_conformance!(point_cloud);
