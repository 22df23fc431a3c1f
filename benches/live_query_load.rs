//! Integration rate with and without a query load on the live map.
//!
//! Maps the shared 150-frame ICL living-room sequence (`../shared/data/icl-livingroom1`, or the
//! folder given as the first argument) offline with the demo's stages (ground-truth poses,
//! colour-names, point-cloud map), once with no queries and once with CLIENTS threads (default 1)
//! each querying the live map at a given rate (default 10 Hz) for TEXTS texts (default 2; colour
//! words, which the demo's encoder embeds) with the `threshold` segmenter. Prints one JSON line per
//! run: frames per second, the mean integration time (which includes waiting for the map's write
//! lock), and the query latencies.
//!
//! ```sh
//! cargo bench --bench live_query_load [-- DATASET [HZ [CLIENTS [TEXTS]]]]
//! ```
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "a benchmark")]

use vlem_maps as _;
use vlem_plugin_colour_names as _;
use vlem_trackers as _;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use vlem_core::pipeline::{Pipeline, Progress};
use vlem_query::answer::{AnswerOptions, Selection, answer_live};

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let dataset = args.first().map_or_else(
        || repo.join("../shared/data/icl-livingroom1"),
        PathBuf::from,
    );
    let hz: f64 = args
        .get(1)
        .map_or(10.0, |a| a.parse().expect("a rate in Hz"));
    let clients: usize = args
        .get(2)
        .map_or(1, |a| a.parse().expect("a number of clients"));
    let texts: usize = args
        .get(3)
        .map_or(2, |a| a.parse().expect("a number of texts per query"));
    let load = Load { hz, clients, texts };
    if !dataset.is_dir() {
        eprintln!("live_query_load: no dataset at {}", dataset.display());
        std::process::exit(2);
    }
    // Warm the page cache and the allocator once, then measure both runs.
    run(&repo, &dataset, None);
    for load in [None, Some(load)] {
        run(&repo, &dataset, load);
    }
}

/// The query load: `clients` threads, each asking `texts` texts at up to `hz`.
#[derive(Clone, Copy)]
struct Load {
    hz: f64,
    clients: usize,
    texts: usize,
}

fn run(repo: &std::path::Path, dataset: &std::path::Path, load: Option<Load>) {
    let (config, ctx) = vlem_core::load_config(&repo.join("configs/demo.toml")).unwrap();
    let mut source = vlem_datasets::open(&config.dataset, dataset).unwrap();
    let mut pipeline = Pipeline::from_config(&config, &ctx).unwrap();
    let live = pipeline.live();
    let segmenter = Selection::threshold().build(&ctx).unwrap();
    const WORDS: [&str; 8] = [
        "white wall",
        "brown",
        "red",
        "green",
        "blue",
        "yellow",
        "grey",
        "black",
    ];
    let texts: Vec<String> = (0..load.map_or(0, |l| l.texts))
        .map(|i| WORDS[i % WORDS.len()].to_owned())
        .collect();
    let mapping = AtomicBool::new(true);
    let start = Instant::now();
    let (report, latencies) = std::thread::scope(|scope| {
        let clients: Vec<_> = (0..load.map_or(0, |l| l.clients))
            .map(|_| {
                let (live, segmenter, texts, mapping) = (&live, &segmenter, &texts, &mapping);
                let period = Duration::from_secs_f64(1.0 / load.map_or(1.0, |l| l.hz));
                scope.spawn(move || {
                    let mut latencies = Vec::new();
                    while mapping.load(Ordering::Acquire) {
                        let t = Instant::now();
                        let _ =
                            answer_live(live, segmenter.as_ref(), texts, &AnswerOptions::default());
                        let took = t.elapsed();
                        latencies.push(took.as_secs_f64() * 1e3);
                        std::thread::sleep(period.saturating_sub(took));
                    }
                    latencies
                })
            })
            .collect();
        let report = pipeline
            .run(source.as_mut(), None, &|_: Progress| {})
            .unwrap();
        mapping.store(false, Ordering::Release);
        let latencies: Vec<f64> = clients
            .into_iter()
            .flat_map(|c| c.join().unwrap())
            .collect();
        (report, latencies)
    });
    let wall = start.elapsed().as_secs_f64();
    let mut sorted = latencies.clone();
    sorted.sort_by(f64::total_cmp);
    let percentile = |p: f64| {
        sorted
            .get(((sorted.len() as f64 - 1.0) * p).round() as usize)
            .copied()
    };
    println!(
        "{}",
        serde_json::json!({
            "query_hz": load.map(|l| l.hz),
            "clients": load.map_or(0, |l| l.clients),
            "texts_per_query": texts.len(),
            "frames": report.frames_processed,
            "frames_per_second": report.frames_processed as f64 / wall,
            "integrate_mean_ms": report.stage_ms.get("integrate").map(|t| t.mean_ms),
            "encode_mean_ms": report.stage_ms.get("encode").map(|t| t.mean_ms),
            "map_points": live.status().map_len,
            "queries": latencies.len(),
            "query_median_ms": percentile(0.5),
            "query_p95_ms": percentile(0.95),
            "query_max_ms": sorted.last(),
        })
    );
}
