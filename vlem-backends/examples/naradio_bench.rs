//! NARADIO speed: milliseconds per 640 x 480 frame through the RADIOv2.5 trunk with the NACLIP
//! last block and the SigLIP adaptor, at full ViT-B/16 and ViT-L/16 size with random weights
//! (speed does not depend on the values). The frame is fed as RayFronts feeds it: 640 x 480, a
//! 40 x 30 patch grid. Threads: set `RAYON_NUM_THREADS`; `VLEM_BENCH_DEVICE=cuda` runs it on a
//! GPU (build with feature `cuda`); `VLEM_BENCH_DTYPE=f16` or `bf16` in half precision.
//! `VLEM_PROFILE=1` adds a per-op profile (`vlem_backends::profile`) at the end.
//!
//! ```text
//! RAYON_NUM_THREADS=1 cargo run --release -p vlem-backends --features naradio --example naradio_bench -- [b|l|both] [iterations] [TEXT_DIR]
//! ```
//! With `TEXT_DIR` (the `text/` folder of `bench/naradio/make_random.py`'s output) it also times
//! one new query through the full-size SigLIP text tower, with 80 templates and with one.

use std::time::Instant;

use candle_core::Tensor;
use vlem_backends::naradio::{
    GaussianGrid, IMAGENET_TEMPLATES, LastBlock, RadioConfig, RadioModel, SiglipText,
};

fn config(embed_dim: usize, depth: usize, num_heads: usize) -> RadioConfig {
    RadioConfig {
        format: "vlem-naradio-1".into(),
        patch_size: 16,
        embed_dim,
        depth,
        num_heads,
        mlp_hidden: 4 * embed_dim,
        qkv_bias: true,
        layer_scale: false,
        layer_norm_eps: 1e-6,
        final_norm: false,
        pos_grid: [128, 128],
        num_cls_tokens: 4,
        num_registers: 4,
        summary_idxs: vec![0, 1, 2],
        adaptor: "siglip".into(),
        adaptor_token_slot: 1,
        adaptor_mlp: "v2".into(),
        adaptor_layer_norm_eps: 1e-5,
        feature_normalizer: false,
        input_mean: [0.481_454_66, 0.457_827_5, 0.408_210_73],
        input_std: [0.268_629_54, 0.261_302_6, 0.275_777_1],
    }
}

fn main() -> anyhow::Result<()> {
    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    vlem_backends::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let which = args.get(1).map_or("both", String::as_str);
    let iterations: usize = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let text_dir = args.get(3).map(std::path::PathBuf::from);
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".into());
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    let dtype = vlem_backends::ModelDtype::from_env("VLEM_BENCH_DTYPE")?;
    let sizes: Vec<(&str, RadioConfig)> = [
        ("B/16", config(768, 12, 12)),
        ("L/16", config(1024, 24, 16)),
    ]
    .into_iter()
    .filter(|(name, _)| match which {
        "b" => *name == "B/16",
        "l" => *name == "L/16",
        _ => true,
    })
    .collect();
    for (name, cfg) in sizes {
        // The SigLIP adaptor of RADIOv2.5: into SO400M's 1152-d space.
        let model = RadioModel::random(cfg, 1536, 1152, &device, dtype)?;
        let x = Tensor::rand(0f32, 1f32, (1, 3, 480, 640), &device)?;
        let last = LastBlock::Naclip {
            std: 7.0,
            grid: GaussianGrid::Rayfronts,
            reduced: false,
        };
        let run = || -> anyhow::Result<()> {
            let x = model.condition(&x)?;
            let out = model.forward(&x, last)?;
            let lang = model.adapt(&out.features)?;
            anyhow::ensure!(lang.dims() == [1, 1200, 1152], "shape {:?}", lang.dims());
            // A GPU runs asynchronously: the time is that of the finished work.
            device.synchronize()?;
            Ok(())
        };
        run()?; // warm-up: caches the position embeddings and the prior
        // Each run timed alone: the best is what bench/models/side_by_side.py compares, as it
        // takes PyTorch's best.
        let mut times = Vec::with_capacity(iterations);
        for _ in 0..iterations {
            let start = Instant::now();
            run()?;
            times.push(start.elapsed().as_secs_f64() * 1000.0);
        }
        let best = times.iter().copied().fold(f64::NAN, f64::min);
        let mean = times.iter().sum::<f64>() / iterations as f64;
        println!(
            "NARADIO {name} 640x480 (40x30 patches), threads {threads}: best {best:.1} ms/frame, \
             mean {mean:.1} ms/frame ({iterations} runs)"
        );
    }
    if let Some(dir) = text_dir {
        time_query(&dir, &device, dtype)?;
    }
    if vlem_backends::profile::enabled() {
        // The steps' times over every call above, the warm-up included.
        println!("per-op profile (the device synchronised around each step):");
        print!("{}", vlem_backends::profile::table());
    }
    Ok(())
}

/// The cost of one new query through the SigLIP SO400M text tower of the folder `dir` (made by
/// `bench/naradio/make_random.py`): RayFronts' 80 templates, then a single template.
fn time_query(
    dir: &std::path::Path,
    device: &candle_core::Device,
    dtype: vlem_backends::ModelDtype,
) -> anyhow::Result<()> {
    let text = SiglipText::load(dir, device, dtype)?;
    let query = "coffee machine";
    for templates in [IMAGENET_TEMPLATES.to_vec(), vec!["a photo of a {}."]] {
        let prompts: Vec<String> = templates.iter().map(|t| t.replace("{}", query)).collect();
        let prompts: Vec<&str> = prompts.iter().map(String::as_str).collect();
        text.embed(&prompts[..1])?; // warm-up
        let start = Instant::now();
        text.embed(&prompts)?;
        println!(
            "NARADIO new query, {} template(s) through the SigLIP SO400M text tower: {:.0} ms",
            prompts.len(),
            start.elapsed().as_secs_f64() * 1000.0
        );
    }
    Ok(())
}
