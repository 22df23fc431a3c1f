//! A new dataset format in one file: its reader, its own `[dataset]` key, the probe that lets
//! `kind = "auto"` recognise its folders, and its registration; then a run through the pipeline.
//!
//! The format, `image-list`, is a folder with a list of frames, one `colour depth` pair of image
//! paths per line (relative to the folder; `#` starts a comment), and the camera as an Open3D
//! intrinsics JSON. Its one setting of its own is the list's name (`[dataset] list`, default
//! `frames.txt`); the shared keys (`stride`, `max_frames`, `depth_scale`) come from core's
//! `DatasetConfig`. Nothing else in vlem changes: `vlem::datasets::open` finds the reader by name
//! or by its probe, and an unknown key of its own is refused naming the key and the line.
//!
//! It lists the 30 committed living-room frames of `data/` in a temporary folder, maps the first
//! ten with the `odometry` tracker (the format has no poses) and the weight-free `colour-names`
//! encoder, and prints the map's size. Run it from the repository root (default features) with
//!
//! ```text
//! cargo run --release --example custom_dataset
//! ```

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Deserialize;
use vlem::core::config::DatasetConfig;
use vlem::core::pipeline::{Pipeline, Progress};
use vlem::core::{
    BuildContext, Config, CoreError, DatasetReader, Frame, FrameSource, Intrinsics, StageKind,
    parse_params,
};

/// The registered name: `[dataset] kind = "image-list"`.
const NAME: &str = "image-list";

/// The list's default name, which the probe looks for.
const DEFAULT_LIST: &str = "frames.txt";

vlem::core::register_dataset!(
    NAME,
    "a folder listing colour/depth image pairs (examples/custom_dataset.rs)",
    DatasetReader::new(open).detected_by(50, "frames.txt (an image list)", |dir| {
        dir.join(DEFAULT_LIST).is_file()
    })
);

/// `[dataset]` keys of this reader, besides the shared ones.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ImageListSettings {
    /// The list file, relative to the folder; default `frames.txt`.
    #[serde(default = "default_list")]
    list: PathBuf,
}

fn default_list() -> PathBuf {
    PathBuf::from(DEFAULT_LIST)
}

/// The reader: the listed pairs (after the stride and frame limit), decoded when asked for.
struct ImageList {
    folder: PathBuf,
    pairs: Vec<(PathBuf, PathBuf)>,
    intrinsics: Intrinsics,
    /// Raw depth units per metre.
    depth_scale: f32,
}

fn open(config: &DatasetConfig, dir: &Path) -> vlem::core::Result<Box<dyn FrameSource>> {
    let settings: ImageListSettings = parse_params(StageKind::Dataset, NAME, &config.params)?;
    let list = dir.join(&settings.list);
    let text = std::fs::read_to_string(&list).map_err(|e| CoreError::io(&list, e))?;
    let pairs = text
        .lines()
        .map(|line| line.split('#').next().unwrap_or_default().trim())
        .filter(|line| !line.is_empty())
        .map(
            |line| match line.split_whitespace().collect::<Vec<_>>()[..] {
                [colour, depth] => Ok((dir.join(colour), dir.join(depth))),
                _ => Err(vlem::datasets::DatasetError::BadConfig {
                    path: list.clone(),
                    message: format!("expected `colour depth` per line, got `{line}`"),
                }),
            },
        )
        .step_by(config.stride.unwrap_or(1).max(1))
        .take(config.max_frames.unwrap_or(usize::MAX))
        .collect::<Result<Vec<_>, _>>()?;
    let intrinsics = vlem::datasets::read_open3d_intrinsics(&dir.join("camera.json"))?;
    Ok(Box::new(ImageList {
        folder: dir.to_path_buf(),
        pairs,
        intrinsics,
        depth_scale: config.depth_scale.unwrap_or(1000.0) as f32,
    }))
}

impl FrameSource for ImageList {
    fn describe(&self) -> String {
        format!(
            "image list {} ({} frames)",
            self.folder.display(),
            self.pairs.len()
        )
    }

    fn len(&self) -> usize {
        self.pairs.len()
    }

    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }

    fn has_poses(&self) -> bool {
        false
    }

    fn frame(&mut self, index: usize) -> vlem::core::Result<Frame> {
        let (colour, depth) = self
            .pairs
            .get(index)
            .ok_or_else(|| CoreError::MissingStage {
                message: format!("frame {index} of {}", self.pairs.len()),
            })?;
        let read = |path: &Path| std::fs::read(path).map_err(|e| CoreError::io(path, e));
        let colour = vlem::datasets::colour_from_bytes(&read(colour)?, colour)?;
        let depth = vlem::datasets::depth_from_bytes(&read(depth)?, self.depth_scale, depth)?;
        // No timestamps in the list: the frame's index stands in, as for other such layouts.
        Frame::new(index, index as f64, colour, depth, self.intrinsics, None)
    }
}

fn main() -> Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let living_room = root.join("data/living-room");
    let folder = std::env::temp_dir().join(format!("vlem-image-list-{}", std::process::id()));
    std::fs::create_dir_all(&folder)?;
    let mut list = String::from("# colour depth\n");
    for k in 0..30 {
        let colour = living_room.join(format!("color/{k:05}.jpg"));
        let depth = living_room.join(format!("depth/{k:05}.png"));
        list.push_str(&format!("{} {}\n", colour.display(), depth.display()));
    }
    std::fs::write(folder.join(DEFAULT_LIST), list)?;
    std::fs::copy(
        living_room.join("intrinsics.json"),
        folder.join("camera.json"),
    )?;

    // `kind = "auto"`: the probe recognises the folder by its frames.txt.
    let text = "[dataset]\nmax_frames = 10\n\n[tracker]\nkind = \"odometry\"\n\n\
                [encoder]\nkind = \"colour-names\"\n\n[map]\nkind = \"point-cloud\"\n";
    let config = Config::from_toml(text)?;
    let detected = vlem::datasets::detect_kind(&folder)?;
    println!("detected: {detected}");
    let ctx = BuildContext::for_config_dir(&folder)?;
    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    let mut source = vlem::datasets::open(&config.dataset, &folder)?;
    println!("{}", source.describe());
    let report = pipeline.run(source.as_mut(), None, &|_: Progress| {})?;
    let points = pipeline.map().context("the config has a [map]")?.len();
    println!(
        "{} frames mapped, {} tracked; the map holds {points} points",
        report.frames_processed, report.frames_tracked
    );

    // An unknown key of the reader's own is refused, naming it and (found again in the text) its
    // line.
    let typo = "[dataset]\nkind = \"image-list\"\nlsit = \"x.txt\"\n";
    let config = Config::from_toml(typo)?.with_source_text(typo, "typo.toml");
    let err = vlem::datasets::open(&config.dataset, &folder)
        .err()
        .context("the typo was accepted")?;
    let err = config.locate(err);
    println!("a typo: {err}");
    std::fs::remove_dir_all(&folder)?;
    Ok(())
}
