//! The rerun recordings of `vlem run`/`demo --rerun` and `vlem query --rerun`, read back with the
//! rerun SDK's decoder: the entities docs/usage.md promises are in the file, with a row per frame.
#![cfg(feature = "cli")]
#![cfg(feature = "rerun")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use std::collections::BTreeMap;
use std::path::Path;

use common::ok;
use re_log_encoding::Decoder;
use rerun::log::{Chunk, LogMsg};

/// Rows logged per entity path, over the whole recording.
fn rows_per_entity(path: &Path) -> BTreeMap<String, usize> {
    let file = std::fs::File::open(path).unwrap();
    let mut rows = BTreeMap::new();
    for message in Decoder::<LogMsg>::decode_lazy(std::io::BufReader::new(file)) {
        if let LogMsg::ArrowMsg(_, arrow) = message.unwrap() {
            let chunk = Chunk::from_arrow_msg(&arrow).unwrap();
            *rows.entry(chunk.entity_path().to_string()).or_default() += chunk.num_rows();
        }
    }
    rows
}

fn assert_has(rows: &BTreeMap<String, usize>, entity: &str, at_least: usize) {
    let n = rows.get(entity).copied().unwrap_or(0);
    assert!(
        n >= at_least,
        "{entity}: {n} rows, expected at least {at_least}; entities: {rows:#?}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn demo_recording_has_frames_map_and_query_heatmaps() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let rrd = tmp.path().join("demo.rrd");
    let stdout = ok(&[
        "demo",
        "--out",
        out.to_str().unwrap(),
        "--rerun",
        rrd.to_str().unwrap(),
        "--rerun-map-every",
        "10",
    ]);
    assert!(stdout.contains("recording: "), "{stdout}");
    let rows = rows_per_entity(&rrd);
    // The demo maps 30 frames: one camera pose, pinhole, colour and depth image each.
    for entity in [
        "/world/camera",
        "/world/camera/image",
        "/world/camera/image/rgb",
        "/world/camera/image/depth",
        "/world/trajectory",
    ] {
        assert_has(&rows, entity, 30);
    }
    // Every 10th integrated frame and once at the end.
    assert_has(&rows, "/world/map", 4);
    for query in ["white-wall", "brown"] {
        assert_has(&rows, &format!("/world/queries/{query}/heatmap"), 1);
        assert_has(&rows, &format!("/world/queries/{query}/selected"), 1);
    }
    // The demo's encoder embeds pixels, not regions: no proposer ran, no segments were logged.
    assert!(
        !rows.contains_key("/world/camera/image/segments"),
        "{rows:#?}"
    );
}

#[cfg(all(feature = "colour-names", feature = "point-cloud"))]
#[test]
fn query_recording_has_heatmap_sets_and_grasp() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    ok(&["demo", "--out", out.to_str().unwrap()]);
    let rrd = tmp.path().join("query.rrd");
    let map = out.join("map.vlem");
    let stdout = ok(&[
        "query",
        "--map",
        map.to_str().unwrap(),
        "--segmenter",
        "cluster",
        "--baseline",
        "white",
        "--grasp",
        "--rerun",
        rrd.to_str().unwrap(),
        "brown",
    ]);
    let rows = rows_per_entity(&rrd);
    assert_has(&rows, "/world/map", 1);
    assert_has(&rows, "/world/queries/brown/heatmap", 1);
    assert_has(&rows, "/world/queries/brown/selected", 1);
    // A grasp is drawn when one was found, and cleared otherwise; the entity exists either way.
    assert_has(&rows, "/world/queries/brown/grasp", 1);
    assert!(stdout.contains("\"brown\": "), "{stdout}");
}

#[test]
fn frame_to_model_recording_has_the_colour_model() {
    let tmp = tempfile::tempdir().unwrap();
    let rrd = tmp.path().join("run.rrd");
    let out = tmp.path().join("run");
    ok(&[
        "run",
        "--config",
        "configs/track-frame-to-model.toml",
        "--max-frames",
        "5",
        "--out",
        out.to_str().unwrap(),
        "--rerun",
        rrd.to_str().unwrap(),
    ]);
    let rows = rows_per_entity(&rrd);
    assert_has(&rows, "/world/colour_model", 1);
    assert_has(&rows, "/world/camera", 5);
}

#[cfg(all(feature = "clip", feature = "graph", feature = "point-cloud"))]
#[test]
fn segment_encoder_recording_has_the_proposer_segments() {
    let tmp = tempfile::tempdir().unwrap();
    let rrd = tmp.path().join("clip.rrd");
    let out = tmp.path().join("clip");
    ok(&[
        "run",
        "--config",
        "configs/synthetic-clip.toml",
        "--max-frames",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--rerun",
        rrd.to_str().unwrap(),
    ]);
    let rows = rows_per_entity(&rrd);
    // The graph proposer's regions of every integrated frame, beside its colour image.
    assert_has(&rows, "/world/camera/image/segments", 3);
    assert_has(&rows, "/world/camera/image/rgb", 3);
    assert_has(&rows, "/world/queries/a-chair/heatmap", 1);
}
