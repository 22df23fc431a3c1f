//! Whole evaluations, from files and configs to one report: a trajectory against its reference,
//! a map's 3D semantic segmentation and an encoder's 2D one.
//!
//! Why it exists: the `vlem eval` command, the study runner and the Python package all run these
//! evaluations and must report the same numbers under the same names. The metrics live in
//! [`crate::trajectory`] and [`crate::semseg`]; this module opens what they need (the config's
//! dataset, the map file, the encoder that embeds the class names), runs them, and gathers every
//! number into a serialisable report. Front-ends only print it or hand it on.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;
use vlem_core::{BuildContext, Config, Encoder, FrameSource, Registry};

use crate::error::{EvalError, Result};
use crate::semseg::{self, Class, ClassIndex, ClassList, ClassScore, SemsegScores, ThresholdSweep};
use crate::trajectory::{
    self, Association, AteStats, DEFAULT_MAX_TIME_DIFF, RpeStats, TrajectoryFormat,
};

/// How a trajectory is evaluated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrajectoryOptions {
    /// RPE frame step: pose pairs `(k, k + delta)` of the associated poses.
    pub delta: usize,
    /// Largest time difference, in seconds, between paired poses (frames, against a `.log`).
    pub max_time_diff: f64,
    /// Align with a similarity transform (rotation, translation and scale) for estimates of
    /// unknown scale; RPE is then computed on the estimate scaled by the same factor.
    pub scale: bool,
}

impl Default for TrajectoryOptions {
    fn default() -> Self {
        Self {
            delta: 1,
            max_time_diff: DEFAULT_MAX_TIME_DIFF,
            scale: false,
        }
    }
}

/// A trajectory file as a report names it.
#[derive(Clone, Debug, Serialize)]
pub struct TrajectoryFile {
    /// The file.
    pub path: PathBuf,
    /// Its format.
    pub format: TrajectoryFormat,
    /// Poses it holds.
    pub poses: usize,
}

/// Everything a trajectory evaluation measures (`vlem eval trajectory --json`).
#[derive(Clone, Debug, Serialize)]
pub struct TrajectoryReport {
    /// The estimate.
    pub estimate: TrajectoryFile,
    /// The reference.
    pub reference: TrajectoryFile,
    /// How poses were paired.
    pub association: Association,
    /// Number of associated pose pairs.
    pub associated: usize,
    /// Absolute trajectory error after the alignment.
    pub ate: AteStats,
    /// Relative pose error.
    pub rpe: RpeStats,
}

/// ATE and RPE of the trajectory file `estimate` against `reference` (TUM or `.log` each; the
/// reference may also be a dataset folder, whose trajectory file is found as its reader finds it,
/// [`vlem_datasets::trajectory_file`]).
///
/// # Errors
/// A file that cannot be read, a folder without one trajectory file, too few associated poses,
/// degenerate input.
pub fn evaluate_trajectory(
    estimate: &Path,
    reference: &Path,
    options: &TrajectoryOptions,
) -> Result<TrajectoryReport> {
    let reference = if reference.is_dir() {
        vlem_datasets::trajectory_file(reference)?
    } else {
        reference.to_path_buf()
    };
    let estimate = trajectory::read_trajectory(estimate, "estimate")?;
    let reference = trajectory::read_trajectory(&reference, "reference")?;
    let association = trajectory::associate(&estimate, &reference, options.max_time_diff)?;
    let (estimated, true_poses) = association.poses(&estimate, &reference);
    let ate = trajectory::ate(&estimated, &true_poses, options.scale)?;
    // RPE has no alignment; with `scale` the estimate's distances get the fitted scale first.
    let scaled: Vec<vlem_core::Pose> = estimated
        .iter()
        .map(|p| {
            let mut p = *p;
            p.translation.vector *= ate.alignment.scale;
            p
        })
        .collect();
    let rpe = trajectory::rpe(&scaled, &true_poses, options.delta)?;
    let file = |t: &trajectory::Trajectory| TrajectoryFile {
        path: t.path.clone(),
        format: t.format,
        poses: t.len(),
    };
    Ok(TrajectoryReport {
        estimate: file(&estimate),
        reference: file(&reference),
        associated: association.len(),
        association,
        ate,
        rpe,
    })
}

/// The 3D protocols.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// The paper's: nearest map point within 5 cm, IoU averaged over similarity thresholds.
    #[default]
    Vlem,
    /// RayFronts': argmax over class prompts, voxels, k-nearest-neighbour votes.
    Rayfronts,
}

impl Protocol {
    /// The protocol named `text` (`vlem`, `rayfronts`).
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] listing the names.
    pub fn parse(text: &str) -> Result<Self> {
        match text {
            "vlem" => Ok(Self::Vlem),
            "rayfronts" => Ok(Self::Rayfronts),
            _ => Err(EvalError::InvalidParameter {
                name: "protocol".into(),
                value: text.into(),
                reason: "expected `vlem` or `rayfronts`".into(),
            }),
        }
    }

    /// The protocol's name.
    pub fn label(self) -> &'static str {
        match self {
            Self::Vlem => "vlem",
            Self::Rayfronts => "rayfronts",
        }
    }
}

/// What both semantic segmentation evaluations start from: a config (its dataset is the ground
/// truth, its encoder embeds the class names) and the class list.
pub struct SemsegInput {
    /// The pipeline configuration.
    pub config: Config,
    /// Where its relative paths point.
    pub ctx: BuildContext,
    /// How messages name the config (its file, or "the config").
    pub config_name: String,
    /// Dataset folder, overriding `[dataset] path`.
    pub dataset: Option<PathBuf>,
    /// At most this many frames of the dataset (after its stride), as a run would use.
    pub max_frames: Option<usize>,
    /// The class list.
    pub classes: ClassList,
    /// Texts to query instead of class names (any NYU40 name; see [`read_prompts`]).
    pub prompts: BTreeMap<String, String>,
}

impl SemsegInput {
    /// The input for the config file at `path`, NYU40 classes queried by name.
    ///
    /// # Errors
    /// The config cannot be read or parsed.
    pub fn from_config_file(path: &Path) -> Result<Self> {
        let (config, ctx) = vlem_core::load_config(path)?;
        Ok(Self {
            config,
            ctx,
            config_name: path.display().to_string(),
            dataset: None,
            max_frames: None,
            classes: ClassList::Nyu40,
            prompts: BTreeMap::new(),
        })
    }
}

/// The prompts file at `path`: a JSON object mapping class names to the texts to query instead
/// (e.g. `{"wall": "white"}`).
///
/// # Errors
/// [`EvalError::Prompts`]: unreadable, not such an object, or a key that is no NYU40 class (the
/// message lists them).
pub fn read_prompts(path: &Path) -> Result<BTreeMap<String, String>> {
    let bad = |reason: String| EvalError::Prompts {
        path: path.to_path_buf(),
        reason,
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read it: {e}")))?;
    let prompts: BTreeMap<String, String> = serde_json::from_str(&text).map_err(|e| {
        bad(format!(
            "expected a JSON object of class names to texts, e.g. {{\"wall\": \"white\"}} ({e})"
        ))
    })?;
    check_prompts(&prompts).map_err(bad)?;
    Ok(prompts)
}

/// One prompts table serves every class list: any NYU40 name is accepted, nothing else.
fn check_prompts(prompts: &BTreeMap<String, String>) -> std::result::Result<(), String> {
    let all = ClassList::Nyu40.all();
    match prompts.keys().find(|k| !all.iter().any(|c| c.name == **k)) {
        Some(unknown) => {
            let names: Vec<&str> = all.iter().map(|c| c.name.as_str()).collect();
            Err(format!(
                "\"{unknown}\" is not an NYU40 class; they are: {}",
                names.join(", ")
            ))
        }
        None => Ok(()),
    }
}

/// Options of the 3D evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Semseg3dOptions {
    /// The protocol.
    pub protocol: Protocol,
    /// Build the ground truth from every n-th frame.
    pub stride: usize,
    /// Ground-truth voxel size in metres (default 0.02 for `vlem`; for `rayfronts` also the
    /// prediction voxel size, default 0.05).
    pub voxel_size: Option<f64>,
    /// `vlem` protocol: association radius in metres.
    pub radius: f32,
    /// `rayfronts` protocol: predicted voxels voting per ground-truth voxel.
    pub k: usize,
}

impl Default for Semseg3dOptions {
    fn default() -> Self {
        Self {
            protocol: Protocol::Vlem,
            stride: 1,
            voxel_size: None,
            radius: semseg::vlem::DEFAULT_ASSOCIATION_RADIUS,
            k: 5,
        }
    }
}

/// Options of the 2D evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Semseg2dOptions {
    /// Evaluate every n-th frame.
    pub stride: usize,
}

impl Default for Semseg2dOptions {
    fn default() -> Self {
        Self { stride: 30 }
    }
}

/// Everything a semantic segmentation evaluation measures (`vlem eval semseg3d|semseg2d --json`).
/// Fields of the other dimension or protocol are absent.
#[derive(Clone, Debug, Serialize)]
pub struct SemsegReport {
    /// `vlem` or `rayfronts`.
    pub protocol: Protocol,
    /// The class list's name.
    pub classes: &'static str,
    /// Mean IoU over the classes present in the ground truth.
    pub miou: Option<f64>,
    /// Each evaluated class's IoU by name (`None`: absent from the ground truth).
    pub per_class: BTreeMap<String, Option<f64>>,
    /// Classes present in the ground truth (the mIoU's denominator).
    pub evaluated_classes: usize,
    /// Each evaluated class's id, name, IoU and support, in class-list order.
    pub class_details: Vec<ClassScore>,
    /// Frequency-weighted mIoU (RayFronts).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fmiou: Option<f64>,
    /// Accuracy (RayFronts).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accuracy: Option<f64>,
    /// Association radius, metres (3D, `vlem`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius: Option<f32>,
    /// Similarity thresholds averaged over (`vlem`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thresholds: Option<usize>,
    /// Ground-truth points with a map point within the radius (3D, `vlem`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub associated_gt_points: Option<usize>,
    /// The protocol's parameters (3D, `rayfronts`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub params: Option<semseg::rayfronts::RayFrontsParams>,
    /// Classes prompt denoising dropped (3D, `rayfronts`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub denoised_classes: Option<Vec<String>>,
    /// Ground-truth voxel size, metres (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub voxel_size: Option<f64>,
    /// Ground-truth points (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gt_points: Option<usize>,
    /// Frames the ground truth was built from (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gt_frames: Option<usize>,
    /// The map file (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map: Option<PathBuf>,
    /// The map's kind (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_kind: Option<String>,
    /// Points in the map (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_points: Option<usize>,
    /// The map's embedding dimension (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_dim: Option<usize>,
    /// What the map file holds per point, summed: position, colour and embedding (3D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_bytes: Option<usize>,
    /// Labelled pixels evaluated (2D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gt_pixels: Option<u64>,
    /// Frames evaluated (2D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<usize>,
    /// Every n-th frame evaluated (2D).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stride: Option<usize>,
    /// The encoder that embedded the class names.
    pub encoder: String,
    /// The dataset as its reader describes it.
    pub dataset: String,
    /// Peak resident memory of the process at the end (Linux).
    pub peak_resident_bytes: Option<u64>,
    /// Wall-clock seconds of the evaluation.
    pub seconds: f64,
    /// Dataset classes that are no NYU40 class and were ignored: `(id, name)`.
    pub ignored_dataset_classes: Vec<(u16, String)>,
    /// The scores as the metrics computed them (what the per-class fields above are made of).
    #[serde(skip)]
    pub scores: SemsegScores,
    /// A one-line description of what was evaluated, for a printed table's title.
    #[serde(skip)]
    pub title: String,
}

impl SemsegReport {
    fn new(
        protocol: Protocol,
        classes: ClassList,
        scores: SemsegScores,
        title: String,
        encoder: &str,
        dataset: String,
    ) -> Self {
        Self {
            protocol,
            classes: classes.label(),
            miou: scores.miou,
            per_class: scores
                .classes
                .iter()
                .map(|c| (c.name.clone(), c.iou))
                .collect(),
            evaluated_classes: scores.evaluated_classes(),
            class_details: scores.classes.clone(),
            fmiou: scores.fmiou,
            accuracy: scores.accuracy,
            radius: None,
            thresholds: None,
            associated_gt_points: None,
            params: None,
            denoised_classes: None,
            voxel_size: None,
            gt_points: None,
            gt_frames: None,
            map: None,
            map_kind: None,
            map_points: None,
            map_dim: None,
            map_bytes: None,
            gt_pixels: None,
            frames: None,
            stride: None,
            encoder: encoder.to_owned(),
            dataset,
            peak_resident_bytes: None,
            seconds: 0.0,
            ignored_dataset_classes: Vec::new(),
            scores,
            title,
        }
    }

    fn finish(mut self, start: Instant) -> Self {
        self.peak_resident_bytes = vlem_core::files::peak_resident_bytes();
        self.seconds = start.elapsed().as_secs_f64();
        self
    }
}

/// The config's dataset opened with the input's overrides, refused when it has no labels.
fn open_labelled(input: &SemsegInput) -> Result<Box<dyn FrameSource>> {
    let mut dataset_config = input.config.dataset.clone();
    if input.max_frames.is_some() {
        dataset_config.max_frames = input.max_frames;
    }
    let dir = vlem_datasets::dataset_folder(&input.config, &input.ctx, input.dataset.as_deref())?;
    let mut source =
        vlem_datasets::open(&dataset_config, &dir).map_err(|e| input.config.locate(e))?;
    if source.is_empty() {
        return Err(EvalError::Setup {
            message: format!("{} has no frames", source.describe()),
        });
    }
    // Refuse an unlabelled dataset before anything long runs.
    if source.frame(0)?.labels.is_none() {
        return Err(EvalError::MissingLabels {
            dataset: source.describe(),
        });
    }
    Ok(source)
}

/// The evaluated classes and the text embedding of each (its name, or its prompt).
fn class_texts(input: &SemsegInput, encoder: &dyn Encoder) -> Result<(Vec<Class>, Vec<Vec<f32>>)> {
    check_prompts(&input.prompts).map_err(|reason| EvalError::Prompts {
        path: PathBuf::from("(prompts)"),
        reason,
    })?;
    let classes = input.classes.evaluated();
    let texts = classes
        .iter()
        .map(|c| {
            let text = input.prompts.get(&c.name).unwrap_or(&c.name);
            encoder
                .encode_text(text)
                .map_err(|source| EvalError::ClassText {
                    class: c.name.clone(),
                    text: text.clone(),
                    encoder: encoder.name().to_owned(),
                    source: Box::new(source),
                })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((classes, texts))
}

/// "frame", "2nd frame", "30th frame": how a stride reads in a sentence.
pub fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    if n == 1 {
        "frame".into()
    } else {
        format!("{n}{suffix} frame")
    }
}

/// 3D semantic segmentation of the map file `map` against the labelled ground truth of the
/// input's dataset: every `stride`-th frame's labelled pixels back-projected with its pose and
/// merged per voxel. `note` hears what is about to take long and what was ignored.
///
/// # Errors
/// An unlabelled dataset, an unreadable map, no encoder for the class names (neither the config
/// nor the map names one), an encoder of another dimension than the map's, an unembeddable class.
pub fn semseg3d(
    input: &SemsegInput,
    map: &Path,
    options: &Semseg3dOptions,
    note: &(dyn Fn(&str) + Sync),
) -> Result<SemsegReport> {
    let start = Instant::now();
    let mut source = open_labelled(input)?;
    let snapshot = vlem_core::read_map_file(map)?;
    let encoder = match (&input.config.encoder, &snapshot.metadata.encoder) {
        (Some(stage), _) => Registry::global()?
            .build_encoder(stage, &input.ctx)
            .map_err(|e| input.config.locate(e))?,
        (None, Some(_)) => {
            vlem_query::answer::encoder_for_map(&snapshot.metadata, &map.display().to_string())?
        }
        (None, None) => {
            return Err(EvalError::Setup {
                message: format!(
                    "neither {} nor {} names an encoder: the class names cannot be embedded",
                    input.config_name,
                    map.display()
                ),
            });
        }
    };
    if snapshot.dim != encoder.dim() {
        return Err(EvalError::Setup {
            message: format!(
                "{} holds {}-d embeddings but the encoder `{}` makes {}-d ones",
                map.display(),
                snapshot.dim,
                encoder.name(),
                encoder.dim()
            ),
        });
    }
    let (classes, texts) = class_texts(input, encoder.as_ref())?;
    let voxel_size = options.voxel_size.unwrap_or(match options.protocol {
        Protocol::Vlem => semseg::ground_truth::DEFAULT_GT_VOXEL_SIZE,
        Protocol::Rayfronts => semseg::rayfronts::RayFrontsParams::default().voxel_size,
    });
    let dataset = source.describe();
    note(&format!(
        "ground truth from every {} of {} frames of {dataset} ({voxel_size} m voxels)",
        ordinal(options.stride),
        source.len()
    ));
    let (gt, ignored) =
        semseg::ground_truth::from_source(source.as_mut(), options.stride, voxel_size, |_, _| {})?;
    for (id, name) in &ignored {
        note(&format!(
            "dataset class {id} \"{name}\" is no NYU40 class: ignored"
        ));
    }
    let list = input.classes;
    let title = |name: &str| {
        format!(
            "semseg3d, {name}, {}: {} ground-truth points, {} map points",
            list.label(),
            gt.len(),
            snapshot.len()
        )
    };
    let mut report = match options.protocol {
        Protocol::Vlem => {
            let steps = semseg::sweep::DEFAULT_THRESHOLD_STEPS;
            let (scores, associated) = semseg::vlem::evaluate(
                &gt.positions,
                &gt.labels,
                &snapshot.positions,
                &snapshot.embeddings,
                snapshot.dim,
                &classes,
                &texts,
                options.radius,
                steps,
            )?;
            let mut report = SemsegReport::new(
                Protocol::Vlem,
                list,
                scores,
                title("vlem protocol (IoU averaged over thresholds 0.00..=1.00)"),
                encoder.name(),
                dataset,
            );
            report.radius = Some(options.radius);
            report.thresholds = Some(steps + 1);
            report.associated_gt_points = Some(associated);
            report
        }
        Protocol::Rayfronts => {
            let params = semseg::rayfronts::RayFrontsParams {
                voxel_size,
                k: options.k,
                ..Default::default()
            };
            let (scores, kept) = semseg::rayfronts::evaluate(
                &gt.positions,
                &gt.labels,
                &snapshot.positions,
                &snapshot.embeddings,
                snapshot.dim,
                &classes,
                &texts,
                &params,
            )?;
            let dropped = classes
                .iter()
                .zip(&kept)
                .filter(|(_, k)| !**k)
                .map(|(c, _)| c.name.clone())
                .collect();
            let mut report = SemsegReport::new(
                Protocol::Rayfronts,
                list,
                scores,
                title("rayfronts protocol (argmax over prompts, k-NN votes)"),
                encoder.name(),
                dataset,
            );
            report.params = Some(params);
            report.denoised_classes = Some(dropped);
            report
        }
    };
    report.voxel_size = Some(voxel_size);
    report.gt_points = Some(gt.len());
    report.gt_frames = Some(gt.views);
    report.map = Some(map.to_path_buf());
    report.map_kind = Some(snapshot.map_kind.clone());
    report.map_points = Some(snapshot.len());
    report.map_dim = Some(snapshot.dim);
    report.map_bytes = Some(snapshot.len() * (12 + 3 + 4 * snapshot.dim));
    report.ignored_dataset_classes = ignored;
    Ok(report.finish(start))
}

/// 2D semantic segmentation: the input's encoder on every `stride`-th frame against its label
/// image, the class names as queries, each class's IoU averaged over the thresholds 0.00, 0.01,
/// …, 1.00 and accumulated over the frames (the paper's 2D tables).
///
/// # Errors
/// An unlabelled dataset, a config without an encoder (or without the proposer a region encoder
/// needs), an unembeddable class, an encoder failing on a frame.
pub fn semseg2d(
    input: &SemsegInput,
    options: &Semseg2dOptions,
    note: &(dyn Fn(&str) + Sync),
) -> Result<SemsegReport> {
    let start = Instant::now();
    if options.stride == 0 {
        return Err(EvalError::InvalidParameter {
            name: "stride".into(),
            value: "0".into(),
            reason: "must be at least 1".into(),
        });
    }
    let mut source = open_labelled(input)?;
    let Some(stage) = &input.config.encoder else {
        return Err(EvalError::Setup {
            message: format!(
                "{} has no [encoder]: semseg2d evaluates an encoder",
                input.config_name
            ),
        });
    };
    let registry = Registry::global()?;
    let located = |e| input.config.locate(e);
    let encoder = registry.build_encoder(stage, &input.ctx).map_err(located)?;
    let proposer = match &input.config.proposer {
        Some(stage) if encoder.needs_regions() => Some(
            registry
                .build_proposer(stage, &input.ctx)
                .map_err(located)?,
        ),
        None if encoder.needs_regions() => {
            return Err(EvalError::Setup {
                message: format!(
                    "encoder `{}` embeds regions: {} needs a [proposer]",
                    encoder.name(),
                    input.config_name
                ),
            });
        }
        _ => None,
    };
    let (classes, texts) = class_texts(input, encoder.as_ref())?;
    let index = ClassIndex::new(&classes);
    let mut sweep = ThresholdSweep::new(classes.len(), semseg::sweep::DEFAULT_THRESHOLD_STEPS)?;
    let dataset = source.describe();
    let mut remap = None;
    let (mut pixels, mut frames) = (0u64, 0usize);
    let total = source.len();
    note(&format!(
        "encoder `{}` on every {} of {total} frames of {dataset}",
        encoder.name(),
        ordinal(options.stride)
    ));
    for i in (0..total).step_by(options.stride) {
        let frame = source.frame(i)?;
        let ids = semseg::ground_truth::nyu40_labels(&frame, &mut remap, &dataset)?;
        let regions = match &proposer {
            Some(p) => p.propose(&frame.colour)?,
            None => Vec::new(),
        };
        let embeddings =
            encoder
                .encode_frame(&frame, &regions)
                .map_err(|source| EvalError::Encode {
                    encoder: encoder.name().to_owned(),
                    frame: i,
                    source: Box::new(source),
                })?;
        let (w, h) = (frame.intrinsics.width, frame.intrinsics.height);
        pixels += semseg::image::add_image(&mut sweep, &ids, w, h, &embeddings, &texts, &index)?;
        frames += 1;
    }
    let scores = SemsegScores::from_sweep(&sweep, &classes);
    let list = input.classes;
    let title = format!(
        "semseg2d, {}: {frames} frames, {pixels} labelled pixels (IoU averaged over thresholds 0.00..=1.00)",
        list.label()
    );
    let mut report =
        SemsegReport::new(Protocol::Vlem, list, scores, title, encoder.name(), dataset);
    report.gt_pixels = Some(pixels);
    report.frames = Some(frames);
    report.stride = Some(options.stride);
    report.thresholds = Some(semseg::sweep::DEFAULT_THRESHOLD_STEPS + 1);
    Ok(report.finish(start))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn ordinals_read_as_english() {
        assert_eq!(ordinal(1), "frame");
        assert_eq!(ordinal(2), "2nd frame");
        assert_eq!(ordinal(11), "11th frame");
        assert_eq!(ordinal(23), "23rd frame");
        assert_eq!(ordinal(30), "30th frame");
    }

    #[test]
    fn protocols_parse_by_name() {
        assert_eq!(Protocol::parse("rayfronts").unwrap(), Protocol::Rayfronts);
        let err = Protocol::parse("paper").unwrap_err().to_string();
        assert!(err.contains("vlem") && err.contains("rayfronts"), "{err}");
    }

    #[test]
    fn prompts_accept_nyu40_names_only() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("prompts.json");
        std::fs::write(&path, r#"{"wall": "white"}"#).unwrap();
        assert_eq!(read_prompts(&path).unwrap()["wall"], "white");
        std::fs::write(&path, r#"{"wal": "white"}"#).unwrap();
        let err = read_prompts(&path).unwrap_err().to_string();
        assert!(
            err.contains("\"wal\" is not an NYU40 class") && err.contains("wall"),
            "{err}"
        );
        std::fs::write(&path, "[1]").unwrap();
        let err = read_prompts(&path).unwrap_err().to_string();
        assert!(err.contains("expected a JSON object"), "{err}");
    }
}
