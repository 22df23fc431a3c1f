//! Prompt templates: a query put into sentences, and the one direction their embeddings share.
//!
//! Why it exists: every encoder with a text side (label-text, clip, onnx, dinov3, naradio) lets
//! the user wrap a query in templates such as `"a photo of a {}."` and averages the embeddings of
//! the filled-in prompts (CLIP's prompt ensembling); one implementation keeps the checks, the
//! messages and the arithmetic the same in all of them.

use crate::error::BackendError;

/// The placeholder in a template that the query replaces.
pub const PLACEHOLDER: &str = "{}";

/// The default: the query alone.
pub fn default_templates() -> Vec<String> {
    vec![PLACEHOLDER.to_owned()]
}

/// Checks that there is a template and that each has a placeholder; `section` names where they
/// were configured (e.g. `[encoder]`).
///
/// # Errors
/// [`BackendError::InvalidParams`] saying which.
pub fn check_templates(templates: &[String], section: &str) -> Result<(), BackendError> {
    if templates.is_empty() {
        return Err(BackendError::InvalidParams(format!(
            "{section} templates must hold at least one template, e.g. [\"a photo of a {{}}.\"]"
        )));
    }
    if let Some(bad) = templates.iter().find(|t| !t.contains(PLACEHOLDER)) {
        return Err(BackendError::InvalidParams(format!(
            "every template needs a {{}} where the query goes, e.g. \"a photo of a {{}}.\"; \
             {bad:?} has none"
        )));
    }
    Ok(())
}

/// The prompts of `texts`: for each text, each template filled in with it (text-major).
pub fn fill(templates: &[String], texts: &[&str]) -> Vec<String> {
    texts
        .iter()
        .flat_map(|text| templates.iter().map(|t| t.replace(PLACEHOLDER, text)))
        .collect()
}

/// The L2-normalised mean of the L2-normalised `rows`; `None` when a row or the mean is zero or
/// not finite.
pub fn mean_of_unit<R: AsRef<[f32]>>(rows: &[R], dim: usize) -> Option<Vec<f32>> {
    let mut mean = vec![0.0f32; dim];
    for row in rows {
        let mut row = row.as_ref().to_vec();
        if row.len() != dim || !vlem_core::embeddings::normalise(&mut row) {
            return None;
        }
        mean.iter_mut().zip(&row).for_each(|(m, x)| *m += x);
    }
    vlem_core::embeddings::normalise(&mut mean).then_some(mean)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn templates_are_checked_and_filled_text_major() {
        let t = vec!["a {}".to_owned(), "the {}!".to_owned()];
        assert!(check_templates(&t, "[encoder]").is_ok());
        assert_eq!(
            fill(&t, &["cat", "dog"]),
            ["a cat", "the cat!", "a dog", "the dog!"]
        );
        let err = check_templates(&[], "[encoder]").unwrap_err().to_string();
        assert!(
            err.contains("[encoder] templates must hold at least one"),
            "{err}"
        );
        let err = check_templates(&["a photo".to_owned()], "[encoder]")
            .unwrap_err()
            .to_string();
        assert!(err.contains("\"a photo\" has none"), "{err}");
    }

    #[test]
    fn mean_of_unit_weighs_every_row_alike() {
        // A long and a short row: their directions count equally.
        let mean = mean_of_unit(&[vec![10.0, 0.0], vec![0.0, 0.1]], 2).unwrap();
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert!(
            (mean[0] - h).abs() < 1e-6 && (mean[1] - h).abs() < 1e-6,
            "{mean:?}"
        );
        assert!(mean_of_unit(&[vec![0.0, 0.0]], 2).is_none());
        assert!(mean_of_unit(&[vec![1.0, 0.0], vec![-1.0, 0.0]], 2).is_none());
        assert!(mean_of_unit(&[vec![1.0]], 2).is_none());
    }
}
