//! With the `python` feature the binary and its tests embed the Python interpreter: they get an
//! rpath to the libpython pyo3 linked, so they load it (with its packages) rather than another
//! libpython of the same name on the loader's default path.

fn main() {
    #[cfg(feature = "python")]
    pyo3_build_config::add_libpython_rpath_link_args();
}
