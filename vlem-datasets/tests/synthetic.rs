//! The synthetic scene: determinism, exact geometry, multi-view consistency, labels, texture,
//! the on-disk round trip through the ICL reader, and config handling.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

use std::path::Path;

use nalgebra::Vector3;
use vlem_core::config::DatasetConfig;
use vlem_core::{Config, FrameSource, Intrinsics};
use vlem_datasets::synthetic::{
    SYNTHETIC_FRAME_RATE, SYNTHETIC_LABELS, SyntheticView, look_along, write_to_disk,
};
use vlem_datasets::{SyntheticConfig, SyntheticNoise};
use vlem_datasets::{SyntheticReader, SyntheticScene, detect_kind, open};

fn config(seed: u64, frames: usize, width: u32, height: u32) -> SyntheticConfig {
    SyntheticConfig {
        seed,
        frames,
        width,
        height,
        ..SyntheticConfig::default()
    }
}

fn grey(view: &SyntheticView, u: u32, v: u32) -> f64 {
    let [r, g, b] = view.colour.get(u, v).unwrap();
    (f64::from(r) + f64::from(g) + f64::from(b)) / 3.0
}

#[test]
fn same_seed_gives_identical_bytes_and_another_seed_another_scene() {
    let a = SyntheticScene::new(&config(5, 20, 160, 120)).unwrap();
    let b = SyntheticScene::new(&config(5, 20, 160, 120)).unwrap();
    let c = SyntheticScene::new(&config(6, 20, 160, 120)).unwrap();
    let (va, vb, vc) = (
        a.render(7).unwrap(),
        b.render(7).unwrap(),
        c.render(7).unwrap(),
    );
    assert_eq!(va.colour, vb.colour);
    assert_eq!(va.depth.as_raw(), vb.depth.as_raw());
    assert_eq!(va.labels, vb.labels);
    assert_eq!(va.instances, vb.instances);
    assert_eq!(va.pose, vb.pose);
    assert_eq!(a.objects(), b.objects());
    assert_ne!(va.colour, vc.colour);
    assert_ne!(va.pose, vc.pose);
    assert_ne!(a.objects(), c.objects());
    // The trajectory does not depend on how many frames are asked for.
    let longer = SyntheticScene::new(&config(5, 200, 160, 120)).unwrap();
    assert_eq!(longer.pose(7).unwrap(), a.pose(7).unwrap());
    assert_eq!(longer.render(7).unwrap().colour, va.colour);
}

#[test]
fn depth_is_the_analytic_distance_to_the_room_surfaces() {
    let cfg = SyntheticConfig {
        room: [4.0, 4.0, 3.0],
        objects: 0,
        ..config(0, 1, 320, 240)
    };
    let scene = SyntheticScene::new(&cfg).unwrap();
    assert_eq!(scene.objects().len(), 6);
    // Facing the wall at x = 2 from 2 m: the whole image is that wall, at depth exactly 2.
    let pose = look_along(Vector3::new(0.0, 0.0, 1.5), Vector3::x());
    let view = scene.render_at(0, &pose).unwrap();
    assert!(
        view.depth.as_raw().iter().all(|&d| (d - 2.0).abs() < 1e-6),
        "a fronto-parallel wall has constant depth"
    );
    assert!(view.labels.iter().all(|&l| l == 1), "all wall");
    assert!(view.instances.iter().all(|&i| i == 4), "the wall at x = +2");

    // Looking down into a corner: every pixel's depth is the nearest of the six planes.
    let pose = look_along(Vector3::new(0.3, -0.2, 1.2), Vector3::new(1.0, 0.8, -0.9));
    let view = scene.render_at(0, &pose).unwrap();
    let k = view.intrinsics;
    let (o, r) = (pose.translation.vector, pose.rotation);
    let mut labels_seen = std::collections::BTreeSet::new();
    for v in 0..k.height {
        for u in 0..k.width {
            let d = r * Vector3::new(
                (f64::from(u) - k.cx) / k.fx,
                (f64::from(v) - k.cy) / k.fy,
                1.0,
            );
            let mut expected = f64::INFINITY;
            for axis in 0..3 {
                let (lo, hi) = if axis == 2 { (0.0, 3.0) } else { (-2.0, 2.0) };
                let plane = if d[axis] > 0.0 { hi } else { lo };
                if d[axis] != 0.0 {
                    expected = expected.min((plane - o[axis]) / d[axis]);
                }
            }
            let depth = f64::from(view.depth.get(u, v).unwrap());
            assert!(
                (depth - expected).abs() < 1e-5 * expected,
                "({u}, {v}): {depth} vs {expected}"
            );
            labels_seen.insert(view.label(u, v).unwrap());
        }
    }
    assert_eq!(
        labels_seen.into_iter().collect::<Vec<_>>(),
        vec![1, 2],
        "walls and floor"
    );
    // The camera must be inside the room.
    let outside = look_along(Vector3::new(5.0, 0.0, 1.0), Vector3::x());
    let err = scene.render_at(0, &outside).unwrap_err().to_string();
    assert!(err.contains("inside the room"), "{err}");
}

/// Bilinear interpolation of `f` at continuous pixel `(u, v)`, or `None` when a neighbour is
/// outside the image.
fn bilinear(k: &Intrinsics, u: f64, v: f64, f: impl Fn(u32, u32) -> Option<f64>) -> Option<f64> {
    let (u0, v0) = (u.floor(), v.floor());
    if u0 < 0.0 || v0 < 0.0 || u0 + 1.0 >= f64::from(k.width) || v0 + 1.0 >= f64::from(k.height) {
        return None;
    }
    let (a, b) = (u - u0, v - v0);
    let (u0, v0) = (u0 as u32, v0 as u32);
    let top = f(u0, v0)? * (1.0 - a) + f(u0 + 1, v0)? * a;
    let bottom = f(u0, v0 + 1)? * (1.0 - a) + f(u0 + 1, v0 + 1)? * a;
    Some(top * (1.0 - b) + bottom * b)
}

#[test]
fn views_agree_on_depth_and_colour_where_both_see_a_surface() {
    let scene = SyntheticScene::new(&config(0, 60, 320, 240)).unwrap();
    for (i, j) in [(10, 25), (40, 52)] {
        let (a, b) = (scene.render(i).unwrap(), scene.render(j).unwrap());
        let k = a.intrinsics;
        let b_from_world = b.pose.inverse();
        let (mut compared, mut within_mm, mut colour_diff) = (0usize, 0usize, 0.0);
        let mut errors = Vec::new();
        for v in (0..k.height).step_by(2) {
            for u in (0..k.width).step_by(2) {
                let z = f64::from(a.depth.get(u, v).unwrap());
                let world = a.pose * k.back_project(f64::from(u), f64::from(v), z);
                let p = b_from_world * world;
                let Some((ub, vb)) = k.project(&p) else {
                    continue;
                };
                let (u0, v0) = (ub.floor(), vb.floor());
                if u0 < 0.0
                    || v0 < 0.0
                    || u0 + 1.0 >= f64::from(k.width)
                    || v0 + 1.0 >= f64::from(k.height)
                {
                    continue;
                }
                // Only inside one surface of one object (inverse depth is then bilinear exact on
                // planes), and not occluded in the other view.
                let instance = |uu: u32, vv: u32| b.instances[(vv * k.width + uu) as usize];
                let (u0, v0) = (u0 as u32, v0 as u32);
                let same = [(u0 + 1, v0), (u0, v0 + 1), (u0 + 1, v0 + 1)]
                    .iter()
                    .all(|&(uu, vv)| instance(uu, vv) == instance(u0, v0));
                let source_instance = a.instances[(v * k.width + u) as usize];
                if !same || instance(u0, v0) != source_instance {
                    continue;
                }
                let inverse = bilinear(&k, ub, vb, |uu, vv| {
                    b.depth.get(uu, vv).map(|d| 1.0 / f64::from(d))
                })
                .unwrap();
                let error = (1.0 / inverse - p.z).abs();
                compared += 1;
                if error < 1e-3 {
                    within_mm += 1;
                }
                errors.push(error);
                for c in 0..3 {
                    let other = bilinear(&k, ub, vb, |uu, vv| {
                        b.colour.get(uu, vv).map(|rgb| f64::from(rgb[c]))
                    })
                    .unwrap();
                    colour_diff += (other - f64::from(a.colour.get(u, v).unwrap()[c])).abs();
                }
            }
        }
        errors.sort_by(f64::total_cmp);
        let median = errors[errors.len() / 2];
        let share = within_mm as f64 / compared as f64;
        let mean_colour = colour_diff / (3.0 * compared as f64);
        eprintln!(
            "frames {i}->{j}: {compared} pixels, {:.2}% within 1 mm, median {median:.2e} m, mean |Δcolour| {mean_colour:.2}",
            100.0 * share
        );
        assert!(compared > 5000, "{compared}");
        assert!(median < 1e-4, "median depth error {median}");
        assert!(share > 0.97, "{share}");
        assert!(mean_colour < 3.0, "mean colour difference {mean_colour}");
    }
}

#[test]
fn every_pixel_has_depth_inside_the_room_and_labels_cover_every_object() {
    // One orbit takes at most 440 frames.
    let scene = SyntheticScene::new(&config(0, 450, 160, 120)).unwrap();
    let (lo, hi) = scene.room();
    let diagonal = (hi - lo).norm() as f32;
    let known: Vec<u16> = SYNTHETIC_LABELS.iter().map(|l| l.id).collect();
    let mut pixels_per_instance = vec![0usize; scene.objects().len() + 1];
    let mut medians = Vec::new();
    let mut nearest = f32::INFINITY;
    for i in (0..450).step_by(6) {
        let view = scene.render(i).unwrap();
        assert_eq!(view.depth.valid_count(), 160 * 120, "frame {i} has holes");
        assert!(view.depth.as_raw().iter().all(|&d| d < diagonal));
        assert!(view.labels.iter().all(|l| *l != 0 && known.contains(l)));
        for &instance in &view.instances {
            pixels_per_instance[usize::from(instance)] += 1;
        }
        let mut depths = view.depth.as_raw().to_vec();
        depths.sort_by(f32::total_cmp);
        medians.push(depths[depths.len() / 2]);
        nearest = nearest.min(depths[0]);
        // The camera stays inside the room.
        let t = view.pose.translation.vector;
        assert!(
            (0..3).all(|k| t[k] > lo[k] + 0.3 && t[k] < hi[k] - 0.3),
            "{t}"
        );
    }
    assert_eq!(pixels_per_instance[0], 0);
    for object in scene.objects() {
        let seen = pixels_per_instance[usize::from(object.instance)];
        assert!(
            seen >= 20,
            "{} (instance {}) covers only {seen} pixels over the path",
            object.name,
            object.instance
        );
    }
    assert!(nearest > 0.35, "nearest depth {nearest}");
    assert!(
        medians.iter().all(|m| (0.5..4.0).contains(m)),
        "median depths {medians:?}"
    );
    let names: Vec<&str> = scene.objects().iter().map(|o| o.name).collect();
    for name in [
        "wall", "floor", "ceiling", "table", "chair", "sofa", "cabinet", "lamp",
    ] {
        assert!(names.contains(&name), "no {name} in {names:?}");
    }
}

#[test]
fn texture_has_gradients_at_several_scales() {
    let scene = SyntheticScene::new(&config(0, 300, 640, 480)).unwrap();
    for i in [0, 100, 200] {
        let view = scene.render(i).unwrap();
        // Mean |∇I| of the grey image at full resolution and on 4x4 block averages.
        for block in [1u32, 4] {
            let (w, h) = (640 / block, 480 / block);
            let mut img = vec![0.0; (w * h) as usize];
            for y in 0..h {
                for x in 0..w {
                    let mut sum = 0.0;
                    for dy in 0..block {
                        for dx in 0..block {
                            sum += grey(&view, x * block + dx, y * block + dy);
                        }
                    }
                    img[(y * w + x) as usize] = sum / f64::from(block * block);
                }
            }
            let mut total = 0.0;
            for y in 0..h - 1 {
                for x in 0..w - 1 {
                    let c = img[(y * w + x) as usize];
                    total += (img[(y * w + x + 1) as usize] - c).abs()
                        + (img[((y + 1) * w + x) as usize] - c).abs();
                }
            }
            let mean = total / f64::from((w - 1) * (h - 1));
            eprintln!("frame {i}, block {block}: mean |grad I| = {mean:.2}");
            assert!(
                mean > 1.0 * f64::from(block).sqrt(),
                "frame {i} block {block}: {mean}"
            );
        }
    }
}

#[test]
fn surface_points_carry_the_labels_and_colours_the_camera_sees() {
    let scene = SyntheticScene::new(&config(0, 300, 320, 240)).unwrap();
    let points = scene.surface_points(0.02).unwrap();
    assert!(points.len() > 50_000, "{}", points.len());
    let (lo, hi) = scene.room();
    for p in &points {
        assert!((0..3).all(|k| p.position[k] >= lo[k] - 1e-9 && p.position[k] <= hi[k] + 1e-9));
        assert!((p.normal.norm() - 1.0).abs() < 1e-9);
        if p.label == 2 {
            assert_eq!(p.position.z, 0.0, "floor points lie on the floor");
        }
    }
    for object in scene.objects() {
        assert!(
            points.iter().any(|p| p.instance == object.instance),
            "{} has no surface points",
            object.name
        );
    }
    // Points the camera sees (within 2 mm of the rendered depth) have the pixel's label and colour.
    let view = scene.render(30).unwrap();
    let k = view.intrinsics;
    let from_world = view.pose.inverse();
    let (mut seen, mut same_label, mut colour_diff) = (0usize, 0usize, 0.0);
    for p in &points {
        let c = from_world * p.position;
        let Some((u, v)) = k.project(&c) else {
            continue;
        };
        let (u, v) = (u.round(), v.round());
        if u < 0.0 || v < 0.0 || u >= f64::from(k.width) || v >= f64::from(k.height) {
            continue;
        }
        let (u, v) = (u as u32, v as u32);
        let depth = f64::from(view.depth.get(u, v).unwrap());
        // Facing the camera, and not hidden.
        if p.normal
            .dot(&(view.pose.translation.vector - p.position.coords))
            <= 0.0
            || (depth - c.z).abs() > 0.01
        {
            continue;
        }
        seen += 1;
        if view.label(u, v) == Some(p.label) {
            same_label += 1;
        }
        let rgb = view.colour.get(u, v).unwrap();
        colour_diff += (0..3)
            .map(|i| (f64::from(rgb[i]) - f64::from(p.colour[i])).abs())
            .sum::<f64>()
            / 3.0;
    }
    let mean_colour = colour_diff / seen as f64;
    eprintln!(
        "{seen} visible points, {same_label} with the pixel's label, mean |Δcolour| {mean_colour:.2}"
    );
    assert!(seen > 2000, "{seen}");
    assert!(same_label as f64 > 0.97 * seen as f64);
    assert!(mean_colour < 8.0, "{mean_colour}");
    assert!(scene.surface_points(0.0).is_err());
    assert!(scene.surface_points(f64::NAN).is_err());
}

#[test]
fn a_scene_written_to_disk_reads_back_through_the_icl_reader() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = SyntheticScene::new(&config(3, 5, 160, 120)).unwrap();
    write_to_disk(&scene, tmp.path()).unwrap();
    assert_eq!(detect_kind(tmp.path()).unwrap(), "icl");
    let mut source = open(&DatasetConfig::default(), tmp.path()).unwrap();
    assert_eq!(source.len(), 5);
    assert!(source.has_poses());
    assert_eq!(source.intrinsics(), scene.intrinsics());
    for i in 0..5 {
        let frame = source.frame(i).unwrap();
        let view = scene.render(i).unwrap();
        assert_eq!(
            frame.colour, view.colour,
            "frame {i}: PNG colour is lossless"
        );
        for (read, exact) in frame.depth.as_raw().iter().zip(view.depth.as_raw()) {
            assert!((read - exact).abs() <= 0.0005 + 1e-6, "{read} vs {exact}");
        }
        let pose = frame.pose.unwrap();
        assert!((pose.translation.vector - view.pose.translation.vector).norm() < 1e-12);
        assert!(pose.rotation.angle_to(&view.pose.rotation) < 1e-9);
        let labels = image::open(tmp.path().join(format!("label/{i:06}.png")))
            .unwrap()
            .into_luma16();
        assert_eq!(labels.into_raw(), view.labels);
        // The ICL reader picks up label/ and labels.json: the frame carries the same labels.
        let read = frame
            .labels
            .as_ref()
            .expect("a labelled folder gives labelled frames");
        assert_eq!(read.ids(), view.labels.as_slice());
        assert_eq!(read.names().name(5), Some("chair"));
    }
    std::fs::remove_file(tmp.path().join("label/000003.png")).unwrap();
    let err = open(&DatasetConfig::default(), tmp.path())
        .err()
        .expect("a missing label image is refused")
        .to_string();
    assert!(
        err.contains("000003.png") && err.contains("labels.json"),
        "{err}"
    );
    let labels: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("labels.json")).unwrap())
            .unwrap();
    assert_eq!(labels["1"], "wall");
    assert_eq!(labels["22"], "ceiling");
    assert_eq!(labels.as_object().unwrap().len(), SYNTHETIC_LABELS.len());
    let description: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("scene.json")).unwrap())
            .unwrap();
    assert_eq!(description["config"]["seed"], 3);
    assert_eq!(
        description["objects"].as_array().unwrap().len(),
        scene.objects().len()
    );
}

#[test]
fn kind_synthetic_opens_from_a_config_without_a_folder() {
    let config = Config::from_toml(
        "[dataset]\nkind = \"synthetic\"\nstride = 4\n\n[dataset.synthetic]\nseed = 2\n\
         frames = 10\nwidth = 64\nheight = 48\n",
    )
    .unwrap();
    let mut source = open(&config.dataset, Path::new("/does/not/exist")).unwrap();
    assert_eq!(source.len(), 3, "frames 0, 4 and 8");
    assert!(source.has_poses());
    assert!(source.describe().contains("synthetic scene (seed 2"));
    let frame = source.frame(2).unwrap();
    let scene = SyntheticScene::new(&SyntheticConfig {
        seed: 2,
        frames: 10,
        width: 64,
        height: 48,
        ..SyntheticConfig::default()
    })
    .unwrap();
    assert_eq!(frame.index, 2);
    assert_eq!(frame.timestamp, 8.0 / SYNTHETIC_FRAME_RATE);
    assert_eq!(frame.pose.unwrap(), scene.pose(8).unwrap());
    assert_eq!(frame.colour, scene.render(8).unwrap().colour);
    let labels = frame
        .labels
        .as_ref()
        .expect("synthetic frames are labelled");
    assert_eq!(labels.ids(), scene.render(8).unwrap().labels.as_slice());
    assert_eq!(labels.names().name(1), Some("wall"));
    let err = source.frame(3).unwrap_err().to_string();
    assert!(err.contains("frame 3 requested"), "{err}");

    // Without [dataset.synthetic] every default applies.
    let reader = SyntheticReader::open(&DatasetConfig {
        kind: "synthetic".into(),
        max_frames: Some(4),
        ..DatasetConfig::default()
    })
    .unwrap();
    assert_eq!(reader.len(), 4);
    assert_eq!(reader.intrinsics().width, 640);
    assert_eq!(reader.scene().len(), 450);
    let k = reader.intrinsics();
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (525.0, 525.0, 319.5, 239.5));
}

#[test]
fn bad_values_are_refused_naming_the_key() {
    let cases: [(SyntheticConfig, &str); 6] = [
        (
            config(0, 0, 64, 48),
            "[dataset.synthetic] frames: must be at least 1",
        ),
        (
            config(0, 5, 0, 48),
            "[dataset.synthetic] width: must be between 1 and",
        ),
        (
            config(0, 5, 64, 0),
            "[dataset.synthetic] height: must be between 1 and",
        ),
        (
            SyntheticConfig {
                room: [1.0, 4.0, 3.0],
                ..config(0, 5, 64, 48)
            },
            "[dataset.synthetic] room: each size",
        ),
        (
            SyntheticConfig {
                room: [4.0, f64::NAN, 3.0],
                ..config(0, 5, 64, 48)
            },
            "[dataset.synthetic] room:",
        ),
        (
            SyntheticConfig {
                objects: 5000,
                ..config(0, 5, 64, 48)
            },
            "[dataset.synthetic] objects: must be at most 1000",
        ),
    ];
    for (cfg, expected) in cases {
        let err = SyntheticScene::new(&cfg).unwrap_err().to_string();
        assert!(err.starts_with(expected), "{err}");
        // The same through the dataset entry point.
        let dataset = cfg.dataset_config().unwrap();
        let err = open(&dataset, Path::new(".")).err().unwrap().to_string();
        assert!(err.starts_with(expected), "{err}");
    }
    let with = |dataset: DatasetConfig| {
        open(
            &DatasetConfig {
                kind: "synthetic".into(),
                ..dataset
            },
            Path::new("."),
        )
        .err()
        .unwrap()
        .to_string()
    };
    let err = with(DatasetConfig {
        depth_scale: Some(1000.0),
        ..DatasetConfig::default()
    });
    assert!(
        err.contains("[dataset] depth_scale does not apply"),
        "{err}"
    );
    let err = with(DatasetConfig {
        stride: Some(0),
        ..DatasetConfig::default()
    });
    assert!(err.contains("stride must be at least 1"), "{err}");
    // [dataset.synthetic] with another kind is a mistake, not silently ignored.
    let tmp = tempfile::tempdir().unwrap();
    let err = open(
        &DatasetConfig::named("icl")
            .with_param("synthetic", SyntheticConfig::default())
            .unwrap(),
        tmp.path(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(
        err.starts_with("[dataset] kind = \"icl\": unknown field `synthetic`"),
        "{err}"
    );
    let scene = SyntheticScene::new(&config(0, 5, 64, 48)).unwrap();
    let err = scene.render(5).unwrap_err().to_string();
    assert_eq!(
        err,
        "synthetic scene: frame 5 requested but the scene has 5 frames"
    );
}

#[test]
fn kinect_noise_is_deterministic_and_close_to_the_truth() {
    let exact = SyntheticScene::new(&config(1, 10, 320, 240)).unwrap();
    let noisy_config = SyntheticConfig {
        noise: SyntheticNoise::Kinect,
        ..config(1, 10, 320, 240)
    };
    let noisy = SyntheticScene::new(&noisy_config).unwrap();
    let again = SyntheticScene::new(&noisy_config).unwrap();
    let (e, n) = (exact.render(4).unwrap(), noisy.render(4).unwrap());
    assert_eq!(n.depth.as_raw(), again.render(4).unwrap().depth.as_raw());
    assert_eq!(n.colour, e.colour, "noise only touches depth");
    assert_eq!(n.labels, e.labels);
    let other_frame = noisy.render(5).unwrap();
    assert_ne!(other_frame.depth.as_raw(), n.depth.as_raw());
    let (mut valid, mut differ, mut sum_sq) = (0usize, 0usize, 0.0);
    for (d, t) in n.depth.as_raw().iter().zip(e.depth.as_raw()) {
        if *d > 0.0 {
            valid += 1;
            if d != t {
                differ += 1;
            }
            sum_sq += f64::from(d - t).powi(2);
            assert!((d - t).abs() < 0.02 + 0.02 * t * t, "{d} vs {t}");
        }
    }
    let rms = (sum_sq / valid as f64).sqrt();
    eprintln!("{valid} valid of {}, rms {rms:.4} m", 320 * 240);
    assert!(valid > 320 * 240 * 9 / 10 && valid < 320 * 240, "{valid}");
    assert!(differ > valid / 2);
    assert!(rms > 0.001 && rms < 0.02, "{rms}");
}

/// CPU time of this process in milliseconds (Linux `/proc`, 10 ms resolution), if available.
fn cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit(')').next()?.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks * 10.0)
}

#[test]
#[ignore = "timing: run alone with `cargo test --release -p vlem-datasets --test synthetic -- --ignored`"]
fn render_time_per_vga_frame() {
    let scene = SyntheticScene::new(&SyntheticConfig::default()).unwrap();
    let _ = scene.render(0).unwrap();
    let n: u32 = 20;
    let cpu_start = cpu_ms().unwrap_or(0.0);
    let start = std::time::Instant::now();
    for i in 0..n {
        std::hint::black_box(scene.render(i as usize * 15).unwrap());
    }
    let per_frame = start.elapsed() / n;
    let cpu = cpu_ms().map_or(String::new(), |end| {
        format!(", {:.1} ms CPU", (end - cpu_start) / f64::from(n))
    });
    eprintln!(
        "640x480: {:.1} ms per frame{cpu} on {} threads",
        per_frame.as_secs_f64() * 1e3,
        rayon::current_num_threads()
    );
    // Generous: the test machine may be busy; the design target is under 20 ms on 2 cores.
    assert!(per_frame.as_secs_f64() < 1.0, "{per_frame:?}");
}

#[test]
fn back_projected_room_pixels_lie_on_their_surfaces() {
    // Checks the conventions end to end: depth is camera-frame z, poses are camera-to-world with
    // x right, y down, z forward, and instance ids 1..=6 are floor, ceiling and the four walls.
    let scene = SyntheticScene::new(&config(4, 300, 160, 120)).unwrap();
    let (lo, hi) = scene.room();
    let mut checked = [0usize; 6];
    for i in (0..300).step_by(25) {
        let view = scene.render(i).unwrap();
        let k = view.intrinsics;
        for v in 0..k.height {
            for u in 0..k.width {
                let instance = view.instances[(v * k.width + u) as usize];
                if instance > 6 {
                    continue;
                }
                let z = f64::from(view.depth.get(u, v).unwrap());
                let p = view.pose * k.back_project(f64::from(u), f64::from(v), z);
                let (axis, value) = match instance {
                    1 => (2, lo.z),
                    2 => (2, hi.z),
                    3 => (0, lo.x),
                    4 => (0, hi.x),
                    5 => (1, lo.y),
                    _ => (1, hi.y),
                };
                assert!(
                    (p[axis] - value).abs() < 1e-5,
                    "frame {i} ({u}, {v}): instance {instance} at {p}"
                );
                checked[usize::from(instance) - 1] += 1;
            }
        }
    }
    assert!(checked.iter().all(|&n| n > 100), "{checked:?}");
}
