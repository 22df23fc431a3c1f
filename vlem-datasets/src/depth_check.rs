//! A plausibility check of the depth scale: the commonest silent mistake with RGB-D folders is a
//! `depth_scale` that does not match how the depth PNGs were written (millimetres read as metres,
//! or TUM's 5000 units per metre read as 1000), which makes every distance off by a constant
//! factor. Such maps look fine in a viewer and answer queries, but nothing in them is metric.
//!
//! Every decoded depth image is checked: the median of its valid depths (in metres, after the
//! scale) must lie in [`PLAUSIBLE_MEDIAN_M`], which any indoor or outdoor RGB-D sensor meets. The
//! error names `[dataset] depth_scale`, the scale in use and a scale that would bring the median
//! into range.

use std::path::Path;

use vlem_core::DepthImage;

use crate::error::{DatasetError, Result};

/// The range (metres) the median valid depth of a frame must lie in.
pub const PLAUSIBLE_MEDIAN_M: (f32, f32) = (0.05, 50.0);

/// Depth scales of the common layouts (raw units per metre): millimetres (ICL-NUIM, ScanNet,
/// Redwood), TUM RGB-D, Replica (NICE-SLAM packaging).
const COMMON_SCALES: [f64; 3] = [1000.0, 5000.0, 6553.5];

/// The median depth a suggested scale aims for when no common scale fits (metres).
const TYPICAL_MEDIAN_M: f64 = 2.0;

/// At most this many valid pixels are looked at (evenly spread), so the check costs little.
const MAX_SAMPLES: usize = 4096;

/// Checks that the median valid depth of `depth` (read with `scale` raw units per metre from
/// `path`) is plausible. Frames with less than 1 % valid depth are not judged.
///
/// # Errors
/// [`DatasetError::BadConfig`] naming `[dataset] depth_scale`, the median it gives and a scale
/// that would fix it.
pub(crate) fn check_depth_scale(depth: &DepthImage, scale: f32, path: &Path) -> Result<()> {
    let Some(median) = median_valid_depth(depth) else {
        return Ok(());
    };
    let (lo, hi) = PLAUSIBLE_MEDIAN_M;
    if (lo..=hi).contains(&median) {
        return Ok(());
    }
    let raw = f64::from(median) * f64::from(scale);
    let options: Vec<String> = suggest_scales(raw)
        .iter()
        .map(|&(s, m)| format!("{s} (median {} m)", three_digits(m)))
        .collect();
    let options = match options.as_slice() {
        [one] => one.clone(),
        [rest @ .., last] => format!("{} or {last}", rest.join(", ")),
        [] => String::new(),
    };
    Err(DatasetError::BadConfig {
        path: path.to_path_buf(),
        message: format!(
            "depth_scale is {scale} raw units per metre, which puts the median depth of this \
             image at {} m, outside the plausible {lo}–{hi} m (raw median {}): set depth_scale to \
             the scale the depth images were written with, e.g. {options}",
            three_digits(f64::from(median)),
            three_digits(raw),
        ),
    })
}

/// The median of (at most [`MAX_SAMPLES`] evenly spread) valid depths; `None` when under 1 % of
/// the pixels are valid.
fn median_valid_depth(depth: &DepthImage) -> Option<f32> {
    let all = depth.as_raw();
    let valid = all.iter().filter(|&&d| d.is_finite() && d > 0.0).count();
    if valid == 0 || valid * 100 < all.len() {
        return None;
    }
    let step = valid.div_ceil(MAX_SAMPLES).max(1);
    let mut samples: Vec<f32> = all
        .iter()
        .copied()
        .filter(|d| d.is_finite() && *d > 0.0)
        .step_by(step)
        .collect();
    let mid = samples.len() / 2;
    let (_, m, _) = samples.select_nth_unstable_by(mid, f32::total_cmp);
    Some(*m)
}

/// Scales that put a raw median of `raw` into the plausible range, each with the median it gives:
/// the common scales that do, the one giving a median closest to 2 m first; where none does, the
/// scale (to three digits) that gives 2 m.
fn suggest_scales(raw: f64) -> Vec<(f64, f64)> {
    let (lo, hi) = (
        f64::from(PLAUSIBLE_MEDIAN_M.0),
        f64::from(PLAUSIBLE_MEDIAN_M.1),
    );
    let distance = |s: f64| (raw / s / TYPICAL_MEDIAN_M).ln().abs();
    let mut fitting: Vec<f64> = COMMON_SCALES
        .iter()
        .copied()
        .filter(|&s| (lo..=hi).contains(&(raw / s)))
        .collect();
    fitting.sort_by(|a, b| distance(*a).total_cmp(&distance(*b)));
    if fitting.is_empty() {
        let s = three_digits(raw / TYPICAL_MEDIAN_M)
            .parse()
            .unwrap_or(raw / TYPICAL_MEDIAN_M);
        fitting.push(s);
    }
    fitting.into_iter().map(|s| (s, raw / s)).collect()
}

/// `x` with at least three significant digits and no exponent: 1500, 1.50, 0.00150.
fn three_digits(x: f64) -> String {
    if !(x.is_finite() && x > 0.0) {
        return format!("{x}");
    }
    let decimals = (2 - x.log10().floor() as i32).max(0) as usize;
    format!("{x:.decimals$}")
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    fn flat(width: u32, height: u32, metres: f32) -> DepthImage {
        DepthImage::new(width, height, vec![metres; (width * height) as usize]).unwrap()
    }

    #[test]
    fn plausible_depth_passes_and_sparse_depth_is_not_judged() {
        let path = Path::new("d.png");
        assert!(check_depth_scale(&flat(4, 3, 1.5), 1000.0, path).is_ok());
        assert!(check_depth_scale(&flat(4, 3, 0.0), 1000.0, path).is_ok());
        // One valid pixel in 200: not judged.
        let mut data = vec![0.0f32; 200];
        data[7] = 1500.0;
        let sparse = DepthImage::new(20, 10, data).unwrap();
        assert!(check_depth_scale(&sparse, 1.0, path).is_ok());
    }

    #[test]
    fn millimetres_read_as_metres_or_a_thousand_times_too_small_are_refused() {
        let path = Path::new("d.png");
        // Raw 1500 (1.5 m in millimetres) read with depth_scale = 1: 1500 m.
        let err = check_depth_scale(&flat(4, 3, 1500.0), 1.0, path)
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "d.png: [dataset] depth_scale is 1 raw units per metre, which puts the median depth \
             of this image at 1500 m, outside the plausible 0.05–50 m (raw median 1500): set \
             depth_scale to the scale the depth images were written with, e.g. 1000 (median \
             1.50 m), 5000 (median 0.300 m) or 6553.5 (median 0.229 m)"
        );
        // The same raw values read with 1e6: 1.5 mm.
        let err = check_depth_scale(&flat(4, 3, 0.0015), 1.0e6, path)
            .unwrap_err()
            .to_string();
        assert!(err.contains("at 0.00150 m"), "{err}");
        assert!(err.contains("e.g. 1000 (median 1.50 m)"), "{err}");
    }

    #[test]
    fn suggestions_are_common_scales_nearest_two_metres_first() {
        let scales = |raw| {
            suggest_scales(raw)
                .into_iter()
                .map(|(s, _)| s)
                .collect::<Vec<_>>()
        };
        assert_eq!(scales(1500.0), [1000.0, 5000.0, 6553.5]);
        // TUM raw values (3 m at 5000 per metre).
        assert_eq!(scales(15000.0), [6553.5, 5000.0, 1000.0]);
        // Nothing common fits: aim at 2 m.
        assert_eq!(scales(3.0), [1.5]);
        assert_eq!(three_digits(123_456.0), "123456");
        assert_eq!(three_digits(0.2289), "0.229");
    }
}
