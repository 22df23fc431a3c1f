//! A deterministic, procedurally generated, labelled RGB-D scene (`[dataset] kind = "synthetic"`).
//!
//! Why it exists: trackers and maps need sequences with *exact* ground truth (poses, depth,
//! per-pixel class labels, labelled 3-D surface points) and nothing to download. This module owns
//! everything about that scene:
//!
//! - the room and its furniture, built from analytic solids (boxes turned about the vertical,
//!   upright cylinders, spheres) and placed from the seed without overlapping each other or the
//!   walls (`layout`); labels are NYU40 ids and names ([`SYNTHETIC_LABELS`]);
//! - solid textures with gradients at several scales and view-independent shading from a fixed
//!   light, so that photometric consistency between views holds (`texture`);
//! - a smooth camera path, about 1 cm and 1° per frame at 30 Hz (at most 1.8 cm and 1.7°),
//!   orbiting near the middle of the room, looking outwards at content 0.7–4 m away and nodding
//!   between the floor and the ceiling; one orbit takes 380–440 frames, and every piece of
//!   furniture is seen during it (`motion`);
//! - ray casting of colour, depth, labels and instances, with an optional Kinect-like depth noise
//!   model (`render`);
//! - ground-truth labelled surface points (`surface`), and writing a sequence to disk in the
//!   ICL-NUIM/Open3D layout that [`crate::icl`] reads, plus labels (`disk`).
//!
//! Conventions: world z is up, the floor is z = 0 and the room spans `[-x/2, x/2] × [-y/2, y/2]`
//! (`[dataset.synthetic] room = [x, y, height]`). Poses are camera-to-world with the camera looking
//! along +z, x right, y down. Depth is the camera-frame z of the nearest surface in metres; without
//! noise every pixel has a valid depth (the room is closed). The camera is fx = fy =
//! 525 · width / 640 with the principal point at the image centre ((width − 1) / 2,
//! (height − 1) / 2). Frame `i` is at time `i / 30` s.
//!
//! Everything is a pure function of [`SyntheticConfig`]: the same config gives the same bytes on
//! every machine and thread count (the randomness is a local SplitMix64, not a crate's generator).

use nalgebra::{Point3, Vector3};
use vlem_core::config::DatasetConfig;
use vlem_core::{
    DatasetReader, DepthImage, Frame, FrameSource, Intrinsics, LabelImage, LabelNames, Pose,
    RgbImage,
};

use crate::error::{DatasetError, Result};

mod config;
mod disk;
mod geometry;
mod layout;
mod motion;
mod render;
mod rng;
mod surface;
mod texture;

pub use config::{SyntheticConfig, SyntheticNoise};
pub use disk::write_to_disk;
pub use layout::SYNTHETIC_LABELS;
pub use motion::look_along;

/// The registered name: `[dataset] kind = "synthetic"`.
pub const SYNTHETIC: &str = "synthetic";

vlem_core::register_dataset!(
    SYNTHETIC,
    "a procedural labelled room rendered on demand, no folder; settings in [dataset.synthetic]",
    DatasetReader::new(open_boxed)
        .without_path()
        .with_settings_check(|config| {
            crate::sequence::check_settings::<config::SyntheticSettings>(SYNTHETIC, config)
        })
);

fn open_boxed(
    config: &DatasetConfig,
    _path: &std::path::Path,
) -> vlem_core::Result<Box<dyn FrameSource>> {
    Ok(Box::new(SyntheticReader::open(config)?))
}

/// The frame rate the camera path is designed for: frame `i` has timestamp `i / 30` s.
pub const SYNTHETIC_FRAME_RATE: f64 = 30.0;

/// Widest and tallest image the generator renders.
const MAX_SIZE: u32 = 16384;

/// Most pieces the generator tries to place.
const MAX_OBJECTS: usize = 1000;

/// Clearance kept between the camera path and any piece of furniture (metres, horizontally).
const CLEARANCE: f64 = 0.65;

/// Frames between probe views.
const PROBE_STEP: usize = 5;
/// Pixels a piece must cover over all probe views to be kept.
const PROBE_MIN_PIXELS: usize = 8;

/// A class: its NYU40 id and name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct LabelInfo {
    /// The id in label images (NYU40; 0 is "unlabelled").
    pub id: u16,
    /// The NYU40 class name.
    pub name: &'static str,
}

impl LabelInfo {
    /// A table entry.
    pub const fn new(id: u16, name: &'static str) -> Self {
        Self { id, name }
    }
}

/// One thing in the scene: a room surface (floor, ceiling, four walls: instances 1–6) or a piece
/// of furniture, wall item or prop (instances 7 and up).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneObject {
    /// Its id in instance images (the position in [`SyntheticScene::objects`] plus one).
    pub instance: u16,
    /// Its class (see [`SYNTHETIC_LABELS`]); some of its parts may carry another class (the
    /// pillows of a sofa, the books of a bookshelf).
    pub label: u16,
    /// The class name.
    pub name: &'static str,
    /// World-frame bounds, lower corner.
    pub min: Point3<f64>,
    /// World-frame bounds, upper corner.
    pub max: Point3<f64>,
}

/// One rendered view with its ground truth.
#[derive(Clone, Debug)]
pub struct SyntheticView {
    /// The frame index (it keys the depth noise).
    pub index: usize,
    /// Shaded colour.
    pub colour: RgbImage,
    /// Depth in metres (camera-frame z); exact without noise, 0 where the noise model drops it.
    pub depth: DepthImage,
    /// Class id per pixel, row-major (see [`SYNTHETIC_LABELS`]); never 0: every ray hits a surface,
    /// and labels are not affected by depth noise.
    pub labels: Vec<u16>,
    /// Instance id per pixel, row-major (see [`SceneObject::instance`]).
    pub instances: Vec<u16>,
    /// Camera-to-world pose (exact).
    pub pose: Pose,
    /// The camera.
    pub intrinsics: Intrinsics,
}

impl SyntheticView {
    /// The class id at pixel `(u, v)`; `None` outside the image.
    pub fn label(&self, u: u32, v: u32) -> Option<u16> {
        let k = &self.intrinsics;
        (u < k.width && v < k.height)
            .then(|| self.labels[v as usize * k.width as usize + u as usize])
    }

    /// The view as a pipeline frame with this timestamp and index.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] if the images and intrinsics disagree (they never do for views
    /// made by [`SyntheticScene`]).
    /// The frame carries the view's class ids as its labels, named by [`synthetic_label_names`].
    pub fn into_frame(self, index: usize, timestamp: f64) -> Result<Frame> {
        let k = self.intrinsics;
        let fail = |e: vlem_core::CoreError| DatasetError::Synthetic {
            message: e.to_string(),
        };
        let labels = LabelImage::new(k.width, k.height, self.labels, synthetic_label_names())
            .map_err(fail)?;
        Frame::new(
            index,
            timestamp,
            self.colour,
            self.depth,
            self.intrinsics,
            Some(self.pose),
        )
        .and_then(|frame| frame.with_labels(labels))
        .map_err(fail)
    }
}

/// The names of [`SYNTHETIC_LABELS`] as frame labels use them (one shared table).
pub fn synthetic_label_names() -> std::sync::Arc<LabelNames> {
    static NAMES: std::sync::OnceLock<std::sync::Arc<LabelNames>> = std::sync::OnceLock::new();
    NAMES
        .get_or_init(|| {
            std::sync::Arc::new(LabelNames::new(
                SYNTHETIC_LABELS.iter().map(|l| (l.id, l.name.to_owned())),
            ))
        })
        .clone()
}

/// A ground-truth point on a scene surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// World position (metres).
    pub position: Point3<f64>,
    /// Outward unit normal (into the room for room surfaces).
    pub normal: Vector3<f64>,
    /// Class id.
    pub label: u16,
    /// Instance id.
    pub instance: u16,
    /// The colour a camera sees there (the same in every view).
    pub colour: [u8; 3],
}

/// The generated scene: room, furniture, textures and camera path.
#[derive(Clone, Debug)]
pub struct SyntheticScene {
    config: SyntheticConfig,
    intrinsics: Intrinsics,
    motion: motion::Motion,
    layout: layout::Layout,
    noise: texture::Noise,
}

impl SyntheticScene {
    /// Generates the scene of `config`: places up to `objects` pieces, then drops any that one
    /// full orbit of the camera path would barely see (hidden behind another piece, or too low and
    /// close), so that every object in [`SyntheticScene::objects`] is observed by a long enough
    /// sequence. The content depends on `seed`, `room` and `objects` only.
    ///
    /// # Errors
    /// [`DatasetError::SyntheticConfig`] naming the key of a value out of range: `frames` 0,
    /// `width` or `height` 0 or above 16384, a `room` size outside 2–100 m or not finite,
    /// `objects` above 1000.
    pub fn new(config: &SyntheticConfig) -> Result<Self> {
        validate(config)?;
        let (w, h) = (config.width, config.height);
        let f = 525.0 * f64::from(w) / 640.0;
        let intrinsics = Intrinsics::new(
            w,
            h,
            f,
            f,
            (f64::from(w) - 1.0) / 2.0,
            (f64::from(h) - 1.0) / 2.0,
        )
        .map_err(|e| DatasetError::SyntheticConfig {
            key: "width",
            message: e.to_string(),
        })?;
        let motion = motion::Motion::new(config.seed, config.room);
        let mut layout = layout::Layout::generate(
            config.seed,
            config.room,
            config.objects,
            motion.max_radius() + CLEARANCE,
        );
        // Drop pieces that one orbit of the path barely sees (hidden behind others, or too low
        // and close), judged on small images, so that every object is observed.
        // A fixed probe camera (the default one at 1/8 size), so that the scene's content does not
        // depend on the image size.
        let probe = Intrinsics {
            width: 80,
            height: 60,
            fx: 525.0 / 8.0,
            fy: 525.0 / 8.0,
            cx: 39.5,
            cy: 29.5,
        };
        let poses: Vec<Pose> = (0..motion.orbit_frames())
            .step_by(PROBE_STEP)
            .map(|i| motion.pose(i))
            .collect();
        let seen = render::coverage(&layout, &probe, &poses);
        layout.retain_pieces(|instance| {
            seen.get(usize::from(instance))
                .is_some_and(|&n| n >= PROBE_MIN_PIXELS)
        });
        Ok(Self {
            config: config.clone(),
            intrinsics,
            motion,
            layout,
            noise: texture::Noise::new(config.seed),
        })
    }

    /// The config the scene was made from.
    pub fn config(&self) -> &SyntheticConfig {
        &self.config
    }

    /// A one-line description for logs.
    pub fn describe(&self) -> String {
        let c = &self.config;
        format!(
            "synthetic scene (seed {}, {} frames of {}x{}, {} objects)",
            c.seed,
            c.frames,
            c.width,
            c.height,
            self.layout.objects.len()
        )
    }

    /// Number of frames (`[dataset.synthetic] frames`).
    pub fn len(&self) -> usize {
        self.config.frames
    }

    /// Always false: a scene has at least one frame.
    pub fn is_empty(&self) -> bool {
        self.config.frames == 0
    }

    /// The camera.
    pub fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }

    /// The room's bounds (floor corner, ceiling corner).
    pub fn room(&self) -> (Point3<f64>, Point3<f64>) {
        (Point3::from(self.layout.min), Point3::from(self.layout.max))
    }

    /// The exact camera-to-world pose of frame `index`.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] for an index past the last frame.
    pub fn pose(&self, index: usize) -> Result<Pose> {
        self.check_index(index)?;
        Ok(self.motion.pose(index))
    }

    /// The poses of every frame, in order.
    pub fn poses(&self) -> Vec<Pose> {
        (0..self.len()).map(|i| self.motion.pose(i)).collect()
    }

    /// Renders frame `index`.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] for an index past the last frame.
    pub fn render(&self, index: usize) -> Result<SyntheticView> {
        self.check_index(index)?;
        self.render_view(index, &self.motion.pose(index))
    }

    /// Renders the scene from any `pose` inside the room (for tests and custom paths); `index`
    /// only keys the depth noise and is copied into the view.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] when the pose is not finite or the camera is not inside the
    /// room.
    pub fn render_at(&self, index: usize, pose: &Pose) -> Result<SyntheticView> {
        let p = pose.translation.vector;
        let inside = (0..3).all(|k| p[k] > self.layout.min[k] && p[k] < self.layout.max[k]);
        if !vlem_core::types::pose_is_finite(pose) || !inside {
            return Err(DatasetError::Synthetic {
                message: format!(
                    "cannot render from ({:.3}, {:.3}, {:.3}): the camera must be inside the room",
                    p.x, p.y, p.z
                ),
            });
        }
        self.render_view(index, pose)
    }

    /// Every class the generator can produce (the same table for every scene).
    pub fn labels(&self) -> &'static [LabelInfo] {
        SYNTHETIC_LABELS
    }

    /// Everything in this scene: the six room surfaces, then each piece in placement order.
    pub fn objects(&self) -> &[SceneObject] {
        &self.layout.objects
    }

    fn check_index(&self, index: usize) -> Result<()> {
        if index >= self.len() {
            return Err(DatasetError::Synthetic {
                message: format!(
                    "frame {index} requested but the scene has {} frames",
                    self.len()
                ),
            });
        }
        Ok(())
    }
}

/// Refuses values the generator cannot use, naming the key.
fn validate(config: &SyntheticConfig) -> Result<()> {
    let bad =
        |key: &'static str, message: String| Err(DatasetError::SyntheticConfig { key, message });
    if config.frames == 0 {
        return bad("frames", "must be at least 1, got 0".to_owned());
    }
    for (key, value) in [("width", config.width), ("height", config.height)] {
        if value == 0 || value > MAX_SIZE {
            return bad(
                key,
                format!("must be between 1 and {MAX_SIZE} pixels, got {value}"),
            );
        }
    }
    if !config
        .room
        .iter()
        .all(|s| s.is_finite() && (2.0..=100.0).contains(s))
    {
        let [x, y, z] = config.room;
        return bad(
            "room",
            format!("each size (x, y, height) must be between 2 and 100 m, got [{x}, {y}, {z}]"),
        );
    }
    if config.objects > MAX_OBJECTS {
        return bad(
            "objects",
            format!("must be at most {MAX_OBJECTS}, got {}", config.objects),
        );
    }
    Ok(())
}

/// A [`FrameSource`] that renders the synthetic scene on demand, honouring `[dataset] stride` and
/// `max_frames`. Frames carry the exact ground-truth pose.
#[derive(Clone, Debug)]
pub struct SyntheticReader {
    scene: SyntheticScene,
    stride: usize,
    len: usize,
}

impl SyntheticReader {
    /// The reader of `[dataset]` with `kind = "synthetic"`: generates the scene of
    /// `[dataset.synthetic]` (defaults when absent). No folder is involved; `path` is ignored.
    ///
    /// # Errors
    /// The errors of [`SyntheticScene::new`], [`DatasetError::Synthetic`] for `stride` or
    /// `max_frames` 0 and for `depth_scale`, which does not apply, and
    /// [`DatasetError::InvalidSettings`] for another reader's keys (`intrinsics`, `trajectory`, …).
    pub fn open(config: &DatasetConfig) -> Result<Self> {
        let settings: config::SyntheticSettings =
            crate::sequence::reader_settings(SYNTHETIC, config)?;
        let refuse = |key: &str| {
            Err(DatasetError::Synthetic {
                message: format!(
                    "[dataset] {key} does not apply to kind = \"synthetic\" (the scene fixes it); \
                     remove it"
                ),
            })
        };
        if config.depth_scale.is_some() {
            return refuse("depth_scale");
        }
        let stride = config.stride.unwrap_or(1);
        if stride == 0 {
            return Err(DatasetError::Synthetic {
                message: "[dataset] stride must be at least 1".to_owned(),
            });
        }
        if config.max_frames == Some(0) {
            return Err(DatasetError::Synthetic {
                message: "[dataset] max_frames must be at least 1 (leave it out to use every \
                          frame)"
                    .to_owned(),
            });
        }
        let scene = SyntheticScene::new(&settings.synthetic)?;
        let len = scene
            .len()
            .div_ceil(stride)
            .min(config.max_frames.unwrap_or(usize::MAX));
        Ok(Self { scene, stride, len })
    }

    /// A reader of every frame of `scene`.
    pub fn new(scene: SyntheticScene) -> Self {
        let len = scene.len();
        Self {
            scene,
            stride: 1,
            len,
        }
    }

    /// The scene (labels, objects, surface points).
    pub fn scene(&self) -> &SyntheticScene {
        &self.scene
    }

    /// The view behind frame `index` of this reader (frame `index * stride` of the scene), with
    /// its labels.
    ///
    /// # Errors
    /// [`DatasetError::Synthetic`] for an index past the end.
    pub fn view(&self, index: usize) -> Result<SyntheticView> {
        if index >= self.len {
            return Err(DatasetError::Synthetic {
                message: format!(
                    "frame {index} requested but the sequence has {} frames",
                    self.len
                ),
            });
        }
        self.scene.render(index * self.stride)
    }

    /// Renders frame `index` as a pipeline frame (timestamp: scene frame / 30 s).
    ///
    /// # Errors
    /// As [`SyntheticReader::view`].
    pub fn load(&self, index: usize) -> Result<Frame> {
        let view = self.view(index)?;
        let timestamp = view.index as f64 / SYNTHETIC_FRAME_RATE;
        view.into_frame(index, timestamp)
    }
}

impl FrameSource for SyntheticReader {
    fn describe(&self) -> String {
        self.scene.describe()
    }

    fn len(&self) -> usize {
        self.len
    }

    fn intrinsics(&self) -> Intrinsics {
        self.scene.intrinsics
    }

    fn has_poses(&self) -> bool {
        true
    }

    fn frame(&mut self, index: usize) -> vlem_core::Result<Frame> {
        Ok(self.load(index)?)
    }
}
