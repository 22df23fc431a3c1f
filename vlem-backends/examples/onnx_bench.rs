//! Images per second of an ONNX image tower through the `onnx` encoder (ONNX Runtime from Rust),
//! for 1 and 2 intra-op threads (set on the session builder through the `threads` parameter) and
//! batches of 1 and 16 crops. The python counterpart is `bench/onnx/ort_python_bench.py`.
//!
//! ```sh
//! python3 bench/onnx/export_clip_b16.py      # CLIP ViT-B/16, random weights, /tmp/vlem-onnx-bench/
//! cargo run --release -p vlem-backends --features onnx --example onnx_bench -- \
//!     [/tmp/vlem-onnx-bench/onnx.toml] [runs] [threads, e.g. 1,2]
//! ```
//!
//! Every measurement is taken twice and both are printed with the better one: the machine is
//! shared, so the better one is the less disturbed. "model" times the image model alone on a
//! ready batch (what the python script times); "encode" times `Encoder::encode_image` on a
//! 640 × 480 frame with 16 regions, crops and region layout included.

use std::path::PathBuf;
use std::time::Instant;

use vlem_backends::onnx::{OnnxConfig, OnnxEncoder};
use vlem_core::{BuildContext, Encoder, PixelRect, Region};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let config_path = PathBuf::from(
        args.next()
            .unwrap_or_else(|| "/tmp/vlem-onnx-bench/onnx.toml".to_owned()),
    );
    let runs: usize = args.next().map_or(Ok(3), |r| r.parse())?;
    let thread_counts: Vec<usize> = args
        .next()
        .unwrap_or_else(|| "1,2".to_owned())
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let text = std::fs::read_to_string(&config_path).map_err(|e| {
        format!(
            "{}: {e} (run bench/onnx/export_clip_b16.py)",
            config_path.display()
        )
    })?;
    let ctx = BuildContext {
        config_dir: config_path.parent().map(PathBuf::from).unwrap_or_default(),
        ..BuildContext::default()
    };

    println!("{}", config_path.display());
    println!("what    threads  batch  img/s (1st)  img/s (2nd)  best  ms/img (best)");
    for threads in thread_counts {
        let mut config: OnnxConfig = toml::from_str(&text)?;
        config.threads = Some(threads);
        let encoder = OnnxEncoder::from_config(config, &ctx)?;
        let (w, h) = encoder.input_size();
        for batch in [1usize, 16] {
            let input = noise(batch * 3 * w as usize * h as usize);
            let calls = if batch == 1 { 4 * runs } else { runs };
            let measure = || -> Result<f64, Box<dyn std::error::Error>> {
                encoder.run_image_model(&input, batch)?; // warm-up
                let start = Instant::now();
                for _ in 0..calls {
                    encoder.run_image_model(&input, batch)?;
                }
                Ok((batch * calls) as f64 / start.elapsed().as_secs_f64())
            };
            let (first, second) = (measure()?, measure()?);
            report("model", threads, batch, first, second);
        }
        if encoder.needs_regions() {
            let frame = vlem_testkit::images::gradient(640, 480);
            let regions = grid_regions(640, 480, 4);
            let measure = || -> Result<f64, Box<dyn std::error::Error>> {
                encoder.encode_image(&frame, &regions)?; // warm-up
                let start = Instant::now();
                for _ in 0..runs {
                    encoder.encode_image(&frame, &regions)?;
                }
                Ok((regions.len() * runs) as f64 / start.elapsed().as_secs_f64())
            };
            let (first, second) = (measure()?, measure()?);
            report("encode", threads, regions.len(), first, second);
        }
    }
    Ok(())
}

fn report(what: &str, threads: usize, batch: usize, first: f64, second: f64) {
    let best = first.max(second);
    println!(
        "{what:6}  {threads:7}  {batch:5}  {first:11.2}  {second:11.2}  {best:5.2}  {:8.0}",
        1000.0 / best
    );
}

/// Deterministic values in about [-2, 2] (xorshift), standing in for a normalised image batch.
fn noise(n: usize) -> Vec<f32> {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    (0..n)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 4.0 - 2.0
        })
        .collect()
}

/// `cells × cells` rectangles tiling a `width × height` frame.
fn grid_regions(width: u32, height: u32, cells: u32) -> Vec<Region> {
    let (cw, ch) = (width / cells, height / cells);
    (0..cells * cells)
        .map(|k| Region {
            bbox: PixelRect {
                x: (k % cells) * cw,
                y: (k / cells) * ch,
                width: cw,
                height: ch,
            },
            mask: vec![true; (cw * ch) as usize],
        })
        .collect()
}
