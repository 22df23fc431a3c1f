//! A run's outputs, written into its folder as one consistent set: the trajectory, the dataset's
//! own poses beside an estimate, the map and `stats.json`, last.
//!
//! Why it exists: `vlem run`, the study's cells and Python's `Pipeline.run(out=…)` all leave a
//! folder that `vlem eval`, `vlem query` and the study table read, and each used to write it in
//! its own way (the cells wrote no `reference.tum` and no map file size). The rules live here
//! once: an earlier run's outputs go first (so a folder never mixes two runs), every file is
//! written whole (a temporary file, synced, renamed), and `stats.json` comes last, so a folder
//! with a `stats.json` holds one complete run.
//!
//! It lives in vlem-eval because the evaluations are what read the folder, and it needs both the
//! pipeline (vlem-core) and the trajectory format (vlem-datasets).

use std::path::Path;

use vlem_core::config::Mode;
use vlem_core::files::write_atomically;
use vlem_core::pipeline::{Pipeline, RunReport, RunStats};

use crate::error::{EvalError, Result};

/// The files a run writes into its folder besides its `query-*.ply` heatmaps;
/// [`clear_earlier_outputs`] removes an earlier run's before a run writes its own.
pub const RUN_OUTPUTS: [&str; 5] = [
    "stats.json",
    "trajectory.tum",
    "reference.tum",
    "map.vlem",
    "colour-model.ply",
];

/// Removes an earlier run's outputs ([`RUN_OUTPUTS`] and its `query-*.ply` heatmaps) from `out`;
/// other files stay. `stats.json` goes first.
///
/// # Errors
/// [`EvalError::Io`] naming a file that exists but cannot be removed.
pub fn clear_earlier_outputs(out: &Path) -> Result<()> {
    let remove = |path: &Path| match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(EvalError::Io {
            path: path.to_path_buf(),
            role: "an earlier run's output, to be replaced".to_owned(),
            source: e,
        }),
        _ => Ok(()),
    };
    for name in RUN_OUTPUTS {
        remove(&out.join(name))?;
    }
    if let Ok(entries) = std::fs::read_dir(out) {
        for entry in entries.flatten() {
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if name.starts_with("query-") && name.ends_with(".ply") {
                remove(&entry.path())?;
            }
        }
    }
    Ok(())
}

/// Writes the outputs of `report`, the run `pipeline` made, into `out` (created when missing):
/// `trajectory.tum`; `reference.tum` when the tracker estimated poses on a dataset that has
/// them; `map.vlem` when the pipeline has a map; `stats.json` last, with the map file's size and
/// `peak_device_bytes` when given. Returns the statistics written.
///
/// # Errors
/// Whatever file cannot be removed, written or encoded, naming it.
pub fn write_run(
    out: &Path,
    pipeline: &Pipeline,
    report: &RunReport,
    mode: Mode,
    peak_device_bytes: Option<u64>,
) -> Result<RunStats> {
    std::fs::create_dir_all(out).map_err(|source| EvalError::Io {
        path: out.to_path_buf(),
        role: "the run's output folder".to_owned(),
        source,
    })?;
    clear_earlier_outputs(out)?;
    vlem_datasets::trajectory::write_tum(&out.join("trajectory.tum"), &report.poses())?;
    // The dataset's own poses beside the estimate, so `vlem eval trajectory` needs nothing else.
    if let Some(reference) = report.reference_poses()
        && !pipeline.tracker().needs_dataset_poses()
    {
        vlem_datasets::trajectory::write_tum(&out.join("reference.tum"), &reference)?;
    }
    let live = pipeline.live();
    let saved = if live.has_map() {
        Some(live.save(&out.join("map.vlem"))?)
    } else {
        None
    };
    let map = pipeline.map();
    let mut stats = report.stats(
        mode,
        map.as_deref(),
        vlem_core::files::peak_resident_bytes(),
    );
    stats.peak_device_bytes = peak_device_bytes;
    if let (Some(map_stats), Some(saved)) = (&mut stats.map, saved) {
        map_stats.file_bytes = Some(saved.bytes);
    }
    let path = out.join("stats.json");
    let json = serde_json::to_string(&stats).map_err(|e| EvalError::Io {
        path: path.clone(),
        role: "the run's statistics".to_owned(),
        source: std::io::Error::other(e.to_string()),
    })?;
    write_atomically(&path, json.as_bytes())?;
    Ok(stats)
}
