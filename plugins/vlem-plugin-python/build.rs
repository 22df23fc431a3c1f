//! With the `python` feature, this crate's tests embed the interpreter: their binaries get an
//! rpath to the libpython that pyo3 linked, so they load it (and its packages) rather than another
//! libpython of the same name on the loader's default path.

fn main() {
    #[cfg(feature = "python")]
    pyo3_build_config::add_libpython_rpath_link_args();
}
