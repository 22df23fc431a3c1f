//! numpy arrays in and out: the checks a caller's arrays pass before vlem uses them (dtype, shape,
//! contiguity, each a `TypeError` or `ValueError` that names the argument), and vlem's buffers
//! handed to numpy without a copy.

use numpy::{
    Element, PyArray1, PyArrayDescrMethods, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

/// A C-contiguous numpy array argument of element type `T` and one of the allowed shapes
/// (`None`: any length along that axis): its values (one copy) and shape.
pub fn read<T: Element + Copy>(
    value: &Bound<'_, PyAny>,
    argument: &str,
    expected: &str,
    shape: &[Option<usize>],
) -> PyResult<(Vec<T>, Vec<usize>)> {
    let array = value.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "{argument} must be a numpy array ({expected}), not {}",
            value.get_type()
        ))
    })?;
    let dtype = array.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<T>(value.py())) {
        return Err(PyTypeError::new_err(format!(
            "{argument} must be {expected}, not an array of dtype {dtype}"
        )));
    }
    let actual = array.shape().to_vec();
    let fits = actual.len() == shape.len()
        && actual
            .iter()
            .zip(shape)
            .all(|(a, s)| s.is_none_or(|s| s == *a));
    if !fits {
        return Err(PyValueError::new_err(format!(
            "{argument} must be {expected}, not an array of shape {actual:?}"
        )));
    }
    if !array.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{argument} must be C-contiguous (pass numpy.ascontiguousarray({argument}))"
        )));
    }
    let typed: PyReadonlyArrayDyn<'_, T> = value.extract()?;
    let values = typed
        .as_slice()
        .map_err(|e| PyValueError::new_err(format!("{argument}: {e}")))?
        .to_vec();
    Ok((values, actual))
}

/// `values` as a numpy array of `shape`; numpy takes over the vector, nothing is copied.
pub fn give<'py, T: Element>(
    py: Python<'py>,
    values: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_vec(py, values)
        .reshape(shape.to_vec())?
        .into_any())
}
