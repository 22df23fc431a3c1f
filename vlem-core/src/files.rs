//! Files every front-end writes, written the same crash-safe way, and the process's memory as
//! reports record it.
//!
//! Why it exists: the `vlem` command, the Python package and the study runner all write small
//! result files (statistics, evaluation reports, study tables) that a reader may open while a run
//! is still going, or after it was killed. Each goes through a temporary file in the same folder,
//! a sync and a rename (the map file too), so a reader sees the old file or the new one.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use crate::error::{CoreError, Result};

/// Writes `bytes` to `path` atomically (a temporary file in the same folder, synced, renamed over
/// `path`).
///
/// # Errors
/// [`CoreError::Io`] naming the file that could not be created, written or renamed.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    replace_file(path, "file", |tmp, mut file| {
        file.write_all(bytes)
            .and_then(|()| file.sync_all())
            .map_err(|e| CoreError::io(tmp, e))
    })
}

/// Replaces `path` with what `write` writes (and syncs) into a fresh temporary file in the same
/// folder: the temporary file is renamed over `path` and the folder synced, or removed when
/// anything fails, so readers see the old file or the new one. `fallback_name` names the
/// temporary file when `path` has no file name. The one way every file of vlem is written whole,
/// the map file included.
pub(crate) fn replace_file<T>(
    path: &Path,
    fallback_name: &str,
    write: impl FnOnce(&Path, File) -> Result<T>,
) -> Result<T> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path.file_name().map_or_else(
        || fallback_name.to_owned(),
        |n| n.to_string_lossy().into_owned(),
    );
    let (tmp, file) = create_temp_file(&dir, &file_name)?;
    let result = write(&tmp, file).and_then(|out| {
        std::fs::rename(&tmp, path).map_err(|e| CoreError::io(path, e))?;
        // Make the rename itself durable; not every platform can open a directory.
        if let Ok(d) = File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(out)
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Saves started by this process (part of the temporary file names).
static SAVES: AtomicU64 = AtomicU64::new(0);

/// Creates a new, exclusively owned temporary file `.<file_name>.tmp-<pid>-<n>-<clock>` in `dir`.
/// The name differs between threads (counter) and processes (pid; the clock and `O_EXCL` cover
/// processes of other pid namespaces sharing the directory), and a name that exists already,
/// e.g. left by a killed save, is skipped rather than reused.
pub(crate) fn create_temp_file(dir: &Path, file_name: &str) -> Result<(PathBuf, File)> {
    let pid = std::process::id();
    let mut last = None;
    for _ in 0..64 {
        let n = SAVES.fetch_add(1, Ordering::Relaxed);
        let clock = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        let tmp = dir.join(format!(".{file_name}.tmp-{pid}-{n}-{clock:x}"));
        match OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Ok(file) => return Ok((tmp, file)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some((tmp, e)),
            Err(e) => return Err(CoreError::io(&tmp, e)),
        }
    }
    let (tmp, e) = last.unwrap_or_else(|| {
        (
            dir.join(file_name),
            std::io::Error::from(std::io::ErrorKind::AlreadyExists),
        )
    });
    Err(CoreError::io(&tmp, e))
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
            // Resident first: other test threads allocate meanwhile, and only a peak read after
            // the resident size is sure to be at least that.
            let resident = resident_bytes().unwrap();
            let peak = peak_resident_bytes().unwrap();
            assert!(
                peak >= resident && resident > 0,
                "peak {peak}, resident {resident}"
            );
        }
    }
}
