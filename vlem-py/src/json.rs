//! Serialisable library results (answers, run statistics, status) as Python dicts and lists, and
//! Python dicts as TOML: through JSON, whose types Python's `json` maps one to one.

use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

/// `value` as the Python object `json.loads` makes of its JSON form.
pub fn to_python<'py, T: serde::Serialize>(
    py: Python<'py>,
    value: &T,
) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value)
        .map_err(|e| PyValueError::new_err(format!("cannot convert a result for Python: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A Python dict (of str, numbers, bools, lists and dicts) as TOML text.
pub fn dict_to_toml(dict: &Bound<'_, PyAny>, argument: &str) -> PyResult<String> {
    let py = dict.py();
    let text: String = py
        .import("json")?
        .call_method1("dumps", (dict,))
        .map_err(|e| {
            PyTypeError::new_err(format!(
                "{argument} must hold only str, numbers, bools, lists and dicts: {e}"
            ))
        })?
        .extract()?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| PyValueError::new_err(format!("{argument}: {e}")))?;
    toml::to_string(&value).map_err(|e| {
        PyValueError::new_err(format!(
            "{argument} cannot be written as TOML ({e}); None values and mixed lists have no TOML form"
        ))
    })
}
