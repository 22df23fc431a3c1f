//! Synthetic inputs for the conformance suites: images with known content and simple regions.
//!
//! The images are chosen to hit the cases that break encoders in practice: a uniform image (one
//! colour, so e.g. one segment or degenerate statistics), a smooth gradient (many distinct but
//! correlated colours) and seeded noise (every pixel different, no structure). All are deterministic.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::sync::Arc;

use vlem_core::{
    DepthImage, Frame, Intrinsics, LabelImage, LabelNames, PixelRect, Region, RgbImage,
};

/// Image sizes every suite runs: a small one and the 640x480 of common RGB-D sensors.
pub const SIZES: [(u32, u32); 2] = [(64, 48), (640, 480)];

/// An image of one colour.
pub fn uniform(width: u32, height: u32, rgb: [u8; 3]) -> RgbImage {
    RgbImage::filled(width, height, rgb)
}

/// A smooth gradient: red grows to the right, green downwards, blue along the diagonal.
pub fn gradient(width: u32, height: u32) -> RgbImage {
    // Scales position to 0..=255 (a 1-pixel-wide axis stays at 0).
    let ramp = |x: u64, size: u32| (x * 255 / u64::from(size.max(2) - 1)).min(255) as u8;
    let mut data = Vec::with_capacity(width as usize * height as usize * 3);
    for v in 0..height {
        for u in 0..width {
            let (u, v) = (u64::from(u), u64::from(v));
            data.extend_from_slice(&[
                ramp(u, width),
                ramp(v, height),
                ramp(u + v, width + height - 1),
            ]);
        }
    }
    from_raw(width, height, data)
}

/// Uniform random bytes from a fixed seed (the same image for the same arguments).
pub fn noise(width: u32, height: u32, seed: u64) -> RgbImage {
    let mut data = vec![0u8; width as usize * height as usize * 3];
    StdRng::seed_from_u64(seed).fill(&mut data[..]);
    from_raw(width, height, data)
}

/// The named synthetic images of one size that the suites encode: a mid-grey uniform image, a
/// saturated uniform image, a gradient and noise.
pub fn synthetic_images(width: u32, height: u32) -> Vec<(&'static str, RgbImage)> {
    vec![
        ("uniform grey", uniform(width, height, [128, 128, 128])),
        ("uniform red", uniform(width, height, [220, 20, 30])),
        ("gradient", gradient(width, height)),
        ("noise", noise(width, height, 0x5eed)),
    ]
}

/// Two rectangular regions with full masks, for encoders that need regions: the left half of the
/// image and a centred box of half the width and height (so they overlap, as proposals do).
pub fn rectangular_regions(width: u32, height: u32) -> Vec<Region> {
    let rect = |x, y, width, height| PixelRect {
        x,
        y,
        width,
        height,
    };
    [
        rect(0, 0, (width / 2).max(1), height),
        rect(
            width / 4,
            height / 4,
            (width / 2).max(1),
            (height / 2).max(1),
        ),
    ]
    .into_iter()
    .map(|bbox| Region {
        mask: vec![true; bbox.width as usize * bbox.height as usize],
        bbox,
    })
    .collect()
}

/// Class names of [`synthetic_labels`]: NYU40 ids and names of a few common classes. Id 9 is
/// deliberately left out: it occurs in the label images but has no name.
pub const LABEL_NAMES: [(u16, &str); 4] = [(1, "wall"), (2, "floor"), (5, "chair"), (6, "sofa")];

/// A class id that [`synthetic_labels`] uses but [`LABEL_NAMES`] does not name: encoders treat
/// its pixels like unlabelled ones.
pub const UNNAMED_LABEL: u16 = 9;

/// Ground-truth labels for label-driven encoders: the top half is "wall" (id 1), the bottom half
/// "floor" (id 2); a centred box of half the width and height is "chair" (id 5) on its left and
/// "sofa" (id 6) on its right; the leftmost eighth of the columns is unlabelled (id 0) and the
/// bottom-right corner eighth of each axis has the unnamed id [`UNNAMED_LABEL`].
pub fn synthetic_labels(width: u32, height: u32) -> LabelImage {
    let names = Arc::new(LabelNames::new(
        LABEL_NAMES.iter().map(|&(id, name)| (id, name.to_owned())),
    ));
    let mut ids = Vec::with_capacity(width as usize * height as usize);
    for v in 0..height {
        for u in 0..width {
            let (x, y) = (
                f64::from(u) / f64::from(width),
                f64::from(v) / f64::from(height),
            );
            let id = if x < 0.125 {
                0
            } else if x >= 0.875 && y >= 0.875 {
                UNNAMED_LABEL
            } else if (0.25..0.75).contains(&x) && (0.25..0.75).contains(&y) {
                if x < 0.5 { 5 } else { 6 }
            } else if y < 0.5 {
                1
            } else {
                2
            };
            ids.push(id);
        }
    }
    expect_valid(LabelImage::new(width, height, ids, names))
}

/// A frame around `image`: constant depth (2 m), pinhole intrinsics of the image's size, no pose,
/// and `labels` if given (which must have the image's size).
pub fn frame_of(image: &RgbImage, labels: Option<LabelImage>) -> Frame {
    let (w, h) = (image.width(), image.height());
    let depth = expect_valid(DepthImage::new(w, h, vec![2.0; w as usize * h as usize]));
    let f = 525.0 * f64::from(w) / 640.0;
    let intrinsics = expect_valid(Intrinsics::new(
        w,
        h,
        f,
        f,
        (f64::from(w) - 1.0) / 2.0,
        (f64::from(h) - 1.0) / 2.0,
    ));
    let frame = expect_valid(Frame::new(0, 0.0, image.clone(), depth, intrinsics, None));
    match labels {
        Some(labels) => expect_valid(frame.with_labels(labels)),
        None => frame,
    }
}

#[allow(
    clippy::expect_used,
    reason = "the generators above build consistent sizes, so construction cannot fail"
)]
fn expect_valid<T>(r: vlem_core::Result<T>) -> T {
    r.expect("test input is consistent")
}

/// A pixel grid of about `per_axis x per_axis` samples including the image corners, for checks that
/// look at pixels one by one (checking all 307 200 pixels of a 640x480 image is needlessly slow).
pub fn sample_pixels(width: u32, height: u32, per_axis: u32) -> Vec<(u32, u32)> {
    let axis = |size: u32| -> Vec<u32> {
        let steps = per_axis.clamp(2, size.max(2));
        let mut xs: Vec<u32> = (0..steps)
            .map(|i| {
                (u64::from(i) * u64::from(size.saturating_sub(1)) / u64::from(steps - 1)) as u32
            })
            .collect();
        xs.dedup();
        xs
    };
    let (us, vs) = (axis(width), axis(height));
    vs.iter()
        .flat_map(|&v| us.iter().map(move |&u| (u, v)))
        .collect()
}

#[allow(
    clippy::expect_used,
    reason = "the generators above build exactly width * height * 3 bytes"
)]
fn from_raw(width: u32, height: u32, data: Vec<u8>) -> RgbImage {
    RgbImage::new(width, height, data).expect("generator buffer matches the image size")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradient_spans_the_full_range() {
        let img = gradient(64, 48);
        assert_eq!(img.get(0, 0), Some([0, 0, 0]));
        assert_eq!(img.get(63, 47), Some([255, 255, 255]));
        assert_eq!(img.get(63, 0).map(|c| c[0]), Some(255));
    }

    #[test]
    fn noise_is_seeded() {
        assert_eq!(noise(8, 8, 1), noise(8, 8, 1));
        assert_ne!(noise(8, 8, 1), noise(8, 8, 2));
    }

    #[test]
    fn regions_lie_inside_the_image() {
        for (w, h) in SIZES {
            for r in rectangular_regions(w, h) {
                assert!(r.bbox.x + r.bbox.width <= w && r.bbox.y + r.bbox.height <= h);
                assert_eq!(r.area(), r.mask.len());
            }
        }
    }

    #[test]
    fn synthetic_labels_have_every_kind_of_pixel() {
        for (w, h) in SIZES {
            let labels = synthetic_labels(w, h);
            for id in [0, 1, 2, 5, 6, UNNAMED_LABEL] {
                assert!(
                    labels.ids().contains(&id),
                    "{w}x{h}: no pixel of class {id}"
                );
            }
            assert_eq!(labels.names().name(5), Some("chair"));
            assert_eq!(labels.names().name(UNNAMED_LABEL), None);
            let frame = frame_of(&gradient(w, h), Some(labels));
            assert!(frame.labels.is_some());
        }
    }

    #[test]
    fn samples_include_the_corners() {
        let s = sample_pixels(640, 480, 16);
        assert_eq!(s.len(), 256);
        for corner in [(0, 0), (639, 0), (0, 479), (639, 479)] {
            assert!(s.contains(&corner), "{corner:?}");
        }
        assert_eq!(sample_pixels(1, 1, 16), vec![(0, 0)]);
    }
}
