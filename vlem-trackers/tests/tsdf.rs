//! The TSDF volume on the committed real living-room frames (ICL-NUIM, 640x480) at their
//! dataset poses: the model ray-cast at a frame's pose must reproduce that frame.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::path::Path;

use vlem_core::config::DatasetConfig;
use vlem_core::{Frame, FrameSource};
use vlem_trackers::tsdf::{RaycastOptions, TsdfConfig, TsdfVolume};

fn living_room() -> Vec<Frame> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/living-room");
    let mut source: Box<dyn FrameSource> =
        vlem_datasets::open(&DatasetConfig::default(), &dir).unwrap();
    (0..source.len())
        .map(|i| source.frame(i).unwrap())
        .collect()
}

fn median(mut values: Vec<f32>) -> f32 {
    values.sort_by(f32::total_cmp);
    values[values.len() / 2]
}

#[test]
fn raycasts_reproduce_the_fused_real_frames() {
    let frames = living_room();
    assert_eq!(frames.len(), 30);
    let config = TsdfConfig::default();
    let mut volume = TsdfVolume::new(config).unwrap();
    for frame in &frames {
        volume
            .try_integrate(
                &frame.depth,
                &frame.colour,
                &frame.intrinsics,
                &frame.pose.unwrap(),
            )
            .unwrap();
    }
    assert_eq!(volume.frame_count(), 30);
    let blocks = volume.block_count();
    println!(
        "{blocks} blocks, {:.1} MiB",
        volume.memory_bytes() as f64 / (1 << 20) as f64
    );
    assert!((5_000..40_000).contains(&blocks), "{blocks}");

    for index in [0, 14, 29] {
        let frame = &frames[index];
        let cast = volume.raycast(&frame.intrinsics, &frame.pose.unwrap());
        let mut depth_errors = Vec::new();
        let mut colour_errors = Vec::new();
        let mut measured = 0;
        for (i, (&model, &sensor)) in cast
            .depth
            .as_raw()
            .iter()
            .zip(frame.depth.as_raw())
            .enumerate()
        {
            if !(sensor > config.depth_min && sensor < config.depth_max) {
                continue;
            }
            measured += 1;
            if model > 0.0 {
                depth_errors.push((model - sensor).abs());
                let (a, b) = (cast.colour.at_index(i), frame.colour.at_index(i));
                let diff = (0..3).map(|c| a[c].abs_diff(b[c]) as f32).sum::<f32>() / 3.0;
                colour_errors.push(diff);
            }
        }
        let coverage = depth_errors.len() as f32 / measured as f32;
        let depth_median = median(depth_errors.clone());
        let within_2cm =
            depth_errors.iter().filter(|&&e| e < 0.02).count() as f32 / depth_errors.len() as f32;
        let colour_median = median(colour_errors);
        println!(
            "frame {index}: {:.1} % of measured pixels hit, depth error median {:.2} mm, \
             {:.1} % within 2 cm; colour error median {colour_median:.1} levels",
            100.0 * coverage,
            depth_median * 1e3,
            100.0 * within_2cm
        );
        assert!(coverage > 0.95, "frame {index}: coverage {coverage}");
        assert!(depth_median < 0.01, "frame {index}: {depth_median} m");
        assert!(within_2cm > 0.95, "frame {index}: {within_2cm}");
        assert!(colour_median < 10.0, "frame {index}: {colour_median}");
    }

    // Normals face the camera.
    let frame = &frames[14];
    let options = RaycastOptions {
        normals: true,
        ..RaycastOptions::default()
    };
    let cast = volume.raycast_with(&frame.intrinsics, &frame.pose.unwrap(), &options);
    let normals = cast.normals.as_deref().unwrap();
    let k = frame.intrinsics;
    let mut facing = 0;
    let mut with_normal = 0;
    for (i, n) in normals.iter().enumerate() {
        if *n == [0.0; 3] {
            continue;
        }
        with_normal += 1;
        let (u, v) = ((i % k.width as usize) as f64, (i / k.width as usize) as f64);
        let ray = [(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0];
        let dot: f64 = ray.iter().zip(n).map(|(r, n)| r * f64::from(*n)).sum();
        facing += usize::from(dot < 0.0);
    }
    assert!(with_normal as f32 > 0.9 * cast.hit_count() as f32);
    assert!(
        facing as f32 > 0.99 * with_normal as f32,
        "{facing} of {with_normal}"
    );

    // The mesh is coloured like the frames and lies where the rays meet the surface.
    let mesh = volume.extract_mesh();
    let points = volume.extract_points();
    println!(
        "mesh: {} vertices, {} triangles; {} points",
        mesh.vertices.len(),
        mesh.triangles.len(),
        points.vertices.len()
    );
    assert!(mesh.triangles.len() > 100_000);
    assert_eq!(mesh.vertices.len(), mesh.colours.len());
    assert!(points.triangles.is_empty());
    assert!(points.vertices.len() > 100_000);
    let n = mesh.vertices.len() as u32;
    assert!(mesh.triangles.iter().all(|t| t.iter().all(|&i| i < n)));
}
