//! `vlem eval`: measure a run against a reference. Only `trajectory` (ATE and RPE) so far; the
//! semantic segmentation protocols will be further subcommands of [`EvalCommand`].

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use vlem_eval::trajectory::{
    self, Association, AssociationMode, AteStats, DEFAULT_MAX_TIME_DIFF, ErrorStats, RpeStats,
    Trajectory,
};

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
}

/// Options of `vlem eval trajectory`.
#[derive(Args)]
pub struct TrajectoryArgs {
    /// The estimated trajectory (TUM or .log).
    #[arg(long)]
    estimate: PathBuf,
    /// The reference ("ground truth") trajectory (TUM or .log).
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
    }
}

/// A trajectory file as the JSON report names it.
#[derive(serde::Serialize)]
struct FileReport<'a> {
    path: &'a Path,
    format: trajectory::TrajectoryFormat,
    poses: usize,
}

impl<'a> FileReport<'a> {
    fn new(t: &'a Trajectory) -> Self {
        Self {
            path: &t.path,
            format: t.format,
            poses: t.len(),
        }
    }
}

/// Everything `vlem eval trajectory --json` writes.
#[derive(serde::Serialize)]
struct TrajectoryReport<'a> {
    estimate: FileReport<'a>,
    reference: FileReport<'a>,
    association: &'a Association,
    /// Number of associated pose pairs.
    associated: usize,
    ate: &'a AteStats,
    rpe: &'a RpeStats,
}

fn evaluate_trajectory(args: &TrajectoryArgs) -> Result<()> {
    let estimate = trajectory::read_trajectory(&args.estimate, "estimate")?;
    let reference = trajectory::read_trajectory(&args.reference, "reference")?;
    let association = trajectory::associate(&estimate, &reference, args.max_time_diff)?;
    let (estimated, true_poses) = association.poses(&estimate, &reference);
    let ate = trajectory::ate(&estimated, &true_poses, args.scale)?;
    // RPE has no alignment; with --scale the estimate's distances get the fitted scale first.
    let scaled: Vec<vlem_core::Pose> = estimated
        .iter()
        .map(|p| {
            let mut p = *p;
            p.translation.vector *= ate.alignment.scale;
            p
        })
        .collect();
    let rpe = trajectory::rpe(&scaled, &true_poses, args.delta)?;

    print_report(&estimate, &reference, &association, &ate, &rpe);
    if let Some(path) = &args.json {
        let report = TrajectoryReport {
            estimate: FileReport::new(&estimate),
            reference: FileReport::new(&reference),
            association: &association,
            associated: association.len(),
            ate: &ate,
            rpe: &rpe,
        };
        let text = serde_json::to_string_pretty(&report).context("cannot encode the report")?;
        output::write_atomically(path, format!("{text}\n").as_bytes())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn print_report(
    estimate: &Trajectory,
    reference: &Trajectory,
    association: &Association,
    ate: &AteStats,
    rpe: &RpeStats,
) {
    println!(
        "estimate  {} ({}, {} poses)",
        estimate.path.display(),
        estimate.format.label(),
        estimate.len()
    );
    println!(
        "reference {} ({}, {} poses)",
        reference.path.display(),
        reference.format.label(),
        reference.len()
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
