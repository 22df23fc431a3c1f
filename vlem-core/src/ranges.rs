//! Range checks for numeric settings, worded one way everywhere.
//!
//! Why this file exists: every numeric key of a config has a documented range
//! (`docs/config-ranges.md`), and a value outside it must be refused at start-up with the key, the
//! range and the value, before it becomes a huge allocation, an endless loop or a panic deep in a
//! stage. Each crate checks its own settings (they live with the crate that owns them) and wraps
//! the message in its own error with the key's name; these functions only decide and word it:
//! `must lie in 1–1024 frames, got 0`.

use std::fmt::{Display, LowerExp};

/// `value` if it lies in `min..=max`, else the message `must lie in MIN–MAX UNIT, got VALUE`
/// (`unit` may be empty).
///
/// # Errors
/// The message, for a value outside the range.
pub fn count<T: PartialOrd + Display + Copy>(
    value: T,
    min: T,
    max: T,
    unit: &str,
) -> Result<T, String> {
    if (min..=max).contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "must lie in {min}–{max}{}, got {value}",
            spaced(unit)
        ))
    }
}

/// `value` if it is a number in `min..=max` (NaN and infinities never are), else the message
/// `must lie in MIN–MAX UNIT, got VALUE`. For `f32` and `f64` settings alike, each printed as
/// written (`1e30`, not the `f64` widening of an `f32`).
///
/// # Errors
/// The message, for a value outside the range.
pub fn number<T: Copy + PartialOrd + Display + LowerExp + Into<f64>>(
    value: T,
    min: T,
    max: T,
    unit: &str,
) -> Result<T, String> {
    if (min..=max).contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "must lie in {}–{}{}, got {}",
            decimal(min),
            decimal(max),
            spaced(unit),
            decimal(value)
        ))
    }
}

fn spaced(unit: &str) -> String {
    if unit.is_empty() {
        String::new()
    } else {
        format!(" {unit}")
    }
}

/// A number as a person writes it: `0.02`, `1000`, `1e-30`, `NaN`.
fn decimal<T: Copy + Display + LowerExp + Into<f64>>(value: T) -> String {
    let wide: f64 = value.into();
    if wide == 0.0 || !wide.is_finite() || (1e-4..1e7).contains(&wide.abs()) {
        format!("{value}")
    } else {
        format!("{value:e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_range_pass_and_others_are_worded_with_the_range_and_value() {
        assert_eq!(count(4usize, 1, 1024, "frames"), Ok(4));
        assert_eq!(
            count(0usize, 1, 1024, "frames").unwrap_err(),
            "must lie in 1–1024 frames, got 0"
        );
        assert_eq!(
            count(300u32, 1, 256, "").unwrap_err(),
            "must lie in 1–256, got 300"
        );
        assert_eq!(number(0.5, 0.0, 1.0, ""), Ok(0.5));
        assert_eq!(
            number(1e-30, 0.001, 1000.0, "m").unwrap_err(),
            "must lie in 0.001–1000 m, got 1e-30"
        );
        assert_eq!(
            number(f64::NAN, 0.0, 1.0, "").unwrap_err(),
            "must lie in 0–1, got NaN"
        );
        assert!(number(f64::INFINITY, 0.0, f64::MAX, "").is_err());
        assert_eq!(
            number(1e30f32, 0.0, 1.0, "m").unwrap_err(),
            "must lie in 0–1 m, got 1e30"
        );
        assert_eq!(
            number(1e-30f32, 1e-4, 10.0, "m").unwrap_err(),
            "must lie in 1e-4–10 m, got 1e-30"
        );
        assert_eq!(
            number(5e9, 0.1, 1e8, "Hz").unwrap_err(),
            "must lie in 0.1–1e8 Hz, got 5e9"
        );
    }
}
