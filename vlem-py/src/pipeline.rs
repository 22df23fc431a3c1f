//! `vlem.Pipeline` and `vlem.Feed`: build a pipeline from a config, run it over a dataset folder,
//! or feed it frames from numpy arrays while other threads query its map.

use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use vlem_core::live::LiveMap;
use vlem_core::pipeline::{Pipeline, Progress, RunReport};
use vlem_core::stream::{FrameSender, FrameStream, StreamSpec, frame_stream};
use vlem_core::{BuildContext, Config, DepthImage, Frame, Intrinsics, RgbImage};

use crate::arrays::{give, read};
use crate::errors;
use crate::json::{dict_to_toml, to_python};
use crate::map::PyMap;

/// A pinhole camera: image size in pixels, focal lengths and principal point in pixels.
#[pyclass(module = "vlem", name = "Intrinsics", frozen, eq)]
#[derive(Clone, Copy, PartialEq)]
pub struct PyIntrinsics(pub Intrinsics);

#[pymethods]
impl PyIntrinsics {
    /// Sizes are read as any Python int and checked here, so that a negative or huge one names
    /// its argument (a plain `u32` argument would raise a bare ``OverflowError``).
    #[new]
    fn new(width: i128, height: i128, fx: f64, fy: f64, cx: f64, cy: f64) -> PyResult<Self> {
        let pixels = |name: &str, value: i128| -> PyResult<u32> {
            u32::try_from(value).ok().filter(|v| *v > 0).ok_or_else(|| {
                PyValueError::new_err(format!(
                    "{name} must be a positive number of pixels below 2**32, got {value}"
                ))
            })
        };
        Intrinsics::new(
            pixels("width", width)?,
            pixels("height", height)?,
            fx,
            fy,
            cx,
            cy,
        )
        .map(Self)
        .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// From a 3x3 camera matrix ``K`` (as in ROS ``CameraInfo.k`` or OpenCV) and the image size.
    #[staticmethod]
    fn from_matrix(k: &Bound<'_, PyAny>, width: i128, height: i128) -> PyResult<Self> {
        let np = k.py().import("numpy")?;
        let k = np.call_method1("asarray", (k, "float64"))?;
        let (values, _) = read::<f64>(&k, "k", "a 3x3 camera matrix", &[Some(3), Some(3)])?;
        if values[1] != 0.0
            || values[3] != 0.0
            || values[6] != 0.0
            || values[7] != 0.0
            || values[8] != 1.0
        {
            return Err(PyValueError::new_err(format!(
                "k must be a pinhole camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {values:?}"
            )));
        }
        Self::new(width, height, values[0], values[4], values[2], values[5])
    }

    #[getter]
    fn width(&self) -> u32 {
        self.0.width
    }
    #[getter]
    fn height(&self) -> u32 {
        self.0.height
    }
    #[getter]
    fn fx(&self) -> f64 {
        self.0.fx
    }
    #[getter]
    fn fy(&self) -> f64 {
        self.0.fy
    }
    #[getter]
    fn cx(&self) -> f64 {
        self.0.cx
    }
    #[getter]
    fn cy(&self) -> f64 {
        self.0.cy
    }

    fn __repr__(&self) -> String {
        let c = &self.0;
        format!(
            "vlem.Intrinsics(width={}, height={}, fx={}, fy={}, cx={}, cy={})",
            c.width, c.height, c.fx, c.fy, c.cx, c.cy
        )
    }
}

/// Where the pipeline is: here, or running on a feed's thread.
type Slot = Arc<Mutex<Option<Pipeline>>>;

/// A mapping pipeline: tracker, optional region proposer and encoder, and a map, built from a
/// config as ``vlem run`` builds it.
///
/// ``config`` is a path to a TOML file (``str`` or ``os.PathLike``), TOML text, or a dict with the
/// same sections (``{"tracker": {"kind": "ground-truth"}, "encoder": {"kind": "colour-names"},
/// "map": {"kind": "point-cloud"}}``). Relative paths in TOML text or a dict resolve against
/// ``config_dir`` (default: the working directory).
#[pyclass(module = "vlem", name = "Pipeline", frozen)]
pub struct PyPipeline {
    pipeline: Slot,
    live: LiveMap,
    config: Config,
    ctx: BuildContext,
    report: Arc<Mutex<Option<RunReport>>>,
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The pipeline, unless a run on another Python thread holds it.
fn busy(slot: &Slot) -> PyResult<std::sync::MutexGuard<'_, Option<Pipeline>>> {
    match slot.try_lock() {
        Ok(guard) => Ok(guard),
        Err(std::sync::TryLockError::Poisoned(poisoned)) => Ok(poisoned.into_inner()),
        Err(std::sync::TryLockError::WouldBlock) => Err(PyRuntimeError::new_err(
            "the pipeline is running (Pipeline.run on another thread); wait for that run to end",
        )),
    }
}

/// The config and build context `config` names. A file or TOML text is kept with the config, so
/// that a key a stage parses is found on its line ([`Config::locate`]); a dict's TOML form has no
/// lines the user wrote.
pub(crate) fn load_config(
    config: &Bound<'_, PyAny>,
    config_dir: Option<PathBuf>,
) -> PyResult<(Config, BuildContext)> {
    let text_context = |text: &str| -> PyResult<(Config, BuildContext)> {
        let config = Config::from_toml(text).map_err(errors::core)?;
        let dir = match config_dir.clone() {
            Some(dir) => dir,
            None => std::env::current_dir().map_err(|e| PyRuntimeError::new_err(e.to_string()))?,
        };
        let ctx = BuildContext::for_config_dir(&dir).map_err(errors::core)?;
        Ok((config, ctx))
    };
    if config.is_instance_of::<PyDict>() {
        return text_context(&dict_to_toml(config, "config")?);
    }
    let is_path_like = config.hasattr("__fspath__")?;
    if let Ok(text) = config.extract::<String>()
        && !is_path_like
    {
        let path = PathBuf::from(&text);
        if !(path.is_file() || text.trim_end().ends_with(".toml") && !text.contains('\n')) {
            let (config, ctx) = text_context(&text)?;
            return Ok((config.with_source_text(text, "text"), ctx));
        }
    }
    let path: PathBuf = config.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "config must be a path to a TOML file, TOML text or a dict, not {}",
            config.get_type()
        ))
    })?;
    vlem_core::load_config(&path).map_err(errors::core)
}

/// A progress event as a dict.
fn event_dict<'py>(py: Python<'py>, event: Progress) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    match event {
        Progress::Tracked { index } => {
            d.set_item("event", "tracked")?;
            d.set_item("index", index)?;
        }
        Progress::Integrated { index, map_len } => {
            d.set_item("event", "integrated")?;
            d.set_item("index", index)?;
            d.set_item("map_len", map_len)?;
        }
        Progress::Skipped { index } => {
            d.set_item("event", "skipped")?;
            d.set_item("index", index)?;
        }
    }
    Ok(d)
}

/// Calls a Python progress callback from the pipeline's threads; the first exception it raises
/// is kept and raised when the run returns.
struct ProgressCallback {
    callback: Option<Py<PyAny>>,
    failure: Mutex<Option<PyErr>>,
}

impl ProgressCallback {
    fn new(callback: Option<Py<PyAny>>) -> Self {
        Self {
            callback,
            failure: Mutex::new(None),
        }
    }

    fn call(&self, event: Progress) {
        let Some(callback) = &self.callback else {
            return;
        };
        if lock(&self.failure).is_some() {
            return;
        }
        Python::attach(|py| {
            let outcome = event_dict(py, event).and_then(|d| callback.bind(py).call1((d,)));
            if let Err(e) = outcome {
                *lock(&self.failure) = Some(e);
            }
        });
    }

    fn check(&self) -> PyResult<()> {
        match lock(&self.failure).take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// The run's statistics (``stats.json``'s content) as a dict.
fn report_dict<'py>(
    py: Python<'py>,
    pipeline: &Pipeline,
    config: &Config,
    report: &RunReport,
) -> PyResult<Bound<'py, PyAny>> {
    let map = pipeline.map();
    let stats = report.stats(config.pipeline.mode, map.as_deref(), None);
    to_python(py, &stats)
}

/// Runs `pipeline` over `source` on a worker thread while this thread, the one that called into
/// Python, waits without the GIL and looks at Python's signal handlers ten times a second: the
/// run is stopped at the next frame when one raises (Ctrl-C's `KeyboardInterrupt`), which is
/// returned beside the run's own outcome.
fn run_interruptible(
    py: Python<'_>,
    pipeline: &mut Pipeline,
    source: &mut dyn vlem_core::FrameSource,
    progress: &ProgressCallback,
) -> PyResult<(vlem_core::Result<RunReport>, Option<PyErr>)> {
    let stop = pipeline.stop_handle();
    std::thread::scope(|scope| {
        let (done, finished) = std::sync::mpsc::channel::<()>();
        // In a mutex only because the wait runs in `detach`, whose closure must be `Send`.
        let finished = Mutex::new(finished);
        let worker = scope.spawn(move || {
            let outcome = pipeline.run(source, None, &|e| progress.call(e));
            let _ = done.send(());
            outcome
        });
        let mut interrupt = None;
        loop {
            let waited =
                py.detach(|| lock(&finished).recv_timeout(std::time::Duration::from_millis(100)));
            if !matches!(waited, Err(std::sync::mpsc::RecvTimeoutError::Timeout)) {
                break; // Finished, or the worker ended without saying so.
            }
            if interrupt.is_none()
                && let Err(e) = py.check_signals()
            {
                stop.stop();
                interrupt = Some(e);
            }
        }
        // A signal that arrived after the last look, while the run was finishing, is the
        // caller's too: without this look it would surface only at some later Python line.
        if interrupt.is_none() {
            interrupt = py.check_signals().err();
        }
        let outcome = worker
            .join()
            .map_err(|_| PyRuntimeError::new_err("the pipeline's run thread panicked"))?;
        Ok((outcome, interrupt))
    })
}

/// A pose from a 4x4 camera-to-world matrix.
fn pose_from(value: &Bound<'_, PyAny>) -> PyResult<vlem_core::Pose> {
    let np = value.py().import("numpy")?;
    let m = np.call_method1("asarray", (value, "float64"))?;
    let (m, _) = read::<f64>(
        &m,
        "pose",
        "a 4x4 camera-to-world matrix",
        &[Some(4), Some(4)],
    )?;
    let rotation = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let orthonormal = (rotation.transpose() * rotation - Matrix3::identity())
        .abs()
        .max()
        < 1e-4
        && (rotation.determinant() - 1.0).abs() < 1e-4;
    if !orthonormal || m[12..16] != [0.0, 0.0, 0.0, 1.0] || m.iter().any(|x| !x.is_finite()) {
        return Err(PyValueError::new_err(
            "pose must be a rigid 4x4 camera-to-world matrix (orthonormal rotation, last row 0 0 0 1)",
        ));
    }
    if let Some(why) = vlem_core::types::implausible_position([m[3], m[7], m[11]]) {
        return Err(PyValueError::new_err(format!("pose: {why}")));
    }
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rotation));
    Ok(Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        rotation,
    ))
}

#[pymethods]
impl PyPipeline {
    #[new]
    #[pyo3(signature = (config, *, config_dir = None))]
    fn new(config: &Bound<'_, PyAny>, config_dir: Option<PathBuf>) -> PyResult<Self> {
        let (config, ctx) = load_config(config, config_dir)?;
        let pipeline = Pipeline::from_config(&config, &ctx).map_err(errors::core)?;
        Ok(Self {
            live: pipeline.live(),
            pipeline: Arc::new(Mutex::new(Some(pipeline))),
            config,
            ctx,
            report: Arc::new(Mutex::new(None)),
        })
    }

    fn __repr__(&self) -> String {
        let c = &self.config;
        format!(
            "<vlem.Pipeline tracker `{}`, encoder `{}`, map `{}`, {:?} mode>",
            c.tracker.kind,
            c.encoder.as_ref().map_or("(none)", |e| e.kind.as_str()),
            c.map.as_ref().map_or("(none)", |m| m.kind.as_str()),
            c.pipeline.mode
        )
    }

    /// The config, as TOML text.
    #[getter]
    fn config(&self) -> String {
        self.config.to_toml()
    }

    /// Runs the pipeline over a dataset folder (``dataset``, default the config's ``[dataset]
    /// path``), blocking until it ends, and returns the run's statistics (``stats.json``).
    ///
    /// The GIL is released meanwhile: other threads query ``self.map``. Ctrl-C stops the run at
    /// the next frame and raises ``KeyboardInterrupt``; the map up to then stays. ``progress`` is a
    /// callable receiving one dict per event (``{"event": "tracked" | "integrated" | "skipped",
    /// "index": ..., "map_len": ...}``) or a tqdm-like object (``update(1)`` per tracked frame).
    /// With ``out``, the run's outputs go into that folder as ``vlem run --out`` writes them
    /// (``trajectory.tum``, ``reference.tum`` beside an estimate, ``map.vlem``, ``stats.json``
    /// last), also when Ctrl-C ended it.
    #[pyo3(signature = (dataset = None, *, max_frames = None, progress = None, out = None))]
    fn run<'py>(
        &self,
        py: Python<'py>,
        dataset: Option<PathBuf>,
        max_frames: Option<usize>,
        progress: Option<Bound<'py, PyAny>>,
        out: Option<PathBuf>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let dir = vlem_datasets::dataset_folder(&self.config, &self.ctx, dataset.as_deref())
            .map_err(errors::dataset)?;
        let mut dataset_config = self.config.dataset.clone();
        if max_frames.is_some() {
            dataset_config.max_frames = max_frames;
        }
        let mut source = vlem_datasets::open(&dataset_config, &dir)
            .map_err(|e| errors::core(self.config.locate(e)))?;
        if let Some(bar) = &progress
            && bar.hasattr("update")?
            && bar.getattr("total").is_ok_and(|t| t.is_none())
        {
            // A tqdm bar learns its total.
            bar.setattr("total", source.len())?;
        }
        let progress = ProgressCallback::new(progress.map(|p| adapt_progress(&p)).transpose()?);
        // Never wait for the mutex with the GIL held: the run holding it may need the GIL (a
        // Python encoder, a progress callback).
        let mut slot = busy(&self.pipeline)?;
        let pipeline = slot.as_mut().ok_or_else(|| {
            PyRuntimeError::new_err(
                "the pipeline is being fed frames (Pipeline.start); finish the feed first",
            )
        })?;
        let (outcome, interrupt) = run_interruptible(py, pipeline, source.as_mut(), &progress)?;
        let report = outcome.map_err(errors::core)?;
        if let Some(folder) = &out {
            let mode = self.config.pipeline.mode;
            py.detach(|| vlem_eval::run_folder::write_run(folder, pipeline, &report, mode, None))
                .map_err(errors::eval)?;
        }
        let out = report_dict(py, pipeline, &self.config, &report)?;
        *lock(&self.report) = Some(report);
        // Ctrl-C (or another signal handler raising) ends the run early; the map stays.
        if let Some(e) = interrupt {
            return Err(e);
        }
        progress.check()?;
        Ok(out)
    }

    /// Starts the pipeline on frames you push (``Feed.push``) from numpy arrays, on a thread of
    /// its own, and returns the feed; ``Feed.finish`` (or leaving a ``with`` block) ends the
    /// run.
    ///
    /// ``intrinsics`` is the camera of every frame. ``poses``: whether frames come with poses
    /// (the ``ground-truth`` tracker needs them; other trackers estimate poses and keep given
    /// ones as the reference). ``capacity``: frames that may wait for the tracker.
    #[pyo3(signature = (intrinsics, *, poses = None, capacity = 4, progress = None))]
    fn start(
        &self,
        py: Python<'_>,
        intrinsics: PyRef<'_, PyIntrinsics>,
        poses: Option<bool>,
        capacity: usize,
        progress: Option<Bound<'_, PyAny>>,
    ) -> PyResult<PyFeed> {
        let mut pipeline = busy(&self.pipeline)?.take().ok_or_else(|| {
            PyRuntimeError::new_err(
                "the pipeline is already being fed frames; finish that feed first",
            )
        })?;
        let has_poses = poses.unwrap_or_else(|| pipeline.tracker().needs_dataset_poses());
        let spec = StreamSpec {
            description: "frames fed from Python".into(),
            intrinsics: intrinsics.0,
            has_poses,
            capacity,
            max_stamp_jump: vlem_core::stream::DEFAULT_MAX_STAMP_JUMP,
        };
        let (sender, mut stream) = match frame_stream(spec) {
            Ok(pair) => pair,
            Err(e) => {
                *lock(&self.pipeline) = Some(pipeline);
                return Err(errors::core(e));
            }
        };
        let progress = Arc::new(ProgressCallback::new(
            progress.map(|p| adapt_progress(&p)).transpose()?,
        ));
        let run_progress = progress.clone();
        let handle = py.detach(|| {
            std::thread::Builder::new()
                .name("vlem-feed".into())
                .spawn(move || {
                    let report = pipeline.run(&mut stream, None, &|e| run_progress.call(e));
                    drop::<FrameStream>(stream);
                    (pipeline, report)
                })
        });
        let handle = handle.map_err(|e| {
            PyRuntimeError::new_err(format!("cannot start the pipeline thread: {e}"))
        })?;
        Ok(PyFeed {
            sender: Mutex::new(Some(sender)),
            run: Mutex::new(Some(handle)),
            slot: self.pipeline.clone(),
            report: self.report.clone(),
            config: self.config.clone(),
            live: self.live.clone(),
            intrinsics: intrinsics.0,
            progress,
            outcome: Mutex::new(None),
        })
    }

    /// The map (live: reads see whole integrated frames, also while a run goes on).
    #[getter]
    fn map(&self) -> PyResult<PyMap> {
        PyMap::live(&self.live)
    }

    /// Where the current or last run is: counters (frames tracked, integrated, skipped, lost),
    /// map size and the tracker's latest pose.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.live.status())
    }

    /// The last finished run's trajectory: ``float64[N, 8]`` rows of timestamp, position
    /// ``x y z`` and orientation quaternion ``qx qy qz qw`` (camera to world, TUM order).
    #[getter]
    fn trajectory<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let report = lock(&self.report);
        let rows: Vec<f64> = report
            .as_ref()
            .map(|r| {
                r.poses()
                    .iter()
                    .flat_map(|(t, pose)| {
                        let p = pose.translation.vector;
                        let q = pose.rotation.quaternion();
                        [*t, p.x, p.y, p.z, q.i, q.j, q.k, q.w]
                    })
                    .collect()
            })
            .unwrap_or_default();
        let n = rows.len() / 8;
        give(py, rows, &[n, 8])
    }
}

/// A callable for the progress events: the callable itself, or a wrapper around a tqdm-like
/// object (anything with ``update``).
fn adapt_progress(progress: &Bound<'_, PyAny>) -> PyResult<Py<PyAny>> {
    let py = progress.py();
    if progress.hasattr("update")? {
        let adapter = py.import("vlem")?.getattr("_progress_adapter")?;
        return Ok(adapter.call1((progress,))?.unbind());
    }
    if progress.is_callable() {
        return Ok(progress.clone().unbind());
    }
    Err(PyTypeError::new_err(
        "progress must be a callable taking an event dict, or a tqdm-like object with update()",
    ))
}

/// The thread a feed's run goes on; it hands the pipeline back with the run's outcome.
type RunThread = JoinHandle<(Pipeline, vlem_core::Result<RunReport>)>;

/// Frames pushed into a running pipeline (from ``Pipeline.start``); a context manager that
/// finishes the run on leaving the ``with`` block.
#[pyclass(module = "vlem", name = "Feed", frozen)]
pub struct PyFeed {
    sender: Mutex<Option<FrameSender>>,
    run: Mutex<Option<RunThread>>,
    slot: Slot,
    report: Arc<Mutex<Option<RunReport>>>,
    config: Config,
    live: LiveMap,
    intrinsics: Intrinsics,
    progress: Arc<ProgressCallback>,
    /// The statistics once finished (a second `finish` returns them again).
    outcome: Mutex<Option<Py<PyAny>>>,
}

impl PyFeed {
    /// Waits for the run to end, gives the pipeline back and returns its statistics.
    fn join(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        if let Some(done) = lock(&self.outcome).as_ref() {
            return Ok(done.clone_ref(py));
        }
        drop(lock(&self.sender).take());
        let Some(handle) = lock(&self.run).take() else {
            return Err(PyRuntimeError::new_err(
                "the feed's run ended with an error (raised before)",
            ));
        };
        let (pipeline, report) = py
            .detach(|| handle.join())
            .map_err(|_| PyRuntimeError::new_err("the pipeline thread panicked"))?;
        let outcome = report.map_err(errors::core).and_then(|report| {
            let out = report_dict(py, &pipeline, &self.config, &report)?;
            *lock(&self.report) = Some(report);
            Ok(out.unbind())
        });
        *lock(&self.slot) = Some(pipeline);
        let outcome = outcome?;
        self.progress.check()?;
        *lock(&self.outcome) = Some(outcome.clone_ref(py));
        Ok(outcome)
    }
}

#[pymethods]
impl PyFeed {
    /// Pushes one RGB-D frame: ``colour`` ``uint8[h, w, 3]``; ``depth`` ``float32[h, w]`` in
    /// metres or ``uint16[h, w]`` in units of 1/``depth_scale`` m (1000: millimetres); 0 or NaN
    /// is no depth. ``timestamp`` in seconds (default: now), increasing; ``pose`` an optional
    /// 4x4 camera-to-world matrix.
    ///
    /// Returns the frame's index in the run. With ``block=False`` a full queue drops the frame
    /// and returns ``None`` (count it) instead of waiting for the tracker.
    #[pyo3(signature = (colour, depth, *, timestamp = None, pose = None, depth_scale = 1000.0, block = true))]
    #[allow(clippy::too_many_arguments, reason = "Feed.push's keyword arguments")]
    fn push(
        &self,
        py: Python<'_>,
        colour: &Bound<'_, PyAny>,
        depth: &Bound<'_, PyAny>,
        timestamp: Option<f64>,
        pose: Option<&Bound<'_, PyAny>>,
        depth_scale: f32,
        block: bool,
    ) -> PyResult<Option<usize>> {
        let c = self.intrinsics;
        let (w, h) = (c.width as usize, c.height as usize);
        let (rgb, _) = read::<u8>(
            colour,
            "colour",
            &format!("uint8[{h}, {w}, 3]"),
            &[Some(h), Some(w), Some(3)],
        )?;
        let depth_image = if depth
            .getattr("dtype")
            .and_then(|d| d.str())
            .is_ok_and(|d| d == "uint16")
        {
            if !(depth_scale.is_finite() && depth_scale > 0.0) {
                return Err(PyValueError::new_err(format!(
                    "depth_scale must be positive, not {depth_scale}"
                )));
            }
            let (raw, _) = read::<u16>(
                depth,
                "depth",
                &format!("uint16[{h}, {w}]"),
                &[Some(h), Some(w)],
            )?;
            DepthImage::from_raw_u16(c.width, c.height, &raw, depth_scale)
        } else {
            let (metres, _) = read::<f32>(
                depth,
                "depth",
                &format!("float32[{h}, {w}] in metres or uint16[{h}, {w}]"),
                &[Some(h), Some(w)],
            )?;
            DepthImage::new(c.width, c.height, metres)
        }
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let colour_image = RgbImage::new(c.width, c.height, rgb)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let pose = pose.map(pose_from).transpose()?;
        let timestamp = match timestamp {
            Some(t) => t,
            None => std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64()),
        };
        let frame = Frame::new(0, timestamp, colour_image, depth_image, c, pose)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let sender = lock(&self.sender)
            .clone()
            .ok_or_else(|| PyRuntimeError::new_err("the feed is finished"))?;
        let sent = py.detach(|| {
            if block {
                sender.send(frame).map(Some)
            } else {
                sender.try_send(frame)
            }
        });
        match sent {
            Ok(index) => Ok(index),
            // The run has stopped: raise why (its error) rather than only that it stopped.
            Err(vlem_core::CoreError::StreamClosed) => {
                self.join(py)?;
                Err(errors::core(vlem_core::CoreError::StreamClosed))
            }
            Err(e) => Err(errors::core(e)),
        }
    }

    /// Ends the stream, waits for the frames already pushed to be tracked and integrated, and
    /// returns the run's statistics; raises the run's error (a Python encoder's own exception
    /// included) if it failed. The map stays readable either way.
    fn finish(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        self.join(py)
    }

    /// The map being built.
    #[getter]
    fn map(&self) -> PyResult<PyMap> {
        PyMap::live(&self.live)
    }

    /// The run's counters and latest pose.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.live.status())
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    /// Finishes the run; an exception already leaving the block is not hidden by one from
    /// finishing.
    #[pyo3(signature = (exc_type = None, _exc_value = None, _traceback = None))]
    fn __exit__(
        &self,
        py: Python<'_>,
        exc_type: Option<&Bound<'_, PyAny>>,
        _exc_value: Option<&Bound<'_, PyAny>>,
        _traceback: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<bool> {
        let finished = self.join(py);
        match (exc_type.filter(|t| !t.is_none()), finished) {
            (None, Err(e)) => Err(e),
            _ => Ok(false),
        }
    }
}
