//! What the colour-names encoder does on synthetic colours, on text, on its parameters and on a
//! real photo.
#![cfg(feature = "colour-names")]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use vlem_core::{
    BuildContext, CoreError, EmbeddingLayout, Encoder, NO_REGION, PixelEmbeddings, Registry,
    RgbImage, StageConfig,
};
use vlem_plugin_colour_names::{ColourNamesError, DIM, TERMS};

fn term(name: &str) -> usize {
    TERMS.iter().position(|t| *t == name).unwrap()
}

fn one_hot(name: &str) -> Vec<f32> {
    let mut v = vec![0.0; DIM];
    v[term(name)] = 1.0;
    v
}

fn best_term(e: &[f32]) -> &'static str {
    TERMS[(0..DIM).max_by(|&a, &b| e[a].total_cmp(&e[b])).unwrap()]
}

/// Built through the registry, as the pipeline does, so the registration is tested too.
fn build(params: &str) -> Box<dyn Encoder> {
    try_build(params).unwrap()
}

fn try_build(params: &str) -> vlem_core::Result<Box<dyn Encoder>> {
    let stage = StageConfig {
        kind: "colour-names".into(),
        params: toml::from_str(params).unwrap(),
    };
    Registry::global()?.build_encoder(&stage, &BuildContext::default())
}

fn segments(e: &PixelEmbeddings) -> (&[u32], &[f32]) {
    match e.layout() {
        EmbeddingLayout::Regions { index, table } => (index, table),
        EmbeddingLayout::PatchGrid { .. } => panic!("colour-names uses the region layout"),
    }
}

/// 640x480 frame 0 of the living-room sequence (white walls, a wooden floor and furniture).
fn living_room() -> RgbImage {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../data/living-room/color/00000.jpg"
    );
    let img = image::open(path).unwrap().to_rgb8();
    let (w, h) = img.dimensions();
    RgbImage::new(w, h, img.into_raw()).unwrap()
}

#[test]
fn pure_colours_get_their_own_term() {
    let colours = [
        ("red", [255, 0, 0]),
        ("white", [255, 255, 255]),
        ("black", [0, 0, 0]),
        ("blue", [0, 0, 255]),
        ("green", [0, 160, 0]),
        ("yellow", [255, 255, 0]),
        ("grey", [128, 128, 128]),
    ];
    // One vertical stripe per colour, 10 pixels wide.
    let (w, h) = (10 * colours.len() as u32, 4);
    let mut data = Vec::new();
    for _ in 0..h {
        for (_, rgb) in &colours {
            for _ in 0..10 {
                data.extend_from_slice(rgb);
            }
        }
    }
    let image = RgbImage::new(w, h, data).unwrap();
    let e = build("").encode_image(&image, &[]).unwrap();
    // Uniform stripes fall into exactly one bin each.
    assert_eq!(segments(&e).1.len(), colours.len() * DIM);
    let mut out = [0.0; DIM];
    for (i, (name, _)) in colours.iter().enumerate() {
        assert!(e.embedding_at(10 * i as u32 + 5, 2, &mut out));
        assert_eq!(best_term(&out), *name, "{out:?}");
    }
}

#[test]
fn every_pixel_has_a_segment_and_every_row_is_unit_norm() {
    let image = living_room();
    let e = build("").encode_image(&image, &[]).unwrap();
    let (index, table) = segments(&e);
    assert_eq!(index.len(), 640 * 480);
    assert!(index.iter().all(|&s| s != NO_REGION));
    let rows = table.len() / DIM;
    assert!(rows <= 16 * 16 * 16);
    // Every row is used by some pixel: rows are occupied bins only.
    let mut used = vec![false; rows];
    index.iter().for_each(|&s| used[s as usize] = true);
    assert!(used.iter().all(|u| *u));
    for row in table.chunks_exact(DIM) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5, "{row:?}");
        assert!(row.iter().all(|x| x.is_finite() && *x >= 0.0));
    }
}

#[test]
fn bins_bound_the_number_of_segments() {
    let noise: Vec<u8> = (0..64u32 * 64 * 3)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
        .collect();
    let image = RgbImage::new(64, 64, noise).unwrap();
    let coarse = build("bins = 2").encode_image(&image, &[]).unwrap();
    assert!(segments(&coarse).1.len() / DIM <= 8);
    let fine = build("bins = 32").encode_image(&image, &[]).unwrap();
    assert!(segments(&fine).1.len() / DIM > 8);
}

#[test]
fn sigma_controls_how_soft_the_assignment_is() {
    // An orange-brown between the two prototypes: a wider sigma gives the runner-up more weight.
    let image = RgbImage::filled(1, 1, [170, 85, 20]);
    let runner_up = |params: &str| {
        let e = build(params).encode_image(&image, &[]).unwrap();
        let mut v = segments(&e).1.to_vec();
        v.sort_by(|a, b| b.total_cmp(a));
        v[1] / v[0]
    };
    assert!(runner_up("sigma = 30") > runner_up("sigma = 5.0"));
}

#[test]
fn text_is_the_average_of_its_colour_words() {
    let encoder = build("");
    assert_eq!(encoder.encode_text("white wall").unwrap(), one_hot("white"));
    assert_eq!(encoder.encode_text("Gray").unwrap(), one_hot("grey"));
    assert_eq!(
        encoder.encode_text("a VIOLET vase").unwrap(),
        one_hot("purple")
    );

    let mix = encoder.encode_text("red and blue").unwrap();
    let half = std::f32::consts::FRAC_1_SQRT_2;
    assert!((mix[term("red")] - half).abs() < 1e-6, "{mix:?}");
    assert_eq!(mix[term("red")], mix[term("blue")]);
    assert_eq!(mix.iter().filter(|x| **x != 0.0).count(), 2);

    // Hyphenated colours name both terms.
    let teal = encoder.encode_text("blue-green").unwrap();
    assert_eq!(teal[term("blue")], teal[term("green")]);
}

#[test]
fn text_without_colour_words_is_refused_with_the_known_words() {
    let err = build("").encode_text("coffee machine").unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.starts_with(
            "encoder `colour-names`: the colour-names encoder understands only colour words \
             (black, white, red, green, yellow, blue, brown, purple, pink, orange, grey, and the \
             synonyms gray, silver, "
        ),
        "{msg}"
    );
    assert!(
        msg.ends_with("); \"coffee machine\" contains none"),
        "{msg}"
    );
    // The plugin's own error stays reachable for callers that want to match on it.
    let CoreError::Stage { source, .. } = &err else {
        panic!("expected a stage error, got {err:?}");
    };
    assert!(matches!(
        source.downcast_ref::<ColourNamesError>(),
        Some(ColourNamesError::NoColourWord { .. })
    ));
    // Words are whole words: "redundant" is not "red".
    assert!(build("").encode_text("redundant").is_err());
}

#[test]
fn parameters_are_checked_with_messages_that_name_the_key() {
    let err = try_build("sigmaa = 10").err().unwrap().to_string();
    assert!(
        err.starts_with("[encoder] kind = \"colour-names\": unknown field `sigmaa`"),
        "{err}"
    );
    let err = try_build("sigma = -1").err().unwrap().to_string();
    assert!(
        err.contains("sigma must lie in 0.1–1000, got -1 (ΔE units"),
        "{err}"
    );
    let err = try_build("sigma = 1e-200").err().unwrap().to_string();
    assert!(err.contains("got 1e-200"), "{err}");
    let err = try_build("bins = 1").err().unwrap().to_string();
    assert!(err.contains("bins must be between 2 and 64"), "{err}");
    let err = try_build("bins = \"many\"").err().unwrap().to_string();
    assert!(err.contains("invalid type"), "{err}");
    // Integers are fine where a float is expected.
    assert!(try_build("sigma = 20\nbins = 8").is_ok());
}

/// Per term, the fraction of the pixels of `image` whose best term it is, and the mean cosine
/// score of the queries "white", "green" and "red".
fn best_terms_and_scores(image: &RgbImage) -> ([f64; DIM], [f64; 3]) {
    let encoder = build("");
    let e = encoder.encode_image(image, &[]).unwrap();
    let queries = ["white", "green", "red"].map(|q| encoder.encode_text(q).unwrap());
    let mut best = [0.0; DIM];
    let mut scores = [0.0; 3];
    let mut out = [0.0; DIM];
    for v in 0..image.height() {
        for u in 0..image.width() {
            assert!(e.embedding_at(u, v, &mut out));
            best[term(best_term(&out))] += 1.0;
            for (score, query) in scores.iter_mut().zip(&queries) {
                *score += out
                    .iter()
                    .zip(query)
                    .map(|(x, y)| f64::from(x * y))
                    .sum::<f64>();
            }
        }
    }
    let n = f64::from(image.width() * image.height());
    (best.map(|b| b / n), scores.map(|s| s / n))
}

fn fraction(best: &[f64; DIM], names: &[&str]) -> f64 {
    names.iter().map(|t| best[term(t)]).sum()
}

/// The living room is mostly white walls under warm light, a light wooden floor and furniture;
/// nothing in it is green, blue or purple. Measured with the defaults: about 41% of the pixels are
/// best "white", 51% "grey", 5% "orange" and 3% "brown", and the mean cosine score of "white" is
/// 0.54 against 0.001 for "red" and 0.000 for "green". The bounds leave room for other reasonable
/// prototypes or sigma, but fail for a broken conversion: without the sRGB decoding, or with red
/// and blue swapped (see the next test), the warm wood is no longer brown or orange.
#[test]
fn a_living_room_with_white_walls_is_mostly_white_and_grey() {
    let (best, [white, green, red]) = best_terms_and_scores(&living_room());
    assert!(fraction(&best, &["white", "grey"]) > 0.8, "{best:?}");
    assert!(fraction(&best, &["white"]) > 0.25, "{best:?}");
    assert!(fraction(&best, &["grey"]) > 0.25, "{best:?}");
    // The wood is warm: it must come out brown or orange, not as a cold colour.
    assert!(fraction(&best, &["brown", "orange"]) > 0.04, "{best:?}");
    assert!(
        fraction(&best, &["blue", "purple", "green"]) < 0.005,
        "{best:?}"
    );

    assert!(white > 0.4, "{white}");
    assert!(white > 20.0 * green, "{white} vs {green}");
    assert!(white > 20.0 * red, "{white} vs {red}");
}

/// The same photo read as BGR (a classic decoding bug): the warm wood turns cold, so the bounds
/// above would catch it.
#[test]
fn the_living_room_read_as_bgr_has_no_warm_wood() {
    let image = living_room();
    let mut raw = image.as_raw().to_vec();
    raw.chunks_exact_mut(3).for_each(|p| p.swap(0, 2));
    let swapped = RgbImage::new(image.width(), image.height(), raw).unwrap();
    let (best, _) = best_terms_and_scores(&swapped);
    assert!(fraction(&best, &["brown", "orange"]) < 0.01, "{best:?}");
}
