//! `vlem._vlem`: the Python module of vlem, wrapped by the pure-Python package `vlem`
//! (`python/vlem/__init__.py`).
//!
//! Why it exists: encoder developers and people running comparison studies work in Python. This
//! crate is a thin front-end over the same library API as the `vlem` command: pipelines from
//! configs ([`pipeline`]), the live or saved map as numpy arrays and its text queries ([`map`]),
//! evaluations and studies with their reports as dicts ([`eval`]),
//! errors as a small exception hierarchy ([`errors`]). Encoders written in Python come from
//! `vlem-plugin-python`, linked here. Every long call releases the GIL, and no Rust panic crosses
//! into Python (pyo3 turns one into `pyo3_runtime.PanicException`; the pipeline's own threads
//! report theirs as errors).

mod arrays;
mod errors;
mod eval;
mod json;
mod map;
mod pipeline;

// The library links every implementation the features turn on (`vlem::plugins`); Python
// encoders are in the package always.
use vlem as _;
use vlem_plugin_python as _;

use pyo3::prelude::*;
use pyo3::types::PyDict;
use vlem_core::{Registry, StageKind};

/// Every implementation compiled into this build, as ``vlem plugins`` lists them: one dict per
/// implementation with ``stage``, ``section`` (its config section), ``name``, ``description`` and
/// ``feature`` (the cargo feature that compiles it in, ``None`` where every build has it).
#[pyfunction]
fn plugins(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    let registry = Registry::global().map_err(errors::core)?;
    let mut out = Vec::new();
    for kind in StageKind::ALL {
        for r in registry.iter().filter(|r| r.builder.kind() == kind) {
            let d = PyDict::new(py);
            d.set_item("stage", kind.to_string())?;
            d.set_item("section", kind.section())?;
            d.set_item("name", r.name)?;
            d.set_item("description", r.description)?;
            d.set_item("feature", registry.feature_of(kind, r.name))?;
            out.push(d);
        }
    }
    Ok(out)
}

#[pymodule]
fn _vlem(module: &Bound<'_, PyModule>) -> PyResult<()> {
    // As the `vlem` binary: keep freed model buffers for reuse (`VLEM_KEEP_FREED_MEMORY=0` before
    // the import turns it off).
    vlem_backends::keep_freed_memory();
    module.add("__version__", env!("CARGO_PKG_VERSION"))?;
    module.add_class::<pipeline::PyPipeline>()?;
    module.add_class::<pipeline::PyFeed>()?;
    module.add_class::<pipeline::PyIntrinsics>()?;
    module.add_class::<map::PyMap>()?;
    module.add_function(wrap_pyfunction!(plugins, module)?)?;
    module.add_function(wrap_pyfunction!(eval::eval_trajectory, module)?)?;
    module.add_function(wrap_pyfunction!(eval::eval_semseg3d, module)?)?;
    module.add_function(wrap_pyfunction!(eval::eval_semseg2d, module)?)?;
    module.add_function(wrap_pyfunction!(eval::study_cells, module)?)?;
    module.add_function(wrap_pyfunction!(eval::class_names, module)?)?;
    module.add_function(wrap_pyfunction!(eval::_study, module)?)?;
    module.add_function(wrap_pyfunction!(eval::_study_cell, module)?)?;
    errors::register(module)?;
    Ok(())
}
