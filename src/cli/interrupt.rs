//! Ctrl-C and SIGTERM for the commands that map: the first signal ends the run the way its
//! `StopHandle` does (no further frame is read, the frames in hand are integrated, and the command
//! writes its outputs with `stopped: true`); a second one exits at once.
//!
//! Why it exists: a robot maps for an hour and is then stopped with Ctrl-C or by its process
//! manager (SIGTERM); without this the process would die with nothing written.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use vlem_core::pipeline::StopHandle;

/// Signals received so far.
static RECEIVED: AtomicUsize = AtomicUsize::new(0);
/// Whether a signal cut a run short (not merely ended `--serve-after`'s serving).
static RUN_CUT_SHORT: AtomicBool = AtomicBool::new(false);

/// The exit status of a process ended by SIGINT, as shells report it (128 + 2).
pub const EXIT_INTERRUPTED: u8 = 130;

/// Routes Ctrl-C and SIGTERM to `stop` (first signal) and to an immediate exit (second).
///
/// # Errors
/// When the handler cannot be installed (one is installed already).
pub fn install(stop: StopHandle) -> Result<()> {
    ctrlc::set_handler(move || {
        if RECEIVED.fetch_add(1, Ordering::SeqCst) == 0 {
            stop.stop();
            eprintln!(
                "\nvlem: interrupted: stopping (a run finishes the frames in hand and writes its \
                 outputs; interrupt again to quit at once, writing nothing more)"
            );
        } else {
            std::process::exit(i32::from(EXIT_INTERRUPTED));
        }
    })
    .context("cannot install the Ctrl-C / SIGTERM handler")
}

/// Whether a signal has arrived.
pub fn received() -> bool {
    RECEIVED.load(Ordering::SeqCst) > 0
}

/// Blocks until a signal arrives (for `--serve-after`).
pub fn wait() {
    while !received() {
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Records that a signal ended a run before its last frame: the command then exits with
/// [`EXIT_INTERRUPTED`] after writing its outputs.
pub fn note_run_cut_short() {
    RUN_CUT_SHORT.store(true, Ordering::SeqCst);
}

/// Whether [`note_run_cut_short`] was called.
pub fn run_cut_short() -> bool {
    RUN_CUT_SHORT.load(Ordering::SeqCst)
}
