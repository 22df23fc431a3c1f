//! Makes the C allocator keep freed memory for reuse, which the candle models need to run at the
//! speed of their arithmetic.
//!
//! Why it exists: candle allocates a fresh buffer for every op's output, many of them larger than
//! glibc's `mmap` threshold (an attention score matrix of a 640×480 NARADIO frame is 69 MB), and
//! glibc maps such buffers from the kernel and unmaps them when freed, also trimming the top of the
//! heap; each new buffer then costs a page fault and a zeroed page per 4 KiB. On this project's
//! 2-core machine that was a quarter of a NARADIO frame at 2 threads, and keeping the memory (both
//! thresholds raised) made the frame 2× faster (BENCHMARKS.md). The cost: the process keeps its
//! peak heap instead of returning it to the system between frames, which a long-running mapping
//! process does anyway.
//!
//! It is a process-wide setting, so the front-ends (the `vlem` binary, the benches) call
//! [`keep_freed_memory`] once at start; `VLEM_KEEP_FREED_MEMORY=0` turns it off. Only glibc has
//! these knobs; elsewhere it does nothing. `unsafe` here is the two `mallopt` calls, which only
//! set allocator parameters and are safe to make at any time.

/// Environment variable that turns [`keep_freed_memory`] off when set to `0`.
pub const KEEP_FREED_MEMORY_ENV: &str = "VLEM_KEEP_FREED_MEMORY";

/// Raises glibc's `mmap` threshold to 1 GiB and its trim threshold to 2 GiB, so that freed
/// model buffers are reused instead of being returned to the kernel and faulted in again (why:
/// `vlem-backends/src/allocator.rs`). Returns whether the allocator took both settings (`false`
/// with another C library, or when `VLEM_KEEP_FREED_MEMORY=0`). The process keeps its peak heap.
pub fn keep_freed_memory() -> bool {
    if std::env::var_os(KEEP_FREED_MEMORY_ENV).is_some_and(|v| v == "0") {
        return false;
    }
    set_thresholds()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(
    unsafe_code,
    reason = "mallopt is a foreign function; it only sets allocator parameters"
)]
fn set_thresholds() -> bool {
    const MMAP_THRESHOLD: libc::c_int = 1 << 30;
    const TRIM_THRESHOLD: libc::c_int = libc::c_int::MAX;
    // SAFETY: `mallopt` takes two integers, touches no memory of ours and is thread-safe (it takes
    // the arena lock); it returns 0 when it refuses a value.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
            && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn set_thresholds() -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_takes_the_thresholds() {
        // The test binary is one process: setting them here changes nothing but speed.
        let took = keep_freed_memory();
        if cfg!(all(target_os = "linux", target_env = "gnu")) {
            assert!(took, "glibc refused the thresholds");
        } else {
            assert!(!took);
        }
        // A large allocation freed and made again still works.
        let a = vec![1.0f32; 1 << 24];
        let sum: f32 = a.iter().take(10).sum();
        drop(a);
        let b = vec![2.0f32; 1 << 24];
        assert_eq!(sum, 10.0);
        assert_eq!(b[(1 << 24) - 1], 2.0);
    }
}
