//! `use_all_cpus_once`, as the `vlem` binary calls it first thing in `main`: afterwards candle
//! takes its CPU thread count from `RAYON_NUM_THREADS` (read from the environment, not counted
//! from /proc/cpuinfo), and the count is what the process may use, or the user's where set.
//!
//! No libtest harness (`harness = false` in Cargo.toml): the function writes the environment only
//! while its thread is the process's only one, and the harness runs each test on a thread of its
//! own. A failed check panics, which fails the test.
#![allow(clippy::panic, reason = "tests")]

use vlem_backends::{CPU_THREADS_ENV, use_all_cpus_once};

fn main() {
    let user = std::env::var(CPU_THREADS_ENV).ok();
    let count = use_all_cpus_once();
    if !cfg!(target_os = "linux") {
        // Nothing tells it there that it runs alone: it leaves an unset variable unset.
        assert_eq!(count.is_some(), user.is_some());
        println!("cpu_threads: not Linux, {count:?}");
        return;
    }
    let Some(count) = count else {
        panic!("use_all_cpus_once left {CPU_THREADS_ENV} unset in a single-threaded process");
    };
    let available = std::thread::available_parallelism().map_or(1, usize::from);
    match user
        .as_deref()
        .and_then(|value| value.parse::<usize>().ok())
    {
        Some(set) if set > 0 => assert_eq!(count, set, "the user's count is kept"),
        _ => assert_eq!(
            count, available,
            "unset, it is the CPUs this process may use"
        ),
    }
    assert_eq!(
        std::env::var(CPU_THREADS_ENV).ok(),
        Some(count.to_string()).or(user)
    );
    assert_eq!(
        candle_core::utils::get_num_threads(),
        count,
        "candle's CPU thread count"
    );
    // A second call finds the count set and keeps it.
    assert_eq!(use_all_cpus_once(), Some(count));
    println!("cpu_threads: ok, {CPU_THREADS_ENV}={count} ({available} CPUs available)");
}
