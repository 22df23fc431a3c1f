#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! `region_crops` on tiny images whose crops and assignments are computed by hand.

use vlem_backends::BackendError;
use vlem_backends::region_crops::{Background, CropSpec, crop_batch, region_embeddings};
use vlem_core::{EmbeddingLayout, NO_REGION, PixelRect, Region, RgbImage};

/// A 4×4 image whose pixel `(u, v)` is `(10u + 1, 10v + 2, 10(u + v) + 3)`, so every value says
/// where it came from.
fn coded_image() -> RgbImage {
    let mut data = Vec::new();
    for v in 0..4u8 {
        for u in 0..4u8 {
            data.extend([10 * u + 1, 10 * v + 2, 10 * (u + v) + 3]);
        }
    }
    RgbImage::new(4, 4, data).unwrap()
}

fn coded(u: u8, v: u8) -> [f32; 3] {
    [10 * u + 1, 10 * v + 2, 10 * (u + v) + 3].map(|c| f32::from(c) / 255.0)
}

fn region(x: u32, y: u32, width: u32, height: u32, mask: &[bool]) -> Region {
    Region {
        bbox: PixelRect {
            x,
            y,
            width,
            height,
        },
        mask: mask.to_vec(),
    }
}

/// The 2×2 region at (1, 1) with the diagonal as foreground: (1, 1) and (2, 2) inside, (2, 1)
/// and (1, 2) outside.
fn diagonal() -> Region {
    region(1, 1, 2, 2, &[true, false, false, true])
}

/// Identity normalisation, so crop values are the `[0, 1]` colours themselves.
fn raw_spec(size: u32, background: Background) -> CropSpec {
    CropSpec {
        size,
        mean: [0.0; 3],
        std: [1.0; 3],
        background,
        seed: 7,
    }
}

/// Pixel `(x, y)` of crop `k` of a CHW batch of `size × size` crops.
fn pixel(batch: &[f32], size: u32, k: usize, x: u32, y: u32) -> [f32; 3] {
    let plane = (size * size) as usize;
    let at = (y * size + x) as usize;
    [0, 1, 2].map(|c| batch[k * 3 * plane + c * plane + at])
}

fn assert_close(actual: [f32; 3], expected: [f32; 3], what: &str) {
    for c in 0..3 {
        assert!(
            (actual[c] - expected[c]).abs() < 1e-6,
            "{what}: got {actual:?}, expected {expected:?}"
        );
    }
}

#[test]
fn a_two_by_two_crop_resized_to_two_by_two_is_exact_and_channel_major() {
    let image = coded_image();
    let batch = crop_batch(&image, &[diagonal()], &raw_spec(2, Background::None)).unwrap();
    // CHW: the red plane first, row by row.
    let expected: Vec<f32> = [0usize, 1, 2]
        .iter()
        .flat_map(|&c| [(1, 1), (2, 1), (1, 2), (2, 2)].map(|(u, v)| coded(u, v)[c]))
        .collect();
    assert_eq!(batch, expected);
}

#[test]
fn values_are_normalised_per_channel() {
    let image = coded_image();
    let spec = CropSpec {
        mean: [0.5, 0.25, 0.0],
        std: [0.5, 2.0, 0.25],
        ..raw_spec(2, Background::None)
    };
    let batch = crop_batch(&image, &[diagonal()], &spec).unwrap();
    // Pixel (2, 2) = bytes (21, 22, 43).
    let expected = [
        (21.0 / 255.0 - 0.5) / 0.5,
        (22.0 / 255.0 - 0.25) / 2.0,
        (43.0 / 255.0) / 0.25,
    ];
    assert_close(pixel(&batch, 2, 0, 1, 1), expected, "normalised (2, 2)");
}

#[test]
fn static_background_is_magenta_and_the_foreground_is_kept() {
    let batch = crop_batch(
        &coded_image(),
        &[diagonal()],
        &raw_spec(2, Background::Static),
    )
    .unwrap();
    assert_close(pixel(&batch, 2, 0, 0, 0), coded(1, 1), "foreground (1, 1)");
    assert_close(pixel(&batch, 2, 0, 1, 1), coded(2, 2), "foreground (2, 2)");
    assert_close(
        pixel(&batch, 2, 0, 1, 0),
        [1.0, 0.0, 1.0],
        "background (2, 1)",
    );
    assert_close(
        pixel(&batch, 2, 0, 0, 1),
        [1.0, 0.0, 1.0],
        "background (1, 2)",
    );
}

#[test]
fn no_background_keeps_the_image_outside_the_mask() {
    let batch = crop_batch(
        &coded_image(),
        &[diagonal()],
        &raw_spec(2, Background::None),
    )
    .unwrap();
    assert_close(pixel(&batch, 2, 0, 1, 0), coded(2, 1), "background (2, 1)");
    assert_close(pixel(&batch, 2, 0, 0, 1), coded(1, 2), "background (1, 2)");
}

#[test]
fn mean_image_background_is_the_mean_of_every_image_pixel() {
    let batch = crop_batch(
        &coded_image(),
        &[diagonal()],
        &raw_spec(2, Background::MeanImage),
    )
    .unwrap();
    // u and v each average 1.5 over the 4×4 image: (16, 17, 33) in bytes.
    let mean = [16.0, 17.0, 33.0].map(|c: f32| c / 255.0);
    assert_close(pixel(&batch, 2, 0, 1, 0), mean, "background (2, 1)");
    assert_close(pixel(&batch, 2, 0, 0, 1), mean, "background (1, 2)");
    assert_close(pixel(&batch, 2, 0, 0, 0), coded(1, 1), "foreground (1, 1)");
}

#[test]
fn mean_segment_background_is_the_mean_of_the_foreground() {
    let batch = crop_batch(
        &coded_image(),
        &[diagonal()],
        &raw_spec(2, Background::MeanSegment),
    )
    .unwrap();
    // Foreground (1, 1) = (11, 12, 23) and (2, 2) = (21, 22, 43): mean (16, 17, 33).
    let diag_mean = [16.0, 17.0, 33.0].map(|c: f32| c / 255.0);
    assert_close(
        pixel(&batch, 2, 0, 1, 0),
        diag_mean,
        "diagonal background (2, 1)",
    );
    // The diagonal's background happens to have the same mean; an L shape tells the readings
    // apart: its background (2, 2) = (21, 22, 43) differs from its foreground mean.
    let l_shape = region(1, 1, 2, 2, &[true, true, true, false]);
    let l_batch = crop_batch(
        &coded_image(),
        &[l_shape],
        &raw_spec(2, Background::MeanSegment),
    )
    .unwrap();
    // Foreground (1, 1), (2, 1), (1, 2): bytes (11, 12, 23), (21, 12, 33), (11, 22, 33).
    let mean = [43.0 / 3.0, 46.0 / 3.0, 89.0 / 3.0].map(|c: f32| c / 255.0);
    assert_close(pixel(&l_batch, 2, 0, 1, 1), mean, "background (2, 2)");
    assert_close(
        pixel(&l_batch, 2, 0, 1, 0),
        coded(2, 1),
        "foreground (2, 1)",
    );
}

#[test]
fn random_background_is_seeded_noise_in_the_unit_range() {
    let image = coded_image();
    let regions = [diagonal(), diagonal()];
    let spec = raw_spec(2, Background::Random);
    let first = crop_batch(&image, &regions, &spec).unwrap();
    assert_eq!(
        first,
        crop_batch(&image, &regions, &spec).unwrap(),
        "not deterministic"
    );
    let reseeded = crop_batch(
        &image,
        &regions,
        &CropSpec {
            seed: 8,
            ..spec.clone()
        },
    )
    .unwrap();
    for k in 0..2 {
        assert_close(pixel(&first, 2, k, 0, 0), coded(1, 1), "foreground (1, 1)");
        assert_close(pixel(&first, 2, k, 1, 1), coded(2, 2), "foreground (2, 2)");
        for (x, y) in [(1, 0), (0, 1)] {
            let noise = pixel(&first, 2, k, x, y);
            assert!(noise.iter().all(|c| (0.0..1.0).contains(c)), "{noise:?}");
            assert_ne!(
                noise,
                pixel(&reseeded, 2, k, x, y),
                "the seed changes nothing"
            );
        }
    }
    // Two crops of the same region get different noise.
    assert_ne!(pixel(&first, 2, 0, 1, 0), pixel(&first, 2, 1, 1, 0));
    // The background pixels of one crop differ from each other.
    assert_ne!(pixel(&first, 2, 0, 1, 0), pixel(&first, 2, 0, 0, 1));
}

#[test]
fn resampling_keeps_uniform_crops_uniform_and_fills_the_batch() {
    let image = RgbImage::filled(9, 7, [51, 102, 204]);
    let regions = [
        region(0, 0, 9, 7, &[true; 63]),
        region(4, 3, 1, 1, &[true]),
        region(2, 1, 5, 2, &[true; 10]),
    ];
    let size = 6;
    let batch = crop_batch(&image, &regions, &raw_spec(size, Background::None)).unwrap();
    assert_eq!(batch.len(), 3 * 3 * 36);
    for k in 0..3 {
        for y in 0..size {
            for x in 0..size {
                assert_close(pixel(&batch, size, k, x, y), [0.2, 0.4, 0.8], "uniform");
            }
        }
    }
}

#[test]
fn catmull_rom_shrinking_averages_a_two_colour_crop() {
    // A 2×1 black-white crop shrunk to 1×1: the centre sample weighs both pixels equally.
    let image = RgbImage::new(2, 1, vec![0, 0, 0, 255, 255, 255]).unwrap();
    let batch = crop_batch(
        &image,
        &[region(0, 0, 2, 1, &[true, true])],
        &raw_spec(1, Background::None),
    )
    .unwrap();
    assert_close(pixel(&batch, 1, 0, 0, 0), [0.5; 3], "averaged");
}

#[test]
fn no_regions_give_an_empty_batch() {
    let batch = crop_batch(&coded_image(), &[], &CropSpec::default()).unwrap();
    assert!(batch.is_empty());
}

#[test]
fn bad_regions_and_specs_are_errors() {
    let image = coded_image();
    let bad_inputs = [
        ("outside", region(3, 3, 2, 1, &[true, true])),
        ("mask length", region(0, 0, 2, 2, &[true; 3])),
        ("empty mask", region(0, 0, 1, 2, &[false, false])),
        ("empty box", region(0, 0, 0, 2, &[])),
        ("huge offset", region(u32::MAX, 0, 2, 1, &[true, true])),
    ];
    for (what, r) in bad_inputs {
        let result = crop_batch(&image, &[diagonal(), r], &CropSpec::default());
        assert!(
            matches!(result, Err(BackendError::InvalidInput(_))),
            "{what}: {result:?}"
        );
    }
    for spec in [
        CropSpec {
            size: 0,
            ..CropSpec::default()
        },
        CropSpec {
            std: [1.0, 0.0, 1.0],
            ..CropSpec::default()
        },
        CropSpec {
            mean: [f32::NAN, 0.0, 0.0],
            ..CropSpec::default()
        },
    ] {
        let result = crop_batch(&image, &[diagonal()], &spec);
        assert!(
            matches!(result, Err(BackendError::InvalidParams(_))),
            "{spec:?}: {result:?}"
        );
    }
}

#[test]
fn background_names_are_kebab_case() {
    #[derive(serde::Deserialize)]
    struct Wrapper {
        background: Background,
    }
    for (text, expected) in [
        ("none", Background::None),
        ("random", Background::Random),
        ("static", Background::Static),
        ("mean-image", Background::MeanImage),
        ("mean-segment", Background::MeanSegment),
    ] {
        let parsed: Wrapper = toml::from_str(&format!("background = \"{text}\"")).unwrap();
        assert_eq!(parsed.background, expected);
    }
    assert_eq!(Background::default(), Background::None);
}

/// The region index of each pixel of a region-layout result.
fn index_of(e: &vlem_core::PixelEmbeddings) -> Vec<u32> {
    match e.layout() {
        EmbeddingLayout::Regions { index, .. } => index.clone(),
        EmbeddingLayout::PatchGrid { .. } => panic!("patch layout"),
    }
}

#[test]
fn the_smaller_segment_wins_on_overlap_in_either_order() {
    // A: the whole 4×1 row; B: its middle two pixels.
    let a = region(0, 0, 4, 1, &[true; 4]);
    let b = region(1, 0, 2, 1, &[true, true]);
    let e = region_embeddings(4, 1, &[a.clone(), b.clone()], 2, vec![3.0, 0.0, 0.0, 2.0]).unwrap();
    assert_eq!(index_of(&e), [0, 1, 1, 0]);
    assert_eq!(
        e.region_row(0, 0).unwrap(),
        [1.0, 0.0],
        "rows are normalised"
    );
    assert_eq!(e.region_row(1, 0).unwrap(), [0.0, 1.0]);
    let swapped = region_embeddings(4, 1, &[b, a], 2, vec![0.0, 2.0, 3.0, 0.0]).unwrap();
    assert_eq!(index_of(&swapped), [1, 0, 0, 1]);
}

#[test]
fn area_counts_mask_pixels_not_the_box() {
    // A has the larger box but only two foreground pixels; B covers three. A wins where both are.
    let a = region(0, 0, 3, 2, &[true, false, false, false, false, true]);
    let b = region(0, 0, 3, 1, &[true, true, true]);
    let e = region_embeddings(3, 2, &[b, a], 1, vec![1.0, 1.0]).unwrap();
    assert_eq!(index_of(&e), [1, 0, 0, NO_REGION, NO_REGION, 1]);
}

#[test]
fn equal_areas_go_to_the_lower_index() {
    let a = region(0, 0, 2, 1, &[true, true]);
    let b = region(1, 0, 2, 1, &[true, true]);
    let e = region_embeddings(3, 1, &[a, b], 1, vec![1.0, -1.0]).unwrap();
    assert_eq!(index_of(&e), [0, 0, 1]);
}

#[test]
fn pixels_in_no_mask_have_no_embedding() {
    // The region's box covers (0, 0) and (1, 0), but its mask only (1, 0); (2, 0) is outside it.
    let r = region(0, 0, 2, 1, &[false, true]);
    let e = region_embeddings(3, 1, &[r], 2, vec![0.0, 5.0]).unwrap();
    assert_eq!(index_of(&e), [NO_REGION, 0, NO_REGION]);
    assert!(!e.has_embedding(0, 0));
    assert!(e.has_embedding(1, 0));
    assert!(!e.has_embedding(2, 0));
    let mut out = [0.0; 2];
    assert!(!e.embedding_at(2, 0, &mut out));
    let none = region_embeddings(3, 1, &[], 2, Vec::new()).unwrap();
    assert_eq!(index_of(&none), [NO_REGION; 3]);
}

#[test]
fn mismatched_inputs_are_errors() {
    let r = region(0, 0, 2, 1, &[true, true]);
    let cases: [(&str, Result<_, _>); 5] = [
        (
            "too few values",
            region_embeddings(2, 1, std::slice::from_ref(&r), 2, vec![1.0]),
        ),
        (
            "too many values",
            region_embeddings(2, 1, std::slice::from_ref(&r), 2, vec![1.0; 3]),
        ),
        (
            "dim 0",
            region_embeddings(2, 1, std::slice::from_ref(&r), 0, Vec::new()),
        ),
        (
            "outside",
            region_embeddings(1, 1, std::slice::from_ref(&r), 1, vec![1.0]),
        ),
        ("zero row", region_embeddings(2, 1, &[r], 1, vec![0.0])),
    ];
    for (what, result) in cases {
        assert!(
            matches!(result, Err(BackendError::InvalidInput(_))),
            "{what}: {result:?}"
        );
    }
    let bad_mask = region(0, 0, 2, 1, &[true]);
    assert!(matches!(
        region_embeddings(2, 1, &[bad_mask], 1, vec![1.0]),
        Err(BackendError::InvalidInput(_))
    ));
}
