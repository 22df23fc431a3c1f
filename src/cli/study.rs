//! `vlem study`: a comparison study of map representations, encoders, trackers and sequences
//! (`vlem_eval::study` runs it; this is its command line, progress bar and plot).
//!
//! Each cell runs as a child process of this binary, `vlem study-cell DIR`, which maps and
//! evaluates the cell in-process. After running, every result found in `OUT` is gathered into
//! `OUT/study.csv` and `OUT/study.svg` / `OUT/study.png` (mIoU against peak memory, the paper's
//! Fig. 4).

use std::path::PathBuf;
use std::process::Command as Process;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use vlem_eval::study::{self, RunSelection, Shard, Study, StudyEvent};

/// Arguments of `vlem study`.
#[derive(clap::Args, Debug)]
pub struct StudyArgs {
    /// The study file (TOML; see docs/evaluation.md, "Comparison studies").
    pub study: PathBuf,
    /// Output folder: one sub-folder per cell, `study.csv`, `study.svg`, `study.png`.
    #[arg(long, default_value = "out/study")]
    pub out: PathBuf,
    /// Run only this slice of the cells, `i/n` with 1 ≤ i ≤ n (e.g. a Slurm array job:
    /// `--shard $((SLURM_ARRAY_TASK_ID + 1))/$SLURM_ARRAY_TASK_COUNT`).
    #[arg(long)]
    pub shard: Option<Shard>,
    /// Run no cell: gather the results already in OUT into the CSV and the plot.
    #[arg(long)]
    pub report: bool,
    /// Run cells again even if OUT already holds their results.
    #[arg(long)]
    pub force: bool,
    /// Print the cells (with their index) and exit.
    #[arg(long)]
    pub list: bool,
}

/// Arguments of `vlem study-cell` (run by `vlem study`, one process per cell).
#[derive(clap::Args, Debug)]
pub struct StudyCellArgs {
    /// The cell folder `vlem study` prepared.
    pub dir: PathBuf,
}

/// Runs `vlem study`.
pub fn execute(args: &StudyArgs) -> Result<()> {
    let study = Study::read(&args.study)?;
    if args.list {
        for cell in &study.cells {
            println!("{:>4}  {}", cell.index, cell.label());
        }
        return Ok(());
    }
    let mut failed = 0usize;
    if !args.report {
        let exe = std::env::current_exe().context("cannot find the vlem executable")?;
        let launch = |dir: &std::path::Path| {
            let mut command = Process::new(&exe);
            command.arg("study-cell").arg(dir);
            command
        };
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template("{bar:30} {pos}/{len} cells, {elapsed} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let mut on_event = |event: StudyEvent<'_>| match event {
            StudyEvent::Planned { total } => bar.set_length(total as u64),
            StudyEvent::Started { cell } => bar.set_message(cell.label()),
            StudyEvent::Finished { cell, result } => {
                if result.status != "ok" {
                    failed += 1;
                    // Printed past the bar, which hides its own output when stderr is no terminal.
                    bar.suspend(|| {
                        eprintln!(
                            "cell {} ({}) failed: {}",
                            cell.index,
                            cell.label(),
                            result.error
                        );
                    });
                }
                bar.inc(1);
            }
        };
        let selection = RunSelection {
            shard: args.shard,
            force: args.force,
        };
        study.run(&args.out, selection, &launch, &mut on_event)?;
        bar.finish_and_clear();
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let results = study.gather(&args.out);
    let csv = args.out.join("study.csv");
    study::write_csv(&csv, &results)?;
    let plotted = super::study_plot::write_plots(&args.out, &results)?;
    println!(
        "{} of {} cells have results: {}{}",
        results.len(),
        study.cells.len(),
        csv.display(),
        plotted
            .iter()
            .map(|p| format!(", {}", p.display()))
            .collect::<String>()
    );
    if failed > 0 {
        bail!(
            "{failed} cell(s) failed; their logs are in {}",
            args.out.join("cells").display()
        );
    }
    Ok(())
}

/// Runs `vlem study-cell`: one cell's mapping and evaluation, in this process.
pub fn execute_cell(args: &StudyCellArgs) -> Result<()> {
    study::run_cell(&args.dir, &|message| eprintln!("vlem: {message}"))?;
    Ok(())
}
