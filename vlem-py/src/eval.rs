//! `vlem.eval_trajectory`, `vlem.eval_semseg3d`, `vlem.eval_semseg2d` and the study runner: the
//! library's evaluations (`vlem_eval::report`, `vlem_eval::study`) with their reports as dicts,
//! the same numbers under the same keys as the `vlem eval ... --json` files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use vlem_eval::report::{
    self, Protocol, Semseg2dOptions, Semseg3dOptions, SemsegInput, TrajectoryOptions,
};
use vlem_eval::semseg::ClassList;
use vlem_eval::study::{self, RunSelection, Shard, Study, StudyEvent};

use crate::errors;
use crate::json::to_python;
use crate::pipeline::load_config;

/// ATE and RPE of the trajectory file ``estimate`` against ``reference`` (TUM or ``.log`` each),
/// as ``vlem eval trajectory --json`` reports them: ``{"estimate": ..., "reference": ...,
/// "association": ..., "associated": n, "ate": {...}, "rpe": {...}}``.
///
/// ``delta``: RPE frame step. ``max_time_diff``: largest stamp difference of paired poses
/// (seconds; frames against a ``.log``). ``scale``: align with a similarity transform.
#[pyfunction]
#[pyo3(signature = (estimate, reference, *, delta = 1, max_time_diff = vlem_eval::trajectory::DEFAULT_MAX_TIME_DIFF, scale = false))]
pub fn eval_trajectory(
    py: Python<'_>,
    estimate: PathBuf,
    reference: PathBuf,
    delta: usize,
    max_time_diff: f64,
    scale: bool,
) -> PyResult<Bound<'_, PyAny>> {
    let options = TrajectoryOptions {
        delta,
        max_time_diff,
        scale,
    };
    let report = py
        .detach(|| report::evaluate_trajectory(&estimate, &reference, &options).map_err(Box::new))
        .map_err(|e| errors::eval(*e))?;
    to_python(py, &report)
}

/// The names of the class list ``classes`` (``"nyu40"``: all 40, which prompts may name;
/// ``"scannet20"``: its 20), for building a ``prompts`` dict.
#[pyfunction]
#[pyo3(signature = (classes = "nyu40"))]
pub fn class_names(classes: &str) -> PyResult<Vec<String>> {
    let list = parse_classes(classes)?;
    Ok(list.all().into_iter().map(|c| c.name).collect())
}

fn parse_classes(classes: &str) -> PyResult<ClassList> {
    ClassList::parse(classes).ok_or_else(|| {
        PyValueError::new_err(format!(
            "classes: expected \"nyu40\" or \"scannet20\", not {classes:?}"
        ))
    })
}

/// The semseg input from the Python arguments both evaluations share.
fn semseg_input(
    config: &Bound<'_, PyAny>,
    config_dir: Option<PathBuf>,
    dataset: Option<PathBuf>,
    max_frames: Option<usize>,
    classes: &str,
    prompts: Option<&Bound<'_, PyAny>>,
) -> PyResult<SemsegInput> {
    let config_name = match config.extract::<PathBuf>() {
        Ok(path) if path.is_file() => path.display().to_string(),
        _ => "the config".to_owned(),
    };
    let (config, ctx) = load_config(config, config_dir)?;
    let classes = parse_classes(classes)?;
    let prompts = match prompts {
        None => BTreeMap::new(),
        Some(p) if p.is_instance_of::<PyDict>() => p.extract().map_err(|_| {
            PyValueError::new_err("prompts: expected a dict of class names to texts")
        })?,
        Some(p) => {
            let path: PathBuf = p.extract().map_err(|_| {
                PyValueError::new_err(
                    "prompts: expected a dict of class names to texts or the path of a JSON file",
                )
            })?;
            report::read_prompts(&path).map_err(errors::eval)?
        }
    };
    Ok(SemsegInput {
        config,
        ctx,
        config_name,
        dataset,
        max_frames,
        classes,
        prompts,
    })
}

/// 3D semantic segmentation of the map file ``map`` against the labelled ground truth of the
/// config's dataset, as ``vlem eval semseg3d --json`` reports it (``miou``, ``per_class``,
/// ``class_details``, ...).
///
/// ``config``: a TOML path, TOML text or a dict (its encoder, or else the map's, embeds the class
/// names). ``classes``: ``"nyu40"`` or ``"scannet20"``. ``prompts``: a dict (or JSON file) of
/// class names to the texts to query instead. ``protocol``: ``"vlem"`` (the paper's: nearest map
/// point within ``radius``, IoU averaged over thresholds) or ``"rayfronts"`` (argmax over
/// prompts, ``k`` voxel votes). ``stride``: ground truth from every n-th frame.
#[pyfunction]
#[pyo3(signature = (config, map, *, dataset = None, max_frames = None, classes = "nyu40", prompts = None, protocol = "vlem", stride = 1, voxel_size = None, radius = vlem_eval::semseg::vlem::DEFAULT_ASSOCIATION_RADIUS, k = 5, config_dir = None))]
#[allow(clippy::too_many_arguments, reason = "Python keyword arguments")]
pub fn eval_semseg3d<'py>(
    py: Python<'py>,
    config: &Bound<'py, PyAny>,
    map: PathBuf,
    dataset: Option<PathBuf>,
    max_frames: Option<usize>,
    classes: &str,
    prompts: Option<&Bound<'py, PyAny>>,
    protocol: &str,
    stride: usize,
    voxel_size: Option<f64>,
    radius: f32,
    k: usize,
    config_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    let input = semseg_input(config, config_dir, dataset, max_frames, classes, prompts)?;
    let options = Semseg3dOptions {
        protocol: Protocol::parse(protocol).map_err(|e| PyValueError::new_err(e.to_string()))?,
        stride,
        voxel_size,
        radius,
        k,
    };
    let report = py
        .detach(|| report::semseg3d(&input, &map, &options, &|_| {}).map_err(Box::new))
        .map_err(|e| errors::eval(*e))?;
    to_python(py, &report)
}

/// 2D semantic segmentation: the config's encoder on every ``stride``-th frame against its label
/// image, as ``vlem eval semseg2d --json`` reports it. Arguments as :func:`eval_semseg3d`.
#[pyfunction]
#[pyo3(signature = (config, *, dataset = None, max_frames = None, classes = "nyu40", prompts = None, stride = 30, config_dir = None))]
#[allow(clippy::too_many_arguments, reason = "Python keyword arguments")]
pub fn eval_semseg2d<'py>(
    py: Python<'py>,
    config: &Bound<'py, PyAny>,
    dataset: Option<PathBuf>,
    max_frames: Option<usize>,
    classes: &str,
    prompts: Option<&Bound<'py, PyAny>>,
    stride: usize,
    config_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    let input = semseg_input(config, config_dir, dataset, max_frames, classes, prompts)?;
    let options = Semseg2dOptions { stride };
    let report = py
        .detach(|| report::semseg2d(&input, &options, &|_| {}).map_err(Box::new))
        .map_err(|e| errors::eval(*e))?;
    to_python(py, &report)
}

/// The cells of the study file ``study``: one dict per cell (``index``, ``id``, ``sequence``,
/// ``tracker``, ``encoder``, ``map``), as ``vlem study --list`` prints them.
#[pyfunction]
pub fn study_cells(py: Python<'_>, study: PathBuf) -> PyResult<Vec<Bound<'_, PyDict>>> {
    let study = Study::read(&study).map_err(errors::eval)?;
    study
        .cells
        .iter()
        .map(|cell| {
            let d = PyDict::new(py);
            d.set_item("index", cell.index)?;
            d.set_item("id", cell.id())?;
            for (axis, name) in ["sequence", "tracker", "encoder", "map"]
                .iter()
                .zip(&cell.names)
            {
                d.set_item(*axis, name)?;
            }
            Ok(d)
        })
        .collect()
}

/// Runs the study (unless ``report``), each cell in a child process ``launcher + [cell_dir]``
/// with ``env`` added, then gathers every result in ``out``; writes ``out/study.csv``. Returns
/// the rows as dicts. ``progress`` hears one dict per started and finished cell.
#[pyfunction]
#[pyo3(signature = (study, out, launcher, env, *, shard = None, force = false, report = false, progress = None))]
#[allow(clippy::too_many_arguments, reason = "Python keyword arguments")]
pub fn _study<'py>(
    py: Python<'py>,
    study: PathBuf,
    out: PathBuf,
    launcher: Vec<String>,
    env: BTreeMap<String, String>,
    shard: Option<String>,
    force: bool,
    report: bool,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let study = Study::read(&study).map_err(errors::eval)?;
    let shard: Option<Shard> = shard
        .map(|s| {
            s.parse()
                .map_err(|e: String| PyValueError::new_err(format!("shard: {e}")))
        })
        .transpose()?;
    let Some((program, args)) = launcher.split_first() else {
        return Err(PyValueError::new_err("launcher: empty command"));
    };
    if !report {
        let launch = |dir: &Path| {
            let mut command = Command::new(program);
            command.args(args).arg(dir).envs(&env);
            command
        };
        let failure: std::sync::Mutex<Option<PyErr>> = std::sync::Mutex::new(None);
        let mut on_event = |event: StudyEvent<'_>| {
            let Some(callback) = &progress else { return };
            Python::attach(|py| {
                let d = PyDict::new(py);
                let outcome = (|| -> PyResult<()> {
                    match event {
                        StudyEvent::Planned { total } => {
                            d.set_item("event", "planned")?;
                            d.set_item("total", total)?;
                        }
                        StudyEvent::Started { cell } => {
                            d.set_item("event", "started")?;
                            d.set_item("cell", cell.index)?;
                            d.set_item("label", cell.label())?;
                        }
                        StudyEvent::Finished { cell, result } => {
                            d.set_item("event", "finished")?;
                            d.set_item("cell", cell.index)?;
                            d.set_item("label", cell.label())?;
                            d.set_item("status", &result.status)?;
                            d.set_item("error", &result.error)?;
                        }
                    }
                    callback.bind(py).call1((d,))?;
                    Ok(())
                })();
                if let Err(e) = outcome
                    && let Ok(mut slot) = failure.lock()
                    && slot.is_none()
                {
                    *slot = Some(e);
                }
            });
        };
        let selection = RunSelection { shard, force };
        py.detach(|| {
            study
                .run(&out, selection, &launch, &mut on_event)
                .map_err(Box::new)
        })
        .map_err(|e| errors::eval(*e))?;
        if let Some(e) = failure.lock().ok().and_then(|mut f| f.take()) {
            return Err(e);
        }
    }
    let results = study.gather(&out);
    study::write_csv(&out.join("study.csv"), &results).map_err(errors::eval)?;
    to_python(py, &results)
}

/// One study cell, in this process (what the child processes of ``vlem.study`` run).
#[pyfunction]
pub fn _study_cell(py: Python<'_>, dir: PathBuf) -> PyResult<()> {
    py.detach(|| study::run_cell(&dir, &|message| eprintln!("vlem: {message}")).map_err(Box::new))
        .map_err(|e| errors::eval(*e))
}
