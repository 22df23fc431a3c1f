//! The embedding side of a run: proposal, encoding and integration as workers joined by bounded
//! queues.
//!
//! Why this file exists: on a GPU each of the three stages takes tens of milliseconds, and run one
//! after another on one thread the embedding rate is their sum (the first H200 run: 23 + 120 +
//! 121 ms, 3.8 frames a second). Each in a worker of its own, frame k is integrated while frame
//! k+1 is encoded and frame k+2 segmented, so the rate is the slowest stage's. With
//! [`StageLayout::Serial`] the same stages run in one worker, as before, for comparisons.
//!
//! The loop that moves frames, times stages and names failures is written once ([`worker`]); the
//! stages are closures over one [`Work`] item. What users rely on holds for any layout:
//! - frames pass every queue in order and each stage runs on one thread, so an offline run
//!   integrates every frame in order and gives the same map as the serial layout, bit for bit;
//! - the integration stage takes the live map's write lock around one frame's integration only;
//! - a stage that fails stops its worker, which closes its queues: the stages before it stop at
//!   their next hand-over, the stages after it finish the frames already handed to them (so the map
//!   holds every frame that got through), and the run reports the failure as
//!   [`CoreError::AtFrame`] naming the stage and the frame.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::time::{Duration, Instant};

use serde::Serialize;

use super::StageTiming;
use crate::config::StageLayout;
use crate::embeddings::PixelEmbeddings;
use crate::error::{CoreError, Result};
use crate::types::{Frame, Pose, Region};

/// One tracked frame on its way through the embedding stages, gathering what each one adds.
pub(super) struct Work {
    pub(super) frame: Frame,
    pub(super) pose: Pose,
    /// The proposer's regions (empty without a proposer).
    pub(super) regions: Vec<Region>,
    /// The encoder's embeddings (`None` without an encoder).
    pub(super) embeddings: Option<PixelEmbeddings>,
}

/// What one stage does to a frame.
pub(super) type StageFn<'a> = Box<dyn FnMut(&mut Work) -> Result<()> + Send + 'a>;

/// A named stage.
pub(super) struct Stage<'a> {
    /// `propose`, `encode` or `integrate`: the key of its timings and of its errors.
    pub(super) name: &'static str,
    pub(super) run: StageFn<'a>,
}

/// How busy one embedding stage was, and how long its worker waited: a stage that sets the rate
/// is busy all the time; the others wait for input (starved) or for room downstream (blocked).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageLoad {
    /// Time spent in the stage itself.
    pub busy: StageTiming,
    /// Milliseconds its worker waited for the next frame (in a serial worker: counted on its first
    /// stage).
    pub wait_input_ms: f64,
    /// Milliseconds its worker waited for room in the next stage's queue (in a serial worker:
    /// counted on its last stage).
    pub wait_output_ms: f64,
}

/// The stages grouped into workers: one group per worker, in pipeline order.
pub(super) fn layout(stages: Vec<Stage<'_>>, layout: StageLayout) -> Vec<Vec<Stage<'_>>> {
    match layout {
        StageLayout::Overlapped => stages.into_iter().map(|s| vec![s]).collect(),
        StageLayout::Serial if stages.is_empty() => Vec::new(),
        StageLayout::Serial => vec![stages],
    }
}

/// Runs the workers in `scope`, the first reading `input`, each handing on to the next through a
/// queue of `capacity` frames. Once `stop` is requested, the frames still queued are dropped
/// instead of run (a stopped run ends after the frame each stage is working on, not after every
/// queued frame has gone through a slow encoder). Returns, once all have ended, every stage's load
/// in pipeline order, or the first failure in pipeline order.
pub(super) fn run_workers<'scope, 'env: 'scope>(
    scope: &'scope std::thread::Scope<'scope, 'env>,
    groups: Vec<Vec<Stage<'env>>>,
    input: Receiver<Work>,
    capacity: usize,
    stop: &'env super::StopHandle,
) -> Result<Vec<(&'static str, StageLoad)>> {
    let count = groups.len();
    let mut input = Some(input);
    let mut handles = Vec::with_capacity(count);
    for (i, group) in groups.into_iter().enumerate() {
        let (output, next) = if i + 1 < count {
            let (sender, receiver) = sync_channel::<Work>(capacity);
            (Some(sender), Some(receiver))
        } else {
            (None, None)
        };
        let Some(receiver) = input.take() else {
            break;
        };
        let names: Vec<&'static str> = group.iter().map(|s| s.name).collect();
        handles.push((
            names,
            scope.spawn(move || worker(group, &receiver, output.as_ref(), stop)),
        ));
        input = next;
    }
    let mut loads = Vec::new();
    let mut failure = None;
    for (names, handle) in handles {
        match handle.join() {
            Ok(Ok(group)) => loads.extend(group),
            Ok(Err(e)) => {
                failure.get_or_insert(e);
            }
            Err(_) => {
                failure.get_or_insert(CoreError::Worker {
                    reason: format!("the {} worker panicked", names.join(" + ")),
                });
            }
        }
    }
    match failure {
        Some(e) => Err(e),
        None => Ok(loads),
    }
}

/// One worker: takes frames from `input` until it closes, runs its stages on each, and hands it on
/// to `output`. Returns at its first failure, which closes both queues (see the module doc).
fn worker(
    mut stages: Vec<Stage<'_>>,
    input: &Receiver<Work>,
    output: Option<&SyncSender<Work>>,
    stop: &super::StopHandle,
) -> Result<Vec<(&'static str, StageLoad)>> {
    let mut loads = vec![StageLoad::default(); stages.len()];
    let mut wait_input = Duration::ZERO;
    let mut wait_output = Duration::ZERO;
    loop {
        let waited = Instant::now();
        let Ok(mut work) = input.recv() else {
            break;
        };
        wait_input += waited.elapsed();
        if stop.requested() {
            continue; // Drained, not run: the run is ending.
        }
        for (stage, load) in stages.iter_mut().zip(&mut loads) {
            let started = Instant::now();
            (stage.run)(&mut work).map_err(|e| CoreError::AtFrame {
                stage: stage.name,
                frame: work.frame.index,
                source: Box::new(e),
            })?;
            load.busy.add(started);
        }
        if let Some(output) = output {
            let waited = Instant::now();
            if output.send(work).is_err() {
                break; // A later stage failed; the run reports its error.
            }
            wait_output += waited.elapsed();
        }
    }
    if let Some(first) = loads.first_mut() {
        first.wait_input_ms = wait_input.as_secs_f64() * 1e3;
    }
    if let Some(last) = loads.last_mut() {
        last.wait_output_ms = wait_output.as_secs_f64() * 1e3;
    }
    Ok(stages.iter().map(|s| s.name).zip(loads).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::{DepthImage, Intrinsics, RgbImage};
    use std::sync::Mutex;

    fn work(index: usize) -> Work {
        let frame = Frame::new(
            index,
            0.0,
            RgbImage::filled(2, 2, [0, 0, 0]),
            DepthImage::new(2, 2, vec![1.0; 4]).unwrap(),
            Intrinsics::new(2, 2, 1.0, 1.0, 0.5, 0.5).unwrap(),
            None,
        )
        .unwrap();
        Work {
            frame,
            pose: Pose::identity(),
            regions: Vec::new(),
            embeddings: None,
        }
    }

    /// Three stages that record which frames they saw; `fail` makes one stage fail at a frame.
    fn run(
        layout_kind: StageLayout,
        fail: Option<(&'static str, usize)>,
    ) -> Result<[Vec<usize>; 3]> {
        run_stopping(layout_kind, fail, None)
    }

    /// [`run`], the encode stage asking the run to stop at frame `stop_at`.
    fn run_stopping(
        layout_kind: StageLayout,
        fail: Option<(&'static str, usize)>,
        stop_at: Option<usize>,
    ) -> Result<[Vec<usize>; 3]> {
        let seen: [Mutex<Vec<usize>>; 3] = Default::default();
        let stop = crate::pipeline::StopHandle::default();
        let stop = &stop;
        let result = std::thread::scope(|scope| {
            let stages = ["propose", "encode", "integrate"]
                .into_iter()
                .enumerate()
                .map(|(i, name)| {
                    let seen = &seen[i];
                    Stage {
                        name,
                        run: Box::new(move |w: &mut Work| {
                            if fail == Some((name, w.frame.index)) {
                                return Err(CoreError::Worker {
                                    reason: "test failure".into(),
                                });
                            }
                            seen.lock().unwrap().push(w.frame.index);
                            if name == "encode" && stop_at == Some(w.frame.index) {
                                stop.stop();
                            }
                            Ok(())
                        }) as StageFn<'_>,
                    }
                })
                .collect();
            let (sender, receiver) = sync_channel(1);
            let feeder = scope.spawn(move || {
                for i in 0..20 {
                    if sender.send(work(i)).is_err() {
                        break;
                    }
                }
            });
            let loads = run_workers(scope, layout(stages, layout_kind), receiver, 1, stop);
            feeder.join().unwrap();
            loads
        });
        let loads = result?;
        let names: Vec<_> = loads.iter().map(|(n, _)| *n).collect();
        assert_eq!(names, ["propose", "encode", "integrate"]);
        Ok(seen.map(|m| m.into_inner().unwrap()))
    }

    #[test]
    fn every_layout_passes_every_frame_through_every_stage_in_order() {
        for layout_kind in [StageLayout::Overlapped, StageLayout::Serial] {
            let seen = run(layout_kind, None).unwrap();
            for stage in &seen {
                assert_eq!(*stage, (0..20).collect::<Vec<_>>(), "{layout_kind:?}");
            }
        }
    }

    #[test]
    fn a_stop_drops_the_queued_frames_instead_of_running_them() {
        for layout_kind in [StageLayout::Overlapped, StageLayout::Serial] {
            let [proposed, encoded, integrated] = run_stopping(layout_kind, None, Some(5)).unwrap();
            // The encoder finishes the frame it holds and runs none of the queued ones.
            assert_eq!(encoded, (0..=5).collect::<Vec<_>>(), "{layout_kind:?}");
            assert!(integrated.iter().all(|&i| i <= 5), "{layout_kind:?}");
            assert!(proposed.len() < 20, "{layout_kind:?}: {proposed:?}");
        }
    }

    #[test]
    fn a_failure_names_the_stage_and_frame_and_later_stages_finish_what_they_hold() {
        for layout_kind in [StageLayout::Overlapped, StageLayout::Serial] {
            let err = run(layout_kind, Some(("encode", 7))).unwrap_err();
            assert_eq!(
                err.to_string(),
                "encode of frame 7: pipeline worker failed: test failure"
            );
            assert!(matches!(err.root(), CoreError::Worker { .. }));
        }
        // What the integration stage saw when encoding failed at frame 7: every frame before it.
        let seen: [Mutex<Vec<usize>>; 1] = Default::default();
        let stop = crate::pipeline::StopHandle::default();
        let _ = std::thread::scope(|scope| {
            let seen = &seen[0];
            let stages = vec![
                Stage {
                    name: "encode",
                    run: Box::new(|w: &mut Work| {
                        if w.frame.index == 7 {
                            Err(CoreError::Worker { reason: "x".into() })
                        } else {
                            Ok(())
                        }
                    }) as StageFn<'_>,
                },
                Stage {
                    name: "integrate",
                    run: Box::new(move |w: &mut Work| {
                        std::thread::sleep(Duration::from_millis(2));
                        seen.lock().unwrap().push(w.frame.index);
                        Ok(())
                    }),
                },
            ];
            let (sender, receiver) = sync_channel(1);
            scope.spawn(move || {
                for i in 0..20 {
                    if sender.send(work(i)).is_err() {
                        break;
                    }
                }
            });
            run_workers(
                scope,
                layout(stages, StageLayout::Overlapped),
                receiver,
                1,
                &stop,
            )
        });
        assert_eq!(seen[0].lock().unwrap().clone(), (0..7).collect::<Vec<_>>());
    }

    #[test]
    fn no_stages_means_no_workers() {
        assert!(layout(Vec::new(), StageLayout::Serial).is_empty());
        assert!(layout(Vec::new(), StageLayout::Overlapped).is_empty());
    }
}
