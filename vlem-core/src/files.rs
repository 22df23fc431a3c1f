//! Files every front-end writes, written the same crash-safe way, and the process's memory as
//! reports record it.
//!
//! Why it exists: the `vlem` command, the Python package and the study runner all write small
//! result files (statistics, evaluation reports, study tables) that a reader may open while a run
//! is still going, or after it was killed. Each goes through a temporary file in the same folder,
//! a sync and a rename (the map file too), so a reader sees the old file or the new one.
//!
//! Two rules keep that safe when a run is interrupted or a path is wrong: a save replaces only a
//! regular file (never a device, a pipe or a folder, whatever the path names; through a symlink it
//! replaces the file the link points to), and each save first removes the temporary files that
//! killed saves of the same file left behind.

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
/// folder (created first when missing): the temporary file is renamed over `path` and the folder
/// synced, or removed when anything fails, so readers see the old file or the new one. `fallback_name` names the
/// temporary file when `path` has no file name. The one way every file of vlem is written whole,
/// the map file included.
pub(crate) fn replace_file<T>(
    path: &Path,
    fallback_name: &str,
    write: impl FnOnce(&Path, File) -> Result<T>,
) -> Result<T> {
    let target = replaceable_target(path)?;
    let path = target.as_path();
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path.file_name().map_or_else(
        || fallback_name.to_owned(),
        |n| n.to_string_lossy().into_owned(),
    );
    // A save into a folder that does not exist yet creates it, as `vlem run --out` does (the
    // error used to name the temporary file instead of the missing folder).
    std::fs::create_dir_all(&dir).map_err(|e| CoreError::io(&dir, e))?;
    remove_stale_temp_files(&dir, &file_name);
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

/// The file a save to `path` replaces: `path` itself, or for a symlink the file it points to; an
/// error naming `path` when that is anything but a regular file or nothing yet (a folder, a device
/// such as `/dev/full`, a pipe, a socket, a symlink to nowhere).
fn replaceable_target(path: &Path) -> Result<PathBuf> {
    let refuse = |what: &str| {
        CoreError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("{what}: vlem writes only regular files and would not replace it"),
            ),
        )
    };
    let target = match std::fs::symlink_metadata(path) {
        Err(_) => return Ok(path.to_path_buf()),
        Ok(meta) if meta.file_type().is_symlink() => {
            std::fs::canonicalize(path).map_err(|_| refuse("a symbolic link to nothing"))?
        }
        Ok(_) => path.to_path_buf(),
    };
    match std::fs::metadata(&target) {
        Err(_) => Ok(target),
        Ok(meta) if meta.is_file() => Ok(target),
        Ok(meta) if meta.is_dir() => Err(refuse("a folder")),
        Ok(_) => Err(refuse("not a regular file (a device, pipe or socket)")),
    }
}

/// How old a dead process's temporary file must be before a save removes it: a live save writes
/// into its file all the time, so only a temporary nobody touched for this long is left over.
const STALE_AFTER: std::time::Duration = std::time::Duration::from_secs(60);

/// Removes `.<file_name>.tmp-<pid>-…` files in `dir` left by saves that were killed: those of
/// a process that no longer runs (Linux: no `/proc/<pid>`) and untouched for [`STALE_AFTER`].
/// This process's own temporaries are in-flight saves of other threads and are kept. Best effort:
/// a file that cannot be removed stays.
fn remove_stale_temp_files(dir: &Path, file_name: &str) {
    if !Path::new("/proc/self").exists() {
        return; // Without /proc a dead process cannot be told from a live one.
    }
    let prefix = format!(".{file_name}.tmp-");
    let own = std::process::id();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(&prefix))
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if pid == own || Path::new(&format!("/proc/{pid}")).exists() {
            continue;
        }
        let untouched = entry
            .metadata()
            .ok()
            .filter(std::fs::Metadata::is_file)
            .and_then(|m| m.modified().ok())
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age >= STALE_AFTER);
        if untouched {
            let _ = std::fs::remove_file(entry.path());
        }
    }
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
    fn only_regular_files_are_replaced_and_symlinks_write_through() {
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("folder");
        std::fs::create_dir(&folder).unwrap();
        let err = write_atomically(&folder, b"x").unwrap_err().to_string();
        assert!(
            err.contains("folder") && err.contains("regular files"),
            "{err}"
        );
        assert!(folder.is_dir());
        if Path::new("/dev/null").exists() {
            let err = write_atomically(Path::new("/dev/null"), b"x")
                .unwrap_err()
                .to_string();
            assert!(err.starts_with("/dev/null: not a regular file"), "{err}");
        }
        #[cfg(unix)]
        {
            let target = dir.path().join("target.json");
            std::fs::write(&target, b"old").unwrap();
            let link = dir.path().join("link.json");
            std::os::unix::fs::symlink(&target, &link).unwrap();
            write_atomically(&link, b"new").unwrap();
            assert!(link.symlink_metadata().unwrap().file_type().is_symlink());
            assert_eq!(std::fs::read(&target).unwrap(), b"new");
            let dangling = dir.path().join("dangling.json");
            std::os::unix::fs::symlink(dir.path().join("nowhere"), &dangling).unwrap();
            let err = write_atomically(&dangling, b"x").unwrap_err().to_string();
            assert!(err.contains("symbolic link to nothing"), "{err}");
        }
    }

    #[test]
    fn a_save_removes_the_old_temporaries_of_killed_saves_only() {
        let dir = tempfile::tempdir().unwrap();
        let old = std::time::SystemTime::now() - 2 * STALE_AFTER;
        let temp = |name: &str, modified: Option<std::time::SystemTime>| {
            let path = dir.path().join(name);
            let file = File::create(&path).unwrap();
            if let Some(t) = modified {
                file.set_modified(t).unwrap();
            }
            path
        };
        // pid 0 is never a user process: a killed save's leftover.
        let dead_old = temp(".map.vlem.tmp-0-3-abc", Some(old));
        let dead_fresh = temp(".map.vlem.tmp-0-4-abd", None);
        let ours = temp(
            &format!(".map.vlem.tmp-{}-9-abe", std::process::id()),
            Some(old),
        );
        let other_file = temp(".stats.json.tmp-0-1-abf", Some(old));
        write_atomically(&dir.path().join("map.vlem"), b"map").unwrap();
        if Path::new("/proc/self").exists() {
            assert!(
                !dead_old.exists(),
                "a dead process's old temporary is removed"
            );
        }
        assert!(
            dead_fresh.exists(),
            "one touched just now may be a save in flight"
        );
        assert!(ours.exists(), "this process's own saves are in flight");
        assert!(
            other_file.exists(),
            "another file's temporaries are its saves' business"
        );
    }

    #[test]
    fn a_missing_folder_is_created_and_one_that_cannot_be_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let nested = dir.path().join("out/run 1/map.json");
        write_atomically(&nested, b"{}").unwrap();
        assert_eq!(std::fs::read(&nested).unwrap(), b"{}");
        // A file where a folder would have to be: the error names that folder.
        let blocker = dir.path().join("file");
        std::fs::write(&blocker, b"x").unwrap();
        let err = write_atomically(&blocker.join("sub/x.json"), b"x").unwrap_err();
        assert!(
            err.to_string()
                .starts_with(&blocker.join("sub").display().to_string()),
            "{err}"
        );
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
