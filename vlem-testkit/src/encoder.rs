//! The conformance suite for [`Encoder`] implementations: [`encoder_conformance!`](crate::encoder_conformance).
//!
//! What every encoder must do, whatever its model:
//! - a positive [`Encoder::dim`];
//! - [`Encoder::encode_image`] returns embeddings of the image's size and of dimension `dim` for
//!   uniform, gradient and noise images at 64x48 and 640x480;
//! - every embedding a pixel has is finite and unit-norm, and at least some pixels have one;
//! - encoding the same image twice gives the same embeddings;
//! - [`Encoder::encode_text`] either says [`CoreError::Unsupported`] or returns a finite, unit-norm,
//!   deterministic vector of length `dim` (and must succeed for the text a suite names).
//!
//! Encoders that [`need regions`](Encoder::needs_regions) get
//! [`rectangular_regions`](crate::images::rectangular_regions); others get none.
//!
//! Encoders that [`need labels`](Encoder::needs_labels) (label-driven upper bounds) are fed
//! through [`Encoder::encode_frame`] instead of [`Encoder::encode_image`]: each synthetic image
//! becomes a frame ([`frame_of`](crate::images::frame_of)) carrying
//! [`synthetic_labels`](crate::images::synthetic_labels), which include unlabelled pixels and an
//! id without a name. They must also answer a frame without labels, and a bare image, with an
//! error rather than a panic.
//!
//! The checks report failures by panicking, like `assert!`, with the encoder, image and pixel in the
//! message.
#![allow(
    clippy::panic,
    reason = "a test kit reports failed checks by panicking, exactly as assert! does"
)]

use vlem_core::{CoreError, Encoder, PixelEmbeddings, RgbImage};

use crate::images;

/// How the suite gets an encoder: a function (or non-capturing closure) building a fresh one.
pub type BuildEncoder = fn() -> Box<dyn Encoder>;

/// The text probed when a suite names none: ordinary words, which an encoder with a general text
/// side embeds.
pub const PROBE_TEXT: &str = "a red chair next to a white wall";

/// Largest accepted deviation of an embedding's L2 norm from 1 (f32 rounding, not sloppiness).
pub const NORM_TOLERANCE: f32 = 1e-4;

/// Largest accepted per-component difference between two encodings of the same input. Not zero so
/// that encoders whose kernels reduce in a non-deterministic order (GPU) still pass.
pub const DETERMINISM_TOLERANCE: f32 = 1e-5;

/// Pixels per axis that the per-pixel checks sample.
const SAMPLES_PER_AXIS: u32 = 16;

/// Runs the encoder conformance suite as `#[test]` functions in a module `encoder_conformance`.
///
/// `$build` is an expression of type [`BuildEncoder`] (`fn() -> Box<dyn Encoder>`): a function
/// path or a closure that captures nothing. Each test builds its own encoder.
///
/// Encoders without a general text side (they may refuse arbitrary text with an error) name a
/// text they do understand with `text = "..."`; that text must then embed successfully. Without
/// it the suite probes [`PROBE_TEXT`] and also accepts [`CoreError::Unsupported`].
///
/// Invoke it once per module (it declares `mod encoder_conformance`), typically in
/// `tests/conformance.rs`. `$build` is expanded inside that module, which imports the invoking
/// module's items with `use super::*`: plain names and `crate::` paths work, `super::` paths do not.
///
/// ```
/// use vlem_core::{Encoder, PixelEmbeddings, Region, Result, RgbImage};
///
/// /// Embeds every pixel as its colour's direction in RGB space.
/// struct Rgb;
///
/// impl Encoder for Rgb {
///     fn name(&self) -> &'static str {
///         "rgb"
///     }
///     fn dim(&self) -> usize {
///         3
///     }
///     fn encode_image(&self, image: &RgbImage, _regions: &[Region]) -> Result<PixelEmbeddings> {
///         // One segment per pixel; +1 keeps black pixels away from the zero vector.
///         let table = image.as_raw().iter().map(|&c| f32::from(c) + 1.0).collect();
///         let index = (0..image.width() * image.height()).collect();
///         PixelEmbeddings::from_regions(image.width(), image.height(), 3, index, table)
///     }
/// }
///
/// fn build() -> Box<dyn Encoder> {
///     Box::new(Rgb)
/// }
///
/// // `Rgb` has no text side, so the default `encode_text` answers `Unsupported`, which passes.
/// vlem_testkit::encoder_conformance!(build);
///
/// // An encoder that understands only some words names one of them; a closure works too:
/// // vlem_testkit::encoder_conformance!(|| Box::new(MyEncoder::default()), text = "red");
/// # fn main() {}
/// ```
#[macro_export]
macro_rules! encoder_conformance {
    (@suite $build:expr, $text:expr) => {
        /// The vlem-testkit encoder conformance suite.
        mod encoder_conformance {
            #[allow(unused_imports, reason = "`$build` may name items of the invoking module")]
            use super::*;

            #[test]
            fn dim_is_positive() {
                $crate::encoder::check_dim($build);
            }

            #[test]
            fn image_embeddings_have_the_image_size_and_dim() {
                $crate::encoder::check_image_shapes($build);
            }

            #[test]
            fn image_embeddings_are_finite_and_unit_norm() {
                $crate::encoder::check_image_embeddings_unit_norm($build);
            }

            #[test]
            fn image_encoding_is_deterministic() {
                $crate::encoder::check_image_determinism($build);
            }

            #[test]
            fn text_embedding_is_unit_norm_and_deterministic() {
                $crate::encoder::check_text($build, $text);
            }

            #[test]
            fn missing_labels_are_an_error() {
                $crate::encoder::check_missing_labels($build);
            }
        }
    };
    ($build:expr, text = $text:expr $(,)?) => {
        $crate::encoder_conformance!(@suite $build, ::core::option::Option::Some($text));
    };
    ($build:expr $(,)?) => {
        $crate::encoder_conformance!(@suite $build, ::core::option::Option::None);
    };
}

/// Checks that [`Encoder::dim`] is positive.
#[track_caller]
pub fn check_dim(build: BuildEncoder) {
    let encoder = build();
    assert!(
        encoder.dim() > 0,
        "encoder `{}` has dim() = 0",
        encoder.name()
    );
}

/// Checks that every synthetic image encodes to embeddings of its own size and of `dim()`.
#[track_caller]
pub fn check_image_shapes(build: BuildEncoder) {
    let encoder = build();
    for_each_image(|label, image| {
        let e = encode(encoder.as_ref(), label, image);
        assert_eq!(
            (e.width(), e.height()),
            (image.width(), image.height()),
            "encoder `{}`, {label}: embeddings cover a different size than the image",
            encoder.name()
        );
        assert_eq!(
            e.dim(),
            encoder.dim(),
            "encoder `{}`, {label}: embedding dim differs from Encoder::dim()",
            encoder.name()
        );
    });
}

/// Checks that the embeddings of sampled pixels are finite and unit-norm and that some pixels of
/// every image have one.
#[track_caller]
pub fn check_image_embeddings_unit_norm(build: BuildEncoder) {
    let encoder = build();
    let mut out = vec![0.0; encoder.dim()];
    for_each_image(|label, image| {
        let e = encode(encoder.as_ref(), label, image);
        let mut embedded = 0;
        for (u, v) in images::sample_pixels(image.width(), image.height(), SAMPLES_PER_AXIS) {
            if e.embedding_at(u, v, &mut out) {
                embedded += 1;
                let what = format!("encoder `{}`, {label}, pixel ({u}, {v})", encoder.name());
                assert_unit_norm(&out, &what);
            }
        }
        assert!(
            embedded > 0,
            "encoder `{}`, {label}: no sampled pixel has an embedding",
            encoder.name()
        );
    });
}

/// Checks that encoding each synthetic image twice gives the same embeddings (within
/// [`DETERMINISM_TOLERANCE`]) at the sampled pixels.
#[track_caller]
pub fn check_image_determinism(build: BuildEncoder) {
    let encoder = build();
    let dim = encoder.dim();
    let (mut a, mut b) = (vec![0.0; dim], vec![0.0; dim]);
    for_each_image(|label, image| {
        let first = encode(encoder.as_ref(), label, image);
        let second = encode(encoder.as_ref(), label, image);
        assert_eq!(
            (first.width(), first.height(), first.dim()),
            (second.width(), second.height(), second.dim()),
            "encoder `{}`, {label}: two encodings differ in shape",
            encoder.name()
        );
        for (u, v) in images::sample_pixels(image.width(), image.height(), SAMPLES_PER_AXIS) {
            let (has_a, has_b) = (
                first.embedding_at(u, v, &mut a),
                second.embedding_at(u, v, &mut b),
            );
            assert_eq!(
                has_a,
                has_b,
                "encoder `{}`, {label}, pixel ({u}, {v}): embedded in one encoding only",
                encoder.name()
            );
            if has_a {
                let what = format!("encoder `{}`, {label}, pixel ({u}, {v})", encoder.name());
                assert_close(&a, &b, &what);
            }
        }
    });
}

/// Checks the text side on `text`, or on [`PROBE_TEXT`] when `text` is `None`.
///
/// With `Some(text)` the encoder must embed it; with `None` it may answer
/// [`CoreError::Unsupported`]. An embedding must have length `dim()`, be finite, unit-norm and
/// the same on a second call.
#[track_caller]
pub fn check_text(build: BuildEncoder, text: Option<&str>) {
    let encoder = build();
    let name = encoder.name();
    let probe = text.unwrap_or(PROBE_TEXT);
    let first = match encoder.encode_text(probe) {
        Ok(v) => v,
        Err(CoreError::Unsupported { .. }) if text.is_none() => return,
        Err(e) => panic!("encoder `{name}` cannot embed the text {probe:?}: {e}"),
    };
    assert_eq!(
        first.len(),
        encoder.dim(),
        "encoder `{name}`: embedding of {probe:?} has the wrong length"
    );
    let what = format!("encoder `{name}`, text {probe:?}");
    assert_unit_norm(&first, &what);
    match encoder.encode_text(probe) {
        Ok(second) => assert_close(&first, &second, &what),
        Err(e) => panic!("{what}: the second call failed after the first succeeded: {e}"),
    }
}

/// For encoders that [need labels](Encoder::needs_labels): checks that a frame without labels and
/// a bare image are refused with an error (the pipeline checks labels itself, but an encoder
/// called directly must not panic). Passes trivially for other encoders.
#[track_caller]
pub fn check_missing_labels(build: BuildEncoder) {
    let encoder = build();
    if !encoder.needs_labels() {
        return;
    }
    let name = encoder.name();
    let image = images::gradient(64, 48);
    let regions = regions_for(encoder.as_ref(), &image);
    let frame = images::frame_of(&image, None);
    assert!(
        encoder.encode_frame(&frame, &regions).is_err(),
        "encoder `{name}` needs labels but embedded a frame without them"
    );
    assert!(
        encoder.encode_image(&image, &regions).is_err(),
        "encoder `{name}` needs labels but embedded a bare image"
    );
}

/// Asserts that `v` is non-empty, finite and has L2 norm 1 within [`NORM_TOLERANCE`]; `what` names
/// the vector in the failure message.
#[track_caller]
pub fn assert_unit_norm(v: &[f32], what: &str) {
    assert!(!v.is_empty(), "{what}: empty embedding");
    assert!(
        v.iter().all(|x| x.is_finite()),
        "{what}: embedding is not finite: {v:?}"
    );
    // Accumulate in f64 so that long vectors do not add rounding of their own.
    let norm = v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
    assert!(
        (norm - 1.0).abs() <= f64::from(NORM_TOLERANCE),
        "{what}: embedding has L2 norm {norm}, expected 1"
    );
}

/// Asserts that `a` and `b` have the same length and differ by at most [`DETERMINISM_TOLERANCE`]
/// in every component.
#[track_caller]
pub fn assert_close(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths differ");
    if let Some((k, (x, y))) = a
        .iter()
        .zip(b)
        .enumerate()
        .find(|(_, (x, y))| (*x - *y).abs() > DETERMINISM_TOLERANCE)
    {
        panic!("{what}: not deterministic, component {k} is {x} and then {y}");
    }
}

/// Encodes `image`, passing [`images::rectangular_regions`] when the encoder needs regions, and
/// panics with the encoder's error otherwise. An encoder that needs labels gets a frame of the
/// image with [`images::synthetic_labels`] through [`Encoder::encode_frame`].
#[track_caller]
pub fn encode(encoder: &dyn Encoder, label: &str, image: &RgbImage) -> PixelEmbeddings {
    let regions = regions_for(encoder, image);
    let result = if encoder.needs_labels() {
        let labels = images::synthetic_labels(image.width(), image.height());
        encoder.encode_frame(&images::frame_of(image, Some(labels)), &regions)
    } else {
        encoder.encode_image(image, &regions)
    };
    match result {
        Ok(e) => e,
        Err(e) => panic!(
            "encoder `{}` failed on the {}x{} {label} image: {e}",
            encoder.name(),
            image.width(),
            image.height()
        ),
    }
}

/// The regions the suite passes: [`images::rectangular_regions`] if the encoder needs regions.
fn regions_for(encoder: &dyn Encoder, image: &RgbImage) -> Vec<vlem_core::Region> {
    if encoder.needs_regions() {
        images::rectangular_regions(image.width(), image.height())
    } else {
        Vec::new()
    }
}

/// Calls `check` on every synthetic image of every size, labelled like "640x480 gradient".
fn for_each_image(mut check: impl FnMut(&str, &RgbImage)) {
    for (width, height) in images::SIZES {
        for (name, image) in images::synthetic_images(width, height) {
            check(&format!("{width}x{height} {name}"), &image);
        }
    }
}
