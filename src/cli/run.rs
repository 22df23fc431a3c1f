//! `vlem run` and `vlem demo`: map a dataset, write the run's outputs, optionally serve the live
//! map over HTTP while mapping (`--serve`).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::{BuildContext, Config, EmbeddingMap, Registry};
use vlem_query::answer::{AnswerOptions, answer_snapshot, slug};
use vlem_query::heatmap::heatmap_ply;
use vlem_server::{QueryServer, RequestLimits, ServeOptions};

use super::RerunArgs;
use crate::output;
use crate::recording::{Recorder, RunRecording};

/// The embedded default configuration that `vlem demo` runs.
const DEMO_CONFIG: &str = include_str!("../../configs/demo.toml");
/// Where the demo config's relative paths point (the repository's `configs/`).
const DEMO_CONFIG_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs");

/// `vlem run`.
#[derive(Args)]
pub struct RunArgs {
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
    serve: ServeArgs,
    #[command(flatten)]
    rerun: RerunArgs,
}

/// `vlem demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    #[command(flatten)]
    serve: ServeArgs,
    #[command(flatten)]
    rerun: RerunArgs,
}

/// The query server's flags.
#[derive(Args, Clone)]
struct ServeArgs {
    /// Serve the live map over HTTP/JSON while mapping, on a loopback address such as
    /// 127.0.0.1:8765 (GET /status, POST /query, GET /heatmap.ply, POST /snapshot, GET /map.vlem;
    /// see docs/server.md). `vlem query --connect ADDR` is its client.
    #[arg(long, value_name = "127.0.0.1:PORT")]
    serve: Option<String>,
    /// Keep serving after the run has finished and written its outputs, until interrupted.
    #[arg(long, requires = "serve")]
    serve_after: bool,
    /// Require `Authorization: Bearer TOKEN` on every request (at least 16 printable
    /// characters), for reaching the port through a tunnel; prefer the environment variable,
    /// which other users cannot read from the process list.
    #[arg(
        long,
        env = "VLEM_SERVE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    serve_token: Option<String>,
    /// Most texts one `POST /query` may ask (413 above it).
    #[arg(long, value_name = "N", default_value_t = RequestLimits::DEFAULT_MAX_TEXTS, requires = "serve")]
    serve_max_texts: usize,
    /// Most bytes of one query text (413 above it).
    #[arg(long, value_name = "BYTES", default_value_t = RequestLimits::DEFAULT_MAX_TEXT_BYTES, requires = "serve")]
    serve_max_text_bytes: usize,
}

/// Command-line choices of `vlem run` beyond the config.
struct RunOptions<'a> {
    dataset: Option<&'a Path>,
    max_frames: Option<usize>,
    colour_model: bool,
    serve: &'a ServeArgs,
    rerun: &'a RerunArgs,
}

/// `vlem run`.
///
/// # Errors
/// Anything that stops the run: the config, the dataset, a stage, the outputs.
pub fn execute(args: &RunArgs) -> Result<()> {
    let (config, ctx) = vlem_core::load_config(&args.config)?;
    run(
        config,
        ctx,
        &args.out,
        &RunOptions {
            dataset: args.dataset.as_deref(),
            max_frames: args.max_frames,
            colour_model: !args.no_colour_model,
            serve: &args.serve,
            rerun: &args.rerun,
        },
    )
}

/// `vlem demo`: the embedded config on the committed frames.
///
/// # Errors
/// As [`execute`].
pub fn demo(args: &DemoArgs) -> Result<()> {
    let config = Config::from_toml(DEMO_CONFIG).context("the embedded demo config")?;
    let ctx = BuildContext::for_config_dir(Path::new(DEMO_CONFIG_DIR))?;
    run(
        config,
        ctx,
        &args.out,
        &RunOptions {
            dataset: None,
            max_frames: None,
            colour_model: true,
            serve: &args.serve,
            rerun: &args.rerun,
        },
    )
}

fn run(mut config: Config, ctx: BuildContext, out: &Path, options: &RunOptions<'_>) -> Result<()> {
    let dataset_dir = vlem_datasets::dataset_folder(&config, &ctx, options.dataset)?;
    if options.max_frames.is_some() {
        config.dataset.max_frames = options.max_frames;
    }
    // A key a stage's owner parses is found again on its line of the file.
    let located = |e| config.locate(e);
    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    // Built before mapping so a bad [query.segmenter] fails at start-up, not after the run.
    let segmenter = Registry::global()?
        .build_segmenter(&config.query.segmenter, &ctx)
        .map_err(located)?;
    // The run's own queries (and the segmenter's baseline) are embedded now, so a text the
    // encoder cannot embed fails at start-up, not after an hour of mapping; the encoders keep
    // the embeddings for the queries after the run.
    if let Some(encoder) = pipeline.encoder()
        && pipeline.live().has_map()
        && !config.query.texts.is_empty()
    {
        vlem_query::answer::embed_texts(encoder, segmenter.as_ref(), &config.query.texts)
            .context("[query] texts are answered after the run")?;
    }
    let mut source = vlem_datasets::open(&config.dataset, &dataset_dir).map_err(located)?;
    // Before mapping, so an unwritable output folder, recording or port fails now rather than
    // after a long run; a start that fails leaves no empty output folder behind.
    let created = !out.exists();
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let live = pipeline.live();
    let started = (|| -> Result<_> {
        let recorder = options.rerun.open()?;
        let server = options
            .serve
            .serve
            .as_deref()
            .map(|address| {
                QueryServer::start(
                    address,
                    live.clone(),
                    ServeOptions {
                        token: options.serve.serve_token.clone(),
                        limits: RequestLimits {
                            max_texts: options.serve.serve_max_texts,
                            max_text_bytes: options.serve.serve_max_text_bytes,
                        },
                        ..ServeOptions::new(out.to_path_buf(), ctx.clone())
                    },
                )
            })
            .transpose()?;
        Ok((recorder, server))
    })();
    let (recorder, server) = match started {
        Ok(started) => started,
        Err(e) => {
            if created {
                // Only an empty folder goes: remove_dir refuses anything else.
                let _ = std::fs::remove_dir(out);
            }
            return Err(e);
        }
    };
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
    for warning in pipeline.warnings().iter().cloned().chain(source.warnings()) {
        eprintln!("warning: {warning}");
    }
    if let Some(server) = &server {
        eprintln!(
            "vlem: serving the live map on http://{} (GET /status, POST /query, GET /heatmap.ply, \
             POST /snapshot, GET /map.vlem)",
            server.address()
        );
    }

    // `/status` says `saving` until the outputs below are written, then `finished`, so a client
    // that waits for `finished` finds map.vlem and the rest complete.
    live.announce_outputs();
    super::interrupt::install(pipeline.stop_handle())?;
    let device_memory = vlem_backends::DeviceMemoryPeak::start(&configured_devices(&config));
    let report = match track_and_map(&mut pipeline, source.as_mut(), recording.as_ref()) {
        Ok(report) => report,
        Err(e) => return Err(save_after_failure(&pipeline, out, e)),
    };
    if let Some(failure) = recording.as_ref().and_then(RunRecording::failure) {
        eprintln!("warning: the rerun recording stopped early: {failure}");
    }
    let peak_device_bytes = device_memory.map(vlem_backends::DeviceMemoryPeak::finish);
    write_outputs(&config, &pipeline, &report, out, peak_device_bytes)?;
    if report.stopped {
        live.outputs_written();
        super::interrupt::note_run_cut_short();
        // Interrupted: the outputs are written; the user asked to end, so no queries and no
        // colour model, and no serving after.
        eprintln!(
            "vlem: stopped after {} of {} frames; the map, trajectory and stats so far are in {}",
            report.frames_tracked,
            report.frames_total,
            out.display()
        );
        if let Some(server) = server {
            server.shutdown();
        }
        return Ok(());
    }
    if let (Some(recorder), Some(map)) = (&recorder, pipeline.map()) {
        recorder.log_map(&map.coloured_points(), report.frames_total)?;
    }
    if options.colour_model || recorder.is_some() {
        let written = options.colour_model.then_some(out);
        export_colour_model(
            pipeline.tracker(),
            written,
            recorder.as_ref(),
            report.frames_total,
        )?;
    }

    if let Some(encoder) = pipeline.encoder()
        && live.has_map()
        && !config.query.texts.is_empty()
    {
        let snapshot = live.snapshot()?;
        let answered = answer_snapshot(
            &snapshot,
            encoder,
            segmenter.as_ref(),
            &config.query.texts,
            &AnswerOptions::default(),
        )?;
        for line in answered.answer.lines() {
            println!("{line}");
        }
        for (text, scores) in config.query.texts.iter().zip(&answered.scores.scores) {
            let path = out.join(format!("query-{}.ply", slug(text)));
            output::write_atomically(&path, &heatmap_ply(&snapshot.positions, scores, &[]))?;
        }
        if let Some(recorder) = &recorder {
            super::query::record_answers(recorder, &snapshot.positions, &answered)?;
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
    live.outputs_written();
    if let Some(server) = server {
        if options.serve.serve_after {
            eprintln!(
                "vlem: the run has finished; still serving on http://{} until interrupted (Ctrl-C)",
                server.address()
            );
            super::interrupt::wait();
            server.shutdown();
        } else {
            server.shutdown();
        }
    }
    Ok(())
}

/// Runs the pipeline with a progress bar (on a terminal).
fn track_and_map(
    pipeline: &mut Pipeline,
    source: &mut dyn vlem_core::FrameSource,
    recording: Option<&RunRecording<'_>>,
) -> Result<RunReport> {
    let bar = ProgressBar::new(source.len() as u64);
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
    let observer: &dyn vlem_core::RunObserver = match recording {
        Some(recording) => recording,
        None => &vlem_core::NoObserver,
    };
    let report = pipeline.run_observed(source, None, &on_progress, observer)?;
    bar.finish_and_clear();
    Ok(report)
}

/// After a failed run: the map so far saved as OUT/map.vlem (nothing integrated is lost), said on
/// stderr before the error itself, which is returned unchanged.
fn save_after_failure(pipeline: &Pipeline, out: &Path, error: anyhow::Error) -> anyhow::Error {
    let live = pipeline.live();
    let frames = live.status().frames_integrated;
    if !live.has_map() || frames == 0 {
        return error;
    }
    let path = out.join("map.vlem");
    match vlem_eval::run_folder::clear_earlier_outputs(out)
        .map_err(anyhow::Error::from)
        .and_then(|()| Ok(live.save(&path)?))
    {
        Ok(saved) => eprintln!(
            "vlem: the run failed after {frames} integrated frames; the map so far ({} points) is \
             saved in {}",
            saved.points,
            path.display()
        ),
        Err(e) => eprintln!(
            "vlem: the run failed, and saving the map so far failed too: {}",
            super::one_line(&e)
        ),
    }
    error
}

/// The devices the config's stages name in their `device` keys (the GPUs whose memory the run's
/// peak device memory samples).
fn configured_devices(config: &Config) -> Vec<vlem_backends::ComputeDevice> {
    [
        Some(&config.tracker),
        config.proposer.as_ref(),
        config.encoder.as_ref(),
        config.map.as_ref(),
    ]
    .into_iter()
    .flatten()
    .filter_map(|stage| stage.params.get("device")?.as_str()?.parse().ok())
    .collect()
}

/// OUT/trajectory.tum, OUT/reference.tum (when the tracker estimated poses on a dataset that has
/// them), OUT/map.vlem and OUT/stats.json (last), and the summary lines.
fn write_outputs(
    config: &Config,
    pipeline: &Pipeline,
    report: &RunReport,
    out: &Path,
    peak_device_bytes: Option<u64>,
) -> Result<()> {
    vlem_eval::run_folder::write_run(
        out,
        pipeline,
        report,
        config.pipeline.mode,
        peak_device_bytes,
    )?;
    let map = pipeline.map();
    print_summary(report, map.as_deref(), out);
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

/// Which embedding stage set the rate: each stage's busy share of the run and the busiest one.
fn stage_load_line(report: &RunReport) -> Option<String> {
    let wall_ms = report.wall_seconds * 1e3;
    if report.stage_load.is_empty() || wall_ms <= 0.0 || report.frames_processed == 0 {
        return None;
    }
    // Pipeline order, not the map's alphabetical one.
    let order = ["propose", "encode", "integrate"];
    let mut loads: Vec<_> = report.stage_load.iter().collect();
    loads.sort_by_key(|(name, _)| order.iter().position(|o| o == *name));
    let shares: Vec<String> = loads
        .iter()
        .map(|(name, load)| format!("{name} {:.0}%", 100.0 * load.busy.total_ms() / wall_ms))
        .collect();
    let busiest = loads
        .iter()
        .max_by(|a, b| a.1.busy.total_ms().total_cmp(&b.1.busy.total_ms()))
        .map(|(name, _)| **name)?;
    Some(format!(
        "embedding stages ({}): busy {}; {:.2} frames/s embedded, set by `{busiest}`",
        match report.stages {
            vlem_core::config::StageLayout::Overlapped => "overlapped",
            vlem_core::config::StageLayout::Serial => "serial",
        },
        shares.join(", "),
        report.frames_processed as f64 / report.wall_seconds
    ))
}

fn print_summary(report: &RunReport, map: Option<&dyn EmbeddingMap>, out: &Path) {
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
    if let Some(line) = stage_load_line(report) {
        println!("{line}");
    }
    if let Some(map) = map {
        let device = match map.device_memory_bytes() {
            0 => String::new(),
            bytes => format!(" (+{:.1} MB on the device)", bytes as f64 / 1e6),
        };
        println!(
            "map `{}`: {} points, {}-d embeddings, {:.1} MB{device}",
            map.name(),
            map.len(),
            map.dim(),
            map.memory_bytes() as f64 / 1e6
        );
    }
    println!("wrote {}", out.display());
}
