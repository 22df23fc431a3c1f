//! `vlem`: run the mapping pipeline on an RGB-D dataset, query saved maps, list plugins, run the demo.

mod eval;
mod output;
mod plugins;
mod soak;
mod study;
mod study_plot;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::{
    BuildContext, Config, Encoder, MapMetadata, MapSnapshot, PointSet, QueryScores, Registry,
    StageConfig, StageKind,
};
use vlem_maps::grasp::GraspParams;

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
        /// Do not write OUT/colour-model.ply, the dense colour model (TSDF mesh) that trackers
        /// with a model (`frame-to-model`) export after the run.
        #[arg(long)]
        no_colour_model: bool,
    },
    /// Query a saved map with text.
    Query {
        /// Map file written by `vlem run`.
        #[arg(long)]
        map: PathBuf,
        /// Write a PLY heatmap (jet colours); with several queries, one file per query.
        #[arg(long)]
        ply: Option<PathBuf>,
        /// How points are selected: `threshold` (similarity ≥ --threshold), `argmax` (the best of
        /// the queries and the baseline "object") or `cluster` (argmax, then GMM on similarity and
        /// DBSCAN on coordinates: one point set per object, best first).
        #[arg(long, default_value = "threshold")]
        segmenter: String,
        /// Normalised similarity at or above which a point counts as a hit (default 0.75 for
        /// `threshold`; for `argmax` and `cluster`, a minimum on top of beating the baseline).
        #[arg(long)]
        threshold: Option<f32>,
        /// The generic text a point must match better to belong to a query, for `argmax` and
        /// `cluster` (default "object"; it must be a text the map's encoder can embed).
        #[arg(long)]
        baseline: Option<String>,
        /// Compute a parallel-gripper grasp (approach from above, +y) on each query's best point
        /// set; with --ply, the gripper is drawn into the heatmap.
        #[arg(long)]
        grasp: bool,
        /// Query texts.
        #[arg(required = true)]
        text: Vec<String>,
    },
    /// Evaluate results against a reference (trajectory accuracy: ATE and RPE).
    Eval {
        /// What to evaluate.
        #[command(subcommand)]
        command: eval::EvalCommand,
    },
    /// List every registered implementation per stage.
    Plugins,
    /// Soak test: map many synthetic frames under a small map budget and check that resident
    /// memory stays flat; writes OUT/soak.json and OUT/soak-samples.csv.
    Soak(soak::SoakArgs),
    /// Run a comparison study (maps × encoders × trackers × sequences): one `vlem run` and one
    /// `vlem eval semseg3d` per cell, then OUT/study.csv and a plot of mIoU against memory.
    Study(study::StudyArgs),
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
            eprintln!("error: {}", one_line(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The cause chain on one line, without a backtrace (these are user errors). Library errors that
/// wrap another one already say its message, so a cause already contained in the line is skipped.
fn one_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
    }
    line
}

fn execute(command: Command) -> Result<()> {
    match command {
        Command::Run {
            config,
            dataset,
            out,
            max_frames,
            no_colour_model,
        } => {
            let parsed = read_config(&config)?;
            let options = RunOptions {
                dataset,
                max_frames,
                colour_model: !no_colour_model,
            };
            run(parsed, config_folder(&config), &out, &options)
        }
        Command::Query {
            map,
            ply,
            segmenter,
            threshold,
            baseline,
            grasp,
            text,
        } => query(
            &map,
            &QueryOptions {
                ply,
                segmenter,
                threshold,
                baseline,
                grasp,
            },
            &text,
        ),
        Command::Eval { command } => eval::execute(command),
        Command::Plugins => list_plugins(),
        Command::Soak(args) => soak::execute(&args),
        Command::Study(args) => study::execute(&args),
        Command::Demo { out } => {
            let config = Config::from_toml(DEMO_CONFIG)
                .map_err(|message| anyhow::anyhow!("embedded demo config: {message}"))?;
            run(
                config,
                Path::new(DEMO_CONFIG_DIR),
                &out,
                &RunOptions {
                    dataset: None,
                    max_frames: None,
                    colour_model: true,
                },
            )
        }
    }
}

/// Command-line choices of `vlem run` beyond the config.
struct RunOptions {
    /// Dataset folder overriding `[dataset] path`.
    dataset: Option<PathBuf>,
    /// Frame limit overriding `[dataset] max_frames`.
    max_frames: Option<usize>,
    /// Export the tracker's dense colour model where it has one.
    colour_model: bool,
}

/// Reads and parses a config file.
fn read_config(path: &Path) -> Result<Config> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read config {}", path.display()))?;
    Config::from_toml(&text)
        .map_err(|message| anyhow::anyhow!("config {}: {message}", path.display()))
}

/// The folder of a config file, against which its relative paths are resolved.
fn config_folder(path: &Path) -> &Path {
    path.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
}

/// The build context of a config in `config_dir` (made absolute, so paths resolve anywhere).
fn build_context(config_dir: &Path) -> Result<BuildContext> {
    let config_dir = config_dir
        .canonicalize()
        .with_context(|| format!("config folder {}", config_dir.display()))?;
    Ok(BuildContext {
        config_dir,
        embedding_dim: None,
    })
}

/// The dataset folder: `--dataset`, else `[dataset] path`; a synthetic scene needs none.
fn dataset_folder(config: &Config, ctx: &BuildContext, dataset: Option<&Path>) -> Result<PathBuf> {
    let synthetic = config.dataset.kind == vlem_core::config::DatasetKind::Synthetic;
    let dataset_dir = match (dataset, &config.dataset.path) {
        (Some(dir), _) => dir.to_path_buf(),
        (None, Some(path)) => ctx.resolve(path),
        // A synthetic scene is generated from [dataset.synthetic]; it has no folder.
        (None, None) if synthetic => ctx.config_dir.clone(),
        (None, None) => bail!("no dataset: pass --dataset DIR or set [dataset] path in the config"),
    };
    if !synthetic && !dataset_dir.is_dir() {
        bail!(
            "dataset folder {} does not exist (pass --dataset DIR to use another one)",
            dataset_dir.display()
        );
    }
    Ok(dataset_dir)
}

fn run(mut config: Config, config_dir: &Path, out: &Path, options: &RunOptions) -> Result<()> {
    let max_frames = options.max_frames;
    let ctx = build_context(config_dir)?;
    let dataset_dir = dataset_folder(&config, &ctx, options.dataset.as_deref())?;
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
    // The dataset's own poses beside the estimate, so `vlem eval trajectory` needs nothing else.
    let reference: Option<Vec<(f64, vlem_core::Pose)>> = report
        .trajectory
        .iter()
        .map(|e| e.reference.map(|pose| (e.timestamp, pose)))
        .collect();
    if let Some(reference) = reference.filter(|r| !r.is_empty())
        && !pipeline.tracker().needs_dataset_poses()
    {
        vlem_datasets::trajectory::write_tum(&out.join("reference.tum"), &reference)?;
    }
    let mut snapshot = None;
    if let Some(map) = pipeline.map() {
        let mut snap = map.snapshot();
        snap.metadata = MapMetadata {
            encoder: config.encoder.clone(),
            config_dir: Some(ctx.config_dir.clone()),
            frames_integrated: snap.metadata.frames_integrated,
            vlem_version: env!("CARGO_PKG_VERSION").into(),
        };
        vlem_core::write_map_file(&out.join("map.vlem"), &snap)?;
        snapshot = Some(snap);
    }
    let stats = stats_json(&config, &report, pipeline.map());
    output::write_atomically(&out.join("stats.json"), stats.to_string().as_bytes())?;
    print_summary(&report, pipeline.map(), out);
    if options.colour_model {
        export_colour_model(pipeline.tracker(), out)?;
    }

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

/// Writes OUT/colour-model.ply when the tracker keeps a dense colour model.
fn export_colour_model(tracker: &dyn vlem_core::Tracker, out: &Path) -> Result<()> {
    match tracker.colour_model() {
        Ok(mesh) => {
            let path = out.join("colour-model.ply");
            output::write_atomically(&path, &output::mesh_ply(&mesh))?;
            println!(
                "dense colour model: {} ({} vertices, {} triangles)",
                path.display(),
                mesh.vertices.len(),
                mesh.triangles.len()
            );
            Ok(())
        }
        Err(vlem_core::CoreError::Unsupported { .. }) => Ok(()),
        Err(e) => Err(e.into()),
    }
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
        "lost_frames": report
            .trajectory
            .iter()
            .filter_map(|e| e.lost.as_ref().map(|reason| serde_json::json!({
                "index": e.index,
                "reason": reason,
            })))
            .collect::<Vec<_>>(),
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

/// The options of `vlem query` besides the map and the texts.
struct QueryOptions {
    ply: Option<PathBuf>,
    segmenter: String,
    threshold: Option<f32>,
    baseline: Option<String>,
    grasp: bool,
}

fn query(map_path: &Path, options: &QueryOptions, texts: &[String]) -> Result<()> {
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
    // The threshold segmenter always has one (0.75 unless given); the others only when asked.
    let threshold = match (options.segmenter.as_str(), options.threshold) {
        ("threshold", t) => Some(t.unwrap_or(0.75)),
        (_, t) => t,
    };
    if let Some(t) = threshold {
        params.insert("threshold".into(), toml::Value::Float(f64::from(t)));
    }
    if let Some(b) = &options.baseline {
        params.insert("baseline".into(), toml::Value::String(b.clone()));
    }
    let segmenter = registry.build_segmenter(
        &StageConfig {
            kind: options.segmenter.clone(),
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
    let (scores, sets) =
        answer_queries(&snapshot, encoder.as_ref(), segmenter.as_ref(), texts, None)?;
    let mut grasps = vec![None; texts.len()];
    if options.grasp {
        for (q, text) in texts.iter().enumerate() {
            // Sets of one query, best first by mean similarity: the paper grasps the best cluster.
            let best = sets
                .iter()
                .filter(|set| set.query == q && !set.indices.is_empty())
                .max_by(|a, b| a.mean_score.total_cmp(&b.mean_score));
            let Some(best) = best else {
                println!("\"{text}\": no grasp: no point set selected");
                continue;
            };
            let points: Vec<[f32; 3]> = best
                .indices
                .iter()
                .map(|&i| snapshot.positions[i])
                .collect();
            match vlem_maps::grasp::grasp_from_points(&points, &GraspParams::default()) {
                Ok(g) => {
                    let (p, c) = (g.position, g.closing);
                    println!(
                        "\"{text}\": grasp at ({:.3}, {:.3}, {:.3}), closing along ({:.3}, {:.3}, {:.3}), width {:.3} m, from a set of {} points",
                        p[0],
                        p[1],
                        p[2],
                        c[0],
                        c[1],
                        c[2],
                        g.width,
                        points.len()
                    );
                    grasps[q] = Some(g);
                }
                Err(e) => println!("\"{text}\": no grasp: {e}"),
            }
        }
    }
    if let Some(ply) = &options.ply {
        for (i, s) in scores.scores.iter().enumerate() {
            let path = if texts.len() == 1 {
                ply.clone()
            } else {
                let stem = ply
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                ply.with_file_name(format!("{stem}-{}.ply", slug(&texts[i])))
            };
            let marker = grasps[i]
                .as_ref()
                .map(output::gripper_vertices)
                .unwrap_or_default();
            output::write_atomically(&path, &output::heatmap_ply(&snapshot.positions, s, &marker))?;
            println!("wrote {}", path.display());
        }
    }
    Ok(())
}

/// Scores every point for every query, segments them, prints a line per query (and one per point
/// set for segmenters that make several), and (with `ply_dir`) writes one heatmap PLY per query
/// there.
fn answer_queries(
    snapshot: &MapSnapshot,
    encoder: &dyn Encoder,
    segmenter: &dyn vlem_core::Segmenter,
    texts: &[String],
    ply_dir: Option<&Path>,
) -> Result<(QueryScores, Vec<PointSet>)> {
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
        baseline: segmenter
            .baseline_query()
            .map(|b| {
                score(b).with_context(|| {
                    format!(
                        "the baseline of segmenter `{}` (set its `baseline` parameter; `vlem query --baseline TEXT`)",
                        segmenter.name()
                    )
                })
            })
            .transpose()?,
    };
    let sets = segmenter.segment(&snapshot.positions, &scores)?;
    for (q, text) in texts.iter().enumerate() {
        let s = &scores.scores[q];
        let best = (0..s.len()).max_by(|&a, &b| s[a].total_cmp(&s[b]));
        let mut own: Vec<&PointSet> = sets
            .iter()
            .filter(|set| set.query == q && !set.indices.is_empty())
            .collect();
        own.sort_by(|a, b| b.mean_score.total_cmp(&a.mean_score));
        let hits: usize = own.iter().map(|set| set.indices.len()).sum();
        match best {
            Some(i) => {
                let p = snapshot.positions[i];
                println!(
                    "\"{text}\": best {:.3} at ({:.2}, {:.2}, {:.2}); {hits} of {} points in {} point set{} selected by `{}`",
                    s[i],
                    p[0],
                    p[1],
                    p[2],
                    s.len(),
                    own.len(),
                    if own.len() == 1 { "" } else { "s" },
                    segmenter.name()
                );
            }
            None => println!("\"{text}\": the map is empty"),
        }
        // Several sets per query are clusters (objects): list the best few.
        if own.len() > 1 {
            const SHOWN: usize = 5;
            for (rank, set) in own.iter().take(SHOWN).enumerate() {
                let n = set.indices.len() as f64;
                let centre = set.indices.iter().fold([0.0f64; 3], |acc, &i| {
                    let p = snapshot.positions[i];
                    [
                        acc[0] + f64::from(p[0]) / n,
                        acc[1] + f64::from(p[1]) / n,
                        acc[2] + f64::from(p[2]) / n,
                    ]
                });
                println!(
                    "  cluster {}: {} points, mean similarity {:.3}, centre ({:.2}, {:.2}, {:.2})",
                    rank + 1,
                    set.indices.len(),
                    set.mean_score,
                    centre[0],
                    centre[1],
                    centre[2]
                );
            }
            if own.len() > SHOWN {
                println!(
                    "  … and {} more clusters with lower similarity",
                    own.len() - SHOWN
                );
            }
        }
        if let Some(dir) = ply_dir {
            let path = dir.join(format!("query-{}.ply", slug(text)));
            output::write_atomically(&path, &output::heatmap_ply(&snapshot.positions, s, &[]))?;
        }
    }
    Ok((scores, sets))
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
