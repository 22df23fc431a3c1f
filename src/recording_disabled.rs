//! Stand-in for `recording.rs` in builds without the cargo feature `rerun`: the command-line
//! flags exist, and asking for a recording says how to get a build that makes one. No value of
//! [`Recorder`] can exist, so nothing here can pretend to record.

use std::path::Path;

use anyhow::{Result, bail};
use vlem_core::{ColouredMesh, PointSet, RunObserver};
use vlem_query::grasp::Grasp;

/// Where a recording would go.
pub enum RecordingTarget<'a> {
    /// An `.rrd` file.
    File(&'a Path),
    /// A running viewer.
    Connect(&'a str),
}

/// A rerun recording; uninhabited in this build.
pub enum Recorder {}

impl Recorder {
    /// Always fails: this build has no rerun SDK.
    ///
    /// # Errors
    /// Always, with the build command that adds the feature.
    pub fn open(target: &RecordingTarget<'_>, _map_every: usize) -> Result<Self> {
        let what = match target {
            RecordingTarget::File(path) => format!("record to {}", path.display()),
            RecordingTarget::Connect(address) => format!("stream to {address}"),
        };
        bail!(
            "cannot {what}: this vlem was built without rerun recordings; rebuild it with the \
             `rerun` feature (`cargo build --release --features rerun`, ~10 minutes the first time)"
        )
    }

    pub fn log_map(&self, _points: &ColouredMesh, _frame: usize) -> Result<()> {
        match *self {}
    }

    pub fn log_colour_model(&self, _mesh: &ColouredMesh, _frame: usize) -> Result<()> {
        match *self {}
    }

    pub fn log_static_map(&self, _positions: &[[f32; 3]], _colours: &[[u8; 3]]) -> Result<()> {
        match *self {}
    }

    pub fn log_query(
        &self,
        _text: &str,
        _positions: &[[f32; 3]],
        _scores: &[f32],
        _sets: &[&PointSet],
        _grasp: Option<Option<&Grasp>>,
    ) -> Result<()> {
        match *self {}
    }

    pub fn flush(&self) -> Result<()> {
        match *self {}
    }
}

/// A run's observer; uninhabited in this build.
pub struct RunRecording<'a>(&'a Recorder);

impl<'a> RunRecording<'a> {
    pub fn new(recorder: &'a Recorder) -> Self {
        Self(recorder)
    }

    pub fn failure(&self) -> Option<String> {
        match *self.0 {}
    }
}

impl RunObserver for RunRecording<'_> {}
