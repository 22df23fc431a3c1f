//! vlem's errors as Python exceptions: one small hierarchy under `vlem.VlemError`, with the message
//! the `vlem` command prints (the cause chain on one line), and the original exception wherever a
//! Python encoder raised one.

use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError};
use pyo3::prelude::*;
use vlem_core::{CoreError, StageKind};

pyo3::create_exception!(
    vlem,
    VlemError,
    PyException,
    "Base class of every error vlem raises (besides TypeError/ValueError for bad arguments and \
     OSError for files)."
);
pyo3::create_exception!(
    vlem,
    ConfigError,
    VlemError,
    "A configuration that cannot be used: unknown stage names (the message lists the known ones \
     and the feature that adds a missing one), bad parameters, stages that do not fit together."
);
pyo3::create_exception!(
    vlem,
    DatasetError,
    VlemError,
    "A dataset or frame that cannot be read or used: missing files, sizes that disagree, frames \
     a stream refuses."
);
pyo3::create_exception!(
    vlem,
    StageError,
    VlemError,
    "A stage (tracker, proposer, encoder, map, segmenter) failed while running."
);
pyo3::create_exception!(
    vlem,
    EncoderError,
    StageError,
    "The encoder failed, e.g. missing model weights (the message names the file and how to get \
     it) or a Python encoder returning the wrong shape."
);
pyo3::create_exception!(
    vlem,
    MapFileError,
    VlemError,
    "A map file that cannot be read back."
);
pyo3::create_exception!(
    vlem,
    QueryError,
    VlemError,
    "A query that cannot be answered: no texts, a map without embeddings, an encoder whose \
     dimension is not the map's."
);

pyo3::create_exception!(
    vlem,
    EvalError,
    VlemError,
    "An evaluation or study that cannot run: a study file's mistakes, prompts that are no class, \
     a class the encoder cannot embed, too few poses to compare, a map and encoder that differ."
);

/// Which exception class a core error is.
fn class_of(error: &CoreError) -> fn(String) -> PyErr {
    // Where in a run it happened does not change what kind of error it is.
    match error.root() {
        CoreError::UnknownImplementation { .. }
        | CoreError::DuplicateImplementation { .. }
        | CoreError::InvalidParams { .. }
        | CoreError::ConfigRead { .. }
        | CoreError::Config { .. }
        | CoreError::ConfigText { .. }
        | CoreError::EmbeddingDimensionMismatch { .. }
        | CoreError::MissingStage { .. } => ConfigError::new_err,
        CoreError::BufferSize { .. }
        | CoreError::InvalidIntrinsics { .. }
        | CoreError::SizeMismatch { .. }
        | CoreError::NonFinitePose { .. }
        | CoreError::MissingLabels { .. }
        | CoreError::Dataset { .. }
        | CoreError::FrameRefused { .. }
        | CoreError::StreamClosed => DatasetError::new_err,
        CoreError::MapFile { .. } => MapFileError::new_err,
        CoreError::Stage {
            kind: StageKind::Encoder,
            ..
        }
        | CoreError::InvalidEmbeddings { .. }
        | CoreError::DimensionMismatch { .. } => EncoderError::new_err,
        CoreError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err
        }
        CoreError::Io { .. } => PyOSError::new_err,
        _ => StageError::new_err,
    }
}

/// The exception for `error` whose class `class` picks: the Python exception itself when a
/// Python encoder raised it, else `class` with the one-line cause chain.
fn raise(error: &(dyn std::error::Error + 'static), class: fn(String) -> PyErr) -> PyErr {
    if let Some(raised) = vlem_plugin_python::raised_exception(error) {
        return Python::attach(|py| raised.clone_ref(py));
    }
    class(vlem_core::message_chain(error))
}

/// A core error as a Python exception.
pub fn core(error: CoreError) -> PyErr {
    let class = class_of(&error);
    raise(&error, class)
}

/// A query error as a Python exception (the core error inside decides the class, where it has
/// one, so a missing model file stays an encoder error).
pub fn query(error: vlem_query::QueryError) -> PyErr {
    let class = match std::error::Error::source(&error).and_then(|s| s.downcast_ref::<CoreError>())
    {
        Some(inner @ CoreError::Stage { .. }) => class_of(inner),
        _ => QueryError::new_err,
    };
    raise(&error, class)
}

/// A dataset error as a Python exception.
pub fn dataset(error: vlem_datasets::DatasetError) -> PyErr {
    raise(&error, DatasetError::new_err)
}

/// An evaluation error as a Python exception: the library error inside decides the class where
/// there is one (a missing model file stays an encoder error, a missing dataset a dataset error).
pub fn eval(error: vlem_eval::EvalError) -> PyErr {
    use vlem_eval::EvalError as E;
    let class: fn(String) -> PyErr = match &error {
        E::Core(inner) => class_of(inner),
        E::Dataset(_) | E::MissingLabels { .. } | E::MissingPose { .. } => DatasetError::new_err,
        E::Query(inner) => {
            match std::error::Error::source(inner).and_then(|s| s.downcast_ref::<CoreError>()) {
                Some(core @ CoreError::Stage { .. }) => class_of(core),
                _ => QueryError::new_err,
            }
        }
        E::Encode { .. } => EncoderError::new_err,
        E::MissingFile { .. } => PyFileNotFoundError::new_err,
        E::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err
        }
        E::Io { .. } => PyOSError::new_err,
        E::InvalidParameter { .. } => pyo3::exceptions::PyValueError::new_err,
        _ => EvalError::new_err,
    };
    raise(&error, class)
}

/// Registers the exception classes on the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = module.py();
    module.add("VlemError", py.get_type::<VlemError>())?;
    module.add("ConfigError", py.get_type::<ConfigError>())?;
    module.add("DatasetError", py.get_type::<DatasetError>())?;
    module.add("StageError", py.get_type::<StageError>())?;
    module.add("EncoderError", py.get_type::<EncoderError>())?;
    module.add("MapFileError", py.get_type::<MapFileError>())?;
    module.add("QueryError", py.get_type::<QueryError>())?;
    module.add("EvalError", py.get_type::<EvalError>())?;
    Ok(())
}
