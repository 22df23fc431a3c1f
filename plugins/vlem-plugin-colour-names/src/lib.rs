//! `colour-names`: a weight-free reference encoder for vlem, and the how-to for writing encoders.
//!
//! **This is a reference encoder for demos and tests, not a substitute for CLIP.** Its embedding
//! space has 11 dimensions, one per basic colour term of Berlin & Kay ("Basic Color Terms", 1969):
//! black, white, red, green, yellow, blue, brown, purple, pink, orange and grey ([`TERMS`]). A pixel
//! is embedded as a soft assignment of its colour to these terms, and a text as the terms it names,
//! so the query "white wall" lights up white things, not walls. It needs no model weights, runs in
//! a few milliseconds per 640x480 frame on one core, and lets the whole pipeline (mapping, queries,
//! segmentation, map files) run and be tested anywhere.
//!
//! # How to add an encoder to vlem
//!
//! This crate is deliberately small so that it can be read as the recipe. A new encoder is a crate
//! (or a module of `vlem-backends`) that does the same five things:
//!
//! 1. **Parameters.** A config struct with `#[derive(Deserialize)]` and
//!    `#[serde(deny_unknown_fields)]`, so a misspelt key in the `[encoder]` section is an error that
//!    names the key instead of being ignored. Give every field a `#[serde(default)]` so that
//!    `kind = "..."` alone works. Here: [`ColourNamesConfig`] (`sigma`, `bins`).
//! 2. **The encoder.** A type implementing [`vlem_core::Encoder`]: `name`, `dim`, `encode_image`
//!    returning [`PixelEmbeddings`] in the layout the model computes natively (never a dense
//!    `w x h x dim` tensor), and `encode_text` if it has a text side (the default answers
//!    [`CoreError::Unsupported`]). Here: [`ColourNamesEncoder`], which uses the region layout with
//!    one segment per colour bin.
//! 3. **Errors.** The crate's own `thiserror` enum ([`ColourNamesError`]) with messages that tell
//!    the user what to do, converted into [`CoreError`] at the trait boundary:
//!    [`CoreError::stage`] wraps runtime failures (the source stays reachable through
//!    `Error::source`), and parameter problems become [`CoreError::InvalidParams`] like those of
//!    [`vlem_core::parse_params`].
//! 4. **Registration.** A build function `fn(&toml::Table, &BuildContext) ->
//!    vlem_core::Result<Box<dyn Encoder>>` that parses its parameters with
//!    [`vlem_core::parse_params`] and constructs the encoder ([`build`]), registered under the name
//!    used as `kind = "..."` in the config:
//!    `vlem_core::register_encoder!("colour-names", "one-line description", build);`.
//!    The registry refuses two plugins registering the same name.
//! 5. **Conformance.** A `tests/conformance.rs` that runs the shared suite of `vlem-testkit`
//!    (`vlem_testkit::encoder_conformance!(build_fn)`), which checks sizes, unit norms,
//!    determinism and the text side on synthetic images; plus tests of the encoder's own behaviour
//!    on real data.
//!
//! Finally, a binary must **reference the crate** or the linker drops it, and with it the
//! registration (it lives in an `inventory` static nothing else points to): the `vlem` binary and
//! any other binary or test that builds encoders by name writes
//!
//! ```
//! use vlem_plugin_colour_names as _;
//! ```
//!
//! An optional encoder goes behind a cargo feature of the `vlem` package, and its crate declares
//! that feature with `vlem_core::feature_hint!` whether or not the encoder is compiled in, so that
//! asking for it in a binary built without it says which feature to enable. The hint only reaches
//! the registry when the crate is linked, so the crate stays linked and the feature turns on what
//! it registers: here `vlem`'s `colour-names` feature turns on this crate's `colour-names`
//! feature, which gates the `register_encoder!` line.
//!
//! # The recipe in one piece
//!
//! A complete (if useless) encoder plugin, compiled as a test of this documentation:
//!
//! ```
//! use serde::Deserialize;
//! use vlem_core::{
//!     BuildContext, CoreError, Encoder, PixelEmbeddings, Region, RgbImage, StageKind,
//!     parse_params,
//! };
//!
//! /// Parameters of the `brightness` encoder (`[encoder] kind = "brightness"`).
//! #[derive(Deserialize)]
//! #[serde(deny_unknown_fields)]
//! struct BrightnessConfig {
//!     #[serde(default)]
//!     gamma: Option<f32>,
//! }
//!
//! #[derive(Debug, thiserror::Error)]
//! enum BrightnessError {
//!     #[error("gamma must be positive, got {0}")]
//!     BadGamma(f32),
//! }
//!
//! /// Embeds each pixel as (dark, bright).
//! struct Brightness {
//!     gamma: f32,
//! }
//!
//! impl Encoder for Brightness {
//!     fn name(&self) -> &'static str {
//!         "brightness"
//!     }
//!     fn dim(&self) -> usize {
//!         2
//!     }
//!     fn encode_image(
//!         &self,
//!         image: &RgbImage,
//!         _regions: &[Region],
//!     ) -> vlem_core::Result<PixelEmbeddings> {
//!         // One segment per grey level: 256 table rows however large the image.
//!         let mut table = Vec::with_capacity(2 * 256);
//!         for level in 0..256 {
//!             let b = (level as f32 / 255.0).powf(self.gamma);
//!             table.extend_from_slice(&[1.0 - b + 1e-3, b + 1e-3]);
//!         }
//!         let index = image
//!             .as_raw()
//!             .chunks_exact(3)
//!             .map(|p| (p.iter().map(|&c| u32::from(c)).sum::<u32>()) / 3)
//!             .collect();
//!         PixelEmbeddings::from_regions(image.width(), image.height(), 2, index, table)
//!     }
//! }
//!
//! fn build(
//!     params: &toml::Table,
//!     _ctx: &BuildContext,
//! ) -> vlem_core::Result<Box<dyn Encoder>> {
//!     let config: BrightnessConfig = parse_params(StageKind::Encoder, "brightness", params)?;
//!     let gamma = config.gamma.unwrap_or(1.0);
//!     if !(gamma > 0.0) {
//!         let e = BrightnessError::BadGamma(gamma);
//!         return Err(CoreError::stage(StageKind::Encoder, "brightness", e));
//!     }
//!     Ok(Box::new(Brightness { gamma }))
//! }
//!
//! vlem_core::register_encoder!("brightness", "pixel brightness (an example)", build);
//!
//! # fn main() -> anyhow::Result<()> {
//! let stage = vlem_core::StageConfig::named("brightness");
//! let registry = vlem_core::Registry::global()?;
//! let encoder = registry.build_encoder(&stage, &BuildContext::default())?;
//! assert_eq!(encoder.dim(), 2);
//! # Ok(())
//! # }
//! ```
//!
//! # The colour model
//!
//! Image side: colours are quantised to `bins` levels per channel; every occupied bin becomes one
//! segment, embedded from the mean colour of its pixels. That colour is converted from sRGB (D65)
//! to CIELAB, its CIE76 colour difference ΔE to the prototype of each term is computed, and the
//! assignment `p_k ∝ exp(-ΔE_k² / (2 σ²))` is L2-normalised. Text side: the colour words of the
//! query (and the synonyms in [`SYNONYMS`]) are averaged as one-hot vectors and L2-normalised; the
//! cosine similarity to a pixel is then the (normalised) weight of the named terms.

use serde::Deserialize;
use vlem_core::{BuildContext, CoreError, Encoder, PixelEmbeddings, Region, RgbImage, StageKind};

/// The name this encoder is registered under (`[encoder] kind = "colour-names"`).
pub const NAME: &str = "colour-names";

/// Embedding dimension: one component per basic colour term.
pub const DIM: usize = 11;

/// The basic colour terms of Berlin & Kay, in the order of the embedding components.
pub const TERMS: [&str; DIM] = [
    "black", "white", "red", "green", "yellow", "blue", "brown", "purple", "pink", "orange", "grey",
];

/// Prototype of each term of [`TERMS`], as an sRGB colour.
///
/// These are the colours published for these names by the xkcd colour survey (R. Munroe, 2010:
/// about 200 000 participants named random colours on their own screens; the results are the
/// `rgb.txt` list, CC0, also shipped as matplotlib's `xkcd:` colours). They describe how people use
/// the words on sRGB displays, which the saturated primaries do not (#0000FF is a dark,
/// violet-leaning blue in CIELAB). Black and white are the ends of the sRGB gamut. The prototypes
/// are converted to CIELAB by the same function as the pixels, so the two cannot disagree. Each
/// prototype's nearest neighbour lies 32 (red-orange) to 64 (green-yellow) ΔE away.
const PROTOTYPES_SRGB: [[u8; 3]; DIM] = [
    [0x00, 0x00, 0x00], // black
    [0xff, 0xff, 0xff], // white
    [0xe5, 0x00, 0x00], // red    #e50000
    [0x15, 0xb0, 0x1a], // green  #15b01a
    [0xff, 0xff, 0x14], // yellow #ffff14
    [0x03, 0x43, 0xdf], // blue   #0343df
    [0x65, 0x37, 0x00], // brown  #653700
    [0x7e, 0x1e, 0x9c], // purple #7e1e9c
    [0xff, 0x81, 0xc0], // pink   #ff81c0
    [0xf9, 0x73, 0x06], // orange #f97306
    [0x92, 0x95, 0x91], // grey   #929591
];

/// Other words the text side accepts, each standing for one of [`TERMS`]. Plain synonyms and
/// near-synonyms only: a word that people split between two terms (magenta, turquoise) is left
/// out rather than guessed.
pub const SYNONYMS: [(&str, &str); 15] = [
    ("gray", "grey"),
    ("silver", "grey"),
    ("ivory", "white"),
    ("cream", "white"),
    ("crimson", "red"),
    ("scarlet", "red"),
    ("navy", "blue"),
    ("azure", "blue"),
    ("gold", "yellow"),
    ("golden", "yellow"),
    ("tan", "brown"),
    ("beige", "brown"),
    ("violet", "purple"),
    ("lilac", "purple"),
    ("lavender", "purple"),
];

/// Parameters of the encoder: the `[encoder]` section without `kind`.
///
/// ```toml
/// [encoder]
/// kind = "colour-names"
/// sigma = 15.0   # ΔE units; larger = softer assignments
/// bins = 16      # quantisation levels per RGB channel
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ColourNamesConfig {
    /// Width σ of the Gaussian soft assignment, in CIE76 ΔE units (> 0). A just noticeable
    /// difference is about 2.3; neighbouring prototypes are 32 to 64 apart. The
    /// default, 15, makes a colour between two prototypes share its weight between them while a
    /// colour close to one prototype is clearly that term.
    pub sigma: f64,
    /// Quantisation levels per RGB channel (2 to 64). Each occupied bin of the `bins³` is one
    /// segment. 16 (4096 bins, steps of 16 in 0..=255) is far finer than the colour terms and keeps
    /// the per-frame table small; 64 is the limit because the bins are counted in a dense array.
    pub bins: u32,
}

impl Default for ColourNamesConfig {
    fn default() -> Self {
        Self {
            sigma: 15.0,
            bins: 16,
        }
    }
}

/// The valid range of [`ColourNamesConfig::bins`].
const BINS_RANGE: std::ops::RangeInclusive<u32> = 2..=64;
/// The accepted `sigma`, in ΔE units: below, the weights underflow to NaN; above, every colour
/// word weighs the same.
const SIGMA_RANGE: (f64, f64) = (0.1, 1000.0);

/// Errors of this encoder.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ColourNamesError {
    /// `sigma` is outside 0.1–1000 (the message of `vlem_core::ranges`).
    #[error(
        "sigma {0} (ΔE units, e.g. 15; outside the range every colour gets the same, or a NaN, \
         embedding)"
    )]
    InvalidSigma(String),
    /// `bins` is outside 2..=64.
    #[error("bins must be between 2 and 64 levels per channel (e.g. 16), got {0}")]
    InvalidBins(u32),
    /// A text query without any colour word.
    #[error(
        "the colour-names encoder understands only colour words ({}); {text:?} contains none",
        understood_words()
    )]
    NoColourWord {
        /// The query as given.
        text: String,
    },
}

/// "black, white, ..., grey and the synonyms gray, silver, ...", for the error message.
fn understood_words() -> String {
    let synonyms: Vec<&str> = SYNONYMS.iter().map(|(word, _)| *word).collect();
    format!(
        "{}, and the synonyms {}",
        TERMS.join(", "),
        synonyms.join(", ")
    )
}

impl From<ColourNamesError> for CoreError {
    fn from(e: ColourNamesError) -> Self {
        match e {
            // Bad parameters read like the parse errors of `parse_params`: section, name, problem.
            ColourNamesError::InvalidSigma(_) | ColourNamesError::InvalidBins(_) => {
                CoreError::InvalidParams {
                    section: StageKind::Encoder.section().to_owned(),
                    name: NAME.to_owned(),
                    message: e.to_string(),
                }
            }
            ColourNamesError::NoColourWord { .. } => CoreError::stage(StageKind::Encoder, NAME, e),
        }
    }
}

/// The colour-names encoder. See the [crate documentation](crate) for the model.
#[derive(Clone, Debug)]
pub struct ColourNamesEncoder {
    config: ColourNamesConfig,
    /// CIELAB of [`PROTOTYPES_SRGB`].
    prototypes: [[f64; 3]; DIM],
}

impl ColourNamesEncoder {
    /// An encoder with the given parameters.
    ///
    /// # Errors
    /// [`ColourNamesError::InvalidSigma`] or [`ColourNamesError::InvalidBins`].
    pub fn new(config: ColourNamesConfig) -> Result<Self, ColourNamesError> {
        vlem_core::ranges::number(config.sigma, SIGMA_RANGE.0, SIGMA_RANGE.1, "")
            .map_err(ColourNamesError::InvalidSigma)?;
        if !BINS_RANGE.contains(&config.bins) {
            return Err(ColourNamesError::InvalidBins(config.bins));
        }
        Ok(Self {
            config,
            prototypes: prototypes_lab(),
        })
    }

    /// The parameters.
    pub fn config(&self) -> &ColourNamesConfig {
        &self.config
    }

    /// The unit-norm embedding of one sRGB colour (channels in 0..=255, fractional values allowed).
    pub fn embed_colour(&self, rgb: [f64; 3]) -> [f32; DIM] {
        let lab = srgb_to_lab(rgb);
        let d2 = self.prototypes.map(|p| {
            let d: [f64; 3] = std::array::from_fn(|i| lab[i] - p[i]);
            d.iter().map(|x| x * x).sum::<f64>()
        });
        // Subtracting the smallest squared distance leaves the normalised result unchanged but
        // keeps the nearest term at weight 1, so far-off colours cannot underflow to a zero vector.
        let nearest = d2.iter().copied().fold(f64::INFINITY, f64::min);
        let two_sigma_sq = 2.0 * self.config.sigma * self.config.sigma;
        let weights = d2.map(|d| (-(d - nearest) / two_sigma_sq).exp());
        let norm = weights.iter().map(|w| w * w).sum::<f64>().sqrt();
        weights.map(|w| (w / norm) as f32)
    }
}

impl Default for ColourNamesEncoder {
    /// The encoder with [`ColourNamesConfig::default`] (which is valid, so this cannot fail).
    fn default() -> Self {
        Self {
            config: ColourNamesConfig::default(),
            prototypes: prototypes_lab(),
        }
    }
}

fn prototypes_lab() -> [[f64; 3]; DIM] {
    PROTOTYPES_SRGB.map(|c| srgb_to_lab(c.map(f64::from)))
}

impl Encoder for ColourNamesEncoder {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        DIM
    }

    /// One segment per occupied colour bin, embedded from the mean colour of its pixels. Two passes
    /// over the pixels and one over the bins, so the cost is linear in the image size and the
    /// CIELAB conversion runs once per bin (at most `bins³`), not once per pixel.
    fn encode_image(
        &self,
        image: &RgbImage,
        _regions: &[Region],
    ) -> vlem_core::Result<PixelEmbeddings> {
        let bins = self.config.bins as usize;
        // Channel value -> level, so that binning a pixel is three table lookups.
        let level: [u32; 256] = std::array::from_fn(|c| (c * bins / 256) as u32);
        let bins = bins as u32;

        // Pass 1: the bin of every pixel, and per bin the colour sums and the pixel count.
        let mut sums = vec![[0u64; 4]; (bins * bins * bins) as usize];
        let mut index: Vec<u32> = image
            .as_raw()
            .chunks_exact(3)
            .map(|p| {
                let bin = (level[p[0] as usize] * bins + level[p[1] as usize]) * bins
                    + level[p[2] as usize];
                let s = &mut sums[bin as usize];
                s[0] += u64::from(p[0]);
                s[1] += u64::from(p[1]);
                s[2] += u64::from(p[2]);
                s[3] += 1;
                bin
            })
            .collect();

        // Occupied bins become segments 0, 1, ... in bin order (deterministic).
        let mut segment_of_bin = vec![vlem_core::NO_REGION; sums.len()];
        let mut table = Vec::new();
        let mut segments = 0u32;
        for (bin, s) in sums.iter().enumerate() {
            if s[3] == 0 {
                continue;
            }
            let n = s[3] as f64;
            let mean = [s[0] as f64 / n, s[1] as f64 / n, s[2] as f64 / n];
            table.extend_from_slice(&self.embed_colour(mean));
            segment_of_bin[bin] = segments;
            segments += 1;
        }

        // Pass 2: bin -> segment, in place.
        for i in &mut index {
            *i = segment_of_bin[*i as usize];
        }
        PixelEmbeddings::from_regions(image.width(), image.height(), DIM, index, table)
    }

    /// The average of the one-hot vectors of the colour words in `text`, L2-normalised.
    ///
    /// Words are the runs of letters of the lower-cased text, so "Blue-green" names blue and green.
    /// A word counts each time it occurs.
    fn encode_text(&self, text: &str) -> vlem_core::Result<Vec<f32>> {
        let mut counts = [0.0f32; DIM];
        let lower = text.to_lowercase();
        for word in lower.split(|c: char| !c.is_alphabetic()) {
            if let Some(k) = term_index(word) {
                counts[k] += 1.0;
            }
        }
        let norm = counts.iter().map(|c| c * c).sum::<f32>().sqrt();
        if norm == 0.0 {
            return Err(ColourNamesError::NoColourWord {
                text: text.to_owned(),
            }
            .into());
        }
        Ok(counts.iter().map(|c| c / norm).collect())
    }

    /// "grey": the colour of no colour in particular, which the baseline of `argmax` and
    /// `cluster` compares each colour query against ("object" is no colour word).
    fn generic_text(&self) -> &str {
        "grey"
    }
}

/// The component of a (lower-case) colour word or synonym; `None` for other words.
pub fn term_index(word: &str) -> Option<usize> {
    let term = SYNONYMS
        .iter()
        .find(|(synonym, _)| *synonym == word)
        .map_or(word, |(_, term)| *term);
    TERMS.iter().position(|t| *t == term)
}

/// Converts an sRGB colour (channels in 0..=255) to CIELAB (L* in 0..=100), D65 white point.
///
/// sRGB decoding and the sRGB-to-XYZ matrix follow IEC 61966-2-1; XYZ to L*a*b* follows CIE 15
/// with the D65 reference white of the 2° observer.
pub fn srgb_to_lab(rgb: [f64; 3]) -> [f64; 3] {
    let linear = rgb.map(|c| {
        let c = (c / 255.0).clamp(0.0, 1.0);
        if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    });
    let [r, g, b] = linear;
    let xyz = [
        0.412_456_4 * r + 0.357_576_1 * g + 0.180_437_5 * b,
        0.212_672_9 * r + 0.715_152_2 * g + 0.072_175_0 * b,
        0.019_333_9 * r + 0.119_192_0 * g + 0.950_304_1 * b,
    ];
    const WHITE: [f64; 3] = [0.950_47, 1.0, 1.088_83];
    // The cube root with CIE's linear segment near black, where the cube root's slope is infinite.
    const DELTA: f64 = 6.0 / 29.0;
    let f = |t: f64| {
        if t > DELTA * DELTA * DELTA {
            t.cbrt()
        } else {
            t / (3.0 * DELTA * DELTA) + 4.0 / 29.0
        }
    };
    let [fx, fy, fz] = std::array::from_fn(|i| f(xyz[i] / WHITE[i]));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// Builds the encoder from its `[encoder]` parameters (the registered build function).
///
/// # Errors
/// [`CoreError::InvalidParams`] for unknown keys, values of the wrong type, a non-positive `sigma`
/// or `bins` outside 2..=64.
pub fn build(params: &toml::Table, _ctx: &BuildContext) -> vlem_core::Result<Box<dyn Encoder>> {
    let config: ColourNamesConfig = vlem_core::parse_params(StageKind::Encoder, NAME, params)?;
    Ok(Box::new(ColourNamesEncoder::new(config)?))
}

// Registered only with this crate's `colour-names` feature (the `vlem` feature of the same name
// turns it on); the hint is declared either way, so that a binary built without the feature
// names it when a config asks for `kind = "colour-names"`.
#[cfg(feature = "colour-names")]
vlem_core::register_encoder!(
    NAME,
    "basic colour terms in CIELAB: a weight-free reference encoder for demos and tests",
    build
);
vlem_core::feature_hint!(Encoder, NAME, "colour-names");

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_lab(rgb: [u8; 3], expected: [f64; 3]) {
        let lab = srgb_to_lab(rgb.map(f64::from));
        for i in 0..3 {
            assert!(
                (lab[i] - expected[i]).abs() < 0.05,
                "{rgb:?} -> {lab:?}, expected {expected:?}"
            );
        }
    }

    #[test]
    fn srgb_to_lab_matches_reference_values() {
        // Reference values from Bruce Lindbloom's calculator (sRGB, D65, 2°).
        assert_lab([255, 255, 255], [100.0, 0.0, 0.0]);
        assert_lab([0, 0, 0], [0.0, 0.0, 0.0]);
        assert_lab([255, 0, 0], [53.24, 80.09, 67.20]);
        assert_lab([0, 255, 0], [87.73, -86.18, 83.18]);
        assert_lab([0, 0, 255], [32.30, 79.19, -107.86]);
        assert_lab([128, 128, 128], [53.59, 0.0, 0.0]);
    }

    #[test]
    fn every_prototype_is_its_own_best_term() {
        let encoder = ColourNamesEncoder::default();
        for (k, rgb) in PROTOTYPES_SRGB.iter().enumerate() {
            let e = encoder.embed_colour(rgb.map(f64::from));
            let best = (0..DIM).max_by(|&a, &b| e[a].total_cmp(&e[b]));
            assert_eq!(best, Some(k), "{}: {e:?}", TERMS[k]);
        }
    }

    #[test]
    fn synonyms_name_terms() {
        for (word, term) in SYNONYMS {
            assert_eq!(term_index(word), term_index(term), "{word}");
            assert!(term_index(word).is_some(), "{word} stands for no term");
        }
        assert_eq!(term_index("gray"), Some(10));
        assert_eq!(term_index("chair"), None);
    }

    #[test]
    fn bad_parameters_are_refused() {
        let sigma = ColourNamesConfig {
            sigma: 0.0,
            ..ColourNamesConfig::default()
        };
        assert!(matches!(
            ColourNamesEncoder::new(sigma),
            Err(ColourNamesError::InvalidSigma(_))
        ));
        let bins = ColourNamesConfig {
            bins: 65,
            ..ColourNamesConfig::default()
        };
        let err = CoreError::from(ColourNamesEncoder::new(bins).unwrap_err());
        assert_eq!(
            err.to_string(),
            "[encoder] kind = \"colour-names\": bins must be between 2 and 64 levels per channel \
             (e.g. 16), got 65"
        );
    }
}
