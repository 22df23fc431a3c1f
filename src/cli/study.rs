//! `vlem study`: a comparison study of map representations, encoders, trackers and sequences.
//!
//! A study file names a base config and lists variants along up to four axes (`[[maps]]`,
//! `[[encoders]]`, `[[trackers]]`, `[[sequences]]`); every combination is a *cell*. Each cell runs
//! as two child processes of this binary, `vlem run` and `vlem eval semseg3d`, so that a crash in
//! one cell loses nothing else and peak resident memory is measured per cell. A cell's results
//! land in `OUT/cells/<cell>/result.json`; finished cells are skipped when the study is run again,
//! so an interrupted study resumes where it stopped. After running, every result found in `OUT`
//! is gathered into `OUT/study.csv` and `OUT/study.svg` / `OUT/study.png` (mIoU against peak
//! memory, the paper's Fig. 4).
//!
//! `--shard i/n` runs only cells `i-1, i-1+n, …` (1-based `i`) so that array jobs of a cluster
//! scheduler spread a study over machines that share `OUT`; `--report` only gathers.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command as Process;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Deserialize;
use vlem_core::Config;

use super::study_result::CellResult;
use crate::output::write_atomically;

/// Arguments of `vlem study`.
#[derive(clap::Args, Debug)]
pub struct StudyArgs {
    /// The study file (TOML; see README "Comparison studies").
    pub study: PathBuf,
    /// Output folder: one sub-folder per cell, `study.csv`, `study.svg`, `study.png`.
    #[arg(long, default_value = "out/study")]
    pub out: PathBuf,
    /// Run only this slice of the cells, `i/n` with 1 ≤ i ≤ n (e.g. a Slurm array job:
    /// `--shard $((SLURM_ARRAY_TASK_ID + 1))/$SLURM_ARRAY_TASK_COUNT`).
    #[arg(long)]
    pub shard: Option<Shard>,
    /// Run no cell: gather the results already in OUT into the CSV and the plot.
    #[arg(long)]
    pub report: bool,
    /// Run cells again even if OUT already holds their results.
    #[arg(long)]
    pub force: bool,
    /// Print the cells (with their index) and exit.
    #[arg(long)]
    pub list: bool,
}

/// `i/n`: the `i`-th of `n` slices, 1-based.
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
    fn contains(self, cell: usize) -> bool {
        cell % self.count == self.index - 1
    }
}

/// The `[study]` table.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct StudySettings {
    /// Config every cell starts from (relative to the study file).
    base: PathBuf,
    /// `vlem eval semseg3d --protocol`.
    #[serde(default = "default_protocol")]
    protocol: String,
    /// `vlem eval semseg3d --classes`.
    #[serde(default = "default_classes")]
    classes: String,
    /// Frames per cell (`vlem run --max-frames`); all of the sequence when absent.
    #[serde(default)]
    max_frames: Option<usize>,
    /// `vlem eval semseg3d --prompts`: a JSON object of class names to query texts (relative to
    /// the study file), for encoders that cannot embed the class names themselves.
    #[serde(default)]
    prompts: Option<PathBuf>,
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
struct Study {
    settings: StudySettings,
    cells: Vec<Cell>,
}

struct Cell {
    index: usize,
    /// Variant names along [`AXES`].
    names: [String; 4],
    config: toml::Table,
}

impl Cell {
    fn id(&self) -> String {
        let mut id = format!("{:03}", self.index);
        for name in &self.names {
            id.push('-');
            id.push_str(&slug(name));
        }
        id
    }
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

impl Study {
    fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read study file {}", path.display()))?;
        let mut table: toml::Table =
            toml::from_str(&text).with_context(|| format!("study file {}", path.display()))?;
        let study_dir = parent_dir(path);
        let mut settings: StudySettings = table
            .remove("study")
            .context("a study file needs a [study] table with `base = \"<config>\"`")?
            .try_into()
            .with_context(|| format!("study file {}: [study]", path.display()))?;
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
            bail!(
                "study file {}: unknown key `{key}` (expected [study], [[maps]], [[encoders]], [[trackers]], [[sequences]])",
                path.display()
            );
        }
        settings.prompts = settings.prompts.map(|p| study_dir.join(p));
        let base_path = study_dir.join(&settings.base);
        let base_text = std::fs::read_to_string(&base_path)
            .with_context(|| format!("cannot read the base config {}", base_path.display()))?;
        let mut base: toml::Table = toml::from_str(&base_text)
            .with_context(|| format!("base config {}", base_path.display()))?;
        absolutise_paths(&mut base, &parent_dir(&base_path));

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
            // Check every cell before running any, so a typo does not surface hours in.
            Config::from_toml(&toml::to_string(&cell.config)?).map_err(|message| {
                anyhow::anyhow!(
                    "study file {}: cell {} ({}): {message}",
                    path.display(),
                    cell.index,
                    cell.names.join(" × ")
                )
            })?;
            cells.push(cell);
        }
        Ok(Self { settings, cells })
    }
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
        bail!(
            "study file {}: `{axis}` must be an array of tables ([[{axis}]])",
            path.display()
        );
    };
    if items.is_empty() {
        bail!(
            "study file {}: [[{axis}]] is empty; leave it out to use the base config's [{section}]",
            path.display()
        );
    }
    let mut names = BTreeSet::new();
    let mut variants = Vec::new();
    for (i, item) in items.into_iter().enumerate() {
        let toml::Value::Table(mut table) = item else {
            bail!("study file {}: {axis}[{i}] is not a table", path.display());
        };
        let name = match table.remove("name") {
            Some(toml::Value::String(name)) => name,
            Some(_) => bail!(
                "study file {}: {axis}[{i}].name must be a string",
                path.display()
            ),
            None => bail!(
                "study file {}: {axis}[{i}] needs a `name` (used in the CSV and the plot)",
                path.display()
            ),
        };
        if !names.insert(slug(&name)) {
            bail!(
                "study file {}: two [[{axis}]] entries are named `{name}`",
                path.display()
            );
        }
        let mut wrapper = toml::Table::new();
        wrapper.insert(section.to_owned(), toml::Value::Table(table));
        absolutise_paths(&mut wrapper, study_dir);
        let Some(toml::Value::Table(table)) = wrapper.remove(section) else {
            bail!("study file {}: {axis}[{i}] lost its table", path.display());
        };
        variants.push(Variant {
            name,
            section: Some(table),
        });
    }
    Ok(variants)
}

/// Cell configs are written into OUT, so relative paths of the files they came from are made
/// absolute against those files' folders: `[dataset] path`, `intrinsics`, `trajectory`, and every
/// stage parameter whose key is `path` or ends in `_dir`, `_path` or `_file`.
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

/// Runs `vlem study`.
pub fn execute(args: &StudyArgs) -> Result<()> {
    let study = Study::read(&args.study)?;
    if args.list {
        for cell in &study.cells {
            println!("{:>4}  {}", cell.index, cell.names.join(" × "));
        }
        return Ok(());
    }
    let cells_dir = args.out.join("cells");
    std::fs::create_dir_all(&cells_dir)
        .with_context(|| format!("cannot create {}", cells_dir.display()))?;
    let mut failed = 0usize;
    if !args.report {
        let todo: Vec<&Cell> = study
            .cells
            .iter()
            .filter(|c| args.shard.is_none_or(|s| s.contains(c.index)))
            .filter(|c| args.force || !finished(&cells_dir.join(c.id())))
            .collect();
        let bar = ProgressBar::new(todo.len() as u64);
        bar.set_style(
            ProgressStyle::with_template("{bar:30} {pos}/{len} cells, {elapsed} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        for cell in todo {
            bar.set_message(cell.names.join(" × "));
            let result = run_cell(&study.settings, cell, &cells_dir.join(cell.id()))?;
            if result.status != "ok" {
                failed += 1;
                // Printed past the bar, which hides its own output when stderr is no terminal.
                bar.suspend(|| {
                    eprintln!(
                        "cell {} ({}) failed: {}",
                        cell.index,
                        cell.names.join(" × "),
                        result.error
                    );
                });
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
    }
    let results = gather(&study, &cells_dir);
    write_csv(&args.out.join("study.csv"), &results)?;
    let plotted = super::study_plot::write_plots(&args.out, &results)?;
    println!(
        "{} of {} cells have results: {}{}",
        results.len(),
        study.cells.len(),
        args.out.join("study.csv").display(),
        plotted
            .iter()
            .map(|p| format!(", {}", p.display()))
            .collect::<String>()
    );
    if failed > 0 {
        bail!(
            "{failed} cell(s) failed; their logs are in {}",
            cells_dir.display()
        );
    }
    Ok(())
}

fn finished(dir: &Path) -> bool {
    read_result(dir).is_some_and(|r| r.status == "ok")
}

fn read_result(dir: &Path) -> Option<CellResult> {
    let text = std::fs::read_to_string(dir.join("result.json")).ok()?;
    serde_json::from_str(&text).ok()
}

/// Runs one cell in child processes and records its result (also when it fails).
fn run_cell(settings: &StudySettings, cell: &Cell, dir: &Path) -> Result<CellResult> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let config_path = dir.join("config.toml");
    write_atomically(&config_path, toml::to_string(&cell.config)?.as_bytes())?;
    let exe = std::env::current_exe().context("cannot find the vlem executable")?;
    let [sequence, tracker, encoder, map] = cell.names.clone();
    let mut result = CellResult {
        cell: cell.index,
        sequence,
        tracker,
        encoder,
        map,
        status: "failed".to_owned(),
        protocol: settings.protocol.clone(),
        classes: settings.classes.clone(),
        ..CellResult::default()
    };
    let mut run = Process::new(&exe);
    run.arg("run")
        .arg("--config")
        .arg(&config_path)
        .arg("--out")
        .arg(dir)
        .arg("--no-colour-model");
    if let Some(n) = settings.max_frames {
        run.arg("--max-frames").arg(n.to_string());
    }
    let eval_json = dir.join("semseg3d.json");
    let outcome = run_logged(run, &dir.join("run.log")).and_then(|()| {
        let mut eval = Process::new(&exe);
        eval.arg("eval")
            .arg("semseg3d")
            .arg("--map")
            .arg(dir.join("map.vlem"))
            .arg("--config")
            .arg(&config_path)
            .arg("--protocol")
            .arg(&settings.protocol)
            .arg("--classes")
            .arg(&settings.classes)
            .arg("--json")
            .arg(&eval_json);
        if let Some(n) = settings.max_frames {
            eval.arg("--max-frames").arg(n.to_string());
        }
        if let Some(prompts) = &settings.prompts {
            eval.arg("--prompts").arg(prompts);
        }
        run_logged(eval, &dir.join("eval.log"))
    });
    match outcome {
        Ok(()) => {
            fill_from_stats(&mut result, &dir.join("stats.json"))?;
            fill_from_eval(&mut result, &eval_json)?;
            result.status = "ok".to_owned();
        }
        Err(e) => result.error = e.to_string(),
    }
    write_atomically(
        &dir.join("result.json"),
        serde_json::to_string_pretty(&result)?.as_bytes(),
    )?;
    Ok(result)
}

/// Runs a child with its output in `log`; an error carries the last line it printed.
fn run_logged(mut command: Process, log: &Path) -> Result<()> {
    let file =
        std::fs::File::create(log).with_context(|| format!("cannot create {}", log.display()))?;
    let status = command
        .stdout(file.try_clone()?)
        .stderr(file)
        .status()
        .context("cannot start the vlem executable")?;
    if status.success() {
        return Ok(());
    }
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let last = text
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("no output");
    let last = last.trim().trim_start_matches("error: ");
    bail!("{last} ({status}); see {}", log.display())
}

fn read_json(path: &Path) -> Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not valid JSON", path.display()))
}

fn fill_from_stats(result: &mut CellResult, path: &Path) -> Result<()> {
    let stats = read_json(path)?;
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
    result.map_bytes = stats["map"]["bytes"].as_u64();
    Ok(())
}

fn fill_from_eval(result: &mut CellResult, path: &Path) -> Result<()> {
    let eval = read_json(path)?;
    result.miou = eval["miou"].as_f64();
    result.eval_seconds = eval["seconds"].as_f64();
    Ok(())
}

/// Every result in OUT of a cell of this study, by cell index. A cell's folder is named after its
/// index and variant names, so results left by an earlier version of the study file are not mixed
/// in.
fn gather(study: &Study, cells_dir: &Path) -> Vec<CellResult> {
    study
        .cells
        .iter()
        .filter_map(|cell| read_result(&cells_dir.join(cell.id())))
        .collect()
}

fn write_csv(path: &Path, results: &[CellResult]) -> Result<()> {
    let mut writer = csv::Writer::from_writer(Vec::new());
    for result in results {
        writer.serialize(result)?;
    }
    if results.is_empty() {
        // The csv writer emits the header with the first row: write a dummy row and keep only the
        // header, so that an empty study's CSV still names its columns.
        writer.serialize(CellResult::default())?;
    }
    let mut bytes = writer.into_inner().context("cannot finish the CSV")?;
    if results.is_empty() {
        let header_end = bytes.iter().position(|&b| b == b'\n').map_or(0, |i| i + 1);
        bytes.truncate(header_end);
    }
    write_atomically(path, &bytes)
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
}
