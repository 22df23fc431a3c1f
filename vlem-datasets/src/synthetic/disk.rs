//! Writing a synthetic sequence as an ICL-NUIM/Open3D folder, so that every tool that reads
//! datasets (and [`crate::icl::IclReader`]) can use it, plus the labels the ICL layout lacks.
//!
//! ```text
//! color/000000.png ...   8-bit RGB
//! depth/000000.png ...   16-bit depth, millimetres (0 = no measurement)
//! label/000000.png ...   16-bit class ids (NYU40, see labels.json)
//! intrinsics.json        Open3D PinholeCameraIntrinsic
//! trajectory.log         Redwood .log, camera-to-world
//! labels.json            {"<id>": "<name>", ...} for every class the generator produces
//! scene.json             the [dataset.synthetic] config and the objects with their bounds
//! ```

use std::fmt::Write as _;
use std::path::Path;

use image::{ImageBuffer, Luma, Rgb};
use rayon::prelude::*;

use super::{SYNTHETIC_FRAME_RATE, SyntheticScene, SyntheticView};
use crate::error::{DatasetError, Result};
use crate::icl::ICL_DEPTH_SCALE;

/// Writes every frame of `scene` and its metadata into `dir` (created if needed) in the layout
/// above. Frames are rendered and encoded in parallel.
///
/// # Errors
/// [`DatasetError::Io`] when a folder or file cannot be written, [`DatasetError::UnwritableImage`]
/// when an image cannot be encoded.
pub fn write_to_disk(scene: &SyntheticScene, dir: &Path) -> Result<()> {
    for sub in ["color", "depth", "label"] {
        let path = dir.join(sub);
        std::fs::create_dir_all(&path).map_err(|e| DatasetError::io(&path, e))?;
    }
    (0..scene.len())
        .into_par_iter()
        .try_for_each(|i| write_view(&scene.render(i)?, dir))?;
    let k = scene.intrinsics();
    let intrinsics = serde_json::json!({
        "width": k.width,
        "height": k.height,
        "intrinsic_matrix": [k.fx, 0.0, 0.0, 0.0, k.fy, 0.0, k.cx, k.cy, 1.0],
    });
    write_json(&dir.join("intrinsics.json"), &intrinsics)?;
    write_text(&dir.join("trajectory.log"), &log_text(&scene.poses()))?;
    let labels: serde_json::Map<String, serde_json::Value> = scene
        .labels()
        .iter()
        .map(|l| (l.id.to_string(), serde_json::Value::from(l.name)))
        .collect();
    write_json(&dir.join("labels.json"), &serde_json::Value::Object(labels))?;
    let objects: Vec<serde_json::Value> = scene
        .objects()
        .iter()
        .map(|o| {
            serde_json::json!({
                "instance": o.instance,
                "label": o.label,
                "name": o.name,
                "min": [o.min.x, o.min.y, o.min.z],
                "max": [o.max.x, o.max.y, o.max.z],
            })
        })
        .collect();
    let (room_min, room_max) = scene.room();
    let description = serde_json::json!({
        "generator": "vlem-datasets synthetic",
        "config": scene.config(),
        "frame_rate": SYNTHETIC_FRAME_RATE,
        "room": {"min": [room_min.x, room_min.y, room_min.z], "max": [room_max.x, room_max.y, room_max.z]},
        "objects": objects,
    });
    write_json(&dir.join("scene.json"), &description)
}

/// Writes the three images of one view.
fn write_view(view: &SyntheticView, dir: &Path) -> Result<()> {
    let name = format!("{:06}.png", view.index);
    let (w, h) = (view.intrinsics.width, view.intrinsics.height);
    let sizes = |path: &Path| DatasetError::Synthetic {
        message: format!("{}: image buffer does not match {w}x{h}", path.display()),
    };
    let path = dir.join("color").join(&name);
    let colour: ImageBuffer<Rgb<u8>, Vec<u8>> =
        ImageBuffer::from_raw(w, h, view.colour.as_raw().to_vec()).ok_or_else(|| sizes(&path))?;
    save(&colour, &path)?;
    let path = dir.join("depth").join(&name);
    let raw: Vec<u16> = view
        .depth
        .as_raw()
        .iter()
        .map(|&d| match vlem_core::types::valid_depth(d) {
            Some(d) => (f64::from(d) * ICL_DEPTH_SCALE).round().clamp(0.0, 65535.0) as u16,
            None => 0,
        })
        .collect();
    let depth: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(w, h, raw).ok_or_else(|| sizes(&path))?;
    save(&depth, &path)?;
    let path = dir.join("label").join(&name);
    let labels: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(w, h, view.labels.clone()).ok_or_else(|| sizes(&path))?;
    save(&labels, &path)
}

fn save<P>(image: &ImageBuffer<P, Vec<P::Subpixel>>, path: &Path) -> Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    image
        .save(path)
        .map_err(|source| DatasetError::UnwritableImage {
            path: path.to_path_buf(),
            source,
        })
}

/// A Redwood `.log`: per frame `i i i+1`, then the 4x4 camera-to-world matrix, rows in full
/// precision (Rust prints the shortest text that reads back to the same number).
pub(crate) fn log_text(poses: &[vlem_core::Pose]) -> String {
    let mut text = String::new();
    for (i, pose) in poses.iter().enumerate() {
        let m = pose.to_homogeneous();
        let _ = writeln!(text, "{i} {i} {}", i + 1);
        for r in 0..4 {
            let _ = writeln!(
                text,
                "{} {} {} {}",
                m[(r, 0)],
                m[(r, 1)],
                m[(r, 2)],
                m[(r, 3)]
            );
        }
    }
    text
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|e| DatasetError::io(path, e))
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| DatasetError::Synthetic {
        message: format!("{}: {e}", path.display()),
    })?;
    write_text(path, &(text + "\n"))
}
