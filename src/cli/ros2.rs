//! `vlem ros2`: the live ROS 2 node (feature `ros2`), a thin front-end over `vlem_ros2::run_node`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

/// `vlem ros2` arguments.
#[derive(Args)]
pub struct Ros2Args {
    /// Config file: the pipeline's stages, and the topics and frames of `[ros2]`.
    #[arg(long)]
    pub config: PathBuf,
    /// Save the map to this file when the node stops.
    #[arg(long, value_name = "FILE.vlem")]
    pub save_map: Option<PathBuf>,
    /// Write the node's counters and the run's summary as JSON to this file when it stops.
    #[arg(long, value_name = "FILE.json")]
    pub status_json: Option<PathBuf>,
    /// Stop after this many seconds; default: run until Ctrl-C (SIGINT) or SIGTERM.
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
}

/// Runs the node until Ctrl-C (or `--duration`), then saves what was asked for.
///
/// # Errors
/// A config that cannot be loaded or built, settings the node refuses, DDS that cannot start,
/// and a pipeline that stops on an error; without the `ros2` feature, always (naming the feature).
#[cfg(feature = "ros2")]
pub fn execute(args: &Ros2Args) -> Result<()> {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    use anyhow::Context as _;
    use vlem_core::Registry;
    use vlem_core::pipeline::Pipeline;

    let (config, ctx) = vlem_core::load_config(&args.config)?;
    let located = |e| config.locate(e);
    let pipeline = Pipeline::from_config(&config, &ctx)?;
    let segmenter = Registry::global()?
        .build_segmenter(&config.query.segmenter, &ctx)
        .map_err(located)?;
    let settings = vlem_ros2::Ros2Config::from_table(config.ros2.as_ref()).map_err(located)?;
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || stop.store(true, Ordering::Relaxed))
            .context("cannot install the Ctrl-C handler")?;
    }
    if let Some(seconds) = args.duration {
        anyhow::ensure!(
            seconds.is_finite() && seconds > 0.0,
            "--duration must be a positive number of seconds, got {seconds}"
        );
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_secs_f64(seconds));
            stop.store(true, Ordering::Relaxed);
        });
    }
    let report = vlem_ros2::run_node(pipeline, segmenter, &settings, &stop)?;
    let status = &report.status;
    eprintln!(
        "vlem ros2: stopped; {} colour and {} depth images, {} frames mapped of {} queued ({} \
         dropped while tracking was busy, {} refused, {} unpaired images, {} bad messages), {} \
         queries",
        status.colour_images,
        status.depth_images,
        report.run.as_ref().map_or(0, |r| r.frames_processed),
        status.frames_queued,
        status.dropped_busy,
        status.refused,
        status.unpaired_images,
        status.bad_messages,
        status.queries
    );
    if let Some(path) = &args.save_map {
        report
            .pipeline
            .live()
            .save(path)
            .with_context(|| format!("cannot save the map to {}", path.display()))?;
        eprintln!("vlem ros2: map saved to {}", path.display());
    }
    if let Some(path) = &args.status_json {
        let json = serde_json::json!({
            "status": status,
            "run": report.run,
            "error": report.error.as_ref().map(|e| vlem_core::message_chain(e)),
            "map_points": report.pipeline.live().status().map_len,
        });
        crate::output::write_atomically(path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    }
    // After saving: the map up to a pipeline error is not lost with it.
    if let Some(e) = report.error {
        return Err(e.into());
    }
    Ok(())
}

/// Without the `ros2` feature: an error that says how to build the node.
#[cfg(not(feature = "ros2"))]
pub fn execute(_args: &Ros2Args) -> Result<()> {
    anyhow::bail!(
        "`vlem ros2` needs vlem built with the `ros2` feature: cargo build --release --features ros2"
    )
}
