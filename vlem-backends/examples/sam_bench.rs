//! Times the `sam` region proposer per 640 x 480 frame: image encoder, mask decoder, the whole
//! automatic mask generator with and without the fill-in refinement.
//!
//! Without `--weights` the network is the full-size architecture filled with the deterministic
//! synthetic weights of `vlem_backends::sam::synthetic` (same cost as real weights for the
//! networks; random weights predict low IoUs, so few masks pass the filters and the
//! postprocessing of real masks is not part of the numbers).
//!
//! ```text
//! RAYON_NUM_THREADS=2 cargo run --release -p vlem-backends --features sam --example sam_bench -- \
//!     --variant mobile-sam --points-per-side 32,16 --refine on,off --points-per-batch 32,256
//! ```
//! `--repeat N` times each row's generator N times and reports the best (default 1: on a CPU one
//! call is seconds; on a GPU the first call of a batch shape pays for its kernels' first launch).
//! `VLEM_BENCH_DEVICE=cuda` runs the network on a GPU (build with feature `cuda`),
//! `VLEM_BENCH_DTYPE=f16` or `bf16` in half precision.
//! `VLEM_PROFILE=1` adds a per-op profile (`vlem_backends::profile`) at the end.
//!
//! `--write-weights PATH` writes the variant's synthetic weights to a safetensors file with the
//! official checkpoint's tensor names, as `[proposer] weights` reads them, and stops: a SAM for
//! end-to-end runs where no checkpoint can be had (`bench/gpu/check.sh` part 4).

use std::time::Instant;

use anyhow::{Context, Result, bail};
use vlem_backends::sam::model::SamModel;
use vlem_backends::sam::synthetic::{SyntheticWeights, synthetic_values};
use vlem_backends::sam::{GeneratorParams, SamProposer, SamVariant};
use vlem_core::RgbImage;

fn parse_list<T: std::str::FromStr>(s: &str) -> Result<Vec<T>> {
    s.split(',')
        .map(|v| {
            v.trim()
                .parse::<T>()
                .ok()
                .context(format!("bad value {v:?}"))
        })
        .collect()
}

/// A 640 x 480 image with smooth gradients and a few flat shapes.
fn frame() -> Result<RgbImage> {
    let (w, h) = (640u32, 480u32);
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            let rect = (120..320).contains(&x) && (100..380).contains(&y);
            let dx = f64::from(x) - 480.0;
            let dy = f64::from(y) - 240.0;
            let disc = dx * dx + dy * dy < 90.0 * 90.0;
            let rgb = if rect {
                [200, 40, 40]
            } else if disc {
                [30, 60, 210]
            } else {
                [(x / 3) as u8, (y / 2) as u8, ((x + y) / 5) as u8]
            };
            data.extend(rgb);
        }
    }
    Ok(RgbImage::new(w, h, data)?)
}

/// Builds `variant` on synthetic weights, then writes every tensor it asked for (f32, the names
/// it asked by) to `path`.
fn write_synthetic_weights(variant: SamVariant, path: &str) -> Result<()> {
    let cpu = candle_core::Device::Cpu;
    let synthetic = SyntheticWeights::new();
    SamModel::new(synthetic.var_builder(&cpu), &variant.encoder())?;
    let tensors = synthetic
        .requested()
        .into_iter()
        .map(|(name, dims)| {
            let t = candle_core::Tensor::from_vec(synthetic_values(&name, &dims), dims, &cpu)?;
            Ok((name, t))
        })
        .collect::<Result<std::collections::HashMap<_, _>>>()?;
    candle_core::safetensors::save(&tensors, path)?;
    println!(
        "{variant:?}: {} synthetic tensors written to {path}",
        tensors.len()
    );
    Ok(())
}

fn main() -> Result<()> {
    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    vlem_backends::keep_freed_memory();
    let mut variant = SamVariant::MobileSam;
    let mut sides = vec![32usize, 16];
    let mut refines = vec![true, false];
    let mut batches = vec![GeneratorParams::default().points_per_batch];
    let mut weights: Option<String> = None;
    let mut write_weights: Option<String> = None;
    let mut repeat = 1usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().context(format!("{a} needs a value"));
        match a.as_str() {
            "--variant" => {
                variant = match value()?.as_str() {
                    "mobile-sam" => SamVariant::MobileSam,
                    "vit-b" => SamVariant::VitB,
                    v => bail!("unknown variant {v}"),
                }
            }
            "--points-per-side" => sides = parse_list(&value()?)?,
            "--refine" => {
                refines = value()?.split(',').map(|v| v.trim() == "on").collect();
            }
            "--points-per-batch" => batches = parse_list(&value()?)?,
            "--weights" => weights = Some(value()?),
            "--write-weights" => write_weights = Some(value()?),
            "--repeat" => {
                repeat = value()?.parse().context("--repeat takes a whole number")?;
                anyhow::ensure!(repeat > 0, "--repeat must be at least 1");
            }
            _ => bail!("unknown argument {a}"),
        }
    }

    if let Some(path) = write_weights {
        return write_synthetic_weights(variant, &path);
    }
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".to_owned());
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    let dtype = vlem_backends::ModelDtype::from_env("VLEM_BENCH_DTYPE")?.candle();
    let start = Instant::now();
    let model = match &weights {
        Some(path) => {
            let tensors = candle_core::safetensors::load(path, &device)?;
            let vb = candle_nn::VarBuilder::from_tensors(tensors, dtype, &device);
            SamModel::new(vb, &variant.encoder())?
        }
        None => SamModel::new(
            SyntheticWeights::new().var_builder_in(&device, dtype),
            &variant.encoder(),
        )?,
    };
    println!(
        "{variant:?}, {} weights, threads {threads}: model built in {:.1} s",
        if weights.is_some() {
            "file"
        } else {
            "synthetic"
        },
        start.elapsed().as_secs_f64()
    );

    let image = frame()?;
    let t = Instant::now();
    let pre = model.preprocess(image.as_raw(), 640, 480)?;
    let pre_ms = t.elapsed().as_secs_f64() * 1e3;
    let t = Instant::now();
    let emb = model.embed(&pre.tensor)?;
    // A GPU runs asynchronously: the times are those of the finished work.
    device.synchronize()?;
    let enc_ms = t.elapsed().as_secs_f64() * 1e3;
    let points: Vec<[f32; 2]> = (0..32).map(|i| [16.0 + 30.0 * i as f32, 300.0]).collect();
    let t = Instant::now();
    let _ = model.decode_points(&emb, &points)?;
    device.synchronize()?;
    let dec_ms = t.elapsed().as_secs_f64() * 1e3 / 32.0;
    println!(
        "preprocess {pre_ms:.0} ms, image encoder {enc_ms:.1} ms, mask decoder {dec_ms:.1} ms per \
         prompt (batch of 32)"
    );

    let mut proposer = Some(SamProposer::new(model, GeneratorParams::default()));
    // The last column is last so that bench/sam/side_by_side.sh reads the rows either way.
    println!(
        "| variant | points_per_side | refine | ms / frame (best of {repeat}) | masks | points_per_batch |"
    );
    println!("|---|---|---|---|---|---|");
    for &side in &sides {
        for (&refine, &batch) in refines
            .iter()
            .flat_map(|r| batches.iter().map(move |b| (r, b)))
        {
            let Some(p) = proposer.take() else {
                bail!("proposer lost")
            };
            let (model, _) = p.into_parts();
            let params = GeneratorParams {
                points_per_side: side,
                points_per_batch: batch,
                refine,
                ..GeneratorParams::default()
            };
            let p = SamProposer::new(model, params);
            let mut ms = f64::INFINITY;
            let mut masks = Vec::new();
            for _ in 0..repeat {
                let t = Instant::now();
                masks = p.generate(&image)?;
                ms = ms.min(t.elapsed().as_secs_f64() * 1e3);
            }
            println!(
                "| {variant:?} | {side} | {} | {ms:.1} | {} | {batch} |",
                if refine { "on" } else { "off" },
                masks.len()
            );
            proposer = Some(p);
        }
    }
    if vlem_backends::profile::enabled() {
        // The steps' times over every call above, the warm-up included.
        println!("per-op profile (the device synchronised around each step):");
        print!("{}", vlem_backends::profile::table());
    }
    Ok(())
}
