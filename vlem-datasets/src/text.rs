//! Small helpers for the whitespace-separated text files that RGB-D datasets use.

use std::path::Path;

use crate::error::{DatasetError, Result};

/// Reads a whole text file.
pub(crate) fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))
}

/// The lines that carry data, with their 1-based line numbers: blank lines and `#` comments
/// (TUM's header) are skipped.
pub(crate) fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
}

/// Parses every whitespace-separated field of `line` as a number.
pub(crate) fn parse_numbers(path: &Path, line_no: usize, line: &str) -> Result<Vec<f64>> {
    line.split_whitespace()
        .map(|field| parse_number(path, line_no, field))
        .collect()
}

/// Parses one number; `inf`, `-inf` and `nan` are accepted so that invalid poses can be reported
/// as such rather than as a syntax error.
pub(crate) fn parse_number(path: &Path, line_no: usize, field: &str) -> Result<f64> {
    field
        .parse::<f64>()
        .map_err(|_| DatasetError::parse(path, line_no, format!("`{field}` is not a number")))
}

/// Parses exactly `n` numbers from `line`.
pub(crate) fn parse_exact(path: &Path, line_no: usize, line: &str, n: usize) -> Result<Vec<f64>> {
    let values = parse_numbers(path, line_no, line)?;
    if values.len() != n {
        return Err(DatasetError::parse(
            path,
            line_no,
            format!("expected {n} numbers, found {}", values.len()),
        ));
    }
    Ok(values)
}
