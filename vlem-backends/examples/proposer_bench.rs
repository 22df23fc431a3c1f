//! Times the `graph` region proposer on real frames: milliseconds per frame and regions per frame.
//!
//! ```text
//! cargo run --release -p vlem-backends --features graph --example proposer_bench -- \
//!     [--downscale F] [--k K] [--sigma S] [--min-size N] [--max-regions N] [--repeat R] \
//!     [--save REGIONS.png] IMAGE_OR_FOLDER...
//! ```
//!
//! Folders contribute their `.jpg` and `.png` files in name order. Each image is proposed on once
//! to warm up, then `R` times (default 3); the report gives the mean and median time per frame
//! and the mean number of regions. `--save` draws the regions of the first image (one colour each,
//! black where no region is) for a look at what the parameters do. The proposer is single-threaded, so the thread count of the
//! machine does not change its time (pin it with `taskset -c 0` to be sure).

#[cfg(not(feature = "graph"))]
fn main() {
    eprintln!("proposer_bench needs the `graph` feature: add `--features graph`");
    std::process::exit(2);
}

#[cfg(feature = "graph")]
fn main() -> anyhow::Result<()> {
    use std::time::Instant;

    use anyhow::{Context, bail};
    use vlem_backends::graph::{GraphConfig, GraphProposer};
    use vlem_core::{RegionProposer, RgbImage};

    let mut config = GraphConfig::default();
    let mut repeat = 3usize;
    let mut save: Option<std::path::PathBuf> = None;
    let mut paths = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = || args.next().with_context(|| format!("{arg} needs a value"));
        match arg.as_str() {
            "--downscale" => config.downscale = value()?.parse()?,
            "--k" => config.k = value()?.parse()?,
            "--sigma" => config.sigma = value()?.parse()?,
            "--min-size" => config.min_size = value()?.parse()?,
            "--max-regions" => config.max_regions = value()?.parse()?,
            "--repeat" => repeat = value()?.parse()?,
            "--save" => save = Some(value()?.into()),
            flag if flag.starts_with("--") => bail!("unknown option {flag}"),
            path => paths.push(std::path::PathBuf::from(path)),
        }
    }
    let mut files = Vec::new();
    for path in paths {
        if path.is_dir() {
            let mut entries: Vec<_> = std::fs::read_dir(&path)?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension().is_some_and(|x| {
                        x.eq_ignore_ascii_case("jpg") || x.eq_ignore_ascii_case("png")
                    })
                })
                .collect();
            entries.sort();
            files.extend(entries);
        } else {
            files.push(path);
        }
    }
    if files.is_empty() {
        bail!("no images given (pass image files or folders of .jpg/.png)");
    }
    let proposer = GraphProposer::new(config.clone())?;
    // On-CPU time of this thread (Linux), which a busy machine inflates much less than the
    // wall clock; `None` elsewhere.
    let cpu_ns = || -> Option<u64> {
        std::fs::read_to_string("/proc/thread-self/schedstat")
            .ok()?
            .split_whitespace()
            .next()?
            .parse()
            .ok()
    };
    let mut cpu_total_ns = Some(0u64);
    let mut times_ms = Vec::new();
    let mut regions = 0usize;
    let mut size = (0, 0);
    for file in &files {
        let decoded = image::open(file)
            .with_context(|| format!("reading {}", file.display()))?
            .to_rgb8();
        size = decoded.dimensions();
        let image = RgbImage::new(decoded.width(), decoded.height(), decoded.into_raw())?;
        let proposed = proposer.propose(&image)?;
        regions += proposed.len();
        if let Some(out) = save.take() {
            let mut canvas = image::RgbImage::new(image.width(), image.height());
            for (k, region) in proposed.iter().enumerate() {
                // Well-spread colours: the golden-ratio hue walk, as bytes.
                let hue = (k as f64 * 0.618_034).fract();
                let colour = [0.0, 1.0 / 3.0, 2.0 / 3.0].map(|shift: f64| {
                    let x = ((hue + shift) * std::f64::consts::TAU).cos();
                    (127.5 + 127.5 * x) as u8
                });
                let b = region.bbox;
                for v in b.y..b.y + b.height {
                    for u in b.x..b.x + b.width {
                        if region.contains(u, v) {
                            canvas.put_pixel(u, v, image::Rgb(colour));
                        }
                    }
                }
            }
            canvas
                .save(&out)
                .with_context(|| format!("writing {}", out.display()))?;
        }
        for _ in 0..repeat {
            let (start, cpu_start) = (Instant::now(), cpu_ns());
            let proposed = proposer.propose(&image)?;
            times_ms.push(start.elapsed().as_secs_f64() * 1e3);
            cpu_total_ns = match (cpu_total_ns, cpu_start, cpu_ns()) {
                (Some(total), Some(a), Some(b)) => Some(total + b.saturating_sub(a)),
                _ => None,
            };
            std::hint::black_box(proposed);
        }
    }
    times_ms.sort_by(f64::total_cmp);
    let mean = times_ms.iter().sum::<f64>() / times_ms.len().max(1) as f64;
    let median = times_ms.get(times_ms.len() / 2).copied().unwrap_or(0.0);
    let cpu = cpu_total_ns.map_or("unknown".to_owned(), |ns| {
        format!("{:.1} ms", ns as f64 / 1e6 / times_ms.len().max(1) as f64)
    });
    println!(
        "graph {config:?}: {} frames of {}x{}, {repeat} runs each: wall mean {mean:.1} ms, \
         median {median:.1} ms, CPU {cpu} per frame; {:.1} regions per frame",
        files.len(),
        size.0,
        size.1,
        regions as f64 / files.len() as f64
    );
    Ok(())
}
