//! ONNX Runtime for the `onnx` encoder: the shared library, loaded once per process, and the
//! sessions over model files.
//!
//! Why it exists: `ort` is built here without its binary download (`load-dynamic`), so the
//! library must be found at run time, and `ort` allows one library and one environment per
//! process. This module owns that process-wide state: it finds the library (config, then
//! `ORT_DYLIB_PATH`, then the pip package `onnxruntime` asked of `python3`), loads it with
//! [`ort::init_from`] (never `ort::init`, which panics when no library is found), refuses a
//! second, different library with an error that says so, and opens sessions with errors that
//! name the model file.

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

use ort::environment::Environment;
use ort::session::{Session, SessionInputValue};
use ort::value::{Outlet, Tensor, TensorElementType, TensorRef, ValueType};

use crate::error::BackendError;

/// How to get the ONNX Runtime library, for the messages that say it is missing.
pub const ORT_INSTALL_HINT: &str = "install it with `python3 -m pip install --no-deps \
     onnxruntime==1.31.1` (found automatically through `python3`, also with `pip install --target \
     DIR` and DIR on PYTHONPATH), or set `[encoder] library = \"/path/to/\
     libonnxruntime.so\"` or the environment variable ORT_DYLIB_PATH (ONNX Runtime 1.31 or newer)";

/// The environment variable naming the library file (the one `ort` itself reads).
pub const LIBRARY_ENV: &str = "ORT_DYLIB_PATH";

/// The Python package whose `capi/` folder holds the library.
pub const PYTHON_PACKAGE: &str = "onnxruntime";

/// The library this process loaded, and the one environment `ort` allows.
struct State {
    /// Canonical path of the library, once loaded (`ort` keeps it for the life of the process).
    library: Option<PathBuf>,
    environment: Option<Environment>,
}

/// Process-wide, like `ort`'s own state.
static RUNTIME: Mutex<State> = Mutex::new(State {
    library: None,
    environment: None,
});

/// The ONNX Runtime environment, loading the library on first use.
///
/// `configured` is the `library` of the config (already resolved against the config folder).
/// When it is unset the library comes from `ORT_DYLIB_PATH`, else from the pip package
/// `onnxruntime`; once a library is loaded, an encoder that names none shares it.
///
/// # Errors
/// [`BackendError::OnnxRuntimeLoad`] for a named library that does not exist or fails to load,
/// [`BackendError::OnnxRuntimeNotFound`] when nothing names or provides one,
/// [`BackendError::OnnxRuntimeConflict`] when another library is already loaded.
pub fn environment(configured: Option<&Path>) -> Result<Environment, BackendError> {
    let named = named_library(configured, std::env::var_os(LIBRARY_ENV));
    // Checked before the process state so that a missing file gets the same answer whether or
    // not a library is loaded already.
    if let Some((path, origin)) = &named
        && !path.is_file()
    {
        return Err(load_error(path, origin, "no such file".to_owned()));
    }

    let mut state = RUNTIME.lock().unwrap_or_else(PoisonError::into_inner);
    let (path, origin) = match (&state.library, named) {
        (Some(loaded), Some((path, _))) if canonical(&path) != *loaded => {
            return Err(BackendError::OnnxRuntimeConflict {
                loaded: loaded.clone(),
                requested: path,
            });
        }
        (Some(loaded), _) => (loaded.clone(), "the library loaded before".to_owned()),
        (None, Some(named)) => named,
        (None, None) => python_library().map_err(not_found)?,
    };
    if let Some(environment) = &state.environment {
        return Ok(environment.clone());
    }
    // Loads the library the first time; later (after a failed environment) it is loaded already
    // and `init_from` of the same path only hands out a builder.
    let builder = ort::init_from(&path).map_err(|e| load_error(&path, &origin, e.to_string()))?;
    state.library = Some(canonical(&path));
    let environment = builder.with_name("vlem").build().map_err(|e| {
        load_error(
            &path,
            &origin,
            format!("cannot create the environment: {e}"),
        )
    })?;
    state.environment = Some(environment.clone());
    Ok(environment)
}

/// The library the config or the environment variable (its value `env`) names, with where the
/// name came from; the config wins.
fn named_library(
    configured: Option<&Path>,
    env: Option<std::ffi::OsString>,
) -> Option<(PathBuf, String)> {
    match configured {
        Some(path) => Some((path.to_path_buf(), "[encoder] library".to_owned())),
        None => env.filter(|v| !v.is_empty()).map(|v| {
            (
                PathBuf::from(v),
                format!("the environment variable {LIBRARY_ENV}"),
            )
        }),
    }
}

/// Nothing named a library and the Python package did not provide one, for the reason `why`.
fn not_found(why: String) -> BackendError {
    BackendError::OnnxRuntimeNotFound {
        searched: vec![
            "[encoder] library: not set".to_owned(),
            format!("{LIBRARY_ENV}: not set"),
            format!("Python package {PYTHON_PACKAGE}: {why}"),
        ],
        hint: ORT_INSTALL_HINT,
    }
}

/// The canonical path of the library this process loaded, if any.
pub fn loaded_library() -> Option<PathBuf> {
    RUNTIME
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .library
        .clone()
}

fn canonical(path: &Path) -> PathBuf {
    path.canonicalize().unwrap_or_else(|_| path.to_path_buf())
}

fn load_error(path: &Path, origin: &str, reason: String) -> BackendError {
    BackendError::OnnxRuntimeLoad {
        path: path.to_path_buf(),
        origin: origin.to_owned(),
        reason,
        hint: ORT_INSTALL_HINT,
    }
}

/// The library inside the pip package `onnxruntime` (`capi/libonnxruntime.so.<version>` on
/// Linux), with where it came from; the package folder is asked of `python3` with
/// `importlib.util.find_spec`, which locates it without importing it.
fn python_library() -> Result<(PathBuf, String), String> {
    let package = crate::model_files::python_package_dir(PYTHON_PACKAGE)?;
    let capi = package.join("capi");
    let entries = std::fs::read_dir(&capi)
        .map_err(|e| format!("installed, but {} cannot be read ({e})", capi.display()))?;
    let mut names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|name| is_library_name(name))
        .collect();
    names.sort();
    match names.pop() {
        Some(name) => Ok((
            capi.join(name),
            format!("the Python package {PYTHON_PACKAGE}"),
        )),
        None => Err(format!(
            "installed, but {} holds no {}onnxruntime{} library",
            capi.display(),
            std::env::consts::DLL_PREFIX,
            std::env::consts::DLL_SUFFIX
        )),
    }
}

/// Whether `name` is the main ONNX Runtime library (`libonnxruntime.so`,
/// `libonnxruntime.so.1.31.1`, `libonnxruntime.1.31.1.dylib`, `onnxruntime.dll`), not one of the
/// provider libraries beside it.
fn is_library_name(name: &str) -> bool {
    let stem = format!("{}onnxruntime", std::env::consts::DLL_PREFIX);
    let suffix = std::env::consts::DLL_SUFFIX;
    let Some(rest) = name.strip_prefix(&stem) else {
        return false;
    };
    // What follows the stem: the suffix, a version then the suffix, or the suffix then a version.
    rest == suffix
        || rest.starts_with(&format!("{suffix}."))
        || (rest.starts_with('.') && rest.ends_with(suffix))
}

/// One ONNX model: its session and the names and types of its inputs and outputs.
pub struct Model {
    session: Mutex<Session>,
    path: PathBuf,
    inputs: Vec<(String, ValueType)>,
    outputs: Vec<(String, ValueType)>,
}

impl std::fmt::Debug for Model {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Model")
            .field("path", &self.path)
            .field("inputs", &self.inputs)
            .field("outputs", &self.outputs)
            .finish_non_exhaustive()
    }
}

/// An input to [`Model::run`]: a name and a tensor of one of the supported element types.
pub enum Input<'a> {
    /// A float tensor, borrowed.
    F32(Vec<i64>, &'a [f32]),
    /// An int64 tensor.
    I64(Vec<i64>, Vec<i64>),
    /// An int32 tensor.
    I32(Vec<i64>, Vec<i32>),
}

/// One output of [`Model::run`], copied out of the session.
#[derive(Clone, Debug, PartialEq)]
pub struct Output {
    /// The tensor's shape.
    pub shape: Vec<i64>,
    /// Its values, row-major.
    pub data: Vec<f32>,
}

impl Model {
    /// Opens `path` on `environment` with `threads` intra-op threads (ONNX Runtime's default,
    /// one per physical core, when `None`).
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] naming the file when it is missing or ONNX Runtime
    /// refuses it; [`BackendError::InvalidParams`] for zero threads.
    pub fn load(
        environment: &Environment,
        path: &Path,
        threads: Option<usize>,
    ) -> Result<Self, BackendError> {
        let invalid = |reason: String| BackendError::InvalidModelFile {
            path: path.to_path_buf(),
            reason,
        };
        if !path.is_file() {
            return Err(invalid(
                "no such file (export the model to ONNX first, e.g. with torch.onnx.export)"
                    .to_owned(),
            ));
        }
        let mut builder = Session::builder(environment)
            .map_err(|e| invalid(format!("cannot create a session: {e}")))?;
        if let Some(threads) = threads {
            // Each session starts this many threads; more than a large machine's cores only
            // oversubscribe it.
            if let Err(range) = vlem_core::ranges::count(threads, 1, 256, "") {
                return Err(BackendError::InvalidParams(format!(
                    "threads {range} (leave it out for ONNX Runtime's default)"
                )));
            }
            builder = builder
                .with_intra_threads(threads)
                .map_err(|e| invalid(format!("cannot set {threads} threads: {e}")))?;
        }
        let session = builder
            .commit_from_file(path)
            .map_err(|e| invalid(format!("ONNX Runtime cannot load it: {e}")))?;
        let describe = |outlets: &[Outlet]| -> Vec<(String, ValueType)> {
            outlets
                .iter()
                .map(|o| (o.name().to_owned(), o.dtype().clone()))
                .collect()
        };
        Ok(Self {
            inputs: describe(session.inputs()),
            outputs: describe(session.outputs()),
            session: Mutex::new(session),
            path: path.to_path_buf(),
        })
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The inputs' names and types, in the model's order.
    pub fn inputs(&self) -> &[(String, ValueType)] {
        &self.inputs
    }

    /// The outputs' names and types, in the model's order.
    pub fn outputs(&self) -> &[(String, ValueType)] {
        &self.outputs
    }

    /// The input called `name`, or the first input when `name` is `None`.
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] naming the inputs there are.
    pub fn input(&self, name: Option<&str>) -> Result<&(String, ValueType), BackendError> {
        self.outlet(&self.inputs, name, "input")
    }

    /// The output called `name`, or the first output when `name` is `None`.
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] naming the outputs there are.
    pub fn output(&self, name: Option<&str>) -> Result<&(String, ValueType), BackendError> {
        self.outlet(&self.outputs, name, "output")
    }

    fn outlet<'a>(
        &self,
        outlets: &'a [(String, ValueType)],
        name: Option<&str>,
        what: &str,
    ) -> Result<&'a (String, ValueType), BackendError> {
        let found = match name {
            Some(name) => outlets.iter().find(|(n, _)| n == name),
            None => outlets.first(),
        };
        found.ok_or_else(|| BackendError::InvalidModelFile {
            path: self.path.clone(),
            reason: format!(
                "the model has no {what} {} (its {what}s: {})",
                name.map_or_else(|| "at all".to_owned(), |n| format!("{n:?}")),
                list_names(outlets)
            ),
        })
    }

    /// Runs the model on `inputs` and copies out the float output `output`.
    ///
    /// # Errors
    /// [`BackendError::Inference`] when ONNX Runtime fails or the output is not a float tensor.
    pub fn run(
        &self,
        inputs: Vec<(&str, Input<'_>)>,
        output: &str,
        what: &str,
    ) -> Result<Output, BackendError> {
        let fail = |e: ort::Error| BackendError::Inference {
            what: what.to_owned(),
            source: Box::new(e),
        };
        let mut values: Vec<(Cow<'_, str>, SessionInputValue<'_>)> =
            Vec::with_capacity(inputs.len());
        for (name, input) in inputs {
            let value: SessionInputValue<'_> = match input {
                Input::F32(shape, data) => TensorRef::from_array_view((shape, data))
                    .map_err(fail)?
                    .into(),
                Input::I64(shape, data) => Tensor::from_array((shape, data)).map_err(fail)?.into(),
                Input::I32(shape, data) => Tensor::from_array((shape, data)).map_err(fail)?.into(),
            };
            values.push((Cow::Borrowed(name), value));
        }
        let mut session = self.session.lock().unwrap_or_else(PoisonError::into_inner);
        let outputs = session.run(values).map_err(fail)?;
        let value = outputs.get(output).ok_or_else(|| BackendError::Inference {
            what: what.to_owned(),
            source: format!("the model returned no output {output:?}").into(),
        })?;
        let (shape, data) = value.try_extract_tensor::<f32>().map_err(fail)?;
        Ok(Output {
            shape: shape.to_vec(),
            data: data.to_vec(),
        })
    }
}

/// The static shape of a tensor type (`-1` for dynamic axes), `None` for other types.
pub fn tensor_shape(dtype: &ValueType) -> Option<&[i64]> {
    match dtype {
        ValueType::Tensor { shape, .. } => Some(&**shape),
        _ => None,
    }
}

/// The element type of a tensor type, `None` for other types.
pub fn element_type(dtype: &ValueType) -> Option<TensorElementType> {
    match dtype {
        ValueType::Tensor { ty, .. } => Some(*ty),
        _ => None,
    }
}

/// `"a", "b"` for the names of `outlets`.
pub fn list_names(outlets: &[(String, ValueType)]) -> String {
    outlets
        .iter()
        .map(|(n, _)| format!("{n:?}"))
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn library_names_match_the_main_library_only() {
        if cfg!(target_os = "linux") {
            assert!(is_library_name("libonnxruntime.so"));
            assert!(is_library_name("libonnxruntime.so.1.31.1"));
            assert!(!is_library_name("libonnxruntime_providers_shared.so"));
            assert!(!is_library_name("onnxruntime_pybind11_state.so"));
        }
    }

    #[test]
    fn the_config_wins_over_the_environment_variable() {
        let env = Some(std::ffi::OsString::from("/env/libonnxruntime.so"));
        let (path, origin) = named_library(Some(Path::new("/cfg/lib.so")), env.clone()).unwrap();
        assert_eq!(
            (path.as_path(), origin.as_str()),
            (Path::new("/cfg/lib.so"), "[encoder] library")
        );
        let (path, origin) = named_library(None, env).unwrap();
        assert_eq!(path, Path::new("/env/libonnxruntime.so"));
        assert_eq!(origin, "the environment variable ORT_DYLIB_PATH");
        assert!(named_library(None, Some(std::ffi::OsString::new())).is_none());
        assert!(named_library(None, None).is_none());
    }

    #[test]
    fn not_found_says_where_it_looked_and_the_setup_command() {
        let message = not_found("not installed for python3".to_owned())
            .into_core("onnx")
            .to_string();
        assert!(
            message.starts_with(
                "encoder `onnx`: the ONNX Runtime shared library was not found (looked: \
                 [encoder] library: not set; ORT_DYLIB_PATH: not set; Python package \
                 onnxruntime: not installed for python3); install it with \
                 `python3 -m pip install --no-deps onnxruntime==1.31.1`"
            ),
            "{message}"
        );
    }
}
