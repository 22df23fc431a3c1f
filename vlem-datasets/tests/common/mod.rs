//! Builders of small synthetic dataset folders, shared by the integration tests.
#![allow(dead_code, reason = "each test file uses a part of the helpers")]
#![allow(clippy::unwrap_used, clippy::panic, reason = "test helpers")]

use std::path::{Path, PathBuf};

use image::{ImageBuffer, Luma, Rgb};

/// The committed ICL-NUIM excerpt.
pub fn living_room() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../data/living-room"))
}

/// The shared read-only data beside the repository clone; `None` (with a note) when absent.
pub fn shared_data(sub: &str) -> Option<PathBuf> {
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data")).join(sub);
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("note: {} is absent, skipping this test", dir.display());
        None
    }
}

fn parent(path: &Path) {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).unwrap();
    }
}

/// A solid-colour RGB image (PNG or JPEG by extension).
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: [u8; 3]) {
    parent(path);
    ImageBuffer::from_pixel(width, height, Rgb(rgb))
        .save(path)
        .unwrap();
}

/// A 16-bit depth PNG with raw value `f(u, v)`.
pub fn write_depth(path: &Path, width: u32, height: u32, f: impl Fn(u32, u32) -> u16) {
    parent(path);
    let img: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_fn(width, height, |u, v| Luma([f(u, v)]));
    img.save(path).unwrap();
}

/// A 16-bit depth PNG holding one raw value everywhere.
pub fn write_flat_depth(path: &Path, width: u32, height: u32, raw: u16) {
    write_depth(path, width, height, |_, _| raw);
}

/// An Open3D PinholeCameraIntrinsic JSON.
pub fn write_intrinsics(path: &Path, width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) {
    parent(path);
    let json = format!(
        r#"{{"width": {width}, "height": {height}, "intrinsic_matrix": [{fx}, 0, 0, 0, {fy}, 0, {cx}, {cy}, 1]}}"#
    );
    std::fs::write(path, json).unwrap();
}

/// A 4x4 matrix as rows of text, one row per line.
pub fn matrix_rows(m: &[[f64; 4]; 4]) -> String {
    m.iter()
        .map(|r| format!("{} {} {} {}\n", r[0], r[1], r[2], r[3]))
        .collect()
}

/// A pure translation as a 4x4 matrix.
pub fn translation(x: f64, y: f64, z: f64) -> [[f64; 4]; 4] {
    [
        [1.0, 0.0, 0.0, x],
        [0.0, 1.0, 0.0, y],
        [0.0, 0.0, 1.0, z],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// A Redwood `.log` holding `matrices`.
pub fn write_log(path: &Path, matrices: &[[[f64; 4]; 4]]) {
    parent(path);
    let text: String = matrices
        .iter()
        .enumerate()
        .map(|(i, m)| format!("{i} {i} {}\n{}", i + 1, matrix_rows(m)))
        .collect();
    std::fs::write(path, text).unwrap();
}

/// An ICL-NUIM folder of `n` 4x3 frames named from `first`: colour of frame `k` is `[k, 2k, 3k]`
/// (PNG, lossless), depth raw `1000 + 100 k`, intrinsics.json, and a trajectory.log with the camera
/// at x = k when `with_poses`.
pub fn write_icl(dir: &Path, first: usize, n: usize, with_poses: bool) {
    for k in 0..n {
        let name = format!("{:05}", first + k);
        let c = u8::try_from(k).unwrap();
        write_rgb(
            &dir.join(format!("color/{name}.png")),
            4,
            3,
            [c, 2 * c, 3 * c],
        );
        write_flat_depth(
            &dir.join(format!("depth/{name}.png")),
            4,
            3,
            1000 + 100 * c as u16,
        );
    }
    write_intrinsics(&dir.join("intrinsics.json"), 4, 3, 5.0, 5.0, 1.5, 1.0);
    if with_poses {
        let poses: Vec<_> = (0..n).map(|k| translation(k as f64, 0.0, 0.0)).collect();
        write_log(&dir.join("trajectory.log"), &poses);
    }
}

/// The message of the error `vlem_datasets::open` fails with.
pub fn open_error(config: &vlem_core::config::DatasetConfig, dir: &Path) -> String {
    match vlem_datasets::open(config, dir) {
        Ok(source) => panic!("{} opened, expected an error", source.describe()),
        Err(e) => e.to_string(),
    }
}
