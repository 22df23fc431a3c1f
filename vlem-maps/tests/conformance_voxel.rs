//! The shared map contract, run against the voxel map.
#![cfg(feature = "voxel")]
#![allow(clippy::panic, reason = "tests")]

/// In a module named `voxel` so that `cargo test voxel` selects these tests too.
mod voxel {
    use vlem_core::EmbeddingMap;
    use vlem_maps::voxel::VoxelConfig;

    /// 2 cm voxels: the suite's 64x48 plane at 2 m has a 4 cm pixel footprint, so every pixel gets
    /// a voxel of its own and the budget checks have thousands of voxels to work with.
    fn voxel_map(dim: usize, max_points: usize) -> Box<dyn EmbeddingMap> {
        let config = VoxelConfig {
            max_voxels: max_points,
            voxel_size: 0.02,
            ..VoxelConfig::default()
        };
        match config.build(Some(dim)) {
            Ok(map) => Box::new(map),
            Err(e) => panic!("valid config refused: {e}"),
        }
    }

    vlem_testkit::map_conformance!(voxel_map);
}
