//! `vlem`: the command line. It parses arguments and dispatches; each command is a module in
//! `cli/` over the library crates (see ARCHITECTURE.md), so other front-ends share everything the
//! command does.

mod cli;
mod output;
#[cfg(feature = "rerun")]
mod recording;
#[cfg(not(feature = "rerun"))]
#[path = "recording_disabled.rs"]
mod recording;

use clap::{Parser, Subcommand};
// The library links every plugin crate the features turn on (`vlem::plugins`).
use vlem as _;

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
    /// Map a dataset: writes OUT/map.vlem, OUT/trajectory.tum and OUT/stats.json; with --serve,
    /// answers queries over HTTP while it maps.
    Run(cli::run::RunArgs),
    /// Query a saved map (--map) or a running `vlem run --serve` (--connect) with text.
    Query(cli::query::QueryArgs),
    /// Evaluate results against a reference (trajectory accuracy: ATE and RPE; semantic
    /// segmentation: mIoU).
    Eval {
        /// What to evaluate.
        #[command(subcommand)]
        command: cli::eval::EvalCommand,
    },
    /// List every registered implementation per stage.
    Plugins,
    /// Soak test: map many synthetic frames under a small map budget and check that resident
    /// memory stays flat; writes OUT/soak.json and OUT/soak-samples.csv.
    Soak(cli::soak::SoakArgs),
    /// Run a comparison study (maps × encoders × trackers × sequences): each cell mapped and
    /// evaluated (semseg3d) in a process of its own, then OUT/study.csv and a plot of mIoU
    /// against memory.
    Study(cli::study::StudyArgs),
    /// One cell of a study, in this process (what `vlem study` runs per cell).
    #[command(hide = true)]
    StudyCell(cli::study::StudyCellArgs),
    /// The live ROS 2 node (feature `ros2`): subscribes to a camera's colour, depth and camera
    /// info topics, maps, and publishes the tracked pose, the map and the answers to queries.
    Ros2(cli::ros2::Ros2Args),
    /// Run the embedded default: the committed living-room frames, pseudo ground-truth poses, the
    /// point-cloud map, the colour-names encoder and two queries.
    Demo(cli::run::DemoArgs),
}

fn main() -> std::process::ExitCode {
    // Before any thread starts: candle would otherwise count the cores anew, from /proc/cpuinfo,
    // for every op it runs on the CPU (`RAYON_NUM_THREADS`, kept where set).
    vlem_backends::use_all_cpus_once();
    // The model backends allocate large buffers per op: keep freed ones for reuse (2x on a
    // NARADIO frame; `VLEM_KEEP_FREED_MEMORY=0` turns it off).
    vlem_backends::keep_freed_memory();
    let outcome = match Cli::parse().command {
        Command::Run(args) => cli::run::execute(&args),
        Command::Query(args) => cli::query::execute(args),
        Command::Eval { command } => cli::eval::execute(command),
        Command::Plugins => cli::plugins::execute(),
        Command::Soak(args) => cli::soak::execute(&args),
        Command::Study(args) => cli::study::execute(&args),
        Command::StudyCell(args) => cli::study::execute_cell(&args),
        Command::Demo(args) => cli::run::demo(&args),
        Command::Ros2(args) => cli::ros2::execute(&args),
    };
    match outcome {
        // A run ended by Ctrl-C / SIGTERM wrote its outputs; its status says it was interrupted.
        Ok(()) if cli::interrupt::run_cut_short() => {
            std::process::ExitCode::from(cli::interrupt::EXIT_INTERRUPTED)
        }
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", cli::one_line(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
