//! The `python` encoder: a Python object behind [`vlem_core::Encoder`].
//!
//! Every call attaches to the interpreter for its duration only, converts the frame into numpy
//! arrays, calls the object, and checks what it returns before vlem uses it: a Python encoder's
//! mistakes are errors that name the class, the method and the shape expected, never a crash or a
//! silently wrong map.

use std::path::PathBuf;

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use serde::Deserialize;
use vlem_core::{
    BuildContext, CoreError, Encoder, NO_REGION, PixelEmbeddings, Region, RgbImage, StageKind,
};

/// The registered name.
pub const NAME: &str = "python";

/// Parameters of the `python` encoder: the `[encoder]` section without `kind`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PythonEncoderConfig {
    /// An importable module (`package.module`); give this or `path`.
    #[serde(default)]
    pub module: Option<String>,
    /// A `.py` file (relative paths resolve against the config's folder); give this or `module`.
    #[serde(default)]
    pub path: Option<PathBuf>,
    /// The class in the module; it is called with `params` as keyword arguments.
    #[serde(rename = "class")]
    pub class_name: String,
    /// Keyword arguments of the constructor (`[encoder.params]`).
    #[serde(default)]
    pub params: toml::Table,
}

/// Errors of the `python` encoder.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PythonEncoderError {
    /// The module or file could not be imported, or has no such class.
    #[error("cannot load the Python encoder {what}: {message}")]
    Load {
        /// Module or file, and class.
        what: String,
        /// The Python exception with its traceback.
        message: String,
        /// The exception itself.
        exception: Option<PyErr>,
    },
    /// The class raised an exception.
    #[error("{class}.{method} raised {message}")]
    Raised {
        /// The encoder's class.
        class: String,
        /// The method that raised.
        method: &'static str,
        /// The exception with its traceback.
        message: String,
        /// The exception itself, raised again by the Python package.
        exception: PyErr,
    },
    /// The class returned something vlem cannot use.
    #[error("{class}.{method} returned {problem}; expected {expected}")]
    Output {
        /// The encoder's class.
        class: String,
        /// The method.
        method: &'static str,
        /// What is wrong.
        problem: String,
        /// What vlem expects.
        expected: String,
    },
}

/// The Python exception raised inside a Python encoder somewhere in `error`'s cause chain, so that
/// a Python front-end can raise that exception again instead of a copy of its message.
pub fn raised_exception<'e>(error: &'e (dyn std::error::Error + 'static)) -> Option<&'e PyErr> {
    let mut cause = Some(error);
    while let Some(e) = cause {
        match e.downcast_ref::<PythonEncoderError>() {
            Some(PythonEncoderError::Raised { exception, .. }) => return Some(exception),
            Some(PythonEncoderError::Load {
                exception: Some(exception),
                ..
            }) => return Some(exception),
            _ => {}
        }
        // `CoreError::Stage` keeps the plugin's error as its source.
        cause = e.source();
    }
    None
}

/// What an array returned by the Python object must be.
struct ArraySpec<'a> {
    /// The method that returned it.
    method: &'static str,
    /// What it is, for the error ("a table").
    what: &'a str,
    /// numpy dtype kinds accepted (`"f"`, `"iu"`, ...).
    kinds: &'a str,
    /// The dtype it is converted to.
    dtype: &'a str,
    /// Its shape; `None` for any length along that axis.
    shape: &'a [Option<usize>],
    /// The sentence that says what vlem expects.
    expected: String,
}

/// An encoder implemented by a Python object.
pub struct PythonEncoder {
    instance: Py<PyAny>,
    class: String,
    dim: usize,
    needs_regions: bool,
    has_text: bool,
}

impl std::fmt::Debug for PythonEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PythonEncoder")
            .field("class", &self.class)
            .field("dim", &self.dim)
            .field("needs_regions", &self.needs_regions)
            .field("has_text", &self.has_text)
            .finish_non_exhaustive()
    }
}

/// The exception's type, message and traceback as Python prints them.
fn describe(py: Python<'_>, err: &PyErr) -> String {
    let mut text = err.to_string();
    if let Some(traceback) = err.traceback(py).and_then(|tb| tb.format().ok()) {
        text.push('\n');
        text.push_str(traceback.trim_end());
    }
    text
}

fn stage_error(e: PythonEncoderError) -> CoreError {
    CoreError::stage(StageKind::Encoder, NAME, e)
}

fn invalid_params(message: String) -> CoreError {
    CoreError::InvalidParams {
        section: StageKind::Encoder.section().to_owned(),
        name: NAME.to_owned(),
        message,
    }
}

/// What `module` and `path` are for.
const SOURCE: &str =
    "give the encoder's code as either `module = \"package.module\"` or `path = \"file.py\"`";

/// Builds the encoder from its `[encoder]` parameters (the registered build function): imports
/// the module or file, constructs the class with `params`, and reads `dim` and `needs_regions`.
///
/// # Errors
/// [`CoreError::InvalidParams`] for unknown keys, missing or doubled `module`/`path`, or a class
/// without a positive integer `dim`; a stage error with the Python exception when importing or
/// constructing fails.
pub fn build(params: &toml::Table, ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: PythonEncoderConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    let source = match (&config.module, &config.path) {
        (Some(module), None) => Source::Module(module.clone()),
        (None, Some(path)) => Source::File(ctx.resolve(path)),
        (None, None) => return Err(invalid_params(SOURCE.into())),
        (Some(_), Some(_)) => return Err(invalid_params(format!("{SOURCE}, not both"))),
    };
    if let Source::File(path) = &source
        && !path.is_file()
    {
        return Err(CoreError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "the Python encoder's file (`path` in [encoder]) does not exist",
            ),
        ));
    }
    Python::initialize();
    Python::attach(|py| PythonEncoder::load(py, &source, &config)).map(|e| Box::new(e) as _)
}

enum Source {
    Module(String),
    File(PathBuf),
}

impl Source {
    fn describe(&self, class: &str) -> String {
        match self {
            Source::Module(m) => format!("class `{class}` of module `{m}`"),
            Source::File(p) => format!("class `{class}` of {}", p.display()),
        }
    }
}

impl PythonEncoder {
    fn load(
        py: Python<'_>,
        source: &Source,
        config: &PythonEncoderConfig,
    ) -> vlem_core::Result<Self> {
        let what = source.describe(&config.class_name);
        let load_error = |err: PyErr| {
            stage_error(PythonEncoderError::Load {
                what: what.clone(),
                message: describe(py, &err),
                exception: Some(err),
            })
        };
        add_virtualenv(py).map_err(load_error)?;
        let module = match source {
            Source::Module(name) => py.import(name.as_str()).map_err(load_error)?,
            Source::File(path) => import_file(py, path).map_err(load_error)?,
        };
        let class = module
            .getattr(config.class_name.as_str())
            .map_err(load_error)?;
        let kwargs = toml_to_python(py, &config.params).map_err(load_error)?;
        let instance = class.call((), Some(&kwargs)).map_err(load_error)?;
        let dim = instance
            .getattr("dim")
            .and_then(|d| d.extract::<usize>())
            .ok()
            .filter(|&d| d > 0)
            .ok_or_else(|| {
                invalid_params(format!(
                    "the {what} has no positive integer attribute `dim` (the embedding dimension)"
                ))
            })?;
        let needs_regions = match instance.getattr_opt("needs_regions").map_err(load_error)? {
            Some(flag) => flag.is_truthy().map_err(load_error)?,
            None => false,
        };
        if !instance.hasattr("encode_image").map_err(load_error)? {
            return Err(invalid_params(format!(
                "the {what} has no method `encode_image(rgb, regions)`"
            )));
        }
        let has_text = instance.hasattr("encode_text").map_err(load_error)?;
        let class = instance
            .get_type()
            .qualname()
            .map_or_else(|_| config.class_name.clone(), |n| n.to_string());
        Ok(Self {
            instance: instance.unbind(),
            class,
            dim,
            needs_regions,
            has_text,
        })
    }

    fn raised(&self, py: Python<'_>, method: &'static str, err: PyErr) -> CoreError {
        stage_error(PythonEncoderError::Raised {
            class: self.class.clone(),
            method,
            message: describe(py, &err),
            exception: err,
        })
    }

    fn output(&self, method: &'static str, problem: String, expected: String) -> CoreError {
        stage_error(PythonEncoderError::Output {
            class: self.class.clone(),
            method,
            problem,
            expected,
        })
    }

    /// `value` as a C-contiguous array of `T` after checking it against `spec`; its values and
    /// shape.
    fn array<'py, T: numpy::Element + Copy>(
        &self,
        py: Python<'py>,
        spec: &ArraySpec<'_>,
        value: &Bound<'py, PyAny>,
    ) -> vlem_core::Result<(Vec<T>, Vec<usize>)> {
        let method = spec.method;
        let raised = |e| self.raised(py, method, e);
        let np = py.import("numpy").map_err(raised)?;
        let array = np.call_method1("asarray", (value,)).map_err(raised)?;
        let dtype = array.getattr("dtype").map_err(raised)?;
        let kind: String = dtype
            .getattr("kind")
            .and_then(|k| k.extract())
            .map_err(raised)?;
        let shape: Vec<usize> = array
            .getattr("shape")
            .and_then(|s| s.extract())
            .map_err(raised)?;
        let refuse = |problem: String| self.output(method, problem, spec.expected.clone());
        if !spec.kinds.contains(kind.as_str()) {
            return Err(refuse(format!("{} of dtype {dtype}", spec.what)));
        }
        let fits = shape.len() == spec.shape.len()
            && shape
                .iter()
                .zip(spec.shape)
                .all(|(a, s)| s.is_none_or(|s| s == *a));
        if !fits {
            return Err(refuse(format!("{} of shape {shape:?}", spec.what)));
        }
        let contiguous = np
            .call_method1("ascontiguousarray", (array, spec.dtype))
            .map_err(raised)?;
        let values: PyReadonlyArrayDyn<'py, T> = contiguous.extract().map_err(raised)?;
        let values = values
            .as_slice()
            .map_err(|e| refuse(format!("{}: {e}", spec.what)))?
            .to_vec();
        Ok((values, shape))
    }

    /// Reads `encode_image`'s result: a region layout or a patch grid.
    fn read_embeddings<'py>(
        &self,
        py: Python<'py>,
        out: &Bound<'py, PyAny>,
        width: u32,
        height: u32,
    ) -> vlem_core::Result<PixelEmbeddings> {
        const METHOD: &str = "encode_image";
        let (w, h, d) = (width as usize, height as usize, self.dim);
        let field = |name: &str| -> vlem_core::Result<Option<Bound<'py, PyAny>>> {
            let value = match out.cast::<PyDict>() {
                Ok(dict) => dict.get_item(name),
                Err(_) => out.getattr_opt(name),
            };
            value
                .map(|v| v.filter(|v| !v.is_none()))
                .map_err(|e| self.raised(py, METHOD, e))
        };
        let layouts = format!(
            "a region layout {{\"index\": int[{h}, {w}] (-1: no embedding), \"table\": \
             float[regions, {d}]}} or a patch grid {{\"grid\": float[grid_h, grid_w, {d}]}} \
             (vlem.Regions / vlem.PatchGrid)"
        );
        if let Some(grid) = field("grid")? {
            let spec = ArraySpec {
                method: METHOD,
                what: "a grid",
                kinds: "f",
                dtype: "float32",
                shape: &[None, None, Some(d)],
                expected: format!("a patch grid float[grid_h, grid_w, {d}]"),
            };
            let (data, shape) = self.array::<f32>(py, &spec, &grid)?;
            let (gh, gw) = (shape[0], shape[1]);
            if let Some(patch) = field("patch_size")? {
                let patch: usize = patch.extract().map_err(|e| self.raised(py, METHOD, e))?;
                if gw * patch != w || gh * patch != h {
                    return Err(self.output(
                        METHOD,
                        format!(
                            "a {gh}x{gw} grid of {patch}-pixel patches ({}x{} pixels)",
                            gw * patch,
                            gh * patch
                        ),
                        format!("patches that cover the {w}x{h} image"),
                    ));
                }
            }
            // A grid of zeros gives no pixel an embedding: the map would stay empty without a
            // word (region tables refuse zero rows themselves).
            if data.iter().all(|x| *x == 0.0) {
                return Err(self.output(
                    METHOD,
                    format!("a {gh}x{gw} grid whose every value is zero"),
                    "patch embeddings with at least one nonzero value (an encoder that failed \
                     silently?)"
                        .to_owned(),
                ));
            }
            let to_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
            return PixelEmbeddings::from_patch_grid(
                width,
                height,
                d,
                to_u32(gw),
                to_u32(gh),
                data,
            )
            .map_err(|e| self.output(METHOD, e.to_string(), spec.expected));
        }
        let (Some(index), Some(table)) = (field("index")?, field("table")?) else {
            let got = out.get_type().to_string();
            return Err(self.output(METHOD, got, layouts));
        };
        let expected = format!("a region index int[{h}, {w}] and a table float[regions, {d}]");
        let index_spec = ArraySpec {
            method: METHOD,
            what: "an index",
            kinds: "iu",
            dtype: "int64",
            shape: &[Some(h), Some(w)],
            expected: expected.clone(),
        };
        let (index, _) = self.array::<i64>(py, &index_spec, &index)?;
        let table_spec = ArraySpec {
            what: "a table",
            kinds: "fiu",
            dtype: "float32",
            shape: &[None, Some(d)],
            ..index_spec
        };
        let (table, _) = self.array::<f32>(py, &table_spec, &table)?;
        let regions = table.len() / d;
        let index = index
            .into_iter()
            .map(|s| match s {
                -1 => Ok(NO_REGION),
                s if s >= 0 && (s as u64) < regions as u64 => Ok(s as u32),
                s => Err(self.output(
                    METHOD,
                    format!("region index {s} with a table of {regions} rows"),
                    "indices in 0..regions, or -1 for no embedding".into(),
                )),
            })
            .collect::<vlem_core::Result<Vec<u32>>>()?;
        PixelEmbeddings::from_regions(width, height, d, index, table)
            .map_err(|e| self.output(METHOD, e.to_string(), expected))
    }
}

impl Encoder for PythonEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn needs_regions(&self) -> bool {
        self.needs_regions
    }

    fn encode_image(
        &self,
        image: &RgbImage,
        regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        const METHOD: &str = "encode_image";
        let (w, h) = (image.width(), image.height());
        Python::attach(|py| {
            let rgb = PyArray1::from_vec(py, image.as_raw().to_vec())
                .reshape([h as usize, w as usize, 3])
                .map_err(|e| self.raised(py, METHOD, e))?;
            let regions = regions_to_python(py, regions).map_err(|e| self.raised(py, METHOD, e))?;
            let out = self
                .instance
                .bind(py)
                .call_method1(METHOD, (rgb, regions))
                .map_err(|e| self.raised(py, METHOD, e))?;
            self.read_embeddings(py, &out, w, h)
        })
    }

    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        const METHOD: &str = "encode_text";
        if !self.has_text {
            return Err(CoreError::Unsupported {
                implementation: format!("the Python encoder {}", self.class),
                capability: "text encoding (it has no `encode_text` method)",
            });
        }
        Python::attach(|py| {
            let out = self
                .instance
                .bind(py)
                .call_method1(METHOD, (text,))
                .map_err(|e| self.raised(py, METHOD, e))?;
            let spec = ArraySpec {
                method: METHOD,
                what: "an embedding",
                kinds: "fiu",
                dtype: "float32",
                shape: &[Some(self.dim)],
                expected: format!("a text embedding float[{}]", self.dim),
            };
            let (mut values, _) = self.array::<f32>(py, &spec, &out)?;
            if !vlem_core::embeddings::normalise(&mut values) {
                return Err(self.output(
                    METHOD,
                    "a zero or non-finite embedding".into(),
                    format!("{} with finite values, not all zero", spec.expected),
                ));
            }
            Ok(values)
        })
    }
}

/// The regions as objects with `bbox = (x, y, width, height)` and `mask = bool[height, width]`.
fn regions_to_python<'py>(py: Python<'py>, regions: &[Region]) -> PyResult<Bound<'py, PyList>> {
    let namespace = py.import("types")?.getattr("SimpleNamespace")?;
    let list = PyList::empty(py);
    for region in regions {
        let b = region.bbox;
        let mask = PyArray1::from_vec(py, region.mask.clone())
            .reshape([b.height as usize, b.width as usize])?;
        let kwargs = PyDict::new(py);
        kwargs.set_item("bbox", PyTuple::new(py, [b.x, b.y, b.width, b.height])?)?;
        kwargs.set_item("mask", mask)?;
        list.append(namespace.call((), Some(&kwargs))?)?;
    }
    Ok(list)
}

/// A TOML table as a Python dict (through JSON, which maps TOML's types onto Python's).
fn toml_to_python<'py>(py: Python<'py>, table: &toml::Table) -> PyResult<Bound<'py, PyDict>> {
    let json = serde_json::to_string(table)
        .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
    Ok(py
        .import("json")?
        .call_method1("loads", (json,))?
        .cast_into::<PyDict>()?)
}

/// Imports a `.py` file as a module of its own.
fn import_file<'py>(py: Python<'py>, path: &std::path::Path) -> PyResult<Bound<'py, PyModule>> {
    let stem: String = path
        .file_stem()
        .map(|s| {
            s.to_string_lossy()
                .chars()
                .map(|c| if c.is_alphanumeric() { c } else { '_' })
                .collect()
        })
        .unwrap_or_default();
    let name = format!("vlem_encoder_{stem}");
    let util = py.import("importlib.util")?;
    let spec = util.call_method1(
        "spec_from_file_location",
        (name.as_str(), path.to_string_lossy().as_ref()),
    )?;
    if spec.is_none() {
        return Err(pyo3::exceptions::PyImportError::new_err(format!(
            "{} is not a Python source file",
            path.display()
        )));
    }
    let module = util.call_method1("module_from_spec", (&spec,))?;
    // Registered before running, as `import` does, so dataclasses and pickling find the module.
    py.import("sys")?
        .getattr("modules")?
        .set_item(name.as_str(), &module)?;
    spec.getattr("loader")?
        .call_method1("exec_module", (&module,))?;
    Ok(module.cast_into::<PyModule>()?)
}

/// In an interpreter embedded in a binary (which is no virtualenv itself), the packages of the
/// active virtualenv (`$VIRTUAL_ENV`), as its `python` would see them.
fn add_virtualenv(py: Python<'_>) -> PyResult<()> {
    let Some(venv) = std::env::var_os("VIRTUAL_ENV") else {
        return Ok(());
    };
    let sys = py.import("sys")?;
    let prefix: String = sys.getattr("prefix")?.extract()?;
    let base: String = sys.getattr("base_prefix")?.extract()?;
    if prefix != base {
        return Ok(()); // Already running in a virtualenv (the Python package's case).
    }
    let (major, minor): (u32, u32) = sys
        .getattr("version_info")?
        .extract::<(u32, u32, u32, String, u32)>()
        .map(|v| (v.0, v.1))?;
    let site = PathBuf::from(venv).join(format!("lib/python{major}.{minor}/site-packages"));
    if site.is_dir() {
        py.import("site")?
            .call_method1("addsitedir", (site.to_string_lossy().as_ref(),))?;
    }
    Ok(())
}
