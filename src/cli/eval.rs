//! `vlem eval`: measure a run against a reference: `trajectory` (ATE and RPE), `semseg3d` (a map
//! against labelled ground truth, under the paper's or RayFronts' protocol) and `semseg2d` (an
//! encoder's pixel embeddings against label images).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use vlem_core::{BuildContext, Config, Encoder, FrameSource, Registry};
use vlem_eval::semseg::{self, Class, ClassIndex, ClassList, SemsegScores, ThresholdSweep};
use vlem_eval::trajectory::{
    self, Association, AssociationMode, AteStats, DEFAULT_MAX_TIME_DIFF, ErrorStats, RpeStats,
    Trajectory,
};

use crate::output;

/// The evaluations `vlem eval` runs.
#[derive(Subcommand)]
pub enum EvalCommand {
    /// Trajectory accuracy: ATE (after a least-squares alignment) and RPE of an estimate (e.g.
    /// OUT/trajectory.tum of `vlem run`) against a reference (TUM or .log).
    ///
    /// Poses are paired by timestamp (nearest within --max-time-diff, one to one) when both files
    /// are TUM; when either is a .log, which has no timestamps, its frames are stamped 0, 1, 2, …
    /// and a TUM pose stamped t pairs with frame round(t) (within --max-time-diff), which is how
    /// `vlem run` stamps frames of datasets without timestamps.
    Trajectory(TrajectoryArgs),
    /// 3D semantic segmentation of a map (OUT/map.vlem of `vlem run`) against the labelled
    /// ground truth of the config's dataset: every --stride-th frame's labelled pixels
    /// back-projected with its pose and merged per voxel.
    ///
    /// `--protocol vlem` (the paper): each ground-truth point takes the similarity of its nearest
    /// map point within --radius (none: predicted negative), and each class's IoU is averaged
    /// over the thresholds 0.00, 0.01, …, 1.00. `--protocol rayfronts`: softmax(100·cos) over
    /// the class prompts, prompt denoising (0.5), no label below 0.1, 5 cm voxels, k = 5 nearest
    /// predicted voxels vote; IoU, f-mIoU and accuracy. Class names are the text queries
    /// (--prompts replaces them); `other*` classes and classes absent from the ground truth are
    /// not averaged.
    Semseg3d(Semseg3dArgs),
    /// 2D semantic segmentation: the config's encoder on every --stride-th frame against its
    /// label image, the class names as queries, each class's IoU averaged over the thresholds
    /// 0.00, 0.01, …, 1.00 and accumulated over the frames (the paper's 2D tables).
    Semseg2d(Semseg2dArgs),
}

/// The 3D protocols.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Protocol {
    /// The paper's: nearest map point within 5 cm, IoU averaged over similarity thresholds.
    Vlem,
    /// RayFronts': argmax over class prompts, voxels, k-nearest-neighbour votes.
    Rayfronts,
}

/// The class lists.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Classes {
    /// NYU40 (37 classes evaluated: not the `other*` ones).
    Nyu40,
    /// The ScanNet benchmark's 20 (19 evaluated: not `otherfurniture`).
    Scannet20,
}

impl Classes {
    fn list(self) -> ClassList {
        match self {
            Self::Nyu40 => ClassList::Nyu40,
            Self::Scannet20 => ClassList::Scannet20,
        }
    }
}

/// Options both semantic segmentation evaluations share.
#[derive(Args)]
pub struct SemsegCommon {
    /// Pipeline configuration (TOML): its dataset is the ground truth, its encoder (or else the
    /// map's) embeds the class names.
    #[arg(long)]
    config: PathBuf,
    /// Dataset folder (overrides `[dataset] path`).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Use at most this many frames of the dataset (after its stride), as `vlem run`.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Class list.
    #[arg(long, value_enum, default_value = "nyu40")]
    classes: Classes,
    /// JSON object mapping class names to the texts to query instead (e.g. {"wall": "white"});
    /// classes not listed are queried by name.
    #[arg(long)]
    prompts: Option<PathBuf>,
    /// Write the results as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Options of `vlem eval semseg3d`.
#[derive(Args)]
pub struct Semseg3dArgs {
    /// Map file written by `vlem run`.
    #[arg(long)]
    map: PathBuf,
    #[command(flatten)]
    common: SemsegCommon,
    /// Evaluation protocol.
    #[arg(long, value_enum, default_value = "vlem")]
    protocol: Protocol,
    /// Build the ground truth from every n-th frame.
    #[arg(long, default_value_t = 1)]
    stride: usize,
    /// Ground-truth voxel size in metres (default 0.02 for `vlem`; for `rayfronts` also the
    /// prediction voxel size, default 0.05).
    #[arg(long)]
    voxel_size: Option<f64>,
    /// `vlem` protocol: association radius in metres.
    #[arg(long, default_value_t = semseg::vlem::DEFAULT_ASSOCIATION_RADIUS)]
    radius: f32,
    /// `rayfronts` protocol: predicted voxels voting per ground-truth voxel.
    #[arg(long, default_value_t = 5)]
    k: usize,
}

/// Options of `vlem eval semseg2d`.
#[derive(Args)]
pub struct Semseg2dArgs {
    #[command(flatten)]
    common: SemsegCommon,
    /// Evaluate every n-th frame.
    #[arg(long, default_value_t = 30)]
    stride: usize,
}

/// Options of `vlem eval trajectory`.
#[derive(Args)]
pub struct TrajectoryArgs {
    /// The estimated trajectory (TUM or .log).
    #[arg(long)]
    estimate: PathBuf,
    /// The reference ("ground truth") trajectory (TUM or .log).
    #[arg(long)]
    reference: PathBuf,
    /// RPE frame step: pose pairs (k, k + delta) of the associated poses.
    #[arg(long, default_value_t = 1)]
    delta: usize,
    /// Largest time difference, in seconds, between paired poses (frames, against a .log).
    #[arg(long, default_value_t = DEFAULT_MAX_TIME_DIFF)]
    max_time_diff: f64,
    /// Align with a similarity transform (rotation, translation and scale) for estimates of
    /// unknown scale; RPE is then computed on the estimate scaled by the same factor.
    #[arg(long)]
    scale: bool,
    /// Also write every number as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Runs one `vlem eval` subcommand.
pub fn execute(command: EvalCommand) -> Result<()> {
    match command {
        EvalCommand::Trajectory(args) => evaluate_trajectory(&args),
        EvalCommand::Semseg3d(args) => evaluate_semseg3d(&args),
        EvalCommand::Semseg2d(args) => evaluate_semseg2d(&args),
    }
}

/// A trajectory file as the JSON report names it.
#[derive(serde::Serialize)]
struct FileReport<'a> {
    path: &'a Path,
    format: trajectory::TrajectoryFormat,
    poses: usize,
}

impl<'a> FileReport<'a> {
    fn new(t: &'a Trajectory) -> Self {
        Self {
            path: &t.path,
            format: t.format,
            poses: t.len(),
        }
    }
}

/// Everything `vlem eval trajectory --json` writes.
#[derive(serde::Serialize)]
struct TrajectoryReport<'a> {
    estimate: FileReport<'a>,
    reference: FileReport<'a>,
    association: &'a Association,
    /// Number of associated pose pairs.
    associated: usize,
    ate: &'a AteStats,
    rpe: &'a RpeStats,
}

fn evaluate_trajectory(args: &TrajectoryArgs) -> Result<()> {
    let estimate = trajectory::read_trajectory(&args.estimate, "estimate")?;
    let reference = trajectory::read_trajectory(&args.reference, "reference")?;
    let association = trajectory::associate(&estimate, &reference, args.max_time_diff)?;
    let (estimated, true_poses) = association.poses(&estimate, &reference);
    let ate = trajectory::ate(&estimated, &true_poses, args.scale)?;
    // RPE has no alignment; with --scale the estimate's distances get the fitted scale first.
    let scaled: Vec<vlem_core::Pose> = estimated
        .iter()
        .map(|p| {
            let mut p = *p;
            p.translation.vector *= ate.alignment.scale;
            p
        })
        .collect();
    let rpe = trajectory::rpe(&scaled, &true_poses, args.delta)?;

    print_report(&estimate, &reference, &association, &ate, &rpe);
    if let Some(path) = &args.json {
        let report = TrajectoryReport {
            estimate: FileReport::new(&estimate),
            reference: FileReport::new(&reference),
            association: &association,
            associated: association.len(),
            ate: &ate,
            rpe: &rpe,
        };
        let text = serde_json::to_string_pretty(&report).context("cannot encode the report")?;
        output::write_atomically(path, format!("{text}\n").as_bytes())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn print_report(
    estimate: &Trajectory,
    reference: &Trajectory,
    association: &Association,
    ate: &AteStats,
    rpe: &RpeStats,
) {
    println!(
        "estimate  {} ({}, {} poses)",
        estimate.path.display(),
        estimate.format.label(),
        estimate.len()
    );
    println!(
        "reference {} ({}, {} poses)",
        reference.path.display(),
        reference.format.label(),
        reference.len()
    );
    println!(
        "associated {} pose pairs {} (max difference {} {})",
        association.len(),
        association.mode.describe(),
        association.max_time_diff,
        match association.mode {
            AssociationMode::Timestamp => "s",
            AssociationMode::FrameIndex => "frames",
        }
    );
    let a = &ate.alignment;
    let t = a.translation;
    println!(
        "alignment ({}): rotation {:.4}°, translation ({:.4}, {:.4}, {:.4}) m, scale {:.6}",
        if ate.with_scale {
            "similarity"
        } else {
            "rigid"
        },
        a.rotation.angle().to_degrees(),
        t.x,
        t.y,
        t.z,
        a.scale
    );
    println!();
    println!(
        "{:<22} {:>6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "metric", "n", "rmse", "mean", "median", "std", "min", "max"
    );
    let d = rpe.delta;
    let rows = [
        ("ATE (m)".to_owned(), &ate.position),
        (format!("RPE trans (m/{d}f)"), &rpe.translation),
        (format!("RPE rot (deg/{d}f)"), &rpe.rotation),
    ];
    for (name, s) in rows {
        print_row(&name, s);
    }
}

fn print_row(name: &str, s: &ErrorStats) {
    println!(
        "{name:<22} {:>6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6}",
        s.count, s.rmse, s.mean, s.median, s.std, s.min, s.max
    );
}

/// The config, its folder, and its dataset opened (with the command line's overrides).
struct Opened {
    config: Config,
    config_dir: PathBuf,
    source: Box<dyn FrameSource>,
}

fn open_dataset(common: &SemsegCommon) -> Result<Opened> {
    let path = &common.config;
    let (mut config, ctx) = vlem_core::load_config(path)?;
    let dataset_dir = vlem_datasets::dataset_folder(&config, &ctx, common.dataset.as_deref())?;
    let config_dir = ctx.config_dir;
    if common.max_frames.is_some() {
        config.dataset.max_frames = common.max_frames;
    }
    let mut source = vlem_datasets::open(&config.dataset, &dataset_dir)?;
    if source.is_empty() {
        bail!("{} has no frames", source.describe());
    }
    // Refuse an unlabelled dataset before anything long runs.
    if source.frame(0)?.labels.is_none() {
        return Err(vlem_eval::EvalError::MissingLabels {
            dataset: source.describe(),
        }
        .into());
    }
    Ok(Opened {
        config,
        config_dir,
        source,
    })
}

/// The evaluated classes and the text embedding of each (its name, or its --prompts text).
fn class_texts(
    common: &SemsegCommon,
    encoder: &dyn Encoder,
) -> Result<(Vec<Class>, Vec<Vec<f32>>)> {
    let classes = common.classes.list().evaluated();
    let mut prompts: std::collections::BTreeMap<String, String> = Default::default();
    if let Some(path) = &common.prompts {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read prompts {}", path.display()))?;
        prompts = serde_json::from_str(&text).with_context(|| {
            format!(
                "prompts {}: expected a JSON object of class names to texts, e.g. {{\"wall\": \"white\"}}",
                path.display()
            )
        })?;
        // One prompts file serves every class list: any NYU40 name is accepted.
        let all = ClassList::Nyu40.all();
        if let Some(unknown) = prompts.keys().find(|k| !all.iter().any(|c| c.name == **k)) {
            let names: Vec<&str> = all.iter().map(|c| c.name.as_str()).collect();
            bail!(
                "prompts {}: \"{unknown}\" is not an NYU40 class; they are: {}",
                path.display(),
                names.join(", ")
            );
        }
    }
    let texts = classes
        .iter()
        .map(|c| {
            let text = prompts.get(&c.name).unwrap_or(&c.name);
            encoder.encode_text(text).with_context(|| {
                format!(
                    "cannot embed the class \"{}\" (query \"{text}\") with encoder `{}`; give a text \
                     the encoder knows with --prompts FILE (a JSON object such as {{\"{}\": \"white\"}})",
                    c.name,
                    encoder.name(),
                    c.name
                )
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((classes, texts))
}

/// Prints the per-class table and the means.
fn print_scores(title: &str, scores: &SemsegScores) {
    println!("{title}");
    println!("{:<16} {:>7} {:>10}", "class", "IoU", "support");
    for c in scores.classes.iter().filter(|c| c.iou.is_some()) {
        println!(
            "{:<16} {:>7.4} {:>10}",
            c.name,
            c.iou.unwrap_or(f64::NAN),
            c.support
        );
    }
    let absent = scores.classes.len() - scores.evaluated_classes();
    let fmt = |x: Option<f64>| x.map_or("n/a".to_owned(), |x| format!("{x:.4}"));
    println!(
        "mIoU {} over {} classes present in the ground truth ({absent} absent)",
        fmt(scores.miou),
        scores.evaluated_classes()
    );
    if scores.fmiou.is_some() || scores.accuracy.is_some() {
        println!(
            "f-mIoU {}, accuracy {}",
            fmt(scores.fmiou),
            fmt(scores.accuracy)
        );
    }
}

/// The report keys every semantic segmentation evaluation writes.
fn scores_json(
    scores: &SemsegScores,
    classes: ClassList,
) -> serde_json::Map<String, serde_json::Value> {
    let per_class: serde_json::Map<String, serde_json::Value> = scores
        .classes
        .iter()
        .map(|c| (c.name.clone(), serde_json::json!(c.iou)))
        .collect();
    let mut m = serde_json::Map::new();
    m.insert("classes".into(), serde_json::json!(classes.label()));
    m.insert("miou".into(), serde_json::json!(scores.miou));
    m.insert("per_class".into(), serde_json::Value::Object(per_class));
    m.insert(
        "evaluated_classes".into(),
        serde_json::json!(scores.evaluated_classes()),
    );
    m.insert("class_details".into(), serde_json::json!(scores.classes));
    m
}

/// Adds what every semseg report ends with (encoder, dataset, peak memory, seconds) and writes it
/// where `--json` says.
fn finish_report(
    mut report: serde_json::Map<String, serde_json::Value>,
    encoder: &str,
    dataset: &str,
    start: Instant,
    json: Option<&Path>,
) -> Result<()> {
    report.insert("encoder".into(), serde_json::json!(encoder));
    report.insert("dataset".into(), serde_json::json!(dataset));
    report.insert(
        "peak_resident_bytes".into(),
        serde_json::json!(output::peak_resident_bytes()),
    );
    report.insert(
        "seconds".into(),
        serde_json::json!(start.elapsed().as_secs_f64()),
    );
    match json {
        Some(path) => write_json(path, report),
        None => Ok(()),
    }
}

fn write_json(path: &Path, report: serde_json::Map<String, serde_json::Value>) -> Result<()> {
    let text = serde_json::to_string_pretty(&serde_json::Value::Object(report))
        .context("cannot encode the report")?;
    output::write_atomically(path, format!("{text}\n").as_bytes())?;
    println!("wrote {}", path.display());
    Ok(())
}

fn evaluate_semseg3d(args: &Semseg3dArgs) -> Result<()> {
    let start = Instant::now();
    let common = &args.common;
    let mut opened = open_dataset(common)?;
    let snapshot = vlem_core::read_map_file(&args.map)?;
    let registry = Registry::global()?;
    let encoder = match (&opened.config.encoder, &snapshot.metadata.encoder) {
        (Some(stage), _) => registry.build_encoder(
            stage,
            &BuildContext {
                config_dir: opened.config_dir.clone(),
                embedding_dim: None,
            },
        )?,
        (None, Some(_)) => vlem_query::answer::encoder_for_map(
            &snapshot.metadata,
            &args.map.display().to_string(),
        )?,
        (None, None) => bail!(
            "neither {} nor {} names an encoder: the class names cannot be embedded",
            common.config.display(),
            args.map.display()
        ),
    };
    if snapshot.dim != encoder.dim() {
        bail!(
            "{} holds {}-d embeddings but the encoder `{}` makes {}-d ones",
            args.map.display(),
            snapshot.dim,
            encoder.name(),
            encoder.dim()
        );
    }
    let (classes, texts) = class_texts(common, encoder.as_ref())?;
    let voxel_size = args.voxel_size.unwrap_or(match args.protocol {
        Protocol::Vlem => semseg::ground_truth::DEFAULT_GT_VOXEL_SIZE,
        Protocol::Rayfronts => semseg::rayfronts::RayFrontsParams::default().voxel_size,
    });
    let dataset = opened.source.describe();
    eprintln!(
        "vlem: ground truth from every {} of {} frames of {dataset} ({voxel_size} m voxels)",
        ordinal(args.stride),
        opened.source.len()
    );
    let (gt, unknown) = semseg::ground_truth::from_source(
        opened.source.as_mut(),
        args.stride,
        voxel_size,
        |_, _| {},
    )?;
    for (id, name) in &unknown {
        eprintln!("vlem: dataset class {id} \"{name}\" is no NYU40 class: ignored");
    }
    let list = common.classes.list();
    let mut report = serde_json::Map::new();
    let (scores, title) = match args.protocol {
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
                args.radius,
                steps,
            )?;
            report.insert("protocol".into(), "vlem".into());
            report.insert("radius".into(), serde_json::json!(args.radius));
            report.insert("thresholds".into(), serde_json::json!(steps + 1));
            report.insert("associated_gt_points".into(), serde_json::json!(associated));
            (
                scores,
                "vlem protocol (IoU averaged over thresholds 0.00..=1.00)",
            )
        }
        Protocol::Rayfronts => {
            let params = semseg::rayfronts::RayFrontsParams {
                voxel_size,
                k: args.k,
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
            let dropped: Vec<&str> = classes
                .iter()
                .zip(&kept)
                .filter(|(_, k)| !**k)
                .map(|(c, _)| c.name.as_str())
                .collect();
            report.insert("protocol".into(), "rayfronts".into());
            report.insert("params".into(), serde_json::json!(params));
            report.insert("fmiou".into(), serde_json::json!(scores.fmiou));
            report.insert("accuracy".into(), serde_json::json!(scores.accuracy));
            report.insert("denoised_classes".into(), serde_json::json!(dropped));
            (
                scores,
                "rayfronts protocol (argmax over prompts, k-NN votes)",
            )
        }
    };
    print_scores(
        &format!(
            "semseg3d, {title}, {}: {} ground-truth points, {} map points",
            list.label(),
            gt.len(),
            snapshot.len()
        ),
        &scores,
    );
    report.extend(scores_json(&scores, list));
    report.insert("voxel_size".into(), serde_json::json!(voxel_size));
    report.insert("gt_points".into(), serde_json::json!(gt.len()));
    report.insert("gt_frames".into(), serde_json::json!(gt.views));
    report.insert("map".into(), serde_json::json!(args.map));
    report.insert("map_kind".into(), serde_json::json!(snapshot.map_kind));
    report.insert("map_points".into(), serde_json::json!(snapshot.len()));
    report.insert("map_dim".into(), serde_json::json!(snapshot.dim));
    // What the map file holds per point: position, colour and embedding.
    report.insert(
        "map_bytes".into(),
        serde_json::json!(snapshot.len() * (12 + 3 + 4 * snapshot.dim)),
    );
    finish_report(
        report,
        encoder.name(),
        &dataset,
        start,
        common.json.as_deref(),
    )
}

fn evaluate_semseg2d(args: &Semseg2dArgs) -> Result<()> {
    let start = Instant::now();
    let common = &args.common;
    if args.stride == 0 {
        bail!("--stride must be at least 1");
    }
    let mut opened = open_dataset(common)?;
    let Some(stage) = &opened.config.encoder else {
        bail!(
            "{} has no [encoder]: semseg2d evaluates an encoder",
            common.config.display()
        );
    };
    let ctx = BuildContext {
        config_dir: opened.config_dir.clone(),
        embedding_dim: None,
    };
    let registry = Registry::global()?;
    let encoder = registry.build_encoder(stage, &ctx)?;
    let proposer = match &opened.config.proposer {
        Some(stage) if encoder.needs_regions() => Some(registry.build_proposer(stage, &ctx)?),
        None if encoder.needs_regions() => bail!(
            "encoder `{}` embeds regions: {} needs a [proposer]",
            encoder.name(),
            common.config.display()
        ),
        _ => None,
    };
    let (classes, texts) = class_texts(common, encoder.as_ref())?;
    let index = ClassIndex::new(&classes);
    let mut sweep = ThresholdSweep::new(classes.len(), semseg::sweep::DEFAULT_THRESHOLD_STEPS)?;
    let dataset = opened.source.describe();
    let mut remap = None;
    let (mut pixels, mut frames) = (0u64, 0usize);
    let total = opened.source.len();
    eprintln!(
        "vlem: encoder `{}` on every {} of {total} frames of {dataset}",
        encoder.name(),
        ordinal(args.stride)
    );
    for i in (0..total).step_by(args.stride) {
        let frame = opened.source.frame(i)?;
        let ids = semseg::ground_truth::nyu40_labels(&frame, &mut remap, &dataset)?;
        let regions = match &proposer {
            Some(p) => p.propose(&frame.colour)?,
            None => Vec::new(),
        };
        let embeddings = encoder
            .encode_frame(&frame, &regions)
            .with_context(|| format!("encoder `{}` on frame {i}", encoder.name()))?;
        let (w, h) = (frame.intrinsics.width, frame.intrinsics.height);
        pixels += semseg::image::add_image(&mut sweep, &ids, w, h, &embeddings, &texts, &index)?;
        frames += 1;
    }
    let scores = SemsegScores::from_sweep(&sweep, &classes);
    let list = common.classes.list();
    print_scores(
        &format!(
            "semseg2d, {}: {frames} frames, {pixels} labelled pixels (IoU averaged over thresholds 0.00..=1.00)",
            list.label()
        ),
        &scores,
    );
    let mut report = serde_json::Map::new();
    report.insert("protocol".into(), "vlem".into());
    report.extend(scores_json(&scores, list));
    report.insert("gt_pixels".into(), serde_json::json!(pixels));
    report.insert("frames".into(), serde_json::json!(frames));
    report.insert("stride".into(), serde_json::json!(args.stride));
    report.insert(
        "thresholds".into(),
        serde_json::json!(semseg::sweep::DEFAULT_THRESHOLD_STEPS + 1),
    );
    finish_report(
        report,
        encoder.name(),
        &dataset,
        start,
        common.json.as_deref(),
    )
}

/// "frame", "2nd frame", "30th frame": how a stride reads in a sentence.
fn ordinal(n: usize) -> String {
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
