//! Times the `dinov3` encoder (DINOv3 ViT-L/16 + the dino.txt vision head) per 640 × 480 frame,
//! and one query through the dino.txt text tower.
//!
//! The networks have the released shapes (backbone 1024 wide, 24 layers, 16 heads, 4 registers;
//! vision head 2 SwiGLU blocks; text tower 1280 wide, 24 layers, 20 heads, 77 positions) filled
//! with random weights: the cost of a forward pass does not depend on the values.
//!
//! ```text
//! RAYON_NUM_THREADS=2 cargo run --release -p vlem-backends --features dinov3 \
//!     --example dinov3_bench -- 448,320 3
//! ```
//! Arguments: the input short sides to time (comma-separated, multiples of 16; default 448),
//! and the timed frames per size (default 3, after one warm-up frame). `VLEM_BENCH_DEVICE=cuda`
//! runs it on a GPU (build with feature `cuda`); `VLEM_BENCH_DTYPE=f16` or `bf16` in half
//! precision.
//! `VLEM_PROFILE=1` adds a per-op profile (`vlem_backends::profile`) at the end.

use std::collections::HashMap;
use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use vlem_backends::ModelDtype;
use vlem_backends::dinov3::{ClipBpe, DinoTxtHeads, Dinov3Backbone, Dinov3Config, Dinov3Encoder};
use vlem_core::{Encoder, RgbImage};

/// Adds a random `shape` tensor (normal, standard deviation `std`, mean `mean`) named `name`.
fn put(
    t: &mut HashMap<String, Tensor>,
    name: String,
    shape: &[usize],
    mean: f64,
    std: f64,
) -> Result<()> {
    let x = Tensor::randn(0f32, 1f32, shape, &Device::Cpu)?;
    t.insert(name, ((x * std)? + mean)?.to_dtype(DType::F32)?);
    Ok(())
}

fn put_linear(
    t: &mut HashMap<String, Tensor>,
    name: &str,
    inputs: usize,
    outputs: usize,
    bias: bool,
) -> Result<()> {
    put(t, format!("{name}.weight"), &[outputs, inputs], 0.0, 0.02)?;
    if bias {
        put(t, format!("{name}.bias"), &[outputs], 0.0, 0.02)?;
    }
    Ok(())
}

fn put_norm(t: &mut HashMap<String, Tensor>, name: &str, width: usize) -> Result<()> {
    put(t, format!("{name}.weight"), &[width], 1.0, 0.02)?;
    put(t, format!("{name}.bias"), &[width], 0.0, 0.02)
}

/// ViT-L/16 in the hub layout (`facebook/dinov3-vitl16-pretrain-lvd1689m`).
fn backbone(device: &Device, dtype: ModelDtype) -> Result<Dinov3Backbone> {
    let c = Dinov3Config {
        hidden_size: 1024,
        intermediate_size: 4096,
        num_hidden_layers: 24,
        num_attention_heads: 16,
        num_register_tokens: 4,
        ..Dinov3Config::default()
    };
    let (h, m) = (c.hidden_size, c.intermediate_size);
    let mut t = HashMap::new();
    put(&mut t, "embeddings.cls_token".into(), &[1, 1, h], 0.0, 0.02)?;
    put(
        &mut t,
        "embeddings.mask_token".into(),
        &[1, 1, h],
        0.0,
        0.02,
    )?;
    put(
        &mut t,
        "embeddings.register_tokens".into(),
        &[1, 4, h],
        0.0,
        0.02,
    )?;
    put(
        &mut t,
        "embeddings.patch_embeddings.weight".into(),
        &[h, 3, 16, 16],
        0.0,
        0.02,
    )?;
    put(
        &mut t,
        "embeddings.patch_embeddings.bias".into(),
        &[h],
        0.0,
        0.02,
    )?;
    for i in 0..c.num_hidden_layers {
        let l = format!("layer.{i}");
        put_norm(&mut t, &format!("{l}.norm1"), h)?;
        put_linear(&mut t, &format!("{l}.attention.q_proj"), h, h, true)?;
        put_linear(&mut t, &format!("{l}.attention.k_proj"), h, h, false)?;
        put_linear(&mut t, &format!("{l}.attention.v_proj"), h, h, true)?;
        put_linear(&mut t, &format!("{l}.attention.o_proj"), h, h, true)?;
        put(&mut t, format!("{l}.layer_scale1.lambda1"), &[h], 1e-5, 0.0)?;
        put_norm(&mut t, &format!("{l}.norm2"), h)?;
        put_linear(&mut t, &format!("{l}.mlp.up_proj"), h, m, true)?;
        put_linear(&mut t, &format!("{l}.mlp.down_proj"), m, h, true)?;
        put(&mut t, format!("{l}.layer_scale2.lambda1"), &[h], 1e-5, 0.0)?;
    }
    put_norm(&mut t, "norm", h)?;
    Ok(Dinov3Backbone::from_tensors(&c, t, device, dtype)?)
}

/// The dino.txt heads in the released checkpoint's layout.
fn heads(vocab: usize, device: &Device, dtype: ModelDtype) -> Result<DinoTxtHeads> {
    let mut t = HashMap::new();
    let (w, hidden) = (1024, 2752);
    for i in 0..2 {
        let b = format!("visual_model.head.blocks.{i}");
        put_norm(&mut t, &format!("{b}.norm1"), w)?;
        put_linear(&mut t, &format!("{b}.attn.qkv"), w, 3 * w, false)?;
        put_linear(&mut t, &format!("{b}.attn.proj"), w, w, true)?;
        put(&mut t, format!("{b}.ls1.gamma"), &[w], 1e-5, 0.0)?;
        put_norm(&mut t, &format!("{b}.norm2"), w)?;
        put_linear(&mut t, &format!("{b}.mlp.w1"), w, hidden, true)?;
        put_linear(&mut t, &format!("{b}.mlp.w2"), w, hidden, true)?;
        put_linear(&mut t, &format!("{b}.mlp.w3"), hidden, w, true)?;
        put(&mut t, format!("{b}.ls2.gamma"), &[w], 1e-5, 0.0)?;
    }
    put_norm(&mut t, "visual_model.head.ln_final", w)?;
    let (d, tb) = (1280, "text_model.backbone");
    put(
        &mut t,
        format!("{tb}.token_embedding.weight"),
        &[vocab, d],
        0.0,
        0.02,
    )?;
    put(
        &mut t,
        format!("{tb}.positional_embedding"),
        &[77, d],
        0.0,
        0.01,
    )?;
    for i in 0..24 {
        let b = format!("{tb}.blocks.{i}");
        put_norm(&mut t, &format!("{b}.attention_norm"), d)?;
        put_linear(&mut t, &format!("{b}.attention.qkv"), d, 3 * d, false)?;
        put_linear(&mut t, &format!("{b}.attention.proj"), d, d, true)?;
        put_norm(&mut t, &format!("{b}.ffn_norm"), d)?;
        put_linear(&mut t, &format!("{b}.feed_forward.fc1"), d, 4 * d, true)?;
        put_linear(&mut t, &format!("{b}.feed_forward.fc2"), 4 * d, d, true)?;
    }
    put_norm(&mut t, &format!("{tb}.ln_final"), d)?;
    put_linear(&mut t, "text_model.head.linear_projection", d, 2048, false)?;
    Ok(DinoTxtHeads::from_tensors(t, 16, None, device, dtype)?)
}

/// A 640 × 480 frame of smooth gradients.
fn frame() -> Result<RgbImage> {
    let (w, h) = (640u32, 480u32);
    let data = (0..h)
        .flat_map(|y| (0..w).flat_map(move |x| [(x / 3) as u8, (y / 2) as u8, ((x + y) / 5) as u8]))
        .collect();
    Ok(RgbImage::new(w, h, data)?)
}

fn main() -> Result<()> {
    // As the `vlem` binary runs the models.
    vlem_backends::use_all_cpus_once();
    vlem_backends::keep_freed_memory();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let sides: Vec<u32> = args.first().map_or(Ok(vec![448]), |s| {
        s.split(',')
            .map(|v| {
                v.trim()
                    .parse::<u32>()
                    .context(format!("bad short side {v:?}"))
            })
            .collect()
    })?;
    let frames: usize = args
        .get(1)
        .map_or(Ok(3), |s| s.parse().context("bad frame count"))?;
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".to_owned());
    let device = vlem_backends::ComputeDevice::from_env("VLEM_BENCH_DEVICE")?.open()?;
    // The type to time: `VLEM_BENCH_DTYPE` (`f32` unless set).
    let dtype = ModelDtype::from_env("VLEM_BENCH_DTYPE")?;
    println!("building random ViT-L/16 + dino.txt weights ...");
    // A merge list whose vocabulary has the released size (49408 = 512 + 48894 + 2) would need
    // the file; the tiny one times the text tower just as well at the same token count.
    let tokenizer = ClipBpe::from_merges("#version\nc h\na i\nch ai\nchai r</w>")?;
    let image = frame()?;
    for side in sides {
        let encoder = Dinov3Encoder::new(
            backbone(&device, dtype)?,
            heads(49408, &device, dtype)?,
            tokenizer.clone(),
            side,
            vec!["{}".to_owned()],
        )?;
        let (w, h) = encoder.input_size(image.width(), image.height());
        encoder.encode_image(&image, &[])?;
        // Each frame timed alone: the best is what bench/models/side_by_side.py compares, as it
        // takes PyTorch's best.
        let mut times = Vec::with_capacity(frames);
        for _ in 0..frames {
            let start = Instant::now();
            encoder.encode_image(&image, &[])?;
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
        let best = times.iter().copied().fold(f64::NAN, f64::min);
        let mean = times.iter().sum::<f64>() / frames as f64;
        let start = Instant::now();
        encoder.encode_text("a photo of a chair")?;
        let text = start.elapsed().as_secs_f64() * 1e3;
        println!(
            "threads {threads}  short side {side}: input {w}x{h} ({} patches)  best {best:.1} ms/frame, \
             mean {mean:.1} ms/frame  text query {text:.0} ms",
            (w / 16) * (h / 16)
        );
    }
    if vlem_backends::profile::enabled() {
        // The steps' times over every call above, the warm-up included.
        println!("per-op profile (the device synchronised around each step):");
        print!("{}", vlem_backends::profile::table());
    }
    Ok(())
}
