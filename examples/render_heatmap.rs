//! Renders a saved map and one query's heatmap side by side into a PNG: the picture on the
//! README's front page comes from this file, so anyone can remake it (and see how a map is read,
//! its encoder rebuilt and a text scored in a few calls of the library).
//!
//! ```sh
//! cargo run --release -- demo
//! cargo run --release --example render_heatmap -- out/demo/map.vlem brown docs/demo-heatmap.png
//! ```
//!
//! The view is the map frame's (the first camera's: x right, y down, z forward), pulled back a
//! little so the first frame's borders show; points are splatted with a depth buffer, nearest
//! wins. Left: the points' colours; right: the similarity to the text with the jet colour map of
//! every vlem heatmap, on the absolute scale 0–1 that the strip under it shows.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use image::{Rgb, RgbImage};
use vlem::query::answer::{EmbeddedTexts, encoder_for_map, score_snapshot};
use vlem::query::heatmap::jet;

/// Width and height of one panel, pixels.
const PANEL: (u32, u32) = (480, 360);
/// Height of the colour-scale strip under the heatmap, pixels.
const STRIP: u32 = 14;
/// How far the virtual camera sits behind the first camera, metres.
const PULL_BACK: f32 = 0.4;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [map, text, png] = args.as_slice() else {
        bail!("usage: render_heatmap MAP.vlem TEXT OUT.png");
    };
    let png = PathBuf::from(png);

    let snapshot = vlem::core::read_map_file(map.as_ref())?;
    let encoder = encoder_for_map(&snapshot.metadata, map)?;
    let texts = EmbeddedTexts {
        texts: vec![text.clone()],
        embeddings: vec![encoder.encode_text(text)?],
        baseline: None,
    };
    let scores = score_snapshot(&snapshot, &texts)?;
    let similarity = &scores.scores[0];

    let (w, h) = PANEL;
    let mut picture = RgbImage::from_pixel(2 * w, h + STRIP, Rgb([255, 255, 255]));
    let mut depth = vec![f32::INFINITY; (w * h) as usize];
    // A pinhole with a 60° horizontal field of view, looking down the map frame's +z.
    let focal = w as f32 * 0.87;
    for ((p, colour), &s) in snapshot
        .positions
        .iter()
        .zip(&snapshot.colours)
        .zip(similarity)
    {
        let z = p[2] + PULL_BACK;
        if z <= 0.05 {
            continue;
        }
        let u = (focal * p[0] / z + w as f32 / 2.0).floor();
        let v = (focal * p[1] / z + h as f32 / 2.0).floor();
        if u < 0.0 || v < 0.0 || u >= w as f32 || v >= h as f32 {
            continue;
        }
        let (u, v) = (u as u32, v as u32);
        let nearest = &mut depth[(v * w + u) as usize];
        if z < *nearest {
            *nearest = z;
            picture.put_pixel(u, v, Rgb(*colour));
            picture.put_pixel(w + u, v, Rgb(jet(s)));
        }
    }
    for u in 0..w {
        let colour = Rgb(jet(u as f32 / (w - 1) as f32));
        for v in h + 2..h + STRIP {
            picture.put_pixel(w + u, v, colour);
        }
    }
    if let Some(folder) = png.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(folder)
            .with_context(|| format!("creating {}", folder.display()))?;
    }
    picture
        .save(&png)
        .with_context(|| format!("writing {}", png.display()))?;
    println!(
        "{}: {} points of {map} and their similarity to {text:?} (best {:.3})",
        png.display(),
        snapshot.len(),
        similarity.iter().copied().fold(f32::NEG_INFINITY, f32::max)
    );
    Ok(())
}
