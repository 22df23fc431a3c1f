//! The conformance suite for [`RegionProposer`] implementations:
//! [`region_proposer_conformance!`](crate::region_proposer_conformance).
//!
//! What every region proposer must do, whatever its model:
//! - [`RegionProposer::name`] is a name registered for the proposer stage in the registry;
//! - on uniform, gradient and noise images at 64x48 and 640x480, every region is well formed: a
//!   non-empty bounding box inside the image, a mask of `bbox.width * bbox.height` flags with at
//!   least one foreground pixel, and a box tight to the mask (its first and last rows and columns
//!   each hold a foreground pixel), so that crops never carry empty margins;
//! - proposing on the same image twice gives the same regions;
//! - tiny and degenerate images (1x1, a single row or column, 2x2, 3x2, and 0x0) do not panic;
//!   a proposer may refuse them with an error or return no region, and what it returns is well
//!   formed.
//!
//! The checks report failures by panicking, like `assert!`, with the proposer, image and region
//! in the message.
#![allow(
    clippy::panic,
    reason = "a test kit reports failed checks by panicking, exactly as assert! does"
)]

use vlem_core::{Region, RegionProposer, Registry, RgbImage, StageKind};

use crate::images;

/// How the suite gets a proposer: a function (or non-capturing closure) building a fresh one.
pub type BuildProposer = fn() -> Box<dyn RegionProposer>;

/// Tiny and degenerate image sizes that must not make a proposer panic.
pub const TINY_SIZES: [(u32, u32); 7] = [(1, 1), (1, 7), (7, 1), (2, 2), (3, 2), (0, 0), (0, 3)];

/// Runs the region proposer conformance suite as `#[test]` functions in a module
/// `region_proposer_conformance`.
///
/// `$build` is an expression of type [`BuildProposer`] (`fn() -> Box<dyn RegionProposer>`): a
/// function path or a closure that captures nothing. Each test builds its own proposer. The
/// crate that registers the proposer must be linked into the test binary (building the proposer
/// through it is enough).
///
/// Invoke it once per module (it declares `mod region_proposer_conformance`). `$build` is
/// expanded inside that module, which imports the invoking module's items with `use super::*`:
/// plain names and `crate::` paths work, `super::` paths do not.
///
/// ```
/// use vlem_core::{PixelRect, Region, RegionProposer, Result, RgbImage};
///
/// /// Proposes the whole image as one region.
/// struct Whole;
///
/// impl RegionProposer for Whole {
///     fn name(&self) -> &'static str {
///         "whole"
///     }
///     fn propose(&self, image: &RgbImage) -> Result<Vec<Region>> {
///         let (width, height) = (image.width(), image.height());
///         if width == 0 || height == 0 {
///             return Ok(Vec::new());
///         }
///         let bbox = PixelRect { x: 0, y: 0, width, height };
///         Ok(vec![Region { bbox, mask: vec![true; (width * height) as usize] }])
///     }
/// }
///
/// // A real proposer also registers itself (`vlem_core::register_proposer!("whole", ...)`),
/// // which the suite's `name_is_registered` checks.
/// vlem_testkit::region_proposer_conformance!(|| Box::new(Whole));
/// # fn main() {}
/// ```
#[macro_export]
macro_rules! region_proposer_conformance {
    ($build:expr $(,)?) => {
        /// The vlem-testkit region proposer conformance suite.
        mod region_proposer_conformance {
            #[allow(
                unused_imports,
                reason = "`$build` may name items of the invoking module"
            )]
            use super::*;

            #[test]
            fn name_is_registered() {
                $crate::proposer::check_registered($build);
            }

            #[test]
            fn regions_are_well_formed() {
                $crate::proposer::check_regions_well_formed($build);
            }

            #[test]
            fn proposals_are_deterministic() {
                $crate::proposer::check_determinism($build);
            }

            #[test]
            fn tiny_images_do_not_panic() {
                $crate::proposer::check_tiny_images($build);
            }
        }
    };
}

/// Checks that the proposer's name is registered for the proposer stage.
#[track_caller]
pub fn check_registered(build: BuildProposer) {
    let proposer = build();
    let name = proposer.name();
    let registry = match Registry::global() {
        Ok(r) => r,
        Err(e) => panic!("the registry cannot be built: {e}"),
    };
    if let Err(e) = registry.get(StageKind::Proposer, name) {
        panic!("region proposer `{name}` is not registered: {e}");
    }
}

/// Checks every region that the proposer returns for the synthetic images with
/// [`check_region`].
#[track_caller]
pub fn check_regions_well_formed(build: BuildProposer) {
    let proposer = build();
    for_each_image(|label, image| {
        for (k, region) in propose(proposer.as_ref(), label, image).iter().enumerate() {
            let what = format!("proposer `{}`, {label}, region {k}", proposer.name());
            check_region(region, image.width(), image.height(), &what);
        }
    });
}

/// Checks that proposing on each synthetic image twice gives the same regions.
#[track_caller]
pub fn check_determinism(build: BuildProposer) {
    let proposer = build();
    for_each_image(|label, image| {
        let first = propose(proposer.as_ref(), label, image);
        let second = propose(proposer.as_ref(), label, image);
        assert!(
            first == second,
            "proposer `{}`, {label}: two proposals differ ({} and {} regions)",
            proposer.name(),
            first.len(),
            second.len()
        );
    });
}

/// Checks that the [`TINY_SIZES`] images do not panic and that whatever regions come back are
/// well formed.
#[track_caller]
pub fn check_tiny_images(build: BuildProposer) {
    let proposer = build();
    for (width, height) in TINY_SIZES {
        for (name, image) in [
            ("noise", images::noise(width, height, 7)),
            ("gradient", images::gradient(width, height)),
        ] {
            if let Ok(regions) = proposer.propose(&image) {
                for (k, region) in regions.iter().enumerate() {
                    let what = format!(
                        "proposer `{}`, {width}x{height} {name}, region {k}",
                        proposer.name()
                    );
                    check_region(region, width, height, &what);
                }
            }
        }
    }
}

/// Asserts that `region` is well formed in a `width x height` image: a non-empty box inside the
/// image, a mask of `bbox.width * bbox.height` flags, at least one foreground pixel, and a box
/// tight to the mask. `what` names the region in the failure message.
#[track_caller]
pub fn check_region(region: &Region, width: u32, height: u32, what: &str) {
    let b = region.bbox;
    assert!(
        b.width > 0 && b.height > 0,
        "{what}: empty bounding box {b:?}"
    );
    assert!(
        u64::from(b.x) + u64::from(b.width) <= u64::from(width)
            && u64::from(b.y) + u64::from(b.height) <= u64::from(height),
        "{what}: bounding box {b:?} reaches outside the {width}x{height} image"
    );
    let (w, h) = (b.width as usize, b.height as usize);
    assert_eq!(
        region.mask.len(),
        w * h,
        "{what}: mask length differs from bbox.width * bbox.height ({b:?})"
    );
    assert!(
        region.mask.contains(&true),
        "{what}: the mask has no foreground pixel"
    );
    let rows: Vec<&[bool]> = region.mask.chunks_exact(w).collect();
    let row_used = |r: usize| rows.get(r).is_some_and(|row| row.contains(&true));
    let column_used = |c: usize| rows.iter().any(|row| row.get(c).copied().unwrap_or(false));
    assert!(
        row_used(0) && row_used(h - 1) && column_used(0) && column_used(w - 1),
        "{what}: bounding box {b:?} is not tight to its mask (an edge row or column is empty)"
    );
}

/// Proposes regions for `image`, panicking with the proposer's error.
#[track_caller]
pub fn propose(proposer: &dyn RegionProposer, label: &str, image: &RgbImage) -> Vec<Region> {
    match proposer.propose(image) {
        Ok(regions) => regions,
        Err(e) => panic!(
            "proposer `{}` failed on the {}x{} {label} image: {e}",
            proposer.name(),
            image.width(),
            image.height()
        ),
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
