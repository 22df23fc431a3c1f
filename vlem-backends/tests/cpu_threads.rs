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
    // A count the user set, parsed as candle and rayon parse it; anything else counts as unset.
    let kept = user
        .as_deref()
        .and_then(|value| value.parse::<usize>().ok())
        .filter(|&count| count > 0);
    let count = use_all_cpus_once();
    if !cfg!(target_os = "linux") {
        // Nothing tells it there that it runs alone: it writes nothing, and reports a kept count.
        assert_eq!(count, kept);
        println!("cpu_threads: not Linux, {count:?}");
        return;
    }
    let Some(count) = count else {
        panic!("use_all_cpus_once left {CPU_THREADS_ENV} unset in a single-threaded process");
    };
    let available = std::thread::available_parallelism().map_or(1, usize::from);
    match kept {
        Some(set) => assert_eq!(count, set, "the user's count is kept"),
        None => assert_eq!(
            count, available,
            "unset, it is the CPUs this process may use"
        ),
    }
    let expected = if kept.is_some() {
        user
    } else {
        Some(count.to_string())
    };
    assert_eq!(std::env::var(CPU_THREADS_ENV).ok(), expected);
    assert_eq!(
        candle_core::utils::get_num_threads(),
        count,
        "candle's CPU thread count"
    );
    // A second call finds the count set and keeps it.
    assert_eq!(use_all_cpus_once(), Some(count));
    println!("cpu_threads: ok, {CPU_THREADS_ENV}={count} ({available} CPUs available)");
}
