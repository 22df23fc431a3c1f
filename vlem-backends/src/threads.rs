//! Gives candle its CPU thread count once, at start, instead of letting it work the count out
//! again for every operation.
//!
//! Why it exists: candle 0.11.1 looks up its CPU thread count for each op it runs on the CPU (each
//! matrix product, convolution, reduction). It takes `RAYON_NUM_THREADS` when that is set;
//! otherwise it counts the physical cores, and on Linux that count (`num_cpus::get_physical`, not
//! cached) opens and parses /proc/cpuinfo anew each time. MobileSAM's image encoder, many small
//! ops, opened it 87,000 times in 20 s (under strace) on this project's 2-core machine and ran
//! 1.5–1.9× slower than with the variable set (BENCHMARKS.md, "candle's thread count"); models of
//! a few large products (NARADIO) lose a few percent. Set once, the variable is what candle reads
//! instead.
//!
//! It writes the process environment, which is only sound while no other thread reads or writes
//! it, so [`use_all_cpus_once`] writes it only when it finds the calling thread alone in the
//! process (Linux: /proc/self/task); the front-ends call it as the first statement of `main` (the
//! `vlem` binary, the benches), and the Python package sets the variable in its `__init__.py`
//! before the native module loads. A value the user set is kept. The count chosen is what rayon's
//! pool takes when the variable is unset (the CPUs this process may use), so vlem's own parallel
//! loops keep their threads, and candle uses as many as every `--threads N` figure in
//! BENCHMARKS.md was measured with (the variable then set for both).

/// The variable candle (and rayon) read their CPU thread count from.
pub const CPU_THREADS_ENV: &str = "RAYON_NUM_THREADS";

/// Sets [`CPU_THREADS_ENV`] to the number of CPUs this process may use, unless it holds a count
/// already (why: `vlem-backends/src/threads.rs`). Returns the count the variable holds, or `None`
/// where it was left unset: another thread already runs (the environment may only be written
/// while no other thread can read it), or the platform has no way to tell (not Linux). Call it
/// first thing in `main`.
pub fn use_all_cpus_once() -> Option<usize> {
    let set = std::env::var(CPU_THREADS_ENV).ok();
    let available = std::thread::available_parallelism().map_or(1, usize::from);
    let (count, write) = cpu_threads(set.as_deref(), available);
    if !write {
        return Some(count);
    }
    if !alone_in_process() {
        return None;
    }
    set_env(count);
    Some(count)
}

#[allow(
    unsafe_code,
    reason = "std::env::set_var is unsafe; called only when this thread is the process's only one"
)]
fn set_env(count: usize) {
    // SAFETY: `alone_in_process` found no other thread, and only this one could start one: nothing
    // can read or write the environment while it is written.
    unsafe { std::env::set_var(CPU_THREADS_ENV, count.to_string()) };
}

/// Whether the calling thread is the only thread of the process.
#[cfg(target_os = "linux")]
fn alone_in_process() -> bool {
    std::fs::read_dir("/proc/self/task").is_ok_and(|tasks| tasks.count() == 1)
}

#[cfg(not(target_os = "linux"))]
fn alone_in_process() -> bool {
    false
}

/// The thread count and whether the variable must be written: a positive count the user set is
/// kept; unset, empty, zero or unparsable (which candle and rayon treat as unset) becomes
/// `available`.
fn cpu_threads(set: Option<&str>, available: usize) -> (usize, bool) {
    // Parsed as candle and rayon parse it: a count with spaces around it is theirs to ignore too.
    match set.and_then(|value| value.parse::<usize>().ok()) {
        Some(count) if count > 0 => (count, false),
        _ => (available.max(1), true),
    }
}

#[cfg(test)]
mod tests {
    use super::cpu_threads;

    #[test]
    fn a_count_the_user_set_is_kept() {
        assert_eq!(cpu_threads(Some("3"), 16), (3, false));
    }

    #[test]
    fn unset_or_unusable_becomes_the_available_cpus() {
        assert_eq!(cpu_threads(None, 16), (16, true));
        for unusable in ["", "0", "all", "-2", "2.5", " 1 "] {
            assert_eq!(cpu_threads(Some(unusable), 4), (4, true), "{unusable:?}");
        }
        assert_eq!(cpu_threads(None, 0), (1, true));
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn another_thread_is_seen() {
        let (stop, wait) = std::sync::mpsc::channel::<()>();
        let other = std::thread::spawn(move || wait.recv());
        assert!(!super::alone_in_process());
        drop(stop);
        let _ = other.join();
    }
}
