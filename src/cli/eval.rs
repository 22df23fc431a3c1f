//! `vlem eval`: measure a run against a reference: `trajectory` (ATE and RPE), `semseg3d` (a map
//! against labelled ground truth, under the paper's or RayFronts' protocol) and `semseg2d` (an
//! encoder's pixel embeddings against label images).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use vlem_eval::report::{
    self, Semseg2dOptions, Semseg3dOptions, SemsegInput, SemsegReport, TrajectoryOptions,
    TrajectoryReport,
};
use vlem_eval::semseg::{self, ClassList};
use vlem_eval::trajectory::{AssociationMode, DEFAULT_MAX_TIME_DIFF, ErrorStats};

use crate::output;

/// The evaluations `vlem eval` runs.
#[derive(Subcommand)]
pub enum EvalCommand {
    /// Trajectory accuracy: ATE (after a least-squares alignment) and RPE of an estimate (e.g.
    /// OUT/trajectory.tum of `vlem run`) against a reference (TUM or .log).
    ///
    /// Poses are paired by timestamp (nearest within --max-time-diff, one to one) when both files
    /// are TUM; when either is a .log, which has no timestamps, its frames are stamped 0, 1, 2, …
    /// and a TUM pose stamped t pairs with frame round(t) (within --max-time-diff), which is how
    /// `vlem run` stamps frames of datasets without timestamps.
    Trajectory(TrajectoryArgs),
    /// 3D semantic segmentation of a map (OUT/map.vlem of `vlem run`) against the labelled
    /// ground truth of the config's dataset: every --stride-th frame's labelled pixels
    /// back-projected with its pose and merged per voxel.
    ///
    /// `--protocol vlem` (the paper): each ground-truth point takes the similarity of its nearest
    /// map point within --radius (none: predicted negative), and each class's IoU is averaged
    /// over the thresholds 0.00, 0.01, …, 1.00. `--protocol rayfronts`: softmax(100·cos) over
    /// the class prompts, prompt denoising (0.5), no label below 0.1, 5 cm voxels, k = 5 nearest
    /// predicted voxels vote; IoU, f-mIoU and accuracy. Class names are the text queries
    /// (--prompts replaces them); `other*` classes and classes absent from the ground truth are
    /// not averaged.
    Semseg3d(Semseg3dArgs),
    /// 2D semantic segmentation: the config's encoder on every --stride-th frame against its
    /// label image, the class names as queries, each class's IoU averaged over the thresholds
    /// 0.00, 0.01, …, 1.00 and accumulated over the frames (the paper's 2D tables).
    Semseg2d(Semseg2dArgs),
}

/// The 3D protocols.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Protocol {
    /// The paper's: nearest map point within 5 cm, IoU averaged over similarity thresholds.
    Vlem,
    /// RayFronts': argmax over class prompts, voxels, k-nearest-neighbour votes.
    Rayfronts,
}

/// The class lists.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Classes {
    /// NYU40 (37 classes evaluated: not the `other*` ones).
    Nyu40,
    /// The ScanNet benchmark's 20 (19 evaluated: not `otherfurniture`).
    Scannet20,
}

impl Protocol {
    fn library(self) -> report::Protocol {
        match self {
            Self::Vlem => report::Protocol::Vlem,
            Self::Rayfronts => report::Protocol::Rayfronts,
        }
    }
}

impl Classes {
    fn list(self) -> ClassList {
        match self {
            Self::Nyu40 => ClassList::Nyu40,
            Self::Scannet20 => ClassList::Scannet20,
        }
    }
}

/// Options both semantic segmentation evaluations share.
#[derive(Args)]
pub struct SemsegCommon {
    /// Pipeline configuration (TOML): its dataset is the ground truth, its encoder (or else the
    /// map's) embeds the class names.
    #[arg(long)]
    config: PathBuf,
    /// Dataset folder (overrides `[dataset] path`).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Use at most this many frames of the dataset (after its stride), as `vlem run`.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Class list.
    #[arg(long, value_enum, default_value = "nyu40")]
    classes: Classes,
    /// JSON object mapping class names to the texts to query instead (e.g. {"wall": "white"});
    /// classes not listed are queried by name.
    #[arg(long)]
    prompts: Option<PathBuf>,
    /// Write the results as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Options of `vlem eval semseg3d`.
#[derive(Args)]
pub struct Semseg3dArgs {
    /// Map file written by `vlem run`.
    #[arg(long)]
    map: PathBuf,
    #[command(flatten)]
    common: SemsegCommon,
    /// Evaluation protocol.
    #[arg(long, value_enum, default_value = "vlem")]
    protocol: Protocol,
    /// Build the ground truth from every n-th frame.
    #[arg(long, default_value_t = 1)]
    stride: usize,
    /// Ground-truth voxel size in metres (default 0.02 for `vlem`; for `rayfronts` also the
    /// prediction voxel size, default 0.05).
    #[arg(long)]
    voxel_size: Option<f64>,
    /// `vlem` protocol: association radius in metres.
    #[arg(long, default_value_t = semseg::vlem::DEFAULT_ASSOCIATION_RADIUS)]
    radius: f32,
    /// `rayfronts` protocol: predicted voxels voting per ground-truth voxel.
    #[arg(long, default_value_t = 5)]
    k: usize,
}

/// Options of `vlem eval semseg2d`.
#[derive(Args)]
pub struct Semseg2dArgs {
    #[command(flatten)]
    common: SemsegCommon,
    /// Evaluate every n-th frame.
    #[arg(long, default_value_t = 30)]
    stride: usize,
}

/// Options of `vlem eval trajectory`.
#[derive(Args)]
pub struct TrajectoryArgs {
    /// The estimated trajectory (TUM or .log).
    #[arg(long)]
    estimate: PathBuf,
    /// The reference ("ground truth") trajectory (TUM or .log), or a dataset folder, whose
    /// trajectory file is found as its reader finds it (trajectory.log or the folder's one .log,
    /// groundtruth.txt, traj.txt).
    #[arg(long)]
    reference: PathBuf,
    /// RPE frame step: pose pairs (k, k + delta) of the associated poses.
    #[arg(long, default_value_t = 1)]
    delta: usize,
    /// Largest time difference, in seconds, between paired poses (frames, against a .log).
    #[arg(long, default_value_t = DEFAULT_MAX_TIME_DIFF)]
    max_time_diff: f64,
    /// Align with a similarity transform (rotation, translation and scale) for estimates of
    /// unknown scale; RPE is then computed on the estimate scaled by the same factor.
    #[arg(long)]
    scale: bool,
    /// Also write every number as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Runs one `vlem eval` subcommand.
pub fn execute(command: EvalCommand) -> Result<()> {
    match command {
        EvalCommand::Trajectory(args) => evaluate_trajectory(&args),
        EvalCommand::Semseg3d(args) => evaluate_semseg3d(&args),
        EvalCommand::Semseg2d(args) => evaluate_semseg2d(&args),
    }
}

fn evaluate_trajectory(args: &TrajectoryArgs) -> Result<()> {
    let report = report::evaluate_trajectory(
        &args.estimate,
        &args.reference,
        &TrajectoryOptions {
            delta: args.delta,
            max_time_diff: args.max_time_diff,
            scale: args.scale,
        },
    )?;
    print_report(&report);
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report).context("cannot encode the report")?;
        output::write_atomically(path, format!("{text}\n").as_bytes())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn print_report(report: &TrajectoryReport) {
    let TrajectoryReport {
        estimate,
        reference,
        association,
        ate,
        rpe,
        ..
    } = report;
    println!(
        "estimate  {} ({}, {} poses)",
        estimate.path.display(),
        estimate.format.label(),
        estimate.poses
    );
    println!(
        "reference {} ({}, {} poses)",
        reference.path.display(),
        reference.format.label(),
        reference.poses
    );
    println!(
        "associated {} pose pairs {} (max difference {} {})",
        association.len(),
        association.mode.describe(),
        association.max_time_diff,
        match association.mode {
            AssociationMode::Timestamp => "s",
            AssociationMode::FrameIndex => "frames",
        }
    );
    let a = &ate.alignment;
    let t = a.translation;
    println!(
        "alignment ({}): rotation {:.4}°, translation ({:.4}, {:.4}, {:.4}) m, scale {:.6}",
        if ate.with_scale {
            "similarity"
        } else {
            "rigid"
        },
        a.rotation.angle().to_degrees(),
        t.x,
        t.y,
        t.z,
        a.scale
    );
    println!();
    println!(
        "{:<22} {:>6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "metric", "n", "rmse", "mean", "median", "std", "min", "max"
    );
    let d = rpe.delta;
    let rows = [
        ("ATE (m)".to_owned(), &ate.position),
        (format!("RPE trans (m/{d}f)"), &rpe.translation),
        (format!("RPE rot (deg/{d}f)"), &rpe.rotation),
    ];
    for (name, s) in rows {
        print_row(&name, s);
    }
}

fn print_row(name: &str, s: &ErrorStats) {
    println!(
        "{name:<22} {:>6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6}",
        s.count, s.rmse, s.mean, s.median, s.std, s.min, s.max
    );
}

/// The library's input for the command line's semseg options.
fn semseg_input(common: &SemsegCommon) -> Result<SemsegInput> {
    let mut input = SemsegInput::from_config_file(&common.config)?;
    input.dataset.clone_from(&common.dataset);
    input.max_frames = common.max_frames;
    input.classes = common.classes.list();
    if let Some(path) = &common.prompts {
        input.prompts = report::read_prompts(path)?;
    }
    Ok(input)
}

/// Prints the per-class table and the means.
fn print_scores(report: &SemsegReport) {
    let scores = &report.scores;
    println!("{}", report.title);
    println!("{:<16} {:>7} {:>10}", "class", "IoU", "support");
    for c in scores.classes.iter().filter(|c| c.iou.is_some()) {
        println!(
            "{:<16} {:>7.4} {:>10}",
            c.name,
            c.iou.unwrap_or(f64::NAN),
            c.support
        );
    }
    let absent = scores.classes.len() - scores.evaluated_classes();
    let fmt = |x: Option<f64>| x.map_or("n/a".to_owned(), |x| format!("{x:.4}"));
    println!(
        "mIoU {} over {} classes present in the ground truth ({absent} absent)",
        fmt(scores.miou),
        scores.evaluated_classes()
    );
    if scores.fmiou.is_some() || scores.accuracy.is_some() {
        println!(
            "f-mIoU {}, accuracy {}",
            fmt(scores.fmiou),
            fmt(scores.accuracy)
        );
    }
}

/// Prints the report and writes it where `--json` says.
fn finish(report: &SemsegReport, json: Option<&Path>) -> Result<()> {
    print_scores(report);
    if let Some(path) = json {
        let text = serde_json::to_string_pretty(report).context("cannot encode the report")?;
        output::write_atomically(path, format!("{text}\n").as_bytes())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn note(message: &str) {
    eprintln!("vlem: {message}");
}

fn evaluate_semseg3d(args: &Semseg3dArgs) -> Result<()> {
    let input = semseg_input(&args.common)?;
    let options = Semseg3dOptions {
        protocol: args.protocol.library(),
        stride: args.stride,
        voxel_size: args.voxel_size,
        radius: args.radius,
        k: args.k,
    };
    let report = report::semseg3d(&input, &args.map, &options, &note)?;
    finish(&report, args.common.json.as_deref())
}

fn evaluate_semseg2d(args: &Semseg2dArgs) -> Result<()> {
    let input = semseg_input(&args.common)?;
    let options = Semseg2dOptions {
        stride: args.stride,
    };
    let report = report::semseg2d(&input, &options, &note)?;
    finish(&report, args.common.json.as_deref())
}
