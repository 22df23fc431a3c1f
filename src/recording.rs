//! Rerun recordings of runs and queries (cargo feature `rerun`).
//!
//! A run logs, on the `frame` timeline: the camera (pose and pinhole), its colour and depth images,
//! the region proposer's regions, the trajectory so far, the embedding map's points every few
//! integrated frames, and at the end the whole map and the tracker's dense colour model. A query
//! logs, on the `query` timeline and under an entity of its own, the heatmap (jet colours, as in
//! the paper's figures), the selected point sets and the grasp. docs/usage.md lists every entity;
//! the recording opens in the stock rerun viewer.

use std::path::Path;
use std::sync::Mutex;

use anyhow::{Context, Result};
use rerun::{ChannelDatatype, RecordingStream, RecordingStreamBuilder, components::ImageFormat};
use vlem_core::{ColouredMesh, EmbeddingMap, Frame, PointSet, Pose, Region, RunObserver};
use vlem_query::grasp::Grasp;

/// Where a recording goes.
pub enum RecordingTarget<'a> {
    /// An `.rrd` file, opened later with `rerun FILE`.
    File(&'a Path),
    /// A running viewer (`rerun` started beforehand), e.g. `rerun+http://127.0.0.1:9876/proxy`.
    Connect(&'a str),
}

/// An open rerun recording.
pub struct Recorder {
    stream: RecordingStream,
    /// Log the map's points after every this many integrated frames.
    map_every: usize,
    /// Camera positions so far (the trajectory strip is re-logged whole each frame).
    trajectory: Mutex<Vec<[f32; 3]>>,
    /// Queries logged so far (their `query` timeline index).
    queries: Mutex<i64>,
}

impl Recorder {
    /// Opens a recording; `map_every` is how often (in integrated frames) a run logs the map.
    ///
    /// # Errors
    /// The file cannot be created, or the viewer address is not a rerun proxy URL.
    pub fn open(target: &RecordingTarget<'_>, map_every: usize) -> Result<Self> {
        let builder = RecordingStreamBuilder::new("vlem");
        let stream = match target {
            RecordingTarget::File(path) => builder
                .save(*path)
                .with_context(|| format!("cannot create the recording {}", path.display()))?,
            RecordingTarget::Connect(address) => {
                builder.connect_grpc_opts(*address).with_context(|| {
                    format!(
                        "cannot stream to the rerun viewer at {address} (expected \
                         rerun+http://HOST:PORT/proxy; start the viewer with `rerun`)"
                    )
                })?
            }
        };
        // Datasets' world frames follow the first camera: x right, y down, z forward.
        stream.log_static("world", &rerun::ViewCoordinates::RIGHT_HAND_Y_DOWN())?;
        Ok(Self {
            stream,
            map_every: map_every.max(1),
            trajectory: Mutex::new(Vec::new()),
            queries: Mutex::new(0),
        })
    }

    /// Logs the final map, on the `frame` timeline after the last frame.
    ///
    /// # Errors
    /// The recording sink failed.
    pub fn log_map(&self, points: &ColouredMesh, frame: usize) -> Result<()> {
        self.stream.set_time_sequence("frame", frame as i64);
        self.stream.log("world/map", &map_points(points))?;
        Ok(())
    }

    /// Logs the tracker's dense colour model.
    ///
    /// # Errors
    /// The recording sink failed.
    pub fn log_colour_model(&self, mesh: &ColouredMesh, frame: usize) -> Result<()> {
        self.stream.set_time_sequence("frame", frame as i64);
        let colours = mesh
            .colours
            .iter()
            .map(|&[r, g, b]| rerun::Color::from_rgb(r, g, b));
        if mesh.triangles.is_empty() {
            self.stream.log(
                "world/colour_model",
                &rerun::Points3D::new(mesh.vertices.iter().copied()).with_colors(colours),
            )?;
        } else {
            self.stream.log(
                "world/colour_model",
                &rerun::Mesh3D::new(mesh.vertices.iter().copied())
                    .with_triangle_indices(mesh.triangles.iter().copied())
                    .with_vertex_colors(colours),
            )?;
        }
        Ok(())
    }

    /// Logs the map points once, for a recording of queries on a saved map.
    ///
    /// # Errors
    /// The recording sink failed.
    pub fn log_static_map(&self, positions: &[[f32; 3]], colours: &[[u8; 3]]) -> Result<()> {
        let points = ColouredMesh {
            vertices: positions.to_vec(),
            colours: colours.to_vec(),
            triangles: Vec::new(),
        };
        self.stream.log_static("world/map", &map_points(&points))?;
        Ok(())
    }

    /// Logs one query: its heatmap over `positions`, the point sets selected for it, and its
    /// grasp (`None`: not asked for; `Some(None)`: asked for, none found). Each query gets the next step of the `query` timeline and an entity named after it.
    ///
    /// # Errors
    /// The recording sink failed.
    pub fn log_query(
        &self,
        text: &str,
        positions: &[[f32; 3]],
        scores: &[f32],
        sets: &[&PointSet],
        grasp: Option<Option<&Grasp>>,
    ) -> Result<()> {
        let step = {
            let mut count = self.queries.lock().map_err(|_| poisoned())?;
            *count += 1;
            *count - 1
        };
        self.stream.set_time_sequence("query", step);
        let root = format!("world/queries/{}", vlem_query::answer::slug(text));
        let colours = scores.iter().map(|&s| {
            let [r, g, b] = vlem_query::heatmap::jet(s);
            rerun::Color::from_rgb(r, g, b)
        });
        self.stream.log(
            format!("{root}/heatmap"),
            &rerun::Points3D::new(positions.iter().copied())
                .with_colors(colours)
                .with_radii([POINT_RADIUS]),
        )?;
        let mut selected = Vec::new();
        let mut class_ids = Vec::new();
        for (k, set) in sets.iter().enumerate() {
            for &i in &set.indices {
                if let Some(&p) = positions.get(i) {
                    selected.push(p);
                    class_ids.push(u16::try_from(k + 1).unwrap_or(u16::MAX));
                }
            }
        }
        self.stream.log(
            format!("{root}/selected"),
            &rerun::Points3D::new(selected)
                .with_class_ids(class_ids)
                .with_radii([POINT_RADIUS * 1.5]),
        )?;
        match grasp {
            Some(Some(g)) => {
                let strips: Vec<Vec<[f32; 3]>> = gripper_strips(g);
                self.stream.log(
                    format!("{root}/grasp"),
                    &rerun::LineStrips3D::new(strips)
                        .with_colors([rerun::Color::from_rgb(255, 0, 255)])
                        .with_labels([format!("grasp, width {:.3} m", g.width)]),
                )?;
            }
            // Asked for but impossible: clear an earlier query's gripper of the same text.
            Some(None) => self
                .stream
                .log(format!("{root}/grasp"), &rerun::Clear::flat())?,
            None => {}
        }
        self.stream.log(
            "log",
            &rerun::TextLog::new(format!(
                "query \"{text}\": {} selected points in {} sets",
                sets.iter().map(|s| s.indices.len()).sum::<usize>(),
                sets.len()
            )),
        )?;
        Ok(())
    }

    /// Writes everything logged so far (to the file or the viewer) before returning.
    ///
    /// # Errors
    /// The sink could not flush.
    pub fn flush(&self) -> Result<()> {
        self.stream
            .flush_blocking()
            .context("cannot write the rerun recording")
    }
}

/// Display radius of map points (m).
const POINT_RADIUS: f32 = 0.005;

fn poisoned() -> anyhow::Error {
    anyhow::anyhow!("a recording thread panicked")
}

fn map_points(points: &ColouredMesh) -> rerun::Points3D {
    rerun::Points3D::new(points.vertices.iter().copied())
        .with_colors(
            points
                .colours
                .iter()
                .map(|&[r, g, b]| rerun::Color::from_rgb(r, g, b)),
        )
        .with_radii([POINT_RADIUS])
}

/// The gripper drawn as line strips: closing axis, fingers, palm and stem.
fn gripper_strips(grasp: &Grasp) -> Vec<Vec<[f32; 3]>> {
    vlem_query::heatmap::gripper_segments(grasp)
        .into_iter()
        .map(|(from, to, _)| vec![from, to])
        .collect()
}

fn pose_transform(pose: &Pose) -> rerun::Transform3D {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    rerun::Transform3D::from_translation_rotation(
        [t.x as f32, t.y as f32, t.z as f32],
        rerun::Quaternion::from_xyzw([q.i as f32, q.j as f32, q.k as f32, q.w as f32]),
    )
}

/// One id per pixel: 0 for no region, else 1 + the region's index; smaller regions are drawn
/// last so they win on overlap, as in the encoders' region layout.
fn region_ids(width: u32, height: u32, regions: &[Region]) -> Vec<u16> {
    let mut ids = vec![0u16; width as usize * height as usize];
    let mut order: Vec<usize> = (0..regions.len()).collect();
    order.sort_by_key(|&k| std::cmp::Reverse(regions[k].area()));
    for k in order {
        let region = &regions[k];
        let id = u16::try_from(k + 1).unwrap_or(u16::MAX);
        let b = &region.bbox;
        for dy in 0..b.height {
            for dx in 0..b.width {
                let (u, v) = (b.x + dx, b.y + dy);
                if u < width
                    && v < height
                    && region
                        .mask
                        .get((dy * b.width + dx) as usize)
                        .copied()
                        .unwrap_or(false)
                {
                    ids[(v * width + u) as usize] = id;
                }
            }
        }
    }
    ids
}

impl Recorder {
    /// Both timelines of a run, for this thread's next logs (rerun's time is per thread).
    fn set_frame_time(&self, frame: &Frame) {
        self.stream.set_time_sequence("frame", frame.index as i64);
        self.stream.set_time(
            "timestamp",
            rerun::TimeCell::from_duration_nanos((frame.timestamp * 1e9) as i64),
        );
    }

    fn log_frame(&self, frame: &Frame, pose: &Pose, lost: Option<&str>) -> Result<()> {
        let s = &self.stream;
        self.set_frame_time(frame);
        s.log("world/camera", &pose_transform(pose))?;
        let k = &frame.intrinsics;
        s.log(
            "world/camera/image",
            &rerun::Pinhole::from_focal_length_and_resolution(
                [k.fx as f32, k.fy as f32],
                [k.width as f32, k.height as f32],
            )
            .with_principal_point([k.cx as f32, k.cy as f32]),
        )?;
        let (w, h) = (frame.colour.width(), frame.colour.height());
        s.log(
            "world/camera/image/rgb",
            &rerun::Image::from_rgb24(frame.colour.as_raw().to_vec(), [w, h]),
        )?;
        let depth_bytes: Vec<u8> = frame
            .depth
            .as_raw()
            .iter()
            .flat_map(|d| d.to_le_bytes())
            .collect();
        s.log(
            "world/camera/image/depth",
            &rerun::DepthImage::from_data_type_and_bytes(depth_bytes, [w, h], ChannelDatatype::F32)
                .with_meter(1.0),
        )?;
        let strip = {
            let mut trajectory = self.trajectory.lock().map_err(|_| poisoned())?;
            let t = pose.translation.vector;
            trajectory.push([t.x as f32, t.y as f32, t.z as f32]);
            trajectory.clone()
        };
        s.log(
            "world/trajectory",
            &rerun::LineStrips3D::new([strip]).with_colors([rerun::Color::from_rgb(255, 200, 0)]),
        )?;
        if let Some(reason) = lost {
            s.log(
                "log",
                &rerun::TextLog::new(format!("frame {}: tracking lost: {reason}", frame.index))
                    .with_level(rerun::TextLogLevel::WARN),
            )?;
        }
        Ok(())
    }

    fn log_integrated(
        &self,
        frame: &Frame,
        regions: &[Region],
        map: &dyn EmbeddingMap,
        integrated: usize,
    ) -> Result<()> {
        let s = &self.stream;
        self.set_frame_time(frame);
        if !regions.is_empty() {
            let (w, h) = (frame.colour.width(), frame.colour.height());
            let ids = region_ids(w, h, regions);
            let bytes: Vec<u8> = ids.iter().flat_map(|id| id.to_le_bytes()).collect();
            s.log(
                "world/camera/image/segments",
                &rerun::SegmentationImage::new(
                    bytes,
                    ImageFormat::segmentation([w, h], ChannelDatatype::U16),
                ),
            )?;
        }
        if integrated.is_multiple_of(self.map_every) {
            s.log("world/map", &map_points(&map.coloured_points()))?;
        }
        Ok(())
    }
}

/// What a run's observer logs; failures are reported once and logging then stops, so a broken
/// viewer connection never stops a mapping run.
pub struct RunRecording<'a> {
    recorder: &'a Recorder,
    integrated: Mutex<usize>,
    failed: Mutex<Option<String>>,
}

impl<'a> RunRecording<'a> {
    /// Observes a run into `recorder`.
    pub fn new(recorder: &'a Recorder) -> Self {
        Self {
            recorder,
            integrated: Mutex::new(0),
            failed: Mutex::new(None),
        }
    }

    /// The first logging error of the run, if any.
    pub fn failure(&self) -> Option<String> {
        self.failed.lock().ok().and_then(|f| f.clone())
    }

    fn attempt(&self, log: impl FnOnce() -> Result<()>) {
        let Ok(mut failed) = self.failed.lock() else {
            return;
        };
        if failed.is_some() {
            return;
        }
        if let Err(e) = log() {
            *failed = Some(format!("{e:#}"));
        }
    }
}

impl RunObserver for RunRecording<'_> {
    fn frame_tracked(&self, frame: &Frame, tracked: &vlem_core::TrackedPose) {
        let lost = match &tracked.state {
            vlem_core::TrackingState::Lost { reason } => Some(reason.as_str()),
            vlem_core::TrackingState::Tracking => None,
        };
        self.attempt(|| self.recorder.log_frame(frame, &tracked.pose, lost));
    }

    fn frame_integrated(
        &self,
        frame: &Frame,
        _pose: &Pose,
        regions: &[Region],
        map: &dyn EmbeddingMap,
    ) {
        let integrated = match self.integrated.lock() {
            Ok(mut n) => {
                *n += 1;
                *n
            }
            Err(_) => return,
        };
        self.attempt(|| {
            self.recorder
                .log_integrated(frame, regions, map, integrated)
        });
    }
}
