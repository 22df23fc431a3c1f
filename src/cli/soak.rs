//! `vlem soak`: a long run on the synthetic scene that checks that memory stays flat.
//!
//! The pipeline of an ordinary config (tracker, encoder, map) maps N generated frames (default
//! 10,000) while the map is held to its budget. Every K frames the run samples the process's
//! resident memory (Linux `VmRSS`) and the map's size. After a warm-up — the latest of the first
//! `warmup` fraction of the frames, the frame at which the map is first seen enforcing its budget,
//! and the last sample at which the map's storage grew by more than `tolerance` (a buffer that
//! doubles once when a merge pass first needs room) — resident memory must stay within ±`tolerance` of its level at the end of the warm-up,
//! and the map must never hold more elements than its budget. The run writes `OUT/soak.json` (the
//! summary and the verdict) and `OUT/soak-samples.csv` (frame, rss bytes, map elements, map
//! bytes), prints a summary, and fails (nonzero exit) when a bound is broken.
//!
//! The frames go through the real [`Pipeline`] (tracking and embedding threads), one call of
//! [`Pipeline::run`] per K frames on a window of the scene, so the tracker and the map carry their
//! state across windows and the map can be measured between them.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::{Config, EmbeddingMap, Frame, FrameSource, Intrinsics};

use crate::output;

/// Frames when neither `--frames` nor `[dataset.synthetic] frames` says otherwise.
const DEFAULT_FRAMES: usize = 10_000;

/// The arguments of `vlem soak`.
#[derive(clap::Args)]
pub struct SoakArgs {
    /// Pipeline configuration (TOML) on a synthetic dataset; its `[map]` must set its budget.
    #[arg(long, default_value = "configs/soak.toml")]
    config: PathBuf,
    /// Frames to map (overrides `[dataset.synthetic] frames`; 10,000 where neither is set).
    #[arg(long)]
    frames: Option<usize>,
    /// Output folder for soak.json and soak-samples.csv.
    #[arg(long, default_value = "out/soak")]
    out: PathBuf,
    /// Frames between two samples of resident memory and map size.
    #[arg(long, default_value_t = 50)]
    sample_every: usize,
    /// Fraction of the frames that is always warm-up (the warm-up also lasts until the map is
    /// first seen enforcing its budget).
    #[arg(long, default_value_t = 0.1)]
    warmup: f64,
    /// Allowed relative deviation of resident memory from its post-warm-up level.
    #[arg(long, default_value_t = 0.1)]
    tolerance: f64,
}

/// One sample, taken after `frame` frames.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
struct Sample {
    /// Frames mapped so far.
    frame: usize,
    /// Resident memory of the process (bytes).
    rss_bytes: u64,
    /// Map elements (points, voxels or cells).
    map_elements: usize,
    /// Bytes of map storage.
    map_bytes: usize,
}

/// The verdict on a series of samples.
#[derive(Clone, Debug, PartialEq)]
struct Verdict {
    /// The sample whose resident memory is the post-warm-up level, if the warm-up ended.
    reference: Option<Sample>,
    /// Frame at which the warm-up ends (before the reference sample is taken).
    warmup_end: usize,
    /// The last sample at which the map's storage grew by more than the tolerance (0: never).
    storage_grew_at: usize,
    /// Lowest and highest resident memory from the reference sample on.
    rss_range: Option<(u64, u64)>,
    /// Every bound broken, in words; empty when the soak passed.
    failures: Vec<String>,
}

/// What the pipeline reported about the map at every integration.
#[derive(Debug, Default)]
struct MapWatch {
    /// Map size after the previous integration.
    last: AtomicUsize,
    /// Largest map size after any integration.
    max: AtomicUsize,
    /// Frames integrated so far.
    integrated: AtomicUsize,
    /// One past the frame index at which the map was first seen enforcing its budget (0: not yet).
    full_at: AtomicUsize,
}

impl MapWatch {
    /// Called from the embedding thread, once per integrated frame, in order.
    fn integrated(&self, index: usize, map_len: usize, budget: usize) {
        let last = self.last.swap(map_len, Ordering::Relaxed);
        self.max.fetch_max(map_len, Ordering::Relaxed);
        self.integrated.fetch_add(1, Ordering::Relaxed);
        // Maps only shrink by enforcing their budget (merging or evicting).
        let enforcing = map_len >= budget || map_len < last;
        if enforcing && self.full_at.load(Ordering::Relaxed) == 0 {
            self.full_at.store(index + 1, Ordering::Relaxed);
        }
    }

    /// The frame index at which the map first enforced its budget.
    fn full_frame(&self) -> Option<usize> {
        self.full_at.load(Ordering::Relaxed).checked_sub(1)
    }
}

/// Frames `start..start + len` of another source, numbered from 0 (their `Frame::index` stays the
/// index in the whole scene).
struct Window<'a> {
    inner: &'a mut dyn FrameSource,
    start: usize,
    len: usize,
}

impl FrameSource for Window<'_> {
    fn describe(&self) -> String {
        self.inner.describe()
    }

    fn len(&self) -> usize {
        self.len
    }

    fn intrinsics(&self) -> Intrinsics {
        self.inner.intrinsics()
    }

    fn has_poses(&self) -> bool {
        self.inner.has_poses()
    }

    fn frame(&mut self, index: usize) -> vlem_core::Result<Frame> {
        self.inner.frame(self.start + index)
    }
}

/// The map's budget ([`EmbeddingMap::budget`]): the parameter that caps its element count,
/// which the soak config must set.
fn map_budget(
    config: &Config,
    map: Option<&dyn EmbeddingMap>,
    path: &Path,
) -> Result<(String, usize)> {
    let (Some(map_config), Some(map)) = (&config.map, map) else {
        bail!(
            "{}: vlem soak needs a [map] (the point of the soak is a map held at its budget)",
            path.display()
        );
    };
    let Some(budget) = map.budget() else {
        bail!(
            "{}: vlem soak checks the map against its budget, and map `{}` has none",
            path.display(),
            map.name()
        );
    };
    let key = budget.parameter;
    if !map_config.params.contains_key(key) {
        bail!(
            "{}: vlem soak checks the map against its budget: set [map] {key} (a small one, so \
             that the map reaches it early)",
            path.display()
        );
    }
    Ok((key.to_owned(), budget.elements))
}

/// Runs the soak of `args`.
pub fn execute(args: &SoakArgs) -> Result<()> {
    if args.sample_every == 0 {
        bail!("--sample-every must be at least 1");
    }
    if !(0.0..1.0).contains(&args.warmup) {
        bail!("--warmup must be a fraction in [0, 1), got {}", args.warmup);
    }
    if !(args.tolerance.is_finite() && args.tolerance > 0.0) {
        bail!(
            "--tolerance must be a positive fraction, got {}",
            args.tolerance
        );
    }
    let path = &args.config;
    let (mut config, ctx) = vlem_core::load_config(path)?;
    if config.dataset.kind != vlem_datasets::synthetic::SYNTHETIC {
        bail!(
            "{}: vlem soak maps the synthetic scene, which has any number of frames: set \
             [dataset] kind = \"synthetic\"",
            path.display()
        );
    }
    // `[dataset.synthetic]` belongs to the reader, which checks it; only `frames` is set here.
    let section = config
        .dataset
        .params
        .entry("synthetic")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    let Some(section) = section.as_table_mut() else {
        bail!(
            "{}: [dataset] synthetic must be a table ([dataset.synthetic])",
            path.display()
        );
    };
    let frames = match (args.frames, section.get("frames")) {
        (Some(frames), _) => frames,
        (None, Some(value)) => value
            .as_integer()
            .and_then(|n| usize::try_from(n).ok())
            .with_context(|| {
                format!(
                    "{}: [dataset.synthetic] frames must be a whole number of frames, got {value}",
                    path.display()
                )
            })?,
        (None, None) => DEFAULT_FRAMES,
    };
    section.insert(
        "frames".to_owned(),
        toml::Value::Integer(i64::try_from(frames).context("--frames is too large")?),
    );

    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    let (budget_key, budget) = map_budget(&config, pipeline.map().as_deref(), path)?;
    let mut source =
        vlem_datasets::open(&config.dataset, &ctx.config_dir).map_err(|e| config.locate(e))?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let total = source.len();
    let map_name = pipeline.map().map_or("(none)", |m| m.name());
    eprintln!(
        "vlem soak: {total} frames from {}; tracker `{}`, encoder `{}`, map `{map_name}` with \
         {budget_key} = {budget}; sampling every {} frames",
        source.describe(),
        pipeline.tracker().name(),
        pipeline.encoder().map_or("(none)", |e| e.name()),
        args.sample_every,
    );

    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {msg} [{elapsed_precise}<{eta}]")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let watch = MapWatch::default();
    let on_progress = |event: Progress| match event {
        Progress::Tracked { .. } => bar.inc(1),
        Progress::Integrated { index, map_len } => watch.integrated(index, map_len, budget),
        Progress::Skipped { .. } => {}
    };
    let sample = |frame: usize, map: Option<&dyn EmbeddingMap>| -> Result<Sample> {
        Ok(Sample {
            frame,
            rss_bytes: vlem_core::files::resident_bytes()
                .context("vlem soak reads resident memory from /proc/self/status (Linux only)")?,
            map_elements: map.map_or(0, |m| m.len()),
            map_bytes: map.map_or(0, |m| m.memory_bytes()),
        })
    };

    let started = Instant::now();
    let mut samples = vec![sample(0, pipeline.map().as_deref())?];
    let mut totals = RunReport::default();
    let mut stage_ms: std::collections::BTreeMap<&'static str, (usize, f64)> = Default::default();
    let mut start = 0;
    while start < total {
        let len = args.sample_every.min(total - start);
        let mut window = Window {
            inner: source.as_mut(),
            start,
            len,
        };
        let report = pipeline.run(&mut window, None, &on_progress)?;
        totals.frames_tracked += report.frames_tracked;
        totals.frames_lost += report.frames_lost;
        totals.frames_processed += report.frames_processed;
        totals.frames_skipped += report.frames_skipped;
        for (stage, t) in &report.stage_ms {
            let entry = stage_ms.entry(*stage).or_default();
            entry.0 += t.count;
            entry.1 += t.mean_ms * t.count as f64;
        }
        start += len;
        samples.push(sample(start, pipeline.map().as_deref())?);
        bar.set_message(format!(
            "map {} / {budget}, rss {:.0} MB",
            samples.last().map_or(0, |s| s.map_elements),
            samples.last().map_or(0.0, |s| s.rss_bytes as f64 / 1e6)
        ));
    }
    bar.finish_and_clear();
    let wall = started.elapsed().as_secs_f64();

    let max_elements = watch.max.load(Ordering::Relaxed);
    let full_frame = watch.full_frame();
    let verdict = judge(
        &samples,
        total,
        args.warmup,
        args.tolerance,
        budget,
        max_elements,
        full_frame,
    );
    let passed = verdict.failures.is_empty();

    let mut csv = String::from("frame,rss_bytes,map_elements,map_bytes\n");
    for s in &samples {
        csv.push_str(&format!(
            "{},{},{},{}\n",
            s.frame, s.rss_bytes, s.map_elements, s.map_bytes
        ));
    }
    output::write_atomically(&args.out.join("soak-samples.csv"), csv.as_bytes())?;
    let last = samples.last().copied();
    let mean_ms: serde_json::Map<String, serde_json::Value> = stage_ms
        .iter()
        .map(|(stage, (count, total_ms))| {
            let mean = if *count > 0 {
                total_ms / *count as f64
            } else {
                0.0
            };
            ((*stage).to_owned(), serde_json::json!(mean))
        })
        .collect();
    let json = serde_json::json!({
        "passed": passed,
        "failures": verdict.failures,
        "config": path.display().to_string(),
        "scene": source.describe(),
        "frames": {
            "total": total,
            "tracked": totals.frames_tracked,
            "integrated": totals.frames_processed,
            "skipped": totals.frames_skipped,
            "lost": totals.frames_lost,
        },
        "wall_seconds": wall,
        "frames_per_second": total as f64 / wall.max(1e-9),
        "mean_ms": mean_ms,
        "sample_every": args.sample_every,
        "warmup": {
            "fraction": args.warmup,
            "map_full_at_frame": full_frame,
            "storage_last_grew_at_frame": verdict.storage_grew_at,
            "ends_at_frame": verdict.warmup_end,
            "reference": verdict.reference,
        },
        "rss_bytes": {
            "tolerance": args.tolerance,
            "at_warmup": verdict.reference.map(|s| s.rss_bytes),
            "min_after_warmup": verdict.rss_range.map(|r| r.0),
            "max_after_warmup": verdict.rss_range.map(|r| r.1),
            "end": last.map(|s| s.rss_bytes),
            "peak": vlem_core::files::peak_resident_bytes(),
        },
        "map": {
            "kind": map_name,
            "budget_key": budget_key,
            "budget": budget,
            "max_elements": max_elements,
            "end_elements": last.map(|s| s.map_elements),
            "end_bytes": last.map(|s| s.map_bytes),
        },
    });
    output::write_atomically(
        &args.out.join("soak.json"),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )?;

    let mb = |b: u64| b as f64 / 1e6;
    println!(
        "{total} frames: {} tracked, {} integrated, {} lost in {wall:.1} s ({:.1} frames/s)",
        totals.frames_tracked,
        totals.frames_processed,
        totals.frames_lost,
        total as f64 / wall.max(1e-9)
    );
    match full_frame {
        Some(f) => println!("map `{map_name}` first enforced its budget of {budget} at frame {f}"),
        None => println!("map `{map_name}` never reached its budget of {budget}"),
    }
    println!(
        "map: at most {max_elements} elements (budget {budget}); at the end {} elements, {:.1} MB",
        last.map_or(0, |s| s.map_elements),
        last.map_or(0.0, |s| s.map_bytes as f64 / 1e6)
    );
    if let (Some(reference), Some((lo, hi))) = (verdict.reference, verdict.rss_range) {
        println!(
            "resident memory: {:.1} MB after warm-up (frame {}), {:.1}–{:.1} MB after it, {:.1} MB \
             at the end (allowed {:.1}–{:.1} MB)",
            mb(reference.rss_bytes),
            reference.frame,
            mb(lo),
            mb(hi),
            mb(last.map_or(0, |s| s.rss_bytes)),
            mb(reference.rss_bytes) * (1.0 - args.tolerance),
            mb(reference.rss_bytes) * (1.0 + args.tolerance),
        );
    }
    println!("wrote {}", args.out.display());
    if passed {
        println!("soak passed");
        Ok(())
    } else {
        bail!("soak failed: {}", verdict.failures.join("; "))
    }
}

/// Judges a series of samples (the first at frame 0, the last at `total`).
///
/// The warm-up ends at the latest of `warmup · total`, one frame past `full_frame` (the frame at
/// which the map was first seen enforcing its budget) and the last sample at which the map's
/// storage (`map_bytes`) grew by more than `tolerance` over the sample before; the first sample at
/// or after that frame is the reference. A map whose storage keeps growing in such steps to the
/// end so leaves too few samples after the warm-up, and fails. Fails when the map never reached its budget, when it ever held more than
/// `budget` elements (`max_elements`), when fewer than two samples follow the reference, or when
/// any sample from the reference on has resident memory outside ±`tolerance` of the reference's.
fn judge(
    samples: &[Sample],
    total: usize,
    warmup: f64,
    tolerance: f64,
    budget: usize,
    max_elements: usize,
    full_frame: Option<usize>,
) -> Verdict {
    let mut failures = Vec::new();
    if max_elements > budget {
        failures.push(format!(
            "the map held {max_elements} elements, above its budget of {budget}"
        ));
    }
    if let Some(s) = samples.iter().find(|s| s.map_elements > budget) {
        failures.push(format!(
            "the map held {} elements at frame {}, above its budget of {budget}",
            s.map_elements, s.frame
        ));
    }
    let by_fraction = (warmup * total as f64).ceil() as usize;
    let storage_settled = samples
        .windows(2)
        .filter(|w| w[1].map_bytes as f64 > w[0].map_bytes as f64 * (1.0 + tolerance))
        .map(|w| w[1].frame)
        .max()
        .unwrap_or(0);
    let Some(full) = full_frame else {
        failures.push(format!(
            "the map never reached its budget of {budget} (at most {max_elements} elements): \
             lower the budget or map more frames"
        ));
        return Verdict {
            reference: None,
            warmup_end: by_fraction,
            storage_grew_at: storage_settled,
            rss_range: None,
            failures,
        };
    };
    let warmup_end = by_fraction.max(full + 1).max(storage_settled);
    let after: Vec<&Sample> = samples.iter().filter(|s| s.frame >= warmup_end).collect();
    if after.len() < 2 {
        failures.push(format!(
            "the warm-up lasted until frame {warmup_end} of {total} (the map reached its budget \
             at frame {full}; its storage last grew by more than {:.0}% at frame \
             {storage_settled}), leaving too few samples after it: map more frames or lower the \
             budget",
            tolerance * 100.0
        ));
        return Verdict {
            reference: after.first().map(|s| **s),
            warmup_end,
            storage_grew_at: storage_settled,
            rss_range: None,
            failures,
        };
    }
    let reference = *after[0];
    let level = reference.rss_bytes as f64;
    let (lo, hi) = after.iter().fold((u64::MAX, 0), |(lo, hi), s| {
        (lo.min(s.rss_bytes), hi.max(s.rss_bytes))
    });
    let outside: Vec<&&Sample> = after
        .iter()
        .filter(|s| (s.rss_bytes as f64 - level).abs() > tolerance * level)
        .collect();
    if let Some(worst) = outside.iter().max_by(|a, b| {
        (a.rss_bytes as f64 - level)
            .abs()
            .total_cmp(&(b.rss_bytes as f64 - level).abs())
    }) {
        failures.push(format!(
            "resident memory left ±{:.0}% of its post-warm-up level {:.1} MB (frame {}) at {} \
             sample(s), farthest {:.1} MB at frame {}",
            tolerance * 100.0,
            level / 1e6,
            reference.frame,
            outside.len(),
            worst.rss_bytes as f64 / 1e6,
            worst.frame
        ));
    }
    Verdict {
        reference: Some(reference),
        warmup_end,
        storage_grew_at: storage_settled,
        rss_range: Some((lo, hi)),
        failures,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    fn series(rss: &[u64], elements: &[usize]) -> Vec<Sample> {
        rss.iter()
            .zip(elements)
            .enumerate()
            .map(|(i, (&rss_mb, &map_elements))| Sample {
                frame: i * 10,
                rss_bytes: rss_mb * 1_000_000,
                map_elements,
                map_bytes: map_elements * 10,
            })
            .collect()
    }

    #[test]
    fn flat_memory_after_the_map_fills_passes() {
        // Memory grows while the map fills (until frame 30), then stays within 5 %.
        let s = series(
            &[50, 60, 80, 100, 104, 98, 101, 103, 99, 100, 102],
            &[0, 40, 80, 100, 100, 99, 100, 98, 100, 100, 100],
        );
        let v = judge(&s, 100, 0.1, 0.1, 100, 100, Some(25));
        assert!(v.failures.is_empty(), "{:?}", v.failures);
        // The storage grew by 25 % at frame 30, the last sample still filling the map.
        assert_eq!(v.warmup_end, 30);
        assert_eq!(v.reference.unwrap().frame, 30);
        assert_eq!(v.rss_range, Some((98_000_000, 104_000_000)));
    }

    #[test]
    fn one_step_of_the_maps_storage_after_the_budget_ends_the_warm_up_there() {
        // The budget is enforced from frame 25; the storage doubles once at frame 60 (a buffer
        // growing when a merge pass first needs room), and resident memory with it.
        let mut s = series(
            &[50, 60, 80, 100, 101, 100, 140, 141, 139, 140, 140],
            &[0, 40, 80, 100, 100, 99, 100, 98, 100, 100, 100],
        );
        s[6..].iter_mut().for_each(|x| x.map_bytes *= 2);
        let v = judge(&s, 100, 0.1, 0.1, 100, 100, Some(25));
        assert!(v.failures.is_empty(), "{:?}", v.failures);
        assert_eq!(v.warmup_end, 60);
        assert_eq!(v.reference.unwrap().frame, 60);
        // Storage that keeps growing leaves no warm-up end to judge from.
        let mut s = series(&[50; 11], &[100; 11]);
        for (i, x) in s.iter_mut().enumerate() {
            x.map_bytes = 1000 << i;
        }
        let v = judge(&s, 100, 0.1, 0.1, 100, 100, Some(0));
        assert!(
            v.failures[0].contains("its storage last grew by more than 10% at frame 100"),
            "{:?}",
            v.failures
        );
    }

    #[test]
    fn memory_that_keeps_growing_fails() {
        let s = series(
            &[50, 60, 80, 100, 105, 108, 109, 111, 115, 119, 123],
            &[0, 40, 80, 100, 100, 100, 100, 100, 100, 100, 100],
        );
        let v = judge(&s, 100, 0.1, 0.1, 100, 100, Some(25));
        assert_eq!(v.failures.len(), 1, "{:?}", v.failures);
        assert_eq!(
            v.failures[0],
            "resident memory left ±10% of its post-warm-up level 100.0 MB (frame 30) at 4 \
             sample(s), farthest 123.0 MB at frame 100"
        );
    }

    #[test]
    fn a_map_above_or_never_at_its_budget_fails() {
        let s = series(
            &[50; 11],
            &[0, 40, 80, 100, 101, 100, 100, 100, 100, 100, 100],
        );
        let v = judge(&s, 100, 0.1, 0.1, 100, 101, Some(25));
        assert_eq!(v.failures.len(), 2, "{:?}", v.failures);
        assert!(v.failures[0].contains("above its budget of 100"));

        let s = series(&[50; 11], &[0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 95]);
        let v = judge(&s, 100, 0.1, 0.1, 100, 95, None);
        assert_eq!(v.reference, None);
        assert!(v.failures[0].contains("never reached its budget of 100"));

        // Reached only at the very end: nothing left to judge.
        let v = judge(&s, 100, 0.1, 0.1, 100, 100, Some(99));
        assert!(
            v.failures[0].contains("too few samples"),
            "{:?}",
            v.failures
        );
    }

    #[test]
    fn the_map_watch_sees_the_budget_enforced() {
        let watch = MapWatch::default();
        for (i, len) in [10, 60, 90, 95, 80, 99].into_iter().enumerate() {
            watch.integrated(i, len, 100);
        }
        // The map first shrank (merged) at frame 4.
        assert_eq!(watch.full_frame(), Some(4));
        assert_eq!(watch.max.load(Ordering::Relaxed), 99);
        let watch = MapWatch::default();
        watch.integrated(0, 100, 100);
        assert_eq!(watch.full_frame(), Some(0));
    }
}
