//! Images per second of the CLIP image tower (`ClipModel::image_features`) on candle, on the CPU
//! or, with `VLEM_BENCH_DEVICE=cuda` in a build with feature `cuda`, a GPU; in half precision
//! with `VLEM_BENCH_DTYPE=f16` or `bf16`.
//! `VLEM_PROFILE=1` adds a per-op profile (`vlem_backends::profile`) at the end.
//!
//! ```text
//! python3 bench/clip/make_random_b16.py /tmp/clip-vit-b16-random   # random ViT-B/16, HF layout
//! RAYON_NUM_THREADS=2 cargo run --release -p vlem-backends --features clip --example clip_bench -- \
//!     /tmp/clip-vit-b16-random [--batch 1 16] [--text 1 80] [--repeat 5]
//! ```
//!
//! Each batch size gets one warm-up call, then `--repeat` timed calls on the same random pixels;
//! the report gives the best and the mean time per call and the images per second of the best,
//! in the same form as `bench/clip/torch_bench.py`, the PyTorch reference. candle reads
//! `RAYON_NUM_THREADS` once, at the first call.

#[cfg(not(feature = "clip"))]
fn main() {
    eprintln!("clip_bench needs the `clip` feature: add `--features clip`");
    std::process::exit(2);
}

#[cfg(feature = "clip")]
fn main() -> anyhow::Result<()> {
    use std::time::Instant;

    use anyhow::{Context, bail};
    use vlem_backends::clip::ClipModel;

    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    vlem_backends::keep_freed_memory();

    let mut dir = None;
    let mut batches = Vec::new();
    let mut texts = Vec::new();
    let mut repeat = 5usize;
    let mut args = std::env::args().skip(1);
    let mut in_batches = false;
    let mut in_texts = false;
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--batch" => (in_batches, in_texts) = (true, false),
            "--text" => (in_batches, in_texts) = (false, true),
            "--repeat" => {
                in_batches = false;
                repeat = args.next().context("--repeat needs a value")?.parse()?;
            }
            _ if in_batches => batches.push(arg.parse::<usize>().context("--batch takes sizes")?),
            _ if in_texts => texts.push(arg.parse::<usize>().context("--text takes sizes")?),
            _ if dir.is_none() => dir = Some(std::path::PathBuf::from(arg)),
            _ => bail!("unexpected argument {arg:?}"),
        }
    }
    let Some(dir) = dir else {
        bail!("usage: clip_bench MODEL_DIR [--batch N...] [--text N...] [--repeat R]");
    };
    if batches.is_empty() && texts.is_empty() {
        batches = vec![1, 16];
    }
    if repeat == 0 {
        bail!("--repeat must be at least 1");
    }
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "(all)".to_owned());
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    let dtype = vlem_backends::ModelDtype::from_env("VLEM_BENCH_DTYPE")?;
    let model = ClipModel::load(&dir, &device, dtype)?;
    let size = model.image_size();
    for batch in batches {
        // A fixed pseudo-random pattern in the range of normalised pixels.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let pixels: Vec<f32> = (0..batch * 3 * size * size)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                ((state >> 40) as f32 / (1u64 << 24) as f32) * 4.0 - 2.0
            })
            .collect();
        model.image_features(&pixels, batch)?;
        let mut times = Vec::with_capacity(repeat);
        for _ in 0..repeat {
            let t = Instant::now();
            let out = model.image_features(&pixels, batch)?;
            times.push(t.elapsed().as_secs_f64());
            std::hint::black_box(out);
        }
        let best = times.iter().copied().fold(f64::INFINITY, f64::min);
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        println!(
            "candle threads={threads} batch={batch}: best {:.1} ms/call, mean {:.1} ms/call, \
             {:.2} images/s",
            best * 1e3,
            mean * 1e3,
            batch as f64 / best
        );
    }
    // The text tower: `n` texts of TEXT_TOKENS tokens each (a query through n prompt templates),
    // the same ids as bench/clip/torch_bench.py's `--text`.
    const TEXT_TOKENS: u32 = 16;
    for n in texts {
        let ids: Vec<Vec<u32>> = (0..n as u32)
            .map(|t| (0..TEXT_TOKENS).map(|i| 1000 + 37 * t + i).collect())
            .collect();
        model.text_features_of_ids(&ids)?;
        let mut best = f64::INFINITY;
        for _ in 0..repeat {
            let t = Instant::now();
            std::hint::black_box(model.text_features_of_ids(&ids)?);
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "candle threads={threads} text={n}x{TEXT_TOKENS}: best {:.1} ms/call",
            best * 1e3
        );
    }
    if vlem_backends::profile::enabled() {
        // The steps' times over every call above, the warm-up included.
        println!("per-op profile (the device synchronised around each step):");
        print!("{}", vlem_backends::profile::table());
    }
    Ok(())
}
