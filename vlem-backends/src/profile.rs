//! Per-op timers of the candle models: where a forward pass spends its time, by the steps the
//! models share (the attention's projections, its scores-softmax-mix, the MLPs, the norms) and
//! SAM's stages.
//!
//! Why it exists: choosing how to speed a model up on a GPU (a fused attention kernel, half
//! precision, fewer launches) needs to know which step dominates, on the device it runs on, and
//! a lent GPU has no Rust toolchain to add timers to. Off unless the environment variable
//! [`PROFILE_ENV`] is `1` when the first timed step runs; then every timed step waits for the
//! device before and after (so a GPU's queued work is charged to the step that queued it), which
//! slows the run: a profile to read shares from, not a benchmark. The benchmarks print
//! [`table`] at their end.

use std::collections::HashMap;
use std::sync::{Mutex, OnceLock, PoisonError};
use std::time::{Duration, Instant};

/// The environment variable that turns the timers on (`1`).
pub const PROFILE_ENV: &str = "VLEM_PROFILE";

/// Time and calls per step.
type Totals = HashMap<&'static str, (u64, Duration)>;

fn totals() -> &'static Mutex<Totals> {
    static TOTALS: OnceLock<Mutex<Totals>> = OnceLock::new();
    TOTALS.get_or_init(Mutex::default)
}

/// Whether the timers are on ([`PROFILE_ENV`] = `1`, read once).
pub fn enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var(PROFILE_ENV).is_ok_and(|v| v.trim() == "1"))
}

/// Runs `step`, charging its time to `label` when the timers are on. A step nested in another
/// is charged to both; labels that contain others end in "(all)".
pub(crate) fn timed<T>(
    label: &'static str,
    device: &candle_core::Device,
    step: impl FnOnce() -> candle_core::Result<T>,
) -> candle_core::Result<T> {
    if !enabled() {
        return step();
    }
    device.synchronize()?;
    let start = Instant::now();
    let out = step()?;
    device.synchronize()?;
    let elapsed = start.elapsed();
    let mut totals = totals().lock().unwrap_or_else(PoisonError::into_inner);
    let entry = totals.entry(label).or_default();
    entry.0 += 1;
    entry.1 += elapsed;
    Ok(out)
}

/// Every step timed so far: label, calls and total time, the most expensive first.
pub fn report() -> Vec<(&'static str, u64, Duration)> {
    let totals = totals().lock().unwrap_or_else(PoisonError::into_inner);
    let mut rows: Vec<_> = totals.iter().map(|(l, (n, t))| (*l, *n, *t)).collect();
    rows.sort_by(|a, b| b.2.cmp(&a.2).then(a.0.cmp(b.0)));
    rows
}

/// Forgets every time so far (e.g. after a warm-up).
pub fn reset() {
    totals()
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .clear();
}

/// [`report`] as a Markdown table (step, calls, total ms, ms per call), empty when nothing was
/// timed.
pub fn table() -> String {
    let rows = report();
    if rows.is_empty() {
        return String::new();
    }
    let mut out = String::from("| step | calls | total ms | ms / call |\n|---|---|---|---|\n");
    for (label, calls, total) in rows {
        let ms = total.as_secs_f64() * 1e3;
        out.push_str(&format!(
            "| {label} | {calls} | {ms:.1} | {:.3} |\n",
            ms / calls.max(1) as f64
        ));
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used, reason = "tests")]
mod tests {
    use super::*;

    #[test]
    fn a_table_lists_the_steps_most_expensive_first() {
        // The switch is read from the environment once per process; the totals themselves are
        // what this checks, filled as `timed` fills them.
        reset();
        {
            let mut totals = totals().lock().unwrap();
            totals.insert("cheap", (3, Duration::from_millis(3)));
            totals.insert("dear", (1, Duration::from_millis(40)));
        }
        let rows = report();
        assert_eq!(rows[0].0, "dear");
        let text = table();
        assert!(text.starts_with("| step | calls |"), "{text}");
        assert!(text.contains("| dear | 1 | 40.0 | 40.000 |"), "{text}");
        assert!(text.contains("| cheap | 3 | 3.0 | 1.000 |"), "{text}");
        reset();
        assert!(table().is_empty());
    }

    #[test]
    fn off_it_runs_the_step_and_records_nothing() {
        if enabled() {
            return; // the whole test binary runs with the timers on
        }
        let out = timed("never", &candle_core::Device::Cpu, || Ok(7)).unwrap();
        assert_eq!(out, 7);
        assert!(!report().iter().any(|r| r.0 == "never"));
    }
}
