//! `python`: vlem encoders written in Python.
//!
//! Why it exists: most people who build vision-language encoders build them in PyTorch. With this
//! plugin a Python class is a vlem encoder, with nothing written in Rust and no ONNX export:
//!
//! ```toml
//! [encoder]
//! kind = "python"
//! path = "my_encoder.py"       # a file (relative to the config), or: module = "package.module"
//! class = "MyEncoder"
//!
//! [encoder.params]             # keyword arguments of the constructor
//! checkpoint = "weights/my.pt"
//! ```
//!
//! The class provides `dim`, optionally `needs_regions`, `encode_image(rgb, regions)` returning a
//! region layout (`{"index": int[h, w] (-1: none), "table": float[segments, dim]}`) or a patch
//! grid (`{"grid": float[gh, gw, dim]}`, optionally with `"patch_size"`), and optionally
//! `encode_text(text)` returning `float[dim]`; `vlem.Regions` and `vlem.PatchGrid` of the Python
//! package are the same with attributes. Every output is checked (dtype, shape, finiteness,
//! dimension) and a violation is an error naming the method and the shape it expects.
//!
//! The plugin works wherever a Python interpreter is: inside the Python package (`import vlem`,
//! the interpreter is the caller's) and in the `vlem` binary built with the `python` feature (the
//! interpreter is embedded; it sees the packages of `$VIRTUAL_ENV` when one is active). The
//! pipeline calls the encoder from its embedding thread, attaching to the interpreter only for
//! the call, so the tracker keeps running on its own thread while Python encodes.
//!
//! A Python exception raised by the class becomes [`PythonEncoderError::Raised`], which keeps the
//! exception itself ([`raised_exception`]): the Python package raises it again, traceback and all;
//! the binary prints its message and traceback.

vlem_core::feature_hint!(Encoder, "python", "python");

#[cfg(feature = "python")]
mod encoder;

#[cfg(feature = "python")]
pub use encoder::{
    NAME, PythonEncoder, PythonEncoderConfig, PythonEncoderError, build, raised_exception,
};

#[cfg(feature = "python")]
vlem_core::register_encoder!(
    "python",
    "an encoder written in Python: a class from a module or .py file (needs the `python` feature)",
    build
);
