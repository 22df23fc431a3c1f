//! The point-cloud and voxel maps with their embedding tables on a candle device (`[map] device`), run on
//! candle's CPU device (or the GPU that `VLEM_TEST_DEVICE=cuda` names, in a build with `cuda`):
//! the map contract, and the same sequence as the host table giving the same
//! points and, within rounding, the same rows and query ranking — through fusion, insertion and
//! the budget's merges, from region tables and from patch grids, in both precisions.
#![cfg(all(feature = "point-cloud", feature = "voxel", feature = "candle"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use candle_core::Device;
use vlem_backends::ComputeDevice;
use vlem_core::{EmbeddingMap, Frame, Observation, PixelEmbeddings};
use vlem_maps::point_cloud::PointCloudConfig;
use vlem_maps::storage::Precision;
use vlem_maps::voxel::VoxelConfig;
use vlem_testkit::map::{half_segments, plane_frame, pose};

/// candle's CPU device, or the one `VLEM_TEST_DEVICE` names.
fn test_device() -> Device {
    let asked = ComputeDevice::from_env("VLEM_TEST_DEVICE").unwrap();
    asked.open().unwrap()
}

fn device_point_cloud(dim: usize, max_points: usize) -> Box<dyn EmbeddingMap> {
    let config = PointCloudConfig {
        max_points,
        ..PointCloudConfig::default()
    };
    match config.build_on(Some(dim), &test_device()) {
        Ok(map) => Box::new(map),
        Err(e) => panic!("valid config refused: {e}"),
    }
}

vlem_testkit::map_conformance!(device_point_cloud);

fn voxel_config(max_voxels: usize, precision: Precision) -> VoxelConfig {
    VoxelConfig {
        max_voxels,
        voxel_size: 0.02,
        precision,
        ..VoxelConfig::default()
    }
}

fn device_voxel(dim: usize, max_voxels: usize) -> Box<dyn EmbeddingMap> {
    match voxel_config(max_voxels, Precision::F32).build_on(Some(dim), &test_device()) {
        Ok(map) => Box::new(map),
        Err(e) => panic!("valid config refused: {e}"),
    }
}

mod voxel {
    use super::*;
    vlem_testkit::map_conformance!(device_voxel);
}

const DIM: usize = 8;

/// A 4×3 patch grid of pseudo-random rows (some pairs nearly opposite, so blends come close to
/// cancelling), different per frame.
fn patch_grid(frame: &Frame, seed: usize) -> PixelEmbeddings {
    let (gw, gh) = (4u32, 3u32);
    let data: Vec<f32> = (0..(gw * gh) as usize * DIM)
        .map(|i| {
            let x = ((i * 7919 + seed * 104_729) % 1000) as f32 / 500.0 - 1.0;
            if i % 5 == 0 { -x } else { x }
        })
        .collect();
    let (w, h) = (frame.depth.width(), frame.depth.height());
    PixelEmbeddings::from_patch_grid(w, h, DIM, gw, gh, data).unwrap()
}

/// The point-cloud map and the voxel map, each on the host and on the device.
fn pairs(precision: Precision) -> Vec<(Box<dyn EmbeddingMap>, Box<dyn EmbeddingMap>)> {
    let point_cloud = PointCloudConfig {
        max_points: 1500,
        precision,
        ..PointCloudConfig::default()
    };
    let voxel = voxel_config(1500, precision);
    vec![
        (
            Box::new(point_cloud.build(Some(DIM)).unwrap()),
            Box::new(point_cloud.build_on(Some(DIM), &test_device()).unwrap()),
        ),
        (
            Box::new(voxel.build(Some(DIM)).unwrap()),
            Box::new(voxel.build_on(Some(DIM), &test_device()).unwrap()),
        ),
    ]
}

fn run_both(precision: Precision, patches: bool) {
    for (host, device) in pairs(precision) {
        compare(host, device, precision, patches);
    }
}

fn compare(
    mut host: Box<dyn EmbeddingMap>,
    mut device: Box<dyn EmbeddingMap>,
    precision: Precision,
    patches: bool,
) {
    let name = host.name();
    assert_eq!(host.device_memory_bytes(), 0);
    assert!(device.device_memory_bytes() >= 1500 * DIM * 2);
    let mut removed = 0;
    for i in 0..14 {
        // A camera that moves and turns, at two depths, so points fuse, are inserted, and the
        // budget merges them.
        let frame = plane_frame(i, if i % 3 == 0 { 1.0 } else { 1.3 });
        let embeddings = if patches {
            patch_grid(&frame, i)
        } else {
            half_segments(&frame, i)
        };
        let camera = pose(0.02 * i as f64, 0.0, 0.0, 0.03 * i as f64);
        let obs = Observation {
            frame: &frame,
            pose: &camera,
            embeddings: Some(&embeddings),
        };
        let a = host.integrate(&obs).unwrap();
        let b = device.integrate(&obs).unwrap();
        assert_eq!(
            a, b,
            "{name}, frame {i}: the same geometry, the same counts"
        );
        removed += a.removed;
    }
    assert!(removed > 0, "{name}: the budget never merged or evicted");
    let (a, b) = (host.snapshot().unwrap(), device.snapshot().unwrap());
    assert_eq!(a.positions, b.positions);
    assert_eq!(a.colours, b.colours);
    let tolerance = match precision {
        Precision::F32 => 1e-5,
        // One f16 rounding (2^-11 relative) per write, on both sides.
        Precision::F16 => 2e-3,
    };
    for (row, (x, y)) in a
        .embeddings
        .chunks_exact(DIM)
        .zip(b.embeddings.chunks_exact(DIM))
        .enumerate()
    {
        for (p, q) in x.iter().zip(y) {
            assert!((p - q).abs() <= tolerance, "{name}, row {row}: {p} vs {q}");
        }
    }
    // Queries: one pass for several texts, the same scores within rounding, so the same ranking
    // wherever two points are further apart than that.
    let texts: Vec<Vec<f32>> = (0..3)
        .map(|t| {
            let mut v: Vec<f32> = (0..DIM).map(|k| ((k + 3 * t) % 5) as f32 - 2.0).collect();
            vlem_core::embeddings::normalise(&mut v);
            v
        })
        .collect();
    let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
    let (mut x, mut y) = (Vec::new(), Vec::new());
    host.similarity_many(&texts, &mut x).unwrap();
    device.similarity_many(&texts, &mut y).unwrap();
    for (t, (x, y)) in x.iter().zip(&y).enumerate() {
        assert_eq!(x.len(), host.len());
        assert!(
            x.iter().zip(y).all(|(p, q)| (p - q).abs() <= tolerance),
            "{name}, text {t}"
        );
        for i in 0..x.len() {
            for j in 0..x.len() {
                if x[i] > x[j] + 2.0 * tolerance {
                    assert!(y[i] > y[j], "{name}, text {t}: {i} and {j} swap places");
                }
            }
        }
    }
    // One text scores as among several, within rounding (the matrix product's blocking differs
    // with the number of texts; the host table's scores are bit for bit the same).
    let mut one = Vec::new();
    device.similarity(texts[1], &mut one).unwrap();
    assert_eq!(one.len(), y[1].len());
    assert!(one.iter().zip(&y[1]).all(|(p, q)| (p - q).abs() <= 1e-6));
    assert!(device.similarity(&[1.0], &mut one).is_err());
}

#[test]
fn the_device_table_follows_the_host_table_with_segments_in_f32() {
    run_both(Precision::F32, false);
}

#[test]
fn the_device_table_follows_the_host_table_with_patches_in_f32() {
    run_both(Precision::F32, true);
}

#[test]
fn the_device_table_follows_the_host_table_in_f16() {
    run_both(Precision::F16, false);
    run_both(Precision::F16, true);
}

#[test]
fn a_restored_device_map_equals_a_restored_host_map() {
    let config = PointCloudConfig {
        max_points: 100,
        ..PointCloudConfig::default()
    };
    let mut source = config.build(Some(DIM)).unwrap();
    let frame = plane_frame(0, 1.0);
    let embeddings = half_segments(&frame, 2);
    let camera = pose(0.0, 0.0, 0.0, 0.0);
    source
        .integrate(&Observation {
            frame: &frame,
            pose: &camera,
            embeddings: Some(&embeddings),
        })
        .unwrap();
    // The restore merges the snapshot down to the budget, on the device as on the host.
    let snapshot = source.snapshot().unwrap();
    let mut host = config.build(Some(DIM)).unwrap();
    let mut device = config.build_on(Some(DIM), &test_device()).unwrap();
    host.restore(snapshot.clone()).unwrap();
    device.restore(snapshot).unwrap();
    assert!(host.len() <= 100);
    let (a, b) = (host.snapshot().unwrap(), device.snapshot().unwrap());
    assert_eq!(a.positions, b.positions);
    assert!(
        a.embeddings
            .iter()
            .zip(&b.embeddings)
            .all(|(p, q)| (p - q).abs() <= 1e-6)
    );
}

#[test]
fn asking_for_a_gpu_in_a_build_without_cuda_names_both() {
    if cfg!(feature = "cuda") {
        return;
    }
    let config: PointCloudConfig = toml::from_str("device = \"cuda:1\"").unwrap();
    let error = config.build(Some(DIM)).err().map(|e| e.to_string());
    let error = error.unwrap_or_default();
    assert!(error.contains("cuda:1"), "{error}");
    assert!(error.contains("no CUDA support"), "{error}");
}
