//! Comparison studies of map representations, encoders, trackers and sequences.
//!
//! Why it exists: a study is what the paper's Fig. 4 is made of, and both the `vlem study` command
//! and the Python package (`vlem.study`) run one, so the study file, its cells, how a cell runs and
//! what it records live here once.
//!
//! A study file names a base config and lists variants along up to four axes (`[[maps]]`,
//! `[[encoders]]`, `[[trackers]]`, `[[sequences]]`); every combination is a *cell*. Each cell runs
//! in a child process that the front-end starts ([`Study::run`] takes the command): the child
//! calls [`run_cell`], which maps the cell's sequence and evaluates the map (3D semantic
//! segmentation) in-process, so that a crash in one cell loses nothing else and peak resident
//! memory is measured per cell (after the mapping, before the evaluation). A cell's results land in
//! `OUT/cells/<cell>/result.json`; finished cells are skipped when the study is run again, so an
//! interrupted study resumes where it stopped. [`Study::gather`] reads every result back and
//! [`write_csv`] writes the table.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde::{Deserialize, Serialize};
use vlem_core::Config;
use vlem_core::files::write_atomically;
use vlem_core::pipeline::{Pipeline, Progress};

use crate::error::{EvalError, Result};
use crate::report::{self, Protocol, Semseg3dOptions, SemsegInput};
use crate::semseg::ClassList;

/// `i/n`: the `i`-th of `n` slices of the cells, 1-based, so that array jobs of a cluster
/// scheduler spread a study over machines that share its output folder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    index: usize,
    count: usize,
}

impl std::str::FromStr for Shard {
    type Err = String;

    fn from_str(text: &str) -> std::result::Result<Self, String> {
        let bad = || format!("expected `i/n` with 1 <= i <= n (e.g. 2/8), found `{text}`");
        let (i, n) = text.split_once('/').ok_or_else(bad)?;
        let index: usize = i.trim().parse().map_err(|_| bad())?;
        let count: usize = n.trim().parse().map_err(|_| bad())?;
        if index == 0 || count == 0 || index > count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }
}

impl Shard {
    /// Whether cell `cell` (0-based) belongs to this slice: cells `i-1, i-1+n, …`.
    pub fn contains(self, cell: usize) -> bool {
        cell % self.count == self.index - 1
    }
}

/// The `[study]` table.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StudySettings {
    /// Config every cell starts from (relative to the study file).
    pub base: PathBuf,
    /// The 3D protocol (`vlem` or `rayfronts`).
    #[serde(default = "default_protocol")]
    pub protocol: String,
    /// The class list (`nyu40` or `scannet20`).
    #[serde(default = "default_classes")]
    pub classes: String,
    /// Frames per cell; all of the sequence when absent.
    #[serde(default)]
    pub max_frames: Option<usize>,
    /// A JSON object of class names to query texts (relative to the study file), for encoders
    /// that cannot embed the class names themselves.
    #[serde(default)]
    pub prompts: Option<PathBuf>,
}

fn default_protocol() -> String {
    "vlem".to_owned()
}

fn default_classes() -> String {
    "nyu40".to_owned()
}

/// The four axes, in the order cells are enumerated (the last varies fastest), with the config
/// section each one replaces.
const AXES: [(&str, &str); 4] = [
    ("sequences", "dataset"),
    ("trackers", "tracker"),
    ("encoders", "encoder"),
    ("maps", "map"),
];

/// One value of an axis: its name in the results and the config section it stands for.
#[derive(Clone, Debug)]
struct Variant {
    name: String,
    section: Option<toml::Table>,
}

/// A study: its settings and every cell's config.
#[derive(Clone, Debug)]
pub struct Study {
    /// The `[study]` table, its paths made absolute.
    pub settings: StudySettings,
    /// Every cell, in index order.
    pub cells: Vec<Cell>,
}

/// One combination of variants.
#[derive(Clone, Debug)]
pub struct Cell {
    /// Position in the study (0-based).
    pub index: usize,
    /// Variant names: sequence, tracker, encoder, map (`base` where an axis is not varied).
    pub names: [String; 4],
    /// The cell's whole config.
    pub config: toml::Table,
}

impl Cell {
    /// The cell's folder name: its index and its variants' names.
    pub fn id(&self) -> String {
        let mut id = format!("{:03}", self.index);
        for name in &self.names {
            id.push('-');
            id.push_str(&slug(name));
        }
        id
    }

    /// The variants' names for people: `sequence × tracker × encoder × map`.
    pub fn label(&self) -> String {
        self.names.join(" × ")
    }
}

/// One cell's outcome: a row of the study's table.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
pub struct CellResult {
    /// The cell's index.
    pub cell: usize,
    /// Variant names along the four axes.
    pub sequence: String,
    /// The tracker variant.
    pub tracker: String,
    /// The encoder variant.
    pub encoder: String,
    /// The map variant.
    pub map: String,
    /// `ok`, or `failed`.
    pub status: String,
    /// The 3D protocol.
    pub protocol: String,
    /// The class list.
    pub classes: String,
    /// Mean IoU.
    pub miou: Option<f64>,
    /// Points in the map at the end.
    pub map_points: Option<u64>,
    /// The map's size in memory at the end.
    pub map_bytes: Option<u64>,
    /// Peak resident memory of the mapping (the cell's process, before the evaluation).
    pub peak_resident_bytes: Option<u64>,
    /// Frames integrated.
    pub frames: Option<u64>,
    /// Seconds of the mapping run.
    pub wall_seconds: Option<f64>,
    /// Mean milliseconds per frame of each stage.
    pub load_ms: Option<f64>,
    /// Tracking.
    pub track_ms: Option<f64>,
    /// Region proposals.
    pub propose_ms: Option<f64>,
    /// Encoding.
    pub encode_ms: Option<f64>,
    /// Integration into the map.
    pub integrate_ms: Option<f64>,
    /// Seconds of the evaluation.
    pub eval_seconds: Option<f64>,
    /// Why a failed cell failed.
    pub error: String,
}

/// Which cells [`Study::run`] runs.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunSelection {
    /// Only this slice of the cells.
    pub shard: Option<Shard>,
    /// Run cells again even if the output folder holds their results.
    pub force: bool,
}

/// What happens while a study runs, for progress displays.
#[derive(Debug)]
pub enum StudyEvent<'a> {
    /// `total` cells are about to run (after the shard and the finished ones are left out).
    Planned {
        /// Cells to run.
        total: usize,
    },
    /// A cell starts.
    Started {
        /// The cell.
        cell: &'a Cell,
    },
    /// A cell has ended, well or not.
    Finished {
        /// The cell.
        cell: &'a Cell,
        /// What it recorded.
        result: &'a CellResult,
    },
}

/// A file-name-safe form of a variant name.
fn slug(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' || c == '_' {
                c.to_ascii_lowercase()
            } else {
                '-'
            }
        })
        .collect();
    let s = s.trim_matches('-').to_owned();
    if s.is_empty() { "x".to_owned() } else { s }
}

/// An error about the study file at `path`.
fn bad(path: &Path, message: impl Into<String>) -> EvalError {
    EvalError::Study {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// An I/O error on a file of the study's output.
fn io(path: &Path, source: std::io::Error) -> EvalError {
    EvalError::Io {
        path: path.to_path_buf(),
        role: "study output".into(),
        source,
    }
}

impl Study {
    /// Reads the study file at `path` and builds every cell's config, checking each one, so a
    /// typo does not surface hours in.
    ///
    /// # Errors
    /// [`EvalError::Study`]: an unreadable file, unknown keys, unnamed or duplicate variants, a
    /// cell whose config is invalid (the message names the cell).
    pub fn read(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).map_err(|e| bad(path, format!("cannot read it: {e}")))?;
        let mut table: toml::Table = toml::from_str(&text).map_err(|e| bad(path, e.to_string()))?;
        let study_dir = parent_dir(path);
        let mut settings: StudySettings = table
            .remove("study")
            .ok_or_else(|| {
                bad(
                    path,
                    "a study file needs a [study] table with `base = \"<config>\"`",
                )
            })?
            .try_into()
            .map_err(|e: toml::de::Error| bad(path, format!("[study]: {e}")))?;
        Protocol::parse(&settings.protocol).map_err(|e| bad(path, format!("[study]: {e}")))?;
        if ClassList::parse(&settings.classes).is_none() {
            return Err(bad(
                path,
                format!(
                    "[study]: unknown classes `{}` (expected `nyu40` or `scannet20`)",
                    settings.classes
                ),
            ));
        }
        let mut axes: Vec<Vec<Variant>> = Vec::new();
        for (axis, section) in AXES {
            let variants = match table.remove(axis) {
                None => vec![Variant {
                    name: "base".to_owned(),
                    section: None,
                }],
                Some(value) => read_axis(path, axis, section, value, &study_dir)?,
            };
            axes.push(variants);
        }
        if let Some(key) = table.keys().next() {
            return Err(bad(
                path,
                format!(
                    "unknown key `{key}` (expected [study], [[maps]], [[encoders]], [[trackers]], [[sequences]])"
                ),
            ));
        }
        settings.prompts = settings.prompts.map(|p| study_dir.join(p));
        let base_path = study_dir.join(&settings.base);
        let base_text = std::fs::read_to_string(&base_path).map_err(|e| {
            bad(
                path,
                format!("cannot read the base config {}: {e}", base_path.display()),
            )
        })?;
        let mut base: toml::Table = toml::from_str(&base_text)
            .map_err(|e| bad(path, format!("base config {}: {e}", base_path.display())))?;
        absolutise_paths(&mut base, &parent_dir(&base_path));
        settings.base = base_path;

        let mut cells = Vec::new();
        let sizes: Vec<usize> = axes.iter().map(Vec::len).collect();
        let total: usize = sizes.iter().product();
        for index in 0..total {
            let mut rest = index;
            let mut picks = [0usize; 4];
            for axis in (0..4).rev() {
                picks[axis] = rest % sizes[axis];
                rest /= sizes[axis];
            }
            let mut config = base.clone();
            let mut names: [String; 4] = Default::default();
            for (axis, &pick) in picks.iter().enumerate() {
                let variant = &axes[axis][pick];
                names[axis] = variant.name.clone();
                if let Some(section) = &variant.section {
                    config.insert(AXES[axis].1.to_owned(), toml::Value::Table(section.clone()));
                }
            }
            let cell = Cell {
                index,
                names,
                config,
            };
            let text = toml::to_string(&cell.config)
                .map_err(|e| bad(path, format!("cell {}: {e}", cell.index)))?;
            let in_cell = |message: String| {
                bad(
                    path,
                    format!("cell {} ({}): {message}", cell.index, cell.label()),
                )
            };
            let parsed = Config::from_toml(&text).map_err(|e| in_cell(e.to_string()))?;
            // The dataset reader's own keys too (the cell's paths are absolute by now).
            vlem_datasets::check_settings(&parsed.dataset, parsed.dataset.path.as_deref())
                .map_err(|e| in_cell(e.to_string()))?;
            cells.push(cell);
        }
        Ok(Self { settings, cells })
    }

    /// Runs the selected cells that have no result yet, one child process each: `launch(dir)` is
    /// the command that runs [`run_cell`] on the cell folder `dir` (the `vlem` executable, or a
    /// Python interpreter importing the package). The child's output goes to `dir/cell.log`. A
    /// failing cell is recorded (status `failed`, its error) and the others still run. Returns
    /// the results of the cells it ran.
    ///
    /// # Errors
    /// Only when the output folder cannot be written or the child cannot be started at all.
    pub fn run(
        &self,
        out: &Path,
        selection: RunSelection,
        launch: &dyn Fn(&Path) -> Command,
        on_event: &mut dyn FnMut(StudyEvent<'_>),
    ) -> Result<Vec<CellResult>> {
        let cells_dir = out.join("cells");
        std::fs::create_dir_all(&cells_dir).map_err(|e| io(&cells_dir, e))?;
        let todo: Vec<&Cell> = self
            .cells
            .iter()
            .filter(|c| selection.shard.is_none_or(|s| s.contains(c.index)))
            .filter(|c| selection.force || !finished(&cells_dir.join(c.id())))
            .collect();
        on_event(StudyEvent::Planned { total: todo.len() });
        let mut results = Vec::new();
        for cell in todo {
            on_event(StudyEvent::Started { cell });
            let result = self.run_one(cell, &cells_dir.join(cell.id()), launch)?;
            on_event(StudyEvent::Finished {
                cell,
                result: &result,
            });
            results.push(result);
        }
        Ok(results)
    }

    fn run_one(
        &self,
        cell: &Cell,
        dir: &Path,
        launch: &dyn Fn(&Path) -> Command,
    ) -> Result<CellResult> {
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
        let config = toml::to_string(&cell.config)
            .map_err(|e| bad(&self.settings.base, format!("cell {}: {e}", cell.index)))?;
        write_atomically(&dir.join(CELL_CONFIG), config.as_bytes())?;
        write_json(
            &dir.join(CELL_SETTINGS),
            serde_json::to_string_pretty(&self.settings),
        )?;
        // A result of an earlier attempt must not survive a failing rerun.
        for stale in [CELL_ERROR, "stats.json", "semseg3d.json"] {
            let _ = std::fs::remove_file(dir.join(stale));
        }
        let [sequence, tracker, encoder, map] = cell.names.clone();
        let mut result = CellResult {
            cell: cell.index,
            sequence,
            tracker,
            encoder,
            map,
            status: "failed".to_owned(),
            protocol: self.settings.protocol.clone(),
            classes: self.settings.classes.clone(),
            ..CellResult::default()
        };
        let log = dir.join(CELL_LOG);
        let file = std::fs::File::create(&log).map_err(|e| io(&log, e))?;
        let mut command = launch(dir);
        let status = command
            .stdout(file.try_clone().map_err(|e| io(&log, e))?)
            .stderr(file)
            .status()
            .map_err(|e| EvalError::Setup {
                message: format!(
                    "cannot start the cell process {:?}: {e}",
                    command.get_program()
                ),
            })?;
        if status.success() {
            fill_from_stats(&mut result, &dir.join("stats.json"))?;
            fill_from_eval(&mut result, &dir.join("semseg3d.json"))?;
            result.status = "ok".to_owned();
        } else {
            // The child's own message when it got to write one (not when it crashed).
            let message = std::fs::read_to_string(dir.join(CELL_ERROR))
                .ok()
                .filter(|m| !m.trim().is_empty())
                .unwrap_or_else(|| last_line(&log));
            result.error = format!("{} ({status}); see {}", message.trim(), log.display());
        }
        write_json(
            &dir.join(CELL_RESULT),
            serde_json::to_string_pretty(&result),
        )?;
        Ok(result)
    }

    /// Every result in `out` of a cell of this study, by cell index. A cell's folder is named
    /// after its index and variant names, so results left by an earlier version of the study
    /// file are not mixed in.
    pub fn gather(&self, out: &Path) -> Vec<CellResult> {
        let cells_dir = out.join("cells");
        self.cells
            .iter()
            .filter_map(|cell| read_result(&cells_dir.join(cell.id())))
            .collect()
    }
}

/// Files of a cell folder.
const CELL_CONFIG: &str = "config.toml";
const CELL_SETTINGS: &str = "study.json";
const CELL_ERROR: &str = "error.txt";
const CELL_LOG: &str = "cell.log";
const CELL_RESULT: &str = "result.json";

fn last_line(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    text.lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("no output")
        .trim()
        .trim_start_matches("error: ")
        .to_owned()
}

fn finished(dir: &Path) -> bool {
    read_result(dir).is_some_and(|r| r.status == "ok")
}

fn read_result(dir: &Path) -> Option<CellResult> {
    read_json(&dir.join(CELL_RESULT)).ok()
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    serde_json::from_str(&text).map_err(|e| io(path, std::io::Error::other(e.to_string())))
}

/// Writes the JSON text `json` to `path` atomically, or names `path` when it could not be encoded.
fn write_json(path: &Path, json: serde_json::Result<String>) -> Result<()> {
    let json = json.map_err(|e| io(path, std::io::Error::other(e.to_string())))?;
    Ok(write_atomically(path, json.as_bytes())?)
}

fn fill_from_stats(result: &mut CellResult, path: &Path) -> Result<()> {
    let stats: serde_json::Value = read_json(path)?;
    let ms = |stage: &str| stats["mean_ms"][stage].as_f64();
    result.load_ms = ms("load");
    result.track_ms = ms("track");
    result.propose_ms = ms("propose");
    result.encode_ms = ms("encode");
    result.integrate_ms = ms("integrate");
    result.wall_seconds = stats["wall_seconds"].as_f64();
    result.frames = stats["frames"]["processed"].as_u64();
    result.peak_resident_bytes = stats["peak_resident_bytes"].as_u64();
    result.map_points = stats["map"]["points"].as_u64();
    result.map_bytes = stats["map"]["memory_bytes"].as_u64();
    Ok(())
}

fn fill_from_eval(result: &mut CellResult, path: &Path) -> Result<()> {
    let eval: serde_json::Value = read_json(path)?;
    result.miou = eval["miou"].as_f64();
    result.eval_seconds = eval["seconds"].as_f64();
    Ok(())
}

/// The work of one cell, run in the cell's own process on the folder [`Study::run`] prepared:
/// maps the cell's sequence with its config (`map.vlem`, `trajectory.tum`, `stats.json`, whose
/// peak memory is the mapping's), then evaluates the map (`semseg3d.json`). `note` hears
/// progress. On failure the message is also left in the folder for the parent.
///
/// # Errors
/// Whatever stops the mapping or the evaluation.
pub fn run_cell(dir: &Path, note: &(dyn Fn(&str) + Sync)) -> Result<()> {
    let outcome = run_cell_inner(dir, note);
    if let Err(e) = &outcome {
        let _ = write_atomically(
            &dir.join(CELL_ERROR),
            vlem_core::message_chain(e).as_bytes(),
        );
    }
    outcome
}

fn run_cell_inner(dir: &Path, note: &(dyn Fn(&str) + Sync)) -> Result<()> {
    let settings: StudySettings = read_json(&dir.join(CELL_SETTINGS))?;
    let config_path = dir.join(CELL_CONFIG);
    let (mut config, ctx) = vlem_core::load_config(&config_path)?;
    if settings.max_frames.is_some() {
        config.dataset.max_frames = settings.max_frames;
    }
    let dataset_dir = vlem_datasets::dataset_folder(&config, &ctx, None)?;
    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    let mut source = vlem_datasets::open(&config.dataset, &dataset_dir)?;
    let total = source.len();
    note(&format!(
        "{total} frames from {}; tracker `{}`, encoder `{}`, map `{}`",
        source.describe(),
        pipeline.tracker().name(),
        pipeline.encoder().map_or("(none)", |e| e.name()),
        pipeline.map().map_or("(none)", |m| m.name()),
    ));
    let on_progress = |event: Progress| {
        if let Progress::Tracked { index } = event
            && (index + 1) % 50 == 0
        {
            note(&format!("{} of {total} frames tracked", index + 1));
        }
    };
    if !pipeline.live().has_map() {
        return Err(EvalError::Setup {
            message: format!(
                "{} has no [map]: a study cell evaluates a map",
                config_path.display()
            ),
        });
    }
    let run = pipeline.run(source.as_mut(), None, &on_progress)?;
    let map_path = dir.join("map.vlem");
    crate::run_folder::write_run(dir, &pipeline, &run, config.pipeline.mode, None)?;
    drop(pipeline);

    let mut input = SemsegInput::from_config_file(&config_path)?;
    input.max_frames = settings.max_frames;
    input.classes = ClassList::parse(&settings.classes).unwrap_or(ClassList::Nyu40);
    if let Some(prompts) = &settings.prompts {
        input.prompts = report::read_prompts(prompts)?;
    }
    let options = Semseg3dOptions {
        protocol: Protocol::parse(&settings.protocol)?,
        ..Semseg3dOptions::default()
    };
    let evaluated = report::semseg3d(&input, &map_path, &options, note)?;
    note(&evaluated.title);
    write_json(
        &dir.join("semseg3d.json"),
        serde_json::to_string_pretty(&evaluated),
    )?;
    Ok(())
}

fn parent_dir(path: &Path) -> PathBuf {
    path.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf()
}

fn read_axis(
    path: &Path,
    axis: &str,
    section: &str,
    value: toml::Value,
    study_dir: &Path,
) -> Result<Vec<Variant>> {
    let toml::Value::Array(items) = value else {
        return Err(bad(
            path,
            format!("`{axis}` must be an array of tables ([[{axis}]])"),
        ));
    };
    if items.is_empty() {
        return Err(bad(
            path,
            format!("[[{axis}]] is empty; leave it out to use the base config's [{section}]"),
        ));
    }
    let mut names = BTreeSet::new();
    let mut variants = Vec::new();
    for (i, item) in items.into_iter().enumerate() {
        let toml::Value::Table(mut table) = item else {
            return Err(bad(path, format!("{axis}[{i}] is not a table")));
        };
        let name = match table.remove("name") {
            Some(toml::Value::String(name)) => name,
            Some(_) => return Err(bad(path, format!("{axis}[{i}].name must be a string"))),
            None => {
                return Err(bad(
                    path,
                    format!("{axis}[{i}] needs a `name` (used in the CSV and the plot)"),
                ));
            }
        };
        if !names.insert(slug(&name)) {
            return Err(bad(
                path,
                format!("two [[{axis}]] entries are named `{name}`"),
            ));
        }
        let mut wrapper = toml::Table::new();
        wrapper.insert(section.to_owned(), toml::Value::Table(table));
        absolutise_paths(&mut wrapper, study_dir);
        let Some(toml::Value::Table(table)) = wrapper.remove(section) else {
            return Err(bad(path, format!("{axis}[{i}] lost its table")));
        };
        variants.push(Variant {
            name,
            section: Some(table),
        });
    }
    Ok(variants)
}

/// Cell configs are written into the output folder, so relative paths of the files they came from
/// are made absolute against those files' folders: `[dataset] path`, `intrinsics`, `trajectory`,
/// and every stage parameter whose key is `path` or ends in `_dir`, `_path` or `_file`.
fn absolutise_paths(config: &mut toml::Table, dir: &Path) {
    let is_path_key = |key: &str| {
        key == "path" || key.ends_with("_dir") || key.ends_with("_path") || key.ends_with("_file")
    };
    for (section, value) in config.iter_mut() {
        let toml::Value::Table(table) = value else {
            continue;
        };
        for (key, value) in table.iter_mut() {
            let dataset_key = section == "dataset" && (key == "intrinsics" || key == "trajectory");
            if !(dataset_key || is_path_key(key)) {
                continue;
            }
            if let toml::Value::String(text) = value
                && Path::new(text.as_str()).is_relative()
            {
                *text = dir.join(text.as_str()).to_string_lossy().into_owned();
            }
        }
    }
}

/// The study's table as CSV: a header and one row per result. An empty table still names its
/// columns.
///
/// # Errors
/// The file cannot be written.
pub fn write_csv(path: &Path, results: &[CellResult]) -> Result<()> {
    let fail = |e: csv::Error| io(path, std::io::Error::other(e.to_string()));
    let mut writer = csv::Writer::from_writer(Vec::new());
    for result in results {
        writer.serialize(result).map_err(fail)?;
    }
    if results.is_empty() {
        // The csv writer emits the header with the first row: write a dummy row and keep only the
        // header.
        writer.serialize(CellResult::default()).map_err(fail)?;
    }
    let mut bytes = writer
        .into_inner()
        .map_err(|e| io(path, std::io::Error::other(e.to_string())))?;
    if results.is_empty() {
        let header_end = bytes.iter().position(|&b| b == b'\n').map_or(0, |i| i + 1);
        bytes.truncate(header_end);
    }
    Ok(write_atomically(path, &bytes)?)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn shards_split_the_cells_without_overlap() {
        let shards: Vec<Shard> = (1..=3).map(|i| format!("{i}/3").parse().unwrap()).collect();
        for cell in 0..10 {
            let owners = shards.iter().filter(|s| s.contains(cell)).count();
            assert_eq!(owners, 1, "cell {cell}");
        }
        assert!("0/3".parse::<Shard>().is_err());
        assert!("4/3".parse::<Shard>().is_err());
        assert!("1-3".parse::<Shard>().is_err());
    }

    #[test]
    fn slugs_are_file_names() {
        assert_eq!(slug("Point cloud / 2 cm"), "point-cloud---2-cm");
        assert_eq!(slug("///"), "x");
    }

    #[test]
    fn relative_paths_become_absolute_against_their_file() {
        let mut config: toml::Table = toml::from_str(
            "[dataset]\npath = \"data\"\ntrajectory = \"t.log\"\n[encoder]\nkind = \"x\"\nmodel_dir = \"m\"\nscale = \"s\"\n",
        )
        .unwrap();
        absolutise_paths(&mut config, Path::new("/a/b"));
        assert_eq!(config["dataset"]["path"].as_str(), Some("/a/b/data"));
        assert_eq!(config["dataset"]["trajectory"].as_str(), Some("/a/b/t.log"));
        assert_eq!(config["encoder"]["model_dir"].as_str(), Some("/a/b/m"));
        assert_eq!(config["encoder"]["scale"].as_str(), Some("s"));
    }

    #[test]
    fn an_empty_table_still_has_its_header() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("study.csv");
        write_csv(&path, &[]).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.starts_with("cell,sequence,tracker,encoder,map,status"),
            "{text}"
        );
        assert_eq!(text.lines().count(), 1);
    }

    #[test]
    fn a_bad_protocol_is_refused_when_the_study_is_read() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("base.toml"),
            "[tracker]\nkind = \"ground-truth\"\n",
        )
        .unwrap();
        let study = dir.path().join("study.toml");
        std::fs::write(
            &study,
            "[study]\nbase = \"base.toml\"\nprotocol = \"paper\"\n",
        )
        .unwrap();
        let err = Study::read(&study).unwrap_err().to_string();
        assert!(
            err.contains("study.toml") && err.contains("rayfronts"),
            "{err}"
        );
    }
}
