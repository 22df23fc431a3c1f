//! `vlem`: run the mapping pipeline on an RGB-D dataset, query saved maps, list plugins, run the demo.

mod eval;
mod output;
mod plugins;
#[cfg(feature = "rerun")]
mod recording;
#[cfg(not(feature = "rerun"))]
#[path = "recording_disabled.rs"]
mod recording;
mod soak;
mod study;
mod study_plot;
mod study_result;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::{
    BuildContext, Config, Encoder, MapMetadata, MapSnapshot, PointSet, QueryScores, Registry,
    StageConfig, StageKind,
};
use vlem_maps::grasp::{Grasp, GraspParams};

use recording::{Recorder, RecordingTarget, RunRecording};

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
        #[command(flatten)]
        rerun: RerunArgs,
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
        /// Read queries from standard input, one per line, on the loaded map and encoder (`:help`
        /// lists the commands); with --ply or --rerun, every query updates them.
        #[arg(long)]
        interactive: bool,
        #[command(flatten)]
        rerun: RerunArgs,
        /// Query texts.
        #[arg(required_unless_present = "interactive")]
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
        #[command(flatten)]
        rerun: RerunArgs,
    },
}

/// Rerun recording options (the recording needs a build with the `rerun` feature).
#[derive(Args, Clone, Default)]
struct RerunArgs {
    /// Record to this .rrd file (open it with the rerun viewer: `rerun FILE`).
    #[arg(long, value_name = "FILE.rrd", conflicts_with = "rerun_connect")]
    rerun: Option<PathBuf>,
    /// Stream to a running rerun viewer instead, e.g. rerun+http://127.0.0.1:9876/proxy.
    #[arg(long, value_name = "ADDR")]
    rerun_connect: Option<String>,
    /// During a run, log the map's points after every this many integrated frames.
    #[arg(long, default_value_t = 10, value_name = "N")]
    rerun_map_every: usize,
}

impl RerunArgs {
    /// The recording these options ask for, if any.
    fn open(&self) -> Result<Option<Recorder>> {
        let target = match (&self.rerun, &self.rerun_connect) {
            (Some(path), _) => RecordingTarget::File(path),
            (None, Some(address)) => RecordingTarget::Connect(address),
            (None, None) => return Ok(None),
        };
        Recorder::open(&target, self.rerun_map_every).map(Some)
    }
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
            rerun,
        } => {
            let parsed = read_config(&config)?;
            let options = RunOptions {
                dataset,
                max_frames,
                colour_model: !no_colour_model,
                rerun,
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
            interactive,
            rerun,
            text,
        } => query(
            &map,
            QueryOptions {
                ply,
                selection: Selection {
                    segmenter,
                    threshold,
                    baseline,
                },
                grasp,
                interactive,
                rerun,
            },
            &text,
        ),
        Command::Eval { command } => eval::execute(command),
        Command::Plugins => list_plugins(),
        Command::Soak(args) => soak::execute(&args),
        Command::Study(args) => study::execute(&args),
        Command::Demo { out, rerun } => {
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
                    rerun,
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
    /// Where to record the run, if anywhere.
    rerun: RerunArgs,
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
    // Before mapping, so an unwritable output folder or recording fails now rather than after a
    // long run.
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let recorder = options.rerun.open()?;
    let recording = recorder.as_ref().map(RunRecording::new);
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
    let observer: &dyn vlem_core::RunObserver = match &recording {
        Some(recording) => recording,
        None => &vlem_core::NoObserver,
    };
    let report = pipeline.run_observed(source.as_mut(), None, &on_progress, observer)?;
    bar.finish_and_clear();
    if let Some(failure) = recording.as_ref().and_then(RunRecording::failure) {
        eprintln!("warning: the rerun recording stopped early: {failure}");
    }

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
    if let (Some(recorder), Some(map)) = (&recorder, pipeline.map()) {
        recorder.log_map(&map.coloured_points(), report.frames_total)?;
    }
    if options.colour_model || recorder.is_some() {
        let written = if options.colour_model {
            Some(out)
        } else {
            None
        };
        export_colour_model(
            pipeline.tracker(),
            written,
            recorder.as_ref(),
            report.frames_total,
        )?;
    }

    if let (Some(snap), Some(encoder)) = (&snapshot, pipeline.encoder())
        && !config.query.texts.is_empty()
    {
        let answers = answer_queries(
            snap,
            encoder,
            segmenter.as_ref(),
            &config.query.texts,
            Some(out),
        )?;
        if let Some(recorder) = &recorder {
            record_queries(recorder, snap, &config.query.texts, &answers, &[])?;
        }
    }
    if let Some(recorder) = &recorder {
        recorder.flush()?;
        if let Some(path) = &options.rerun.rerun {
            println!(
                "recording: {} (open it with `rerun {}`)",
                path.display(),
                path.display()
            );
        }
    }
    Ok(())
}

/// Writes OUT/colour-model.ply (with `out`) and records the mesh (with `recorder`) when the
/// tracker keeps a dense colour model.
fn export_colour_model(
    tracker: &dyn vlem_core::Tracker,
    out: Option<&Path>,
    recorder: Option<&Recorder>,
    frames: usize,
) -> Result<()> {
    let mesh = match tracker.colour_model() {
        Ok(mesh) => mesh,
        Err(vlem_core::CoreError::Unsupported { .. }) => return Ok(()),
        Err(e) => return Err(e.into()),
    };
    if let Some(out) = out {
        let path = out.join("colour-model.ply");
        output::write_atomically(&path, &output::mesh_ply(&mesh))?;
        println!(
            "dense colour model: {} ({} vertices, {} triangles)",
            path.display(),
            mesh.vertices.len(),
            mesh.triangles.len()
        );
    }
    if let Some(recorder) = recorder {
        recorder.log_colour_model(&mesh, frames)?;
    }
    Ok(())
}

/// Logs each query's heatmap, point sets and grasp (`grasps` is empty when none were asked for)
/// to `recorder`.
fn record_queries(
    recorder: &Recorder,
    snapshot: &MapSnapshot,
    texts: &[String],
    (scores, sets): &(QueryScores, Vec<PointSet>),
    grasps: &[Option<Grasp>],
) -> Result<()> {
    for (q, text) in texts.iter().enumerate() {
        let own: Vec<&PointSet> = sets
            .iter()
            .filter(|set| set.query == q && !set.indices.is_empty())
            .collect();
        let Some(s) = scores.scores.get(q) else {
            continue;
        };
        // No grasps at all: none were asked for.
        let grasp = if grasps.is_empty() {
            None
        } else {
            Some(grasps.get(q).and_then(Option::as_ref))
        };
        recorder.log_query(text, &snapshot.positions, s, &own, grasp)?;
    }
    recorder.flush()
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
    selection: Selection,
    grasp: bool,
    interactive: bool,
    rerun: RerunArgs,
}

fn query(map_path: &Path, options: QueryOptions, texts: &[String]) -> Result<()> {
    let mut session = QuerySession::open(map_path, options)?;
    if !texts.is_empty() {
        session.ask(texts)?;
    }
    if session.options.interactive {
        session.interact()?;
    }
    Ok(())
}

/// A loaded map with its text encoder and segmenter: answers queries without reloading either.
struct QuerySession {
    snapshot: MapSnapshot,
    encoder: Box<dyn Encoder>,
    segmenter: Box<dyn vlem_core::Segmenter>,
    ctx: BuildContext,
    options: QueryOptions,
    recorder: Option<Recorder>,
}

impl QuerySession {
    fn open(map_path: &Path, options: QueryOptions) -> Result<Self> {
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
        let encoder = Registry::global()?.build_encoder(&stage, &ctx)?;
        let segmenter = build_query_segmenter(&options.selection, &ctx)?;
        let recorder = options.rerun.open()?;
        if let Some(recorder) = &recorder {
            recorder.log_static_map(&snapshot.positions, &snapshot.colours)?;
        }
        println!(
            "{}: {} points, {}-d embeddings from `{}`",
            map_path.display(),
            snapshot.len(),
            snapshot.dim,
            stage.kind
        );
        Ok(Self {
            snapshot,
            encoder,
            segmenter,
            ctx,
            options,
            recorder,
        })
    }

    /// Answers `texts`: the summary lines, grasps, PLY heatmaps and the recording.
    fn ask(&self, texts: &[String]) -> Result<()> {
        let snapshot = &self.snapshot;
        let answers = answer_queries(
            snapshot,
            self.encoder.as_ref(),
            self.segmenter.as_ref(),
            texts,
            None,
        )?;
        let (scores, sets) = &answers;
        // Empty unless asked for, so a recording can tell "not asked" from "none found".
        let grasps: Vec<Option<Grasp>> = if self.options.grasp {
            texts
                .iter()
                .enumerate()
                .map(|(q, text)| grasp_query(snapshot, sets, q, text))
                .collect()
        } else {
            Vec::new()
        };
        if let Some(ply) = &self.options.ply {
            for (i, s) in scores.scores.iter().enumerate() {
                // One query on the command line writes FILE itself; several, or a session of
                // queries, write one file per query beside it.
                let path = if texts.len() == 1 && !self.options.interactive {
                    ply.clone()
                } else {
                    let stem = ply
                        .file_stem()
                        .map(|s| s.to_string_lossy().into_owned())
                        .unwrap_or_default();
                    ply.with_file_name(format!("{stem}-{}.ply", slug(&texts[i])))
                };
                let marker = grasps
                    .get(i)
                    .and_then(Option::as_ref)
                    .map(output::gripper_vertices)
                    .unwrap_or_default();
                output::write_atomically(
                    &path,
                    &output::heatmap_ply(&snapshot.positions, s, &marker),
                )?;
                println!("wrote {}", path.display());
            }
        }
        if let Some(recorder) = &self.recorder {
            record_queries(recorder, snapshot, texts, &answers, &grasps)?;
        }
        Ok(())
    }

    /// The read-eval loop of `--interactive`: one query per line until `:quit` or end of input.
    fn interact(&mut self) -> Result<()> {
        use std::io::{BufRead, IsTerminal, Write};
        let stdin = std::io::stdin();
        let prompt = stdin.is_terminal();
        println!("type a query, or :help");
        let mut lines = stdin.lock().lines();
        loop {
            if prompt {
                print!("vlem> ");
                std::io::stdout().flush()?;
            }
            let Some(line) = lines.next().transpose()? else {
                break;
            };
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let outcome = match line.strip_prefix(':') {
                Some(command) => match self.command(command) {
                    Ok(Continue::Stop) => break,
                    other => other.map(|_| ()),
                },
                None => self.ask(&[line.to_owned()]),
            };
            // A failed query (an unknown word, a bad threshold) does not end the session.
            if let Err(e) = outcome {
                println!("error: {}", one_line(&e));
            }
            std::io::stdout().flush()?;
        }
        Ok(())
    }

    fn command(&mut self, command: &str) -> Result<Continue> {
        let mut words = command.split_whitespace();
        let name = words.next().unwrap_or_default();
        let argument = words.collect::<Vec<_>>().join(" ");
        match name {
            "q" | "quit" | "exit" => return Ok(Continue::Stop),
            "help" | "h" => println!("{INTERACTIVE_HELP}"),
            "threshold" => {
                let value: f32 = argument
                    .parse()
                    .with_context(|| format!(":threshold needs a number, got \"{argument}\""))?;
                self.reconfigure(|s| s.threshold = Some(value))?;
                println!("threshold {value}");
            }
            "segmenter" => {
                self.reconfigure(|s| s.segmenter = argument.clone())?;
                println!("segmenter `{}`", self.segmenter.name());
            }
            "baseline" => {
                self.reconfigure(|s| s.baseline = Some(argument.clone()))?;
                println!("baseline \"{argument}\"");
            }
            "grasp" => {
                self.options.grasp = match argument.as_str() {
                    "on" => true,
                    "off" => false,
                    _ => bail!(":grasp takes on or off"),
                };
                println!("grasp {argument}");
            }
            _ => bail!("unknown command :{name} (:help lists them)"),
        }
        Ok(Continue::Go)
    }

    /// Changes how points are selected and rebuilds the segmenter; on failure nothing changes.
    fn reconfigure(&mut self, change: impl FnOnce(&mut Selection)) -> Result<()> {
        let mut selection = self.options.selection.clone();
        change(&mut selection);
        self.segmenter = build_query_segmenter(&selection, &self.ctx)?;
        self.options.selection = selection;
        Ok(())
    }
}

/// What the interactive loop does after a command.
enum Continue {
    Go,
    Stop,
}

const INTERACTIVE_HELP: &str = "\
a line of text      query the map with it (summary, and --ply / --rerun output)
:threshold X        select points with normalised similarity >= X
:segmenter NAME     threshold, argmax or cluster (as --segmenter)
:baseline TEXT      the generic text argmax and cluster compare against
:grasp on|off       compute a grasp for each query's best point set
:quit               leave (so does end of input)";

/// How `vlem query` selects points: the segmenter and its two tunable parameters.
#[derive(Clone)]
struct Selection {
    segmenter: String,
    threshold: Option<f32>,
    baseline: Option<String>,
}

fn build_query_segmenter(
    selection: &Selection,
    ctx: &BuildContext,
) -> Result<Box<dyn vlem_core::Segmenter>> {
    let mut params = toml::Table::new();
    // The threshold segmenter always has one (0.75 unless given); the others only when asked.
    let threshold = match (selection.segmenter.as_str(), selection.threshold) {
        ("threshold", t) => Some(t.unwrap_or(0.75)),
        (_, t) => t,
    };
    if let Some(t) = threshold {
        params.insert("threshold".into(), toml::Value::Float(f64::from(t)));
    }
    if let Some(b) = &selection.baseline {
        params.insert("baseline".into(), toml::Value::String(b.clone()));
    }
    Ok(Registry::global()?.build_segmenter(
        &StageConfig {
            kind: selection.segmenter.clone(),
            params,
        },
        ctx,
    )?)
}

/// The grasp on query `q`'s best point set (the paper grasps the best cluster), printing a line
/// either way.
fn grasp_query(snapshot: &MapSnapshot, sets: &[PointSet], q: usize, text: &str) -> Option<Grasp> {
    let best = sets
        .iter()
        .filter(|set| set.query == q && !set.indices.is_empty())
        .max_by(|a, b| a.mean_score.total_cmp(&b.mean_score));
    let Some(best) = best else {
        println!("\"{text}\": no grasp: no point set selected");
        return None;
    };
    let points: Vec<[f32; 3]> = best
        .indices
        .iter()
        .filter_map(|&i| snapshot.positions.get(i).copied())
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
            Some(g)
        }
        Err(e) => {
            println!("\"{text}\": no grasp: {e}");
            None
        }
    }
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
