//! The `python` encoder: the shared conformance suite on the numpy colour-names encoder of
//! `examples/python/colour_names.py`, equality with the Rust colour-names encoder it copies, and
//! the errors a wrong Python class gets. Needs numpy in the interpreter pyo3 links (CI installs it).
#![cfg(feature = "python")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::path::{Path, PathBuf};

use vlem_core::{BuildContext, Encoder, RgbImage};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn params(toml_text: &str) -> toml::Table {
    toml::from_str(toml_text).unwrap()
}

fn build(toml_text: &str) -> vlem_core::Result<Box<dyn Encoder>> {
    let ctx = BuildContext::for_config_dir(&repo()).unwrap();
    vlem_plugin_python::build(&params(toml_text), &ctx)
}

fn numpy_colour_names() -> Box<dyn Encoder> {
    build(
        r#"
        path = "examples/python/colour_names.py"
        class = "ColourNames"
        "#,
    )
    .unwrap()
}

vlem_testkit::encoder_conformance!(super::numpy_colour_names, text = "red");

/// A small image with every kind of colour in it.
fn test_image() -> RgbImage {
    let (w, h) = (37u32, 23u32);
    let data = (0..w * h)
        .flat_map(|i| {
            let (u, v) = (i % w, i / w);
            [(u * 7) as u8, (v * 11) as u8, ((u * v) % 256) as u8]
        })
        .collect();
    RgbImage::new(w, h, data).unwrap()
}

#[test]
fn the_numpy_encoder_embeds_like_the_rust_one_it_copies() {
    let python = numpy_colour_names();
    let rust = vlem_plugin_colour_names::ColourNamesEncoder::default();
    assert_eq!(python.dim(), rust.dim());
    let image = test_image();
    let (a, b) = (
        python.encode_image(&image, &[]).unwrap(),
        rust.encode_image(&image, &[]).unwrap(),
    );
    let (mut ea, mut eb) = (vec![0.0; 11], vec![0.0; 11]);
    for v in 0..image.height() {
        for u in 0..image.width() {
            assert!(a.embedding_at(u, v, &mut ea) && b.embedding_at(u, v, &mut eb));
            for (x, y) in ea.iter().zip(&eb) {
                assert!((x - y).abs() < 1e-5, "pixel ({u}, {v}): {ea:?} vs {eb:?}");
            }
        }
    }
    for text in ["white wall", "Navy-blue and GOLD"] {
        let (ta, tb) = (
            python.encode_text(text).unwrap(),
            rust.encode_text(text).unwrap(),
        );
        assert!(
            ta.iter().zip(&tb).all(|(x, y)| (x - y).abs() < 1e-6),
            "{text}: {ta:?} vs {tb:?}"
        );
    }
    let e = python.encode_text("a chair").unwrap_err().to_string();
    assert!(
        e.contains("ColourNames.encode_text raised ValueError"),
        "{e}"
    );
    assert!(e.contains("Traceback"), "{e}");
}

#[test]
fn constructor_parameters_come_from_the_params_table() {
    let e = build(
        r#"
        path = "examples/python/colour_names.py"
        class = "ColourNames"
        params = { sigma = -1.0 }
        "#,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("sigma must be a positive number"), "{e}");
}

/// Writes `code` as a module into a temporary folder and builds its class `Bad`.
fn build_code(code: &str) -> (tempfile::TempDir, vlem_core::Result<Box<dyn Encoder>>) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bad.py"), code).unwrap();
    let ctx = BuildContext::for_config_dir(dir.path()).unwrap();
    let built = vlem_plugin_python::build(&params("path = \"bad.py\"\nclass = \"Bad\""), &ctx);
    (dir, built)
}

#[test]
fn wrong_outputs_are_errors_that_name_the_method_and_the_shape() {
    let cases = [
        (
            "return {'grid': np.zeros((3, 4, 5), np.float32)}",
            "a grid of shape [3, 4, 5]",
        ),
        (
            "return {'index': np.zeros((23, 37), np.float32), 'table': np.ones((1, 2))}",
            "an index of dtype float32",
        ),
        (
            "return {'index': np.full((23, 37), 3), 'table': np.ones((1, 2))}",
            "region index 3 with a table of 1 rows",
        ),
        (
            "return {'index': np.zeros((23, 37), int), 'table': np.full((1, 2), np.nan)}",
            "non-finite",
        ),
        // An encoder that failed silently: no pixel would get an embedding.
        (
            "return {'grid': np.zeros((2, 3, 2), np.float32)}",
            "a 2x3 grid whose every value is zero",
        ),
        ("return 42", "<class 'int'>"),
        (
            "raise RuntimeError('model exploded')",
            "Bad.encode_image raised RuntimeError: model exploded",
        ),
    ];
    for (body, expected) in cases {
        let code = format!(
            "import numpy as np\nclass Bad:\n    dim = 2\n    def encode_image(self, rgb, regions):\n        assert rgb.shape == (23, 37, 3) and rgb.dtype == np.uint8\n        {body}\n"
        );
        let (_dir, built) = build_code(&code);
        let e = built
            .unwrap()
            .encode_image(&test_image(), &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains(expected), "{body}: {e}");
    }
    // A patch grid of the right dimension is accepted; its patch size is checked.
    let code = "import numpy as np\nclass Bad:\n    dim = 2\n    def encode_image(self, rgb, regions):\n        return {'grid': np.ones((2, 3, 2)), 'patch_size': 8}\n";
    let (_dir, built) = build_code(code);
    let e = built
        .unwrap()
        .encode_image(&test_image(), &[])
        .unwrap_err()
        .to_string();
    assert!(e.contains("patches that cover the 37x23 image"), "{e}");
}

#[test]
fn a_class_without_what_vlem_needs_is_refused_at_build_time() {
    let (_dir, built) = build_code("class Bad:\n    pass\n");
    let e = built.err().unwrap().to_string();
    assert!(e.contains("no positive integer attribute `dim`"), "{e}");
    let (_dir, built) = build_code("class Bad:\n    dim = 3\n");
    assert!(built.err().unwrap().to_string().contains("encode_image"));
    let (_dir, built) = build_code("raise ImportError('no torch here')\n");
    let e = built.err().unwrap().to_string();
    assert!(
        e.contains("cannot load the Python encoder") && e.contains("no torch here"),
        "{e}"
    );
    // Text encoding is optional.
    let (_dir, built) = build_code(
        "class Bad:\n    dim = 3\n    def encode_image(self, rgb, regions):\n        return None\n",
    );
    let e = built.unwrap().encode_text("red").unwrap_err();
    assert!(matches!(e, vlem_core::CoreError::Unsupported { .. }), "{e}");
    let e = build("class = \"X\"").err().unwrap().to_string();
    assert!(e.contains("either `module"), "{e}");
    let e = build("class = \"X\"\npath = \"nowhere.py\"")
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("nowhere.py"), "{e}");
}
