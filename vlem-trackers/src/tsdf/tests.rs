//! Tests of the TSDF volume on synthetic scenes with known geometry.

use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use rustc_hash::FxHashMap;
use vlem_core::{DepthImage, Intrinsics, Pose, RgbImage};

use super::block::{BLOCK_RES, Block, voxel_index};
use super::mc_table::{EDGE_CORNERS, TABLE, case_loops};
use super::*;

fn camera() -> Intrinsics {
    Intrinsics::new(320, 240, 262.5, 262.5, 159.5, 119.5).unwrap()
}

fn volume() -> TsdfVolume {
    TsdfVolume::new(TsdfConfig::default()).unwrap()
}

fn voxel() -> f32 {
    TsdfConfig::default().voxel_size
}

/// A pose looking from `eye` towards `target`, y down as far as possible.
fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
    let eye = Point3::from(eye);
    let target = Point3::from(target);
    let z = (target - eye).normalize();
    let x = z.cross(&Vector3::new(0.0, -1.0, 0.0)).normalize();
    let y = z.cross(&x);
    let r = nalgebra::Matrix3::from_columns(&[x, y, z]);
    let rot = UnitQuaternion::from_matrix(&r);
    Pose::from_parts(Translation3::from(eye.coords), rot)
}

/// A surface the rays of a camera can hit: the distance along a unit ray, if any.
trait Surface {
    fn hit(&self, origin: Vector3<f64>, dir: Vector3<f64>) -> Option<f64>;
}

/// The plane `n . x = d`.
struct Plane {
    n: Vector3<f64>,
    d: f64,
}

impl Surface for Plane {
    fn hit(&self, o: Vector3<f64>, r: Vector3<f64>) -> Option<f64> {
        let denom = self.n.dot(&r);
        if denom.abs() < 1e-9 {
            return None;
        }
        let t = (self.d - self.n.dot(&o)) / denom;
        (t > 0.0).then_some(t)
    }
}

struct Sphere {
    c: Vector3<f64>,
    r: f64,
}

impl Surface for Sphere {
    fn hit(&self, o: Vector3<f64>, dir: Vector3<f64>) -> Option<f64> {
        let oc = o - self.c;
        let b = oc.dot(&dir);
        let c = oc.dot(&oc) - self.r * self.r;
        let disc = b * b - c;
        if disc < 0.0 {
            return None;
        }
        let t = -b - disc.sqrt();
        (t > 0.0).then_some(t)
    }
}

/// The analytic depth image (camera z) of `surface` seen from `pose`; 0 where nothing is hit.
fn render(surface: &dyn Surface, k: &Intrinsics, pose: &Pose) -> DepthImage {
    let mut data = vec![0.0_f32; (k.width * k.height) as usize];
    let o = pose.translation.vector;
    for v in 0..k.height {
        for u in 0..k.width {
            let ray_c = Vector3::new(
                (f64::from(u) - k.cx) / k.fx,
                (f64::from(v) - k.cy) / k.fy,
                1.0,
            );
            let len = ray_c.norm();
            let dir = pose.rotation * (ray_c / len);
            if let Some(t) = surface.hit(o, dir) {
                data[(v * k.width + u) as usize] = (t / len) as f32;
            }
        }
    }
    DepthImage::new(k.width, k.height, data).unwrap()
}

/// Max and mean |raycast - truth| over pixels valid in both, and how many there are.
fn depth_errors(cast: &DepthImage, truth: &DepthImage) -> (f32, f32, usize) {
    let mut max = 0.0_f32;
    let mut sum = 0.0_f64;
    let mut n = 0;
    for (&a, &b) in cast.as_raw().iter().zip(truth.as_raw()) {
        if a > 0.0 && b > 0.0 {
            let e = (a - b).abs();
            max = max.max(e);
            sum += f64::from(e);
            n += 1;
        }
    }
    (max, (sum / n.max(1) as f64) as f32, n)
}

/// The `q`-quantile of |raycast - truth| over pixels valid in both.
fn percentile_error(cast: &DepthImage, truth: &DepthImage, q: f64) -> f32 {
    let mut errors: Vec<f32> = cast
        .as_raw()
        .iter()
        .zip(truth.as_raw())
        .filter(|(a, b)| **a > 0.0 && **b > 0.0)
        .map(|(a, b)| (a - b).abs())
        .collect();
    errors.sort_by(f32::total_cmp);
    errors[((errors.len() - 1) as f64 * q) as usize]
}

fn tilted_plane() -> Plane {
    // Tilted 30 degrees about x, through (0, 0, 1.5).
    let n = Vector3::new(0.0, 0.5_f64, -(3.0_f64.sqrt()) / 2.0);
    Plane {
        n,
        d: n.dot(&Vector3::new(0.0, 0.0, 1.5)),
    }
}

/// The tilted plane seen once from the identity pose: the camera, the depth and colour fused,
/// and the volume.
fn fused_tilted_plane() -> (Intrinsics, DepthImage, RgbImage, TsdfVolume) {
    let k = camera();
    let depth = render(&tilted_plane(), &k, &Pose::identity());
    let colour = RgbImage::filled(k.width, k.height, [200, 100, 50]);
    let mut tsdf = volume();
    tsdf.integrate(&depth, &colour, &k, &Pose::identity());
    (k, depth, colour, tsdf)
}

#[test]
fn raycast_reproduces_a_plane_at_the_integration_pose_and_a_shifted_pose() {
    let (k, depth, _, tsdf) = fused_tilted_plane();
    let plane = tilted_plane();
    let pose = Pose::identity();
    assert_eq!(tsdf.frame_count(), 1);

    let cast = tsdf.raycast(&k, &pose);
    let (max, mean, n) = depth_errors(&cast.depth, &depth);
    let p99 = percentile_error(&cast.depth, &depth, 0.99);
    println!("same pose: max {max} m, p99 {p99} m, mean {mean} m over {n} px");
    assert!(n as f32 > 0.97 * depth.valid_count() as f32, "{n} hits");
    // Fusion reads the depth at the nearest pixel, which on this tilted plane is up to half a
    // pixel (about 2 mm of depth here) off: the error floor of a projective TSDF.
    assert!(mean < 0.2 * voxel(), "mean error {mean}");
    assert!(p99 < 0.5 * voxel(), "p99 error {p99}");
    // The worst pixels are image corners, whose cells are partly outside the view.
    assert!(max < 1.5 * voxel(), "max error {max}");

    // 4 cm sideways, 3 cm closer, 3 degrees of yaw.
    let shifted = Pose::from_parts(
        Translation3::new(0.04, -0.01, 0.03),
        UnitQuaternion::from_euler_angles(0.01, 0.05, 0.0),
    );
    let truth = render(&plane, &k, &shifted);
    let cast = tsdf.raycast(&k, &shifted);
    let (max, mean, n) = depth_errors(&cast.depth, &truth);
    let p99 = percentile_error(&cast.depth, &truth, 0.99);
    println!("shifted pose: max {max} m, p99 {p99} m, mean {mean} m over {n} px");
    assert!(n as f32 > 0.85 * truth.valid_count() as f32, "{n} hits");
    assert!(mean < 0.2 * voxel(), "mean error {mean}");
    assert!(p99 < 0.5 * voxel(), "p99 error {p99}");
    // The worst pixels look at the edge of what the first view saw.
    assert!(max < 1.5 * voxel(), "max error {max}");
    // Nothing is hit where the model has no surface.
    for (&c, &t) in cast.depth.as_raw().iter().zip(truth.as_raw()) {
        assert!(c == 0.0 || t > 0.0);
    }
}

/// Casting near the depth just fused: on a static scene it reproduces the surface as well as
/// the full march; where the hint has no depth it is the full march, to the bit; a wrong-sized
/// hint is ignored; and where a surface moved away it shows the surface measured now.
#[test]
fn raycast_near_depth_matches_the_full_cast_and_follows_what_was_just_measured() {
    let (k, depth, colour, tsdf) = fused_tilted_plane();
    let pose = Pose::identity();
    let options = RaycastOptions::default();
    let full = tsdf.raycast_with(&k, &pose, &options);
    let near = tsdf.raycast_near_depth(&k, &pose, &options, &depth);
    let (max, mean, n) = depth_errors(&near.depth, &depth);
    assert!(n as f32 > 0.97 * depth.valid_count() as f32, "{n} hits");
    assert!(mean < 0.2 * voxel(), "mean error {mean}");
    assert!(max < 1.5 * voxel(), "max error {max}");
    // The same pixels are hit with the same depths, up to where the marches sample, but for
    // some in the two outermost columns, whose cells are partly outside the view (there,
    // whether a march meets the surface depends on where it samples).
    let inner = |i: usize| (2..k.width - 2).contains(&(i as u32 % k.width));
    let mut differences: Vec<f32> = (0..full.depth.as_raw().len())
        .filter(|&i| inner(i))
        .map(|i| (full.depth.as_raw()[i] - near.depth.as_raw()[i]).abs())
        .collect();
    differences.sort_by(f32::total_cmp);
    let quantile = |q: f64| differences[((differences.len() - 1) as f64 * q) as usize];
    println!(
        "near against full: median {} m, p99 {} m, max {} m",
        quantile(0.5),
        quantile(0.99),
        quantile(1.0)
    );
    assert!(quantile(0.99) < 0.25 * voxel(), "p99 {}", quantile(0.99));
    // The full cast itself is within 1.5 voxels of the truth (see above).
    assert!(quantile(1.0) < 1.5 * voxel(), "max {}", quantile(1.0));
    let one_only = (0..full.depth.as_raw().len())
        .filter(|&i| (full.depth.as_raw()[i] > 0.0) != (near.depth.as_raw()[i] > 0.0))
        .collect::<Vec<_>>();
    assert!(one_only.iter().all(|&i| !inner(i)), "{one_only:?}");
    assert!(one_only.len() < 50, "{} pixels", one_only.len());

    let nothing = DepthImage::new(k.width, k.height, vec![0.0; (k.width * k.height) as usize]);
    assert_eq!(
        tsdf.raycast_near_depth(&k, &pose, &options, &nothing.unwrap()),
        full
    );
    let small = DepthImage::new(4, 4, vec![1.0; 16]).unwrap();
    assert_eq!(tsdf.raycast_near_depth(&k, &pose, &options, &small), full);

    // A wall 1 m away, seen ten times, then gone: three frames see a wall 1.6 m away instead
    // (a surface counts once three frames have seen it).
    let wall = |d: f64| Plane {
        n: Vector3::new(0.0, 0.0, 1.0),
        d,
    };
    let mut tsdf = volume();
    let before = render(&wall(1.0), &k, &pose);
    for _ in 0..10 {
        tsdf.integrate(&before, &colour, &k, &pose);
    }
    let after = render(&wall(1.6), &k, &pose);
    for _ in 0..3 {
        tsdf.integrate(&after, &colour, &k, &pose);
    }
    let centre = (k.height / 2 * k.width + k.width / 2) as usize;
    // Three observations of free space do not outweigh ten of the wall: the full march still
    // meets it (a little further back), the cast near the new depth meets the wall seen now.
    let full = tsdf.raycast_with(&k, &pose, &options).depth.as_raw()[centre];
    assert!(full > 0.99 && full < 1.1, "{full}");
    let near = tsdf.raycast_near_depth(&k, &pose, &options, &after);
    let near = near.depth.as_raw()[centre];
    assert!((near - 1.6).abs() < voxel(), "{near}");
}

#[test]
fn raycast_reproduces_a_sphere_fused_from_several_views() {
    let k = camera();
    let sphere = Sphere {
        c: Vector3::new(0.0, 0.0, 0.0),
        r: 0.3,
    };
    let mut tsdf = volume();
    let colour = RgbImage::filled(k.width, k.height, [10, 20, 30]);
    let eyes = [
        [0.0, 0.0, -1.2],
        [0.5, -0.2, -1.0],
        [-0.5, 0.2, -1.0],
        [0.0, -0.6, -1.0],
    ];
    for eye in eyes {
        let pose = look_at(eye, [0.0; 3]);
        tsdf.integrate(&render(&sphere, &k, &pose), &colour, &k, &pose);
    }
    let pose = look_at([0.2, -0.1, -1.1], [0.0; 3]);
    let truth = render(&sphere, &k, &pose);
    let cast = tsdf.raycast(&k, &pose);
    let (max, mean, n) = depth_errors(&cast.depth, &truth);
    let p99 = percentile_error(&cast.depth, &truth, 0.99);
    println!("sphere: max {max} m, p99 {p99} m, mean {mean} m over {n} px");
    assert!(n as f32 > 0.9 * truth.valid_count() as f32, "{n} hits");
    assert!(mean < 0.25 * voxel(), "mean error {mean}");
    assert!(p99 < 2.0 * voxel(), "p99 error {p99}");
    // Near the rim of a view, projective distances mark space beside the sphere as behind its
    // surface; fused with other views this bulges the surface out by up to the truncation
    // distance (Open3D's fusion does the same).
    assert!(max < TsdfConfig::default().sdf_trunc(), "max error {max}");
}

#[test]
fn raycast_normals_follow_the_surface() {
    let k = camera();
    let plane = tilted_plane();
    let pose = Pose::identity();
    let mut tsdf = volume();
    let colour = RgbImage::filled(k.width, k.height, [0, 0, 0]);
    tsdf.integrate(&render(&plane, &k, &pose), &colour, &k, &pose);
    let options = RaycastOptions {
        normals: true,
        ..RaycastOptions::default()
    };
    let cast = tsdf.raycast_with(&k, &pose, &options);
    let normals = cast.normals.clone().unwrap();
    // The plane's normal facing the camera (free space), in the camera frame = world frame.
    let expect = plane.n.map(|x| x as f32);
    let mut cosines = Vec::new();
    for (n, &d) in normals.iter().zip(cast.depth.as_raw()) {
        if d > 0.0 && *n != [0.0; 3] {
            let length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((length - 1.0).abs() < 1e-4);
            cosines.push(n[0] * expect[0] + n[1] * expect[1] + n[2] * expect[2]);
        } else if d == 0.0 {
            assert_eq!(*n, [0.0; 3]);
        }
    }
    cosines.sort_by(f32::total_cmp);
    let (worst, p10, median) = (
        cosines[0],
        cosines[cosines.len() / 10],
        cosines[cosines.len() / 2],
    );
    println!(
        "normal cosines: worst {worst}, 10th percentile {p10}, median {median}; {} of {} hits \
         have a normal",
        cosines.len(),
        cast.hit_count()
    );
    // The TSDF carries the nearest-pixel quantisation of fusion (about 2 mm here), which tilts
    // individual normals by a few degrees.
    assert!(median > 0.995, "{median}");
    assert!(p10 > 0.98, "{p10}");
    assert!(worst > 0.9, "{worst}");
    // Only hits whose stencil reaches unobserved voxels (at the image border) go without.
    assert!(cosines.len() as f32 > 0.95 * cast.hit_count() as f32);
    assert!(tsdf.raycast(&k, &pose).normals.is_none());
}

#[test]
fn rays_along_the_axes_are_cast() {
    // An integer principal point: the centre column and row have rays with zero x or y
    // components, which must not stall the march in empty space.
    let k = Intrinsics::new(64, 48, 500.0, 500.0, 32.0, 24.0).unwrap();
    let plane = Plane {
        n: Vector3::new(0.0, 0.0, -1.0),
        d: -2.0,
    };
    let pose = Pose::identity();
    let depth = render(&plane, &k, &pose);
    let mut tsdf = volume();
    tsdf.integrate(&depth, &RgbImage::filled(64, 48, [5; 3]), &k, &pose);
    // A small object near the camera widens the tiles' depth ranges, so rays cross empty space.
    let mut near = vec![0.0_f32; 64 * 48];
    near[64 * 47] = 0.5;
    let near = DepthImage::new(64, 48, near).unwrap();
    tsdf.integrate(&near, &RgbImage::filled(64, 48, [5; 3]), &k, &pose);
    let options = RaycastOptions {
        min_weight: Some(1),
        ..RaycastOptions::default()
    };
    let cast = tsdf.raycast_with(&k, &pose, &options);
    assert_eq!(cast.hit_count(), 64 * 48);
    for (u, v) in [(32, 24), (32, 0), (0, 24), (32, 47), (63, 24)] {
        let d = cast.depth.get(u, v);
        assert!(
            d.is_some_and(|d| (d - 2.0).abs() < 1e-3),
            "({u}, {v}): {d:?}"
        );
    }
}

#[test]
fn colour_round_trips_and_averages() {
    let k = camera();
    let plane = Plane {
        n: Vector3::new(0.0, 0.0, -1.0),
        d: -1.0,
    };
    let pose = Pose::identity();
    let depth = render(&plane, &k, &pose);
    // Four flat quadrants.
    let quadrant = |u: u32, v: u32| -> [u8; 3] {
        match (u < k.width / 2, v < k.height / 2) {
            (true, true) => [255, 0, 0],
            (false, true) => [0, 255, 0],
            (true, false) => [0, 0, 255],
            (false, false) => [17, 130, 250],
        }
    };
    let mut data = Vec::new();
    for v in 0..k.height {
        for u in 0..k.width {
            data.extend(quadrant(u, v));
        }
    }
    let colour = RgbImage::new(k.width, k.height, data).unwrap();
    let mut tsdf = volume();
    tsdf.integrate(&depth, &colour, &k, &pose);
    let cast = tsdf.raycast(&k, &pose);
    let mut checked = 0;
    for v in 0..k.height {
        for u in 0..k.width {
            let near_edge = u.abs_diff(k.width / 2) < 6 || v.abs_diff(k.height / 2) < 6;
            if near_edge || cast.depth.get(u, v).is_none() {
                continue;
            }
            let got = cast.colour.get(u, v).unwrap();
            let want = quadrant(u, v);
            for (g, w) in got.iter().zip(want) {
                assert!(g.abs_diff(w) <= 1, "({u}, {v}): {got:?} vs {want:?}");
            }
            checked += 1;
        }
    }
    assert!(checked > 60_000, "{checked}");

    // A second frame of another colour: the average.
    let mut tsdf = volume();
    tsdf.integrate(
        &depth,
        &RgbImage::filled(k.width, k.height, [100, 0, 7]),
        &k,
        &pose,
    );
    tsdf.integrate(
        &depth,
        &RgbImage::filled(k.width, k.height, [202, 254, 9]),
        &k,
        &pose,
    );
    let cast = tsdf.raycast(&k, &pose);
    let c = cast.colour.get(160, 120).unwrap();
    assert_eq!(c, [151, 127, 8], "{c:?}");

    // Colour can be switched off.
    let options = RaycastOptions {
        colour: false,
        ..RaycastOptions::default()
    };
    let cast = tsdf.raycast_with(&k, &pose, &options);
    assert!(cast.hit_count() > 0);
    assert!(cast.colour.as_raw().iter().all(|&c| c == 0));
}

#[test]
fn weights_are_capped() {
    let k = camera();
    let plane = Plane {
        n: Vector3::new(0.0, 0.0, -1.0),
        d: -1.0,
    };
    let pose = Pose::identity();
    let depth = render(&plane, &k, &pose);
    let config = TsdfConfig {
        max_weight: 3.0,
        ..TsdfConfig::default()
    };
    let mut tsdf = TsdfVolume::new(config).unwrap();
    for grey in [0, 0, 0, 0, 0, 240] {
        tsdf.integrate(
            &depth,
            &RgbImage::filled(k.width, k.height, [grey; 3]),
            &k,
            &pose,
        );
    }
    let max = tsdf
        .blocks
        .iter()
        .flat_map(|b| b.weight.iter().copied())
        .max()
        .unwrap();
    assert_eq!(max, 3);
    // A moving average over the last 4 observations: 240 / 4.
    let c = tsdf.raycast(&k, &pose).colour.get(160, 120).unwrap();
    assert_eq!(c, [60; 3]);
}

/// Writes the signed distance `sdf(p)` (metres) into every voxel of the blocks whose box
/// meets `[lo, hi]`, as if observed once.
fn fill_analytic(tsdf: &mut TsdfVolume, lo: [f32; 3], hi: [f32; 3], sdf: impl Fn([f32; 3]) -> f32) {
    let vs = tsdf.config.voxel_size;
    let trunc = tsdf.config.sdf_trunc();
    let block = vs * BLOCK_RES as f32;
    let range = |a: usize| floor_i32(lo[a] / block)..=floor_i32(hi[a] / block);
    for bz in range(2) {
        for by in range(1) {
            for bx in range(0) {
                let coord = [bx, by, bz];
                let mut b = Block::boxed(coord);
                for z in 0..BLOCK_RES {
                    for y in 0..BLOCK_RES {
                        for x in 0..BLOCK_RES {
                            let p = [
                                (bx * 8 + x as i32) as f32 * vs,
                                (by * 8 + y as i32) as f32 * vs,
                                (bz * 8 + z as i32) as f32 * vs,
                            ];
                            let i = voxel_index(x, y, z);
                            b.tsdf[i] = (sdf(p) / trunc).clamp(-1.0, 1.0);
                            b.weight[i] = 1;
                            b.rgb[0][i] = (p[0] * 100.0 + 128.0) as u16 * 256;
                            b.rgb[2][i] = 65280;
                        }
                    }
                }
                tsdf.index.insert(coord, tsdf.blocks.len() as u32);
                tsdf.blocks.push(b);
                tsdf.stamps.push(0);
            }
        }
    }
}

fn sphere_volume(c: [f32; 3], r: f32) -> TsdfVolume {
    let mut tsdf = volume();
    let m = r + 0.05;
    fill_analytic(
        &mut tsdf,
        [c[0] - m, c[1] - m, c[2] - m],
        [c[0] + m, c[1] + m, c[2] + m],
        |p| ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r,
    );
    tsdf
}

#[test]
fn marching_cubes_meshes_a_sphere_closed_and_on_the_surface() {
    let (c, r) = ([0.013, -0.021, 0.5], 0.1_f32);
    let tsdf = sphere_volume(c, r);
    let mesh = tsdf.extract_mesh();
    assert!(mesh.triangles.len() > 1000, "{}", mesh.triangles.len());
    assert_eq!(mesh.vertices.len(), mesh.colours.len());
    let dist = |p: &[f32; 3]| {
        ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt()
    };
    let worst = mesh
        .vertices
        .iter()
        .map(|p| (dist(p) - r).abs())
        .fold(0.0_f32, f32::max);
    println!(
        "sphere mesh: {} vertices, {} triangles, worst radial error {worst} m",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    assert!(worst < 0.5 * voxel(), "{worst}");

    // Closed: every edge is shared by exactly two triangles, in opposite directions.
    let mut edges: FxHashMap<(u32, u32), i32> = FxHashMap::default();
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            assert_ne!(a, b, "degenerate triangle {t:?}");
            *edges.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
        }
    }
    let mut counts: FxHashMap<(u32, u32), usize> = FxHashMap::default();
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *counts.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    assert!(
        counts.values().all(|&n| n == 2),
        "open or non-manifold edges"
    );
    assert!(edges.values().all(|&s| s == 0), "inconsistent winding");
    // A sphere: V - E + F = 2.
    let euler = mesh.vertices.len() as i64 - counts.len() as i64 + mesh.triangles.len() as i64;
    assert_eq!(euler, 2);

    // Triangles face out of the sphere (into free space).
    let outward = mesh
        .triangles
        .iter()
        .filter(|t| {
            let [a, b, cc] = t.map(|i| Vector3::from(mesh.vertices[i as usize]));
            let n = (b - a).cross(&(cc - a));
            let centre = (a + b + cc) / 3.0 - Vector3::from(c);
            n.dot(&centre) > 0.0
        })
        .count();
    assert_eq!(outward, mesh.triangles.len());

    // The points are the mesh's vertices (each sign-changing edge once).
    let points = tsdf.extract_points();
    assert!(points.triangles.is_empty());
    assert_eq!(points.vertices.len(), mesh.vertices.len());
    let worst = points
        .vertices
        .iter()
        .map(|p| (dist(p) - r).abs())
        .fold(0.0_f32, f32::max);
    assert!(worst < 0.5 * voxel(), "{worst}");
}

#[test]
fn marching_cubes_on_a_fused_sphere_stays_near_the_surface() {
    let k = camera();
    let sphere = Sphere {
        c: Vector3::new(0.0, 0.0, 0.0),
        r: 0.25,
    };
    let mut tsdf = volume();
    let colour = RgbImage::filled(k.width, k.height, [90, 60, 30]);
    for (i, eye) in [
        [0.0, 0.0, -1.0],
        [1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.01],
        [0.0, 1.0, 0.01],
    ]
    .into_iter()
    .enumerate()
    {
        let pose = look_at(eye, [0.0; 3]);
        tsdf.integrate(&render(&sphere, &k, &pose), &colour, &k, &pose);
        assert_eq!(tsdf.frame_count(), i + 1);
    }
    let mesh = tsdf.extract_mesh();
    let errors: Vec<f32> = mesh
        .vertices
        .iter()
        .map(|p| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.25).abs())
        .collect();
    let within = errors.iter().filter(|&&e| e < voxel()).count();
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    println!(
        "fused sphere: {} vertices, {} within a voxel, mean error {mean}",
        errors.len(),
        within
    );
    assert!(errors.len() > 5000);
    assert!(within as f32 > 0.97 * errors.len() as f32);
    assert!(mean < 0.25 * voxel());
    assert!(
        mesh.colours
            .iter()
            .all(|c| c.iter().zip([90, 60, 30]).all(|(a, b)| a.abs_diff(b) <= 1))
    );
}

#[test]
fn case_table_is_consistent() {
    let mut most = 0;
    for mask in 0..=255_u8 {
        let inside = |c: u8| mask >> c & 1 == 1;
        let crossing: Vec<u8> = (0..12)
            .filter(|&e| {
                let [a, b] = EDGE_CORNERS[usize::from(e)];
                inside(a) != inside(b)
            })
            .collect();
        let mut seen: Vec<u8> = case_loops(mask).concat();
        assert!(case_loops(mask).iter().all(|l| l.len() >= 3), "case {mask}");
        seen.sort_unstable();
        assert_eq!(seen, crossing, "case {mask}");
        let triangles = TABLE.triangles(mask);
        let expected: usize = case_loops(mask).iter().map(|l| l.len() - 2).sum();
        assert_eq!(triangles.len(), expected);
        most = most.max(triangles.len());
        // Complementary cases cut the same edges.
        let mut a: Vec<u8> = triangles.concat();
        let mut b: Vec<u8> = TABLE.triangles(!mask).concat();
        a.sort_unstable();
        a.dedup();
        b.sort_unstable();
        b.dedup();
        assert_eq!(a, b, "case {mask}");
    }
    assert!(TABLE.triangles(0).is_empty() && TABLE.triangles(255).is_empty());
    assert_eq!(TABLE.triangles(1).len(), 1);
    println!("at most {most} triangles per cell");
    assert!(most <= 12);
}

#[test]
fn memory_grows_with_the_observed_surface_only() {
    let k = camera();
    let plane = Plane {
        n: Vector3::new(0.0, 0.0, -1.0),
        d: -1.0,
    };
    let pose = Pose::identity();
    let full = render(&plane, &k, &pose);
    // Only a 24 x 24 pixel patch (about 9 cm) has depth.
    let patch: Vec<f32> = full
        .as_raw()
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            let (u, v) = (i as u32 % k.width, i as u32 / k.width);
            if (150..174).contains(&u) && (100..124).contains(&v) {
                d
            } else {
                0.0
            }
        })
        .collect();
    let patch = DepthImage::new(k.width, k.height, patch).unwrap();
    let colour = RgbImage::filled(k.width, k.height, [1, 2, 3]);
    let mut small = volume();
    assert_eq!(small.block_count(), 0);
    let empty_memory = small.memory_bytes();
    small.integrate(&patch, &colour, &k, &pose);
    let blocks = small.block_count();
    println!(
        "patch: {blocks} blocks, {} bytes",
        small.memory_bytes() - empty_memory
    );
    // 9 cm square = 2 x 2 blocks (3 x 3 when straddling borders), 2-3 deep.
    assert!((4..=27).contains(&blocks), "{blocks}");
    assert!(small.memory_bytes() < 27 * size_of::<Block>() + 16_384);
    // Seeing the same patch again allocates nothing.
    small.integrate(&patch, &colour, &k, &pose);
    assert_eq!(small.block_count(), blocks);

    let mut big = volume();
    big.integrate(&full, &colour, &k, &pose);
    println!(
        "full frame: {} blocks, {} bytes",
        big.block_count(),
        big.memory_bytes()
    );
    // 1.22 m x 0.91 m at 1 m: ~26 x 20 blocks, 2-3 deep.
    assert!(
        (500..=2000).contains(&big.block_count()),
        "{}",
        big.block_count()
    );
    assert!(big.memory_bytes() >= big.block_count() * size_of::<Block>());
    assert!(size_of::<Block>() < 7 * 1024);
    big.clear();
    assert_eq!(big.block_count(), 0);
    assert_eq!(big.frame_count(), 0);
}

#[test]
fn invalid_depths_are_ignored() {
    let k = camera();
    let config = TsdfConfig::default();
    let n = (k.width * k.height) as usize;
    let colour = RgbImage::filled(k.width, k.height, [9, 9, 9]);
    let pose = Pose::identity();
    for bad in [
        0.0,
        -1.0,
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        config.depth_max + 0.01,
        config.depth_min * 0.5,
    ] {
        let mut tsdf = volume();
        tsdf.integrate(
            &DepthImage::new(k.width, k.height, vec![bad; n]).unwrap(),
            &colour,
            &k,
            &pose,
        );
        assert_eq!(tsdf.block_count(), 0, "depth {bad}");
        assert_eq!(tsdf.raycast(&k, &pose).hit_count(), 0);
    }
    // Half the image invalid: the model only has the valid half.
    let plane = Plane {
        n: Vector3::new(0.0, 0.0, -1.0),
        d: -1.5,
    };
    let mut depth = render(&plane, &k, &pose).as_raw().to_vec();
    for (i, d) in depth.iter_mut().enumerate() {
        if i as u32 % k.width < k.width / 2 {
            *d = [0.0, -2.0, f32::NAN, 7.0][i % 4];
        }
    }
    let depth = DepthImage::new(k.width, k.height, depth).unwrap();
    let mut tsdf = volume();
    tsdf.integrate(&depth, &colour, &k, &pose);
    let cast = tsdf.raycast(&k, &pose);
    for v in 0..k.height {
        for u in 0..k.width / 2 - 8 {
            assert_eq!(cast.depth.get(u, v), None, "({u}, {v})");
        }
    }
    assert!(cast.hit_count() as f32 > 0.45 * n as f32);
    // Only the plane at 1.5 m is there (the worst pixels border the unobserved half).
    assert!(
        cast.depth
            .as_raw()
            .iter()
            .all(|&d| d == 0.0 || (d - 1.5).abs() < voxel())
    );
}

#[test]
fn bad_inputs_are_refused_or_give_empty_casts() {
    let k = camera();
    let pose = Pose::identity();
    let n = (k.width * k.height) as usize;
    let depth = DepthImage::new(k.width, k.height, vec![1.0; n]).unwrap();
    let colour = RgbImage::filled(k.width, k.height, [1, 1, 1]);
    let mut tsdf = volume();

    let small = RgbImage::filled(10, 10, [0; 3]);
    let err = tsdf.try_integrate(&depth, &small, &k, &pose).unwrap_err();
    assert_eq!(
        err.to_string(),
        "TSDF volume: colour image is 10x10, the intrinsics are for 320x240"
    );
    let short = DepthImage::new(2, 2, vec![1.0; 4]).unwrap();
    let err = tsdf.try_integrate(&short, &colour, &k, &pose).unwrap_err();
    assert!(err.to_string().contains("depth image is 2x2"), "{err}");
    let mut nan_pose = pose;
    nan_pose.translation.vector.x = f64::NAN;
    let err = tsdf
        .try_integrate(&depth, &colour, &k, &nan_pose)
        .unwrap_err();
    assert!(err.to_string().contains("pose is not finite"), "{err}");
    let far = Pose::translation(1e7, 0.0, 0.0);
    let err = tsdf.try_integrate(&depth, &colour, &k, &far).unwrap_err();
    assert!(err.to_string().contains("too far from the origin"), "{err}");
    let mut bad_k = k;
    bad_k.fx = -1.0;
    let err = tsdf
        .try_integrate(&depth, &colour, &bad_k, &pose)
        .unwrap_err();
    assert!(err.to_string().contains("intrinsics are unusable"), "{err}");
    tsdf.integrate(&depth, &colour, &bad_k, &pose);
    assert_eq!((tsdf.block_count(), tsdf.frame_count()), (0, 0));

    tsdf.try_integrate(&depth, &colour, &k, &pose).unwrap();
    assert!(tsdf.raycast(&k, &pose).hit_count() > 0);
    let cast = tsdf.raycast(&bad_k, &pose);
    assert_eq!(
        (cast.width(), cast.height(), cast.hit_count()),
        (320, 240, 0)
    );
    assert_eq!(tsdf.raycast(&k, &nan_pose).hit_count(), 0);
    assert_eq!(tsdf.raycast(&k, &far).hit_count(), 0);
    // Looking away from the surface sees nothing.
    let away = Pose::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
    );
    assert_eq!(tsdf.raycast(&k, &away).hit_count(), 0);
    // An empty volume.
    assert_eq!(volume().raycast(&k, &pose).hit_count(), 0);
    assert!(volume().extract_mesh().vertices.is_empty());
}

#[test]
fn bad_config_values_are_refused_naming_the_parameter() {
    let d = TsdfConfig::default();
    let cases: Vec<(&str, TsdfConfig)> = vec![
        (
            "voxel_size",
            TsdfConfig {
                voxel_size: 0.0,
                ..d
            },
        ),
        (
            "voxel_size",
            TsdfConfig {
                voxel_size: -0.01,
                ..d
            },
        ),
        (
            "voxel_size",
            TsdfConfig {
                voxel_size: f32::NAN,
                ..d
            },
        ),
        (
            "voxel_size",
            TsdfConfig {
                voxel_size: f32::INFINITY,
                ..d
            },
        ),
        (
            "block_resolution",
            TsdfConfig {
                block_resolution: 16,
                ..d
            },
        ),
        (
            "truncation_voxels",
            TsdfConfig {
                truncation_voxels: 0.5,
                ..d
            },
        ),
        (
            "truncation_voxels",
            TsdfConfig {
                truncation_voxels: f32::NAN,
                ..d
            },
        ),
        (
            "depth_min",
            TsdfConfig {
                depth_min: -0.1,
                ..d
            },
        ),
        (
            "depth_min",
            TsdfConfig {
                depth_min: f32::NAN,
                ..d
            },
        ),
        (
            "depth_max",
            TsdfConfig {
                depth_max: 0.05,
                ..d
            },
        ),
        (
            "depth_max",
            TsdfConfig {
                depth_max: f32::INFINITY,
                ..d
            },
        ),
        (
            "max_weight",
            TsdfConfig {
                max_weight: 0.0,
                ..d
            },
        ),
        (
            "max_weight",
            TsdfConfig {
                max_weight: 70_000.0,
                ..d
            },
        ),
        (
            "max_weight",
            TsdfConfig {
                max_weight: f32::NAN,
                ..d
            },
        ),
        (
            "allocation_stride",
            TsdfConfig {
                allocation_stride: 0,
                ..d
            },
        ),
        (
            // Ran for minutes without progress before it was refused.
            "voxel_size",
            TsdfConfig {
                voxel_size: 0.00001,
                ..d
            },
        ),
        (
            "voxel_size",
            TsdfConfig {
                voxel_size: 2.0,
                ..d
            },
        ),
    ];
    for (name, config) in cases {
        let err = TsdfVolume::new(config).unwrap_err();
        assert!(
            matches!(&err, TrackerError::InvalidParameter { name: n, .. } if *n == name),
            "{config:?}: {err}"
        );
        assert!(
            err.to_string().starts_with(&format!("parameter `{name}` ")),
            "{err}"
        );
    }
    assert!(TsdfVolume::new(d).is_ok());
    assert!((d.sdf_trunc() - 8.0 * 3.0 / 512.0).abs() < 1e-9);
}

#[test]
fn floor_matches_std() {
    for x in [-2.5_f32, -2.0, -1e-7, 0.0, 0.3, 1.0, 7.999, -7.999, 1e6] {
        assert_eq!(floor_i32(x), x.floor() as i32, "{x}");
    }
}
