//! Finding a model's files: which of a folder's required files are missing, and where a pip
//! package that ships model files (or a runtime library) is installed.
//!
//! Why it exists: every backend that loads files answers the same two questions before it reads a
//! byte, and its missing-file error must name exactly what is absent. Each backend keeps its own
//! list of files and its own install hint; this module owns only the lookups.

use std::path::{Path, PathBuf};

use crate::BackendError;

/// The entries of `required` that are not files in `dir` (all of them when `dir` does not exist).
pub fn missing_files(dir: &Path, required: &[&'static str]) -> Vec<&'static str> {
    required
        .iter()
        .copied()
        .filter(|f| !dir.join(f).is_file())
        .collect()
}

/// `dir` when it holds every file of `required`, else [`BackendError::MissingModelFiles`] naming
/// the missing ones, the `model`, where the folder came from (`origin`) and how to get them (`hint`).
///
/// # Errors
/// As above.
pub fn require_files(
    dir: &Path,
    required: &[&'static str],
    model: &'static str,
    origin: String,
    hint: &'static str,
) -> Result<PathBuf, BackendError> {
    let missing = missing_files(dir, required);
    if missing.is_empty() {
        Ok(dir.to_path_buf())
    } else {
        Err(BackendError::MissingModelFiles {
            model,
            dir: dir.to_path_buf(),
            origin,
            missing,
            hint,
        })
    }
}

/// The text of the model file `path`.
///
/// # Errors
/// [`BackendError::InvalidModelFile`] saying why it cannot be read.
pub fn read_text(path: &Path) -> Result<String, BackendError> {
    std::fs::read_to_string(path).map_err(|e| BackendError::InvalidModelFile {
        path: path.to_path_buf(),
        reason: format!("cannot read it: {e}"),
    })
}

/// The folder of the installed Python package `package`, asked of `python3` with
/// `importlib.util.find_spec` (which locates a top-level package without importing it).
///
/// # Errors
/// Why there is none, in words for an error message: python3 cannot run, or the package is not
/// installed for it.
pub fn python_package_dir(package: &str) -> Result<PathBuf, String> {
    let script = format!(
        "import importlib.util as u\n\
         s = u.find_spec({package:?})\n\
         print(list(s.submodule_search_locations)[0] if s and s.submodule_search_locations else '')"
    );
    let output = std::process::Command::new("python3")
        .args(["-c", &script])
        .stdin(std::process::Stdio::null())
        .output()
        .map_err(|e| format!("cannot run python3 ({e})"))?;
    if !output.status.success() {
        return Err(format!("python3 failed ({})", output.status));
    }
    let dir = String::from_utf8_lossy(&output.stdout).trim().to_owned();
    if dir.is_empty() {
        Err("not installed for python3".to_owned())
    } else {
        Ok(PathBuf::from(dir))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_files_lists_what_is_absent_in_order() {
        let dir = std::env::temp_dir().join(format!("vlem-model-files-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        std::fs::write(dir.join("config.json"), "{}").ok();
        let missing = missing_files(
            &dir,
            &["config.json", "model.safetensors", "tokenizer.json"],
        );
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(missing, vec!["model.safetensors", "tokenizer.json"]);
        assert_eq!(
            missing_files(&dir.join("absent"), &["a", "b"]),
            vec!["a", "b"]
        );
    }

    #[test]
    fn an_absent_package_is_reported_not_found() {
        let reason = python_package_dir("vlem_no_such_package_4711").unwrap_err();
        assert!(
            reason.contains("not installed") || reason.contains("python3"),
            "{reason}"
        );
    }
}
