//! Files every front-end writes, written the same crash-safe way, and the process's memory as
//! reports record it.
//!
//! Why it exists: the `vlem` command, the Python package and the study runner all write small
//! result files (statistics, evaluation reports, study tables) that a reader may open while a run
//! is still going, or after it was killed. Each goes through a temporary file in the same folder,
//! a sync and a rename, as the map file does, so a reader sees the old file or the new one.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::{CoreError, Result};

/// Writes `bytes` to `path` atomically (a temporary file in the same folder, synced, renamed over
/// `path`).
///
/// # Errors
/// [`CoreError::Io`] naming the file that could not be created, written or renamed.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let (tmp, mut file) = crate::mapfile::create_temp_file(&dir, &file_name)?;
    let result = file
        .write_all(bytes)
        .and_then(|()| file.sync_all())
        .map_err(|e| CoreError::io(&tmp, e))
        .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| CoreError::io(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Peak resident memory of this process in bytes (Linux `VmHWM`), `None` where unavailable.
pub fn peak_resident_bytes() -> Option<u64> {
    proc_status_bytes("VmHWM:")
}

/// Current resident memory of this process in bytes (Linux `VmRSS`), `None` where unavailable.
pub fn resident_bytes() -> Option<u64> {
    proc_status_bytes("VmRSS:")
}

/// A `kB` field of `/proc/self/status`, in bytes.
fn proc_status_bytes(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn an_atomic_write_replaces_the_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("stats.json");
        write_atomically(&path, b"old").unwrap();
        write_atomically(&path, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "only the file itself is left");
    }

    #[test]
    fn an_unwritable_folder_names_the_file() {
        let err = write_atomically(Path::new("/nonexistent-vlem-dir/x.json"), b"x").unwrap_err();
        assert!(err.to_string().contains("nonexistent-vlem-dir"), "{err}");
    }

    #[test]
    fn memory_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            let peak = peak_resident_bytes().unwrap();
            assert!(peak >= resident_bytes().unwrap() && peak > 0);
        }
    }
}
