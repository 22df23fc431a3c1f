//! What the map benches that run a whole sequence share: which sequence, and how much of it.

use std::path::{Path, PathBuf};

use vlem_core::FrameSource;
use vlem_core::config::DatasetConfig;

/// The shared 150-frame living-room sequence (`../shared/data/icl-livingroom1`), or the
/// committed 30 frames where it is absent: its folder, the opened source and the number of frames
/// to run (all, or the first `VLEM_BENCH_FRAMES`).
pub fn sequence() -> (PathBuf, Box<dyn FrameSource>, usize) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let shared = root.join("../../shared/data/icl-livingroom1");
    let data = if shared.is_dir() {
        shared
    } else {
        root.join("../data/living-room")
    };
    let source = vlem_datasets::open(&DatasetConfig::default(), &data).unwrap();
    let frames = std::env::var("VLEM_BENCH_FRAMES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(source.len())
        .min(source.len());
    (data, source, frames)
}
