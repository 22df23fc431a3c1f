//! The commands of `vlem`, one module each; shared command-line pieces (rerun flags, error
//! formatting) live here.

pub mod eval;
pub mod interrupt;
pub mod plugins;
pub mod query;
pub mod ros2;
pub mod run;
pub mod soak;
pub mod study;
mod study_plot;

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use crate::recording::{Recorder, RecordingTarget};

/// The cause chain on one line, without a backtrace (these are user errors), as
/// [`vlem_core::message_chain`] writes it for every front-end.
pub fn one_line(e: &anyhow::Error) -> String {
    vlem_core::message_chain(e.as_ref())
}

/// Rerun recording options (the recording needs a build with the `rerun` feature).
#[derive(Args, Clone, Default)]
pub struct RerunArgs {
    /// Record to this .rrd file (open it with the rerun viewer: `rerun FILE`).
    #[arg(long, value_name = "FILE.rrd", conflicts_with = "rerun_connect")]
    pub rerun: Option<PathBuf>,
    /// Stream to a running rerun viewer instead, e.g. rerun+http://127.0.0.1:9876/proxy.
    #[arg(long, value_name = "ADDR")]
    pub rerun_connect: Option<String>,
    /// During a run, log the map's points after every this many integrated frames.
    #[arg(long, default_value_t = 10, value_name = "N")]
    pub rerun_map_every: usize,
}

impl RerunArgs {
    /// The recording these options ask for, if any.
    pub fn open(&self) -> Result<Option<Recorder>> {
        let target = match (&self.rerun, &self.rerun_connect) {
            (Some(path), _) => RecordingTarget::File(path),
            (None, Some(address)) => RecordingTarget::Connect(address),
            (None, None) => return Ok(None),
        };
        Recorder::open(&target, self.rerun_map_every).map(Some)
    }
}
