//! Files the `vlem` command writes: statistics JSON and PLY heatmaps, each written atomically.

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};

/// Writes `bytes` to `path` through a temporary file in the same directory and a rename, so an
/// interrupted run never leaves a half-written file.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let result = (|| -> Result<()> {
        let mut file = std::fs::File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)?;
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.with_context(|| format!("cannot write {}", path.display()))
}

/// Peak resident memory of this process in bytes (Linux `VmHWM`), `None` where unavailable.
pub fn peak_resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The jet colour map (dark blue → cyan → yellow → dark red) for `t` in `[0, 1]`, as in the
/// paper's figures.
pub fn jet(t: f32) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let channel = |offset: f32| (1.5 - (4.0 * t - offset).abs()).clamp(0.0, 1.0);
    [channel(3.0), channel(2.0), channel(1.0)].map(|c| (c * 255.0).round() as u8)
}

/// Binary little-endian PLY of points coloured by `scores` (jet), with the score as a property.
pub fn heatmap_ply(positions: &[[f32; 3]], scores: &[f32]) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment vlem query heatmap: colour = jet(similarity)\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         property float similarity\nend_header\n",
        positions.len()
    )
    .into_bytes();
    out.reserve(positions.len() * 19);
    for (p, &s) in positions.iter().zip(scores) {
        p.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        out.extend_from_slice(&jet(s));
        out.extend_from_slice(&s.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jet_runs_from_dark_blue_to_dark_red() {
        assert_eq!(jet(0.0), [0, 0, 128]);
        assert_eq!(jet(0.5), [128, 255, 128]);
        assert_eq!(jet(1.0), [128, 0, 0]);
        assert_eq!(jet(f32::NAN), jet(0.0));
    }

    #[test]
    fn ply_has_a_header_and_19_bytes_per_point() {
        let ply = heatmap_ply(&[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], &[0.0, 1.0]);
        let text = String::from_utf8_lossy(&ply);
        let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 2"));
        assert_eq!(ply.len() - header_end, 2 * 19);
        assert_eq!(&ply[header_end + 12..header_end + 15], &[0, 0, 128]);
    }
}
