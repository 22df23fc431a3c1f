//! vlem as a library: build a pipeline in code, feed it frames from your own source, and query the
//! map from another thread while it is being built.
//!
//! Run it from the repository root (it reads the committed living-room frames in `data/`):
//!
//! ```sh
//! cargo run --release --example library_pipeline
//! ```
//!
//! The frame source here replays a dataset folder at a camera's rate; a robot would return
//! frames from its driver instead. The stages are built through the registry by name, exactly as
//! a TOML config names them, so any encoder or map compiled in can be swapped in. It names only
//! the `vlem` crate: the library links every implementation its features turn on.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Result;
use vlem::prelude::*;

/// A "camera": frames come from a dataset reader, at most at 30 Hz.
struct Camera {
    recording: Box<dyn FrameSource>,
}

impl FrameSource for Camera {
    fn describe(&self) -> String {
        format!("a camera replaying {}", self.recording.describe())
    }
    fn len(&self) -> usize {
        self.recording.len()
    }
    fn intrinsics(&self) -> Intrinsics {
        self.recording.intrinsics()
    }
    fn has_poses(&self) -> bool {
        // This camera comes with poses (e.g. from the robot's odometry); without them, build an
        // `odometry` or `frame-to-model` tracker instead of `ground-truth`.
        self.recording.has_poses()
    }
    fn frame(&mut self, index: usize) -> vlem::core::Result<Frame> {
        self.recording.frame(index)
    }
}

fn main() -> Result<()> {
    let registry = Registry::global()?;
    let ctx = BuildContext::default();
    let tracker = registry.build_tracker(&StageConfig::named("ground-truth"), &ctx)?;
    let encoder = registry.build_encoder(&StageConfig::named("colour-names"), &ctx)?;
    let map_ctx = BuildContext {
        embedding_dim: Some(encoder.dim()),
        ..ctx.clone()
    };
    let mut map_stage = StageConfig::named("point-cloud");
    map_stage
        .params
        .insert("max_points".into(), toml::Value::Integer(200_000));
    let map = registry.build_map(&map_stage, &map_ctx)?;
    let mut pipeline = Pipeline::new(
        tracker,
        None,
        Some(encoder),
        Some(map),
        PipelineConfig {
            mode: Mode::RealTime,
            queue_capacity: 2,
            frame_rate: 30.0,
            ..PipelineConfig::default()
        },
    )?;

    let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/living-room");
    let mut camera = Camera {
        recording: vlem::datasets::open(&DatasetConfig::default(), &folder)?,
    };

    // The handle other threads query through; it stays valid during and after the run.
    let live = pipeline.live();
    let segmenter = Selection::threshold().build(&ctx)?;
    let texts = vec!["white wall".to_owned(), "brown".to_owned()];
    let mapping = AtomicBool::new(true);
    let report = std::thread::scope(|scope| {
        scope.spawn(|| {
            while mapping.load(Ordering::Acquire) {
                match answer_live(&live, segmenter.as_ref(), &texts, &AnswerOptions::default()) {
                    Ok((answered, _)) => {
                        let a = &answered.answer;
                        let best = a.queries[0].best.map_or(0.0, |b| b.score);
                        println!(
                            "after {:>2} frames: {:>6} points, \"{}\" best {best:.3}, {} points selected",
                            a.frames_integrated, a.points, a.queries[0].text, a.queries[0].selected
                        );
                    }
                    Err(e) => println!("query failed: {e}"),
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        let report = pipeline.run(&mut camera, None, &|_: Progress| {});
        mapping.store(false, Ordering::Release);
        report
    })?;
    let pose = live.latest_pose();
    println!(
        "{} frames tracked, {} integrated, {} skipped (real-time mode); last pose at frame {:?}",
        report.frames_tracked,
        report.frames_processed,
        report.frames_skipped,
        pose.map(|p| p.index)
    );
    Ok(())
}
