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
//! With `--http` the clients ask through the query server instead (`POST /query` on a
//! `QueryServer` on 127.0.0.1, as `vlem run --serve` runs it), and one more client asks
//! `GET /status` every 50 ms in both runs: its latencies show whether status answers wait behind
//! the queries.
//!
//! ```sh
//! cargo bench --bench live_query_load [-- DATASET [HZ [CLIENTS [TEXTS]]]] [--http]
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
    let http = std::env::args().any(|a| a == "--http");
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
    let load = Load {
        hz,
        clients,
        texts,
        http,
    };
    if !dataset.is_dir() {
        eprintln!("live_query_load: no dataset at {}", dataset.display());
        std::process::exit(2);
    }
    // Warm the page cache and the allocator once, then measure both runs.
    let idle = Load { clients: 0, ..load };
    run(&repo, &dataset, idle);
    for load in [idle, load] {
        run(&repo, &dataset, load);
    }
}

/// The query load: `clients` threads, each asking `texts` texts at up to `hz`, in the library or
/// over HTTP.
#[derive(Clone, Copy)]
struct Load {
    hz: f64,
    clients: usize,
    texts: usize,
    http: bool,
}

/// An HTTP agent that reads error statuses as answers.
fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .build()
        .new_agent()
}

fn run(repo: &std::path::Path, dataset: &std::path::Path, load: Load) {
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
    let texts: Vec<String> = (0..if load.clients > 0 { load.texts } else { 0 })
        .map(|i| WORDS[i % WORDS.len()].to_owned())
        .collect();
    let out = tempfile::tempdir().unwrap();
    let server = load.http.then(|| {
        vlem_server::QueryServer::start(
            "127.0.0.1:0",
            live.clone(),
            vlem_server::ServeOptions::new(out.path().to_path_buf(), ctx.clone()),
        )
        .unwrap()
    });
    let address = server.as_ref().map(|s| s.address().to_string());
    let body = serde_json::json!({ "texts": texts }).to_string();
    let mapping = AtomicBool::new(true);
    let start = Instant::now();
    let (report, latencies, status_latencies) = std::thread::scope(|scope| {
        let status = address.as_deref().map(|address| {
            let mapping = &mapping;
            scope.spawn(move || {
                let (agent, mut latencies) = (agent(), Vec::new());
                while mapping.load(Ordering::Acquire) {
                    let t = Instant::now();
                    let answer = agent.get(format!("http://{address}/status")).call();
                    assert_eq!(answer.unwrap().status().as_u16(), 200);
                    latencies.push(t.elapsed().as_secs_f64() * 1e3);
                    std::thread::sleep(Duration::from_millis(50));
                }
                latencies
            })
        });
        let clients: Vec<_> = (0..load.clients)
            .map(|_| {
                let (live, segmenter, texts, mapping) = (&live, &segmenter, &texts, &mapping);
                let (address, body) = (address.as_deref(), &body);
                let period = Duration::from_secs_f64(1.0 / load.hz);
                scope.spawn(move || {
                    let agent = agent();
                    let mut latencies = Vec::new();
                    while mapping.load(Ordering::Acquire) {
                        let t = Instant::now();
                        match address {
                            Some(address) => {
                                let _ = agent
                                    .post(format!("http://{address}/query"))
                                    .header("Content-Type", "application/json")
                                    .send(body.as_str())
                                    .and_then(|mut r| r.body_mut().read_to_string());
                            }
                            None => {
                                let _ = answer_live(
                                    live,
                                    segmenter.as_ref(),
                                    texts,
                                    &AnswerOptions::default(),
                                );
                            }
                        }
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
        let status_latencies = status.map(|s| s.join().unwrap()).unwrap_or_default();
        (report, latencies, status_latencies)
    });
    drop(server);
    let wall = start.elapsed().as_secs_f64();
    let (sorted, status_sorted) = (sorted(&latencies), sorted(&status_latencies));
    println!(
        "{}",
        serde_json::json!({
            "query_hz": (load.clients > 0).then_some(load.hz),
            "clients": load.clients,
            "over_http": load.http,
            "texts_per_query": texts.len(),
            "frames": report.frames_processed,
            "frames_per_second": report.frames_processed as f64 / wall,
            "integrate_mean_ms": report.stage_ms.get("integrate").map(|t| t.mean_ms),
            "encode_mean_ms": report.stage_ms.get("encode").map(|t| t.mean_ms),
            "map_points": live.status().map_len,
            "queries": latencies.len(),
            "query_median_ms": percentile(&sorted, 0.5),
            "query_p95_ms": percentile(&sorted, 0.95),
            "query_max_ms": sorted.last(),
            "status_requests": status_sorted.len(),
            "status_median_ms": percentile(&status_sorted, 0.5),
            "status_p95_ms": percentile(&status_sorted, 0.95),
            "status_max_ms": status_sorted.last(),
        })
    );
}

fn sorted(values: &[f64]) -> Vec<f64> {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted
}

fn percentile(sorted: &[f64], p: f64) -> Option<f64> {
    sorted
        .get(((sorted.len() as f64 - 1.0) * p).round() as usize)
        .copied()
}
