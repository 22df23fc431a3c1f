//! Every numeric setting has a range (`docs/config-ranges.md`): a value outside it fails when the
//! pipeline is built, before any frame, with the key, the range and the value. One config per
//! stage setting that used to pass and then allocate without bound, loop or smear the map.
#![cfg(all(
    feature = "colour-names",
    feature = "point-cloud",
    feature = "voxel",
    feature = "segment",
    feature = "graph"
))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use vlem_backends as _;
use vlem_maps as _;
use vlem_plugin_colour_names as _;
use vlem_query as _;
use vlem_trackers as _;

use vlem_core::pipeline::Pipeline;
use vlem_core::{BuildContext, Config, Registry};

fn context() -> BuildContext {
    BuildContext {
        config_dir: std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("configs"),
        embedding_dim: None,
    }
}

/// The error of building a pipeline from `stages` (TOML sections besides `[dataset]`).
fn pipeline_error(stages: &str) -> String {
    let config = Config::from_toml(stages).unwrap();
    match Pipeline::from_config(&config, &context()) {
        Ok(_) => panic!("built, though out of range:\n{stages}"),
        Err(e) => vlem_core::message_chain(&e),
    }
}

#[test]
fn out_of_range_stage_settings_are_refused_naming_key_range_and_value() {
    let encoder = "[encoder]\nkind = \"colour-names\"\n";
    let cases = [
        (
            "[tracker]\nkind = \"frame-to-model\"\n[tracker.volume]\ntruncation_voxels = 1e6\n",
            "truncation_voxels",
            "must lie in 1–64 voxels, got 1000000",
        ),
        (
            &format!("{encoder}[map]\nkind = \"point-cloud\"\nmax_distance = 1e30\n"),
            "max_distance",
            "must lie in 0–1 m, got 1e30",
        ),
        (
            &format!("{encoder}[map]\nkind = \"point-cloud\"\nmax_points = 9223372036854775807\n"),
            "max_points",
            "must lie in 1–1073741824 points",
        ),
        (
            &format!("{encoder}[map]\nkind = \"voxel\"\nvoxel_size = 1e30\n"),
            "voxel_size",
            "must lie in 1e-4–10 m, got 1e30",
        ),
        (
            &format!("{encoder}[map]\nkind = \"segment\"\npoint_spacing = 1e-30\n"),
            "point_spacing",
            "must lie in 1e-4–10 m, got 1e-30",
        ),
        (
            &format!("{encoder}[map]\nkind = \"point-cloud\"\npixel_stride = 1000000\n"),
            "pixel_stride",
            "must lie in 1–64 pixels, got 1000000",
        ),
        (
            &format!("{encoder}[map]\nkind = \"voxel\"\nmax_depth = 1e20\n"),
            "max_depth",
            "must lie in 0–1000 m",
        ),
        (
            "[encoder]\nkind = \"colour-names\"\nsigma = 1e-200\n[map]\nkind = \"point-cloud\"\n",
            "sigma",
            "must lie in 0.1–1000, got 1e-200 (ΔE units",
        ),
    ];
    for (config, key, range) in cases {
        let error = pipeline_error(config);
        assert!(
            error.contains(key) && error.contains(range),
            "{config}\n→ {error}"
        );
    }
}

/// The error of building the stage `params` (a TOML section) with `build`.
fn stage_error<T>(
    params: &str,
    build: impl FnOnce(&vlem_core::StageConfig) -> vlem_core::Result<T>,
) -> String {
    let stage: vlem_core::StageConfig = toml::from_str(params).unwrap();
    match build(&stage) {
        Ok(_) => panic!("built, though out of range: {params}"),
        Err(e) => vlem_core::message_chain(&e),
    }
}

#[test]
fn out_of_range_proposer_and_segmenter_settings_are_refused() {
    let registry = Registry::global().unwrap();
    let proposer = |stage: &vlem_core::StageConfig| registry.build_proposer(stage, &context());
    let segmenter = |stage: &vlem_core::StageConfig| registry.build_segmenter(stage, &context());
    for (error, expected) in [
        (
            stage_error("kind = \"graph\"\nk = 1e30\n", proposer),
            "k must lie in 0–1000000, got 1e30",
        ),
        (
            stage_error("kind = \"graph\"\nmin_size = 4000000000\n", proposer),
            "min_size must lie in 0–16777216 pixels",
        ),
        (
            stage_error("kind = \"cluster\"\ncomponents = 1000000\n", segmenter),
            "components` must lie in 1–64, got 1000000",
        ),
        (
            stage_error("kind = \"cluster\"\neps = 1e-30\n", segmenter),
            "must lie in 1e-4–10 m, got 1e-30",
        ),
        (
            stage_error(
                "kind = \"cluster\"\nmin_points = 9223372036854775807\n",
                segmenter,
            ),
            "must lie in 1–1000000 points",
        ),
    ] {
        assert!(error.contains(expected), "{error}");
    }
}
