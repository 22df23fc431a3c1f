//! `vlem`: run the mapping pipeline on an RGB-D dataset, query saved maps, list plugins, run the demo.

mod output;
mod plugins;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::{
    BuildContext, Config, Encoder, MapMetadata, MapSnapshot, QueryScores, Registry, StageConfig,
    StageKind,
};

/// The embedded default configuration that `vlem demo` runs.
const DEMO_CONFIG: &str = include_str!("../configs/demo.toml");
/// Where the demo config's relative paths point (the repository's `configs/`).
const DEMO_CONFIG_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs");

#[derive(Parser)]
#[command(
    name = "vlem",
    version,
    about = "Real-time 3D vision-language embedding mapping"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Map a dataset: writes OUT/map.vlem, OUT/trajectory.tum and OUT/stats.json.
    Run {
        /// Pipeline configuration (TOML).
        #[arg(long)]
        config: PathBuf,
        /// Dataset folder (overrides `[dataset] path`).
        #[arg(long)]
        dataset: Option<PathBuf>,
        /// Output folder.
        #[arg(long, default_value = "out")]
        out: PathBuf,
        /// Process at most this many frames.
        #[arg(long)]
        max_frames: Option<usize>,
    },
    /// Query a saved map with text.
    Query {
        /// Map file written by `vlem run`.
        #[arg(long)]
        map: PathBuf,
        /// Write a PLY heatmap (jet colours); with several queries, one file per query.
        #[arg(long)]
        ply: Option<PathBuf>,
        /// Normalised similarity at or above which a point counts as a hit.
        #[arg(long, default_value_t = 0.75)]
        threshold: f32,
        /// Query texts.
        #[arg(required = true)]
        text: Vec<String>,
    },
    /// List every registered implementation per stage.
    Plugins,
    /// Run the embedded default: the committed living-room frames, pseudo ground-truth poses, the
    /// point-cloud map, the colour-names encoder and two queries.
    Demo {
        /// Output folder.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
    },
}

fn main() -> std::process::ExitCode {
    match execute(Cli::parse().command) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // The whole cause chain on one line, without a backtrace: these are user errors.
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn execute(command: Command) -> Result<()> {
    match command {
        Command::Run {
            config,
            dataset,
            out,
            max_frames,
        } => {
            let text = std::fs::read_to_string(&config)
                .with_context(|| format!("cannot read config {}", config.display()))?;
            let dir = config
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            let parsed = Config::from_toml(&text)
                .map_err(|message| anyhow::anyhow!("config {}: {message}", config.display()))?;
            run(parsed, dir, dataset, &out, max_frames)
        }
        Command::Query {
            map,
            ply,
            threshold,
            text,
        } => query(&map, ply.as_deref(), threshold, &text),
        Command::Plugins => list_plugins(),
        Command::Demo { out } => {
            let config = Config::from_toml(DEMO_CONFIG)
                .map_err(|message| anyhow::anyhow!("embedded demo config: {message}"))?;
            run(config, Path::new(DEMO_CONFIG_DIR), None, &out, None)
        }
    }
}

fn run(
    mut config: Config,
    config_dir: &Path,
    dataset: Option<PathBuf>,
    out: &Path,
    max_frames: Option<usize>,
) -> Result<()> {
    let config_dir = config_dir
        .canonicalize()
        .with_context(|| format!("config folder {}", config_dir.display()))?;
    let ctx = BuildContext {
        config_dir: config_dir.clone(),
        embedding_dim: None,
    };
    let dataset_dir = match (dataset, &config.dataset.path) {
        (Some(dir), _) => dir,
        (None, Some(path)) => ctx.resolve(path),
        (None, None) => bail!("no dataset: pass --dataset DIR or set [dataset] path in the config"),
    };
    if !dataset_dir.is_dir() {
        bail!(
            "dataset folder {} does not exist (pass --dataset DIR to use another one)",
            dataset_dir.display()
        );
    }
    if max_frames.is_some() {
        config.dataset.max_frames = max_frames;
    }
    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    // Built before mapping so a bad [query.segmenter] fails at start-up, not after the run.
    let segmenter = Registry::global()?.build_segmenter(&config.query.segmenter, &ctx)?;
    let mut source = vlem_datasets::open(&config.dataset, &dataset_dir)?;
    // Before mapping, so an unwritable output folder fails now rather than after a long run.
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let total = source.len();
    eprintln!(
        "vlem: {} frames from {}; tracker `{}`, encoder `{}`, map `{}`",
        total,
        source.describe(),
        pipeline.tracker().name(),
        pipeline.encoder().map_or("(none)", |e| e.name()),
        pipeline.map().map_or("(none)", |m| m.name()),
    );

    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {msg} [{elapsed_precise}<{eta}]")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let (integrated, skipped, points) = (
        AtomicUsize::new(0),
        AtomicUsize::new(0),
        AtomicUsize::new(0),
    );
    let on_progress = |event: Progress| {
        match event {
            Progress::Tracked { .. } => bar.inc(1),
            Progress::Integrated { map_len, .. } => {
                integrated.fetch_add(1, Ordering::Relaxed);
                points.store(map_len, Ordering::Relaxed);
            }
            Progress::Skipped { .. } => {
                skipped.fetch_add(1, Ordering::Relaxed);
            }
        }
        bar.set_message(format!(
            "({} integrated, {} skipped, {} map points)",
            integrated.load(Ordering::Relaxed),
            skipped.load(Ordering::Relaxed),
            points.load(Ordering::Relaxed)
        ));
    };
    let report = pipeline.run(source.as_mut(), None, &on_progress)?;
    bar.finish_and_clear();

    let trajectory: Vec<(f64, vlem_core::Pose)> = report
        .trajectory
        .iter()
        .map(|e| (e.timestamp, e.pose))
        .collect();
    vlem_datasets::trajectory::write_tum(&out.join("trajectory.tum"), &trajectory)?;
    let mut snapshot = None;
    if let Some(map) = pipeline.map() {
        let mut snap = map.snapshot();
        snap.metadata = MapMetadata {
            encoder: config.encoder.clone(),
            config_dir: Some(config_dir.clone()),
            frames_integrated: snap.metadata.frames_integrated,
            vlem_version: env!("CARGO_PKG_VERSION").into(),
        };
        vlem_core::write_map_file(&out.join("map.vlem"), &snap)?;
        snapshot = Some(snap);
    }
    let stats = stats_json(&config, &report, pipeline.map());
    output::write_atomically(&out.join("stats.json"), stats.to_string().as_bytes())?;
    print_summary(&report, pipeline.map(), out);

    if let (Some(snap), Some(encoder)) = (&snapshot, pipeline.encoder())
        && !config.query.texts.is_empty()
    {
        answer_queries(
            snap,
            encoder,
            segmenter.as_ref(),
            &config.query.texts,
            Some(out),
        )?;
    }
    Ok(())
}

fn stats_json(
    config: &Config,
    report: &RunReport,
    map: Option<&dyn vlem_core::EmbeddingMap>,
) -> serde_json::Value {
    let mean_ms: serde_json::Map<String, serde_json::Value> = report
        .stage_ms
        .iter()
        .map(|(stage, t)| ((*stage).to_owned(), serde_json::json!(t.mean_ms)))
        .collect();
    serde_json::json!({
        "frames": {
            "total": report.frames_total,
            "tracked": report.frames_tracked,
            "processed": report.frames_processed,
            "skipped": report.frames_skipped,
            "lost": report.frames_lost,
        },
        "mode": config.pipeline.mode,
        "mean_ms": mean_ms,
        "wall_seconds": report.wall_seconds,
        "map": map.map(|m| serde_json::json!({
            "kind": m.name(),
            "points": m.len(),
            "dim": m.dim(),
            "bytes": m.memory_bytes(),
        })),
        "peak_resident_bytes": output::peak_resident_bytes(),
    })
}

fn print_summary(report: &RunReport, map: Option<&dyn vlem_core::EmbeddingMap>, out: &Path) {
    println!(
        "{} frames: {} tracked, {} integrated, {} skipped, {} lost in {:.1} s",
        report.frames_total,
        report.frames_tracked,
        report.frames_processed,
        report.frames_skipped,
        report.frames_lost,
        report.wall_seconds
    );
    let stages: Vec<String> = report
        .stage_ms
        .iter()
        .map(|(stage, t)| format!("{stage} {:.1}", t.mean_ms))
        .collect();
    println!("mean ms per frame: {}", stages.join(", "));
    if let Some(map) = map {
        println!(
            "map `{}`: {} points, {}-d embeddings, {:.1} MB",
            map.name(),
            map.len(),
            map.dim(),
            map.memory_bytes() as f64 / 1e6
        );
    }
    println!("wrote {}", out.display());
}

fn query(map_path: &Path, ply: Option<&Path>, threshold: f32, texts: &[String]) -> Result<()> {
    let snapshot = vlem_core::read_map_file(map_path)?;
    let Some(stage) = snapshot.metadata.encoder.clone() else {
        bail!(
            "{} was mapped without an encoder (geometry only): it cannot answer text queries",
            map_path.display()
        );
    };
    let ctx = BuildContext {
        config_dir: snapshot.metadata.config_dir.clone().unwrap_or_default(),
        embedding_dim: None,
    };
    let registry = Registry::global()?;
    let encoder = registry.build_encoder(&stage, &ctx)?;
    let mut params = toml::Table::new();
    params.insert("threshold".into(), toml::Value::Float(f64::from(threshold)));
    let segmenter = registry.build_segmenter(
        &StageConfig {
            kind: "threshold".into(),
            params,
        },
        &ctx,
    )?;
    println!(
        "{}: {} points, {}-d embeddings from `{}`",
        map_path.display(),
        snapshot.len(),
        snapshot.dim,
        stage.kind
    );
    let scores = answer_queries(&snapshot, encoder.as_ref(), segmenter.as_ref(), texts, None)?;
    if let Some(ply) = ply {
        for (i, s) in scores.scores.iter().enumerate() {
            let path = if texts.len() == 1 {
                ply.to_path_buf()
            } else {
                let stem = ply
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                ply.with_file_name(format!("{stem}-{}.ply", slug(&texts[i])))
            };
            output::write_atomically(&path, &output::heatmap_ply(&snapshot.positions, s))?;
            println!("wrote {}", path.display());
        }
    }
    Ok(())
}

/// Scores every point for every query, prints a line per query, and (with `ply_dir`) writes one
/// heatmap PLY per query there.
fn answer_queries(
    snapshot: &MapSnapshot,
    encoder: &dyn Encoder,
    segmenter: &dyn vlem_core::Segmenter,
    texts: &[String],
    ply_dir: Option<&Path>,
) -> Result<QueryScores> {
    if snapshot.dim != encoder.dim() {
        bail!(
            "the map holds {}-d embeddings but the encoder `{}` makes {}-d ones",
            snapshot.dim,
            encoder.name(),
            encoder.dim()
        );
    }
    let score = |text: &str| -> Result<Vec<f32>> {
        let e = encoder
            .encode_text(text)
            .with_context(|| format!("cannot embed the query \"{text}\""))?;
        let mut s = Vec::new();
        vlem_core::query::normalised_similarity(&snapshot.embeddings, snapshot.dim, &e, &mut s)?;
        Ok(s)
    };
    let scores = QueryScores {
        queries: texts.to_vec(),
        scores: texts.iter().map(|t| score(t)).collect::<Result<_>>()?,
        baseline: segmenter.baseline_query().map(score).transpose()?,
    };
    let sets = segmenter.segment(&snapshot.positions, &scores)?;
    for (q, text) in texts.iter().enumerate() {
        let s = &scores.scores[q];
        let best = (0..s.len()).max_by(|&a, &b| s[a].total_cmp(&s[b]));
        let hits: usize = sets
            .iter()
            .filter(|set| set.query == q)
            .map(|set| set.indices.len())
            .sum();
        match best {
            Some(i) => {
                let p = snapshot.positions[i];
                println!(
                    "\"{text}\": best {:.3} at ({:.2}, {:.2}, {:.2}); {hits} of {} points selected by `{}`",
                    s[i],
                    p[0],
                    p[1],
                    p[2],
                    s.len(),
                    segmenter.name()
                );
            }
            None => println!("\"{text}\": the map is empty"),
        }
        if let Some(dir) = ply_dir {
            let path = dir.join(format!("query-{}.ply", slug(text)));
            output::write_atomically(&path, &output::heatmap_ply(&snapshot.positions, s))?;
        }
    }
    Ok(scores)
}

/// A file-name-safe form of a query.
fn slug(text: &str) -> String {
    let s: String = text
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '-'
            }
        })
        .collect();
    let s = s.trim_matches('-').to_owned();
    if s.is_empty() { "query".into() } else { s }
}

fn list_plugins() -> Result<()> {
    let registry = Registry::global()?;
    for kind in StageKind::ALL {
        println!("{kind}s ([{}] kind = ...):", kind.section());
        let mut any = false;
        for r in registry.iter().filter(|r| r.builder.kind() == kind) {
            println!("  {:<16} {}", r.name, r.description);
            any = true;
        }
        if !any {
            println!("  (none compiled in)");
        }
    }
    Ok(())
}
