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

/// One data line of an `rgbd.match` file (ICL-NUIM / Redwood): a depth image and the colour image
/// paired with it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MatchPair<'a> {
    /// 1-based line number in the file.
    pub line: usize,
    /// The depth image, relative to the dataset folder, as written.
    pub depth: &'a str,
    /// The colour image, relative to the dataset folder, as written.
    pub colour: &'a str,
}

/// Parses the text of an `rgbd.match` file: one `depth-file colour-file` pair per line (blank
/// lines and `#` comments skipped), in file order; `path` is the file it came from, as errors name
/// it. The listed files are not looked at. These are the rules of the ICL-NUIM/Redwood reader
/// ([`crate::IclReader`]).
///
/// # Errors
/// [`DatasetError::Parse`] for a line that does not hold exactly two fields.
pub fn match_pairs_from_str<'a>(text: &'a str, path: &Path) -> Result<Vec<MatchPair<'a>>> {
    let mut pairs = Vec::new();
    for (line, content) in data_lines(text) {
        let fields: Vec<&str> = content.split_whitespace().collect();
        let &[depth, colour] = fields.as_slice() else {
            return Err(DatasetError::parse(
                path,
                line,
                format!(
                    "expected `depth-file colour-file`, found {} fields",
                    fields.len()
                ),
            ));
        };
        pairs.push(MatchPair {
            line,
            depth,
            colour,
        });
    }
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn match_pairs_keep_line_numbers_and_refuse_other_field_counts() {
        let text = "# pairs\ndepth/0.png color/0.jpg\n\n  depth/1.png\tcolor/1.jpg  \n";
        let pairs = match_pairs_from_str(text, Path::new("rgbd.match")).unwrap();
        assert_eq!(
            pairs,
            [
                MatchPair {
                    line: 2,
                    depth: "depth/0.png",
                    colour: "color/0.jpg"
                },
                MatchPair {
                    line: 4,
                    depth: "depth/1.png",
                    colour: "color/1.jpg"
                }
            ]
        );
        let err = match_pairs_from_str("a b\na b c\n", Path::new("/d/rgbd.match")).unwrap_err();
        assert_eq!(
            err.to_string(),
            "/d/rgbd.match:2: expected `depth-file colour-file`, found 3 fields"
        );
    }
}
