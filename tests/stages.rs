//! Overlapped embedding stages give the same map as serial ones: the demo's stages (ground-truth
//! poses, colour-names, the point-cloud map) and the voxel and segment maps on the committed
//! living-room frames, offline, bit for bit.
#![cfg(all(feature = "colour-names", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

// Link the crates whose stages the config names (registrations of unreferenced crates vanish).
use vlem_maps as _;
use vlem_plugin_colour_names as _;
use vlem_trackers as _;

use std::path::PathBuf;

use vlem_core::config::StageLayout;
use vlem_core::pipeline::{Pipeline, Progress};
use vlem_core::{MapSnapshot, StageConfig};

fn no_progress(_: Progress) {}

/// The demo config with `map` as its map, run offline with `stages`: the map afterwards.
fn map_after_run(map: Option<StageConfig>, stages: StageLayout) -> MapSnapshot {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let (mut config, ctx) = vlem_core::load_config(&repo.join("configs/demo.toml")).unwrap();
    if let Some(map) = map {
        config.map = Some(map);
    }
    config.pipeline.stages = stages;
    config.dataset.max_frames = Some(12);
    let dir = vlem_datasets::dataset_folder(&config, &ctx, None).unwrap();
    let mut source = vlem_datasets::open(&config.dataset, &dir).unwrap();
    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let report = pipeline.run(source.as_mut(), None, &no_progress).unwrap();
    assert_eq!(report.frames_processed, report.frames_total);
    assert_eq!(report.stages, stages);
    pipeline.live().snapshot().unwrap()
}

fn map_stage(kind: &str) -> StageConfig {
    StageConfig::named(kind)
}

#[test]
fn overlapped_stages_build_the_same_map_as_serial_ones() {
    let mut maps = vec![None];
    if cfg!(feature = "voxel") {
        maps.push(Some(map_stage("voxel")));
    }
    if cfg!(feature = "segment") {
        maps.push(Some(map_stage("segment")));
    }
    for map in maps {
        let serial = map_after_run(map.clone(), StageLayout::Serial);
        let overlapped = map_after_run(map.clone(), StageLayout::Overlapped);
        assert!(!serial.positions.is_empty());
        // MapSnapshot compares every position, colour and embedding value exactly.
        assert!(serial == overlapped, "{map:?}: the maps differ");
    }
}
