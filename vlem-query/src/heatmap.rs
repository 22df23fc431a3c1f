//! Heatmaps of query answers as binary PLY files: every point coloured by its similarity with the
//! jet colour map (an absolute scale, as in the paper's figures), and a grasp drawn as coloured
//! vertices after the points. The `vlem` command, its query server and any other front-end write
//! the same bytes.

use nalgebra::Vector3;

use crate::grasp::Grasp;

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

/// A coloured vertex drawn into a PLY besides the map points (the gripper of a grasp).
pub type Marker = ([f32; 3], [u8; 3]);

/// The similarity written for marker vertices, outside `[0, 1]` so they can be filtered out.
pub const MARKER_SIMILARITY: f32 = -1.0;

/// The straight segments (from, to, colour) of a parallel gripper at `grasp`: white along the
/// closing axis between the fingertips, magenta along the two fingers, the palm joining them and
/// a stem back along the approach direction.
pub fn gripper_segments(grasp: &Grasp) -> Vec<([f32; 3], [f32; 3], [u8; 3])> {
    const WHITE: [u8; 3] = [255, 255, 255];
    const MAGENTA: [u8; 3] = [255, 0, 255];
    /// Finger length and stem length (m), only for drawing.
    const FINGER: f64 = 0.04;
    const STEM: f64 = 0.06;
    let c = Vector3::from(grasp.position);
    let k = Vector3::from(grasp.closing);
    let a = Vector3::from(grasp.approach);
    // A little clearance so the fingers are drawn beside the object, not inside it.
    let half = grasp.width / 2.0 + 0.005;
    let point = |p: Vector3<f64>| [p.x as f32, p.y as f32, p.z as f32];
    [
        (c - k * half, c + k * half, WHITE),
        (c - k * half, c - k * half - a * FINGER, MAGENTA),
        (c + k * half, c + k * half - a * FINGER, MAGENTA),
        (
            c - k * half - a * FINGER,
            c + k * half - a * FINGER,
            MAGENTA,
        ),
        (c - a * FINGER, c - a * (FINGER + STEM), MAGENTA),
    ]
    .into_iter()
    .map(|(from, to, colour)| (point(from), point(to), colour))
    .collect()
}

/// Vertices drawing [`gripper_segments`] as points, for a PLY (which has no lines).
pub fn gripper_vertices(grasp: &Grasp) -> Vec<Marker> {
    /// Vertices per drawn segment.
    const STEPS: usize = 16;
    gripper_segments(grasp)
        .into_iter()
        .flat_map(|(from, to, colour)| {
            (0..=STEPS).map(move |i| {
                let t = i as f32 / STEPS as f32;
                let p = [0, 1, 2].map(|d| from[d] + (to[d] - from[d]) * t);
                (p, colour)
            })
        })
        .collect()
}

/// Binary little-endian PLY of points coloured by `scores` (jet), with the score as a property,
/// followed by the `markers` (similarity [`MARKER_SIMILARITY`]).
pub fn heatmap_ply(positions: &[[f32; 3]], scores: &[f32], markers: &[Marker]) -> Vec<u8> {
    let marker_comment = if markers.is_empty() {
        String::new()
    } else {
        format!(
            "comment the last {} vertices draw the grasp: white = closing axis between the \
             fingertips, magenta = fingers, palm and approach; their similarity is {MARKER_SIMILARITY}\n",
            markers.len()
        )
    };
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment vlem query heatmap: colour = jet(similarity)\n\
         {marker_comment}element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         property float similarity\nend_header\n",
        positions.len() + markers.len()
    )
    .into_bytes();
    out.reserve((positions.len() + markers.len()) * 19);
    let mut vertex = |p: &[f32; 3], colour: [u8; 3], s: f32| {
        p.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        out.extend_from_slice(&colour);
        out.extend_from_slice(&s.to_le_bytes());
    };
    for (p, &s) in positions.iter().zip(scores) {
        vertex(p, jet(s), s);
    }
    for (p, colour) in markers {
        vertex(p, *colour, MARKER_SIMILARITY);
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

    /// The legend image of docs/usage.md lists `jet` at its stops; it must not drift from the code.
    #[test]
    fn legend_image_matches_jet() {
        let svg = include_str!("../../docs/heatmap-legend.svg");
        let stops: Vec<(f32, [u8; 3])> = svg
            .lines()
            .filter_map(|line| {
                let offset = line.split("offset=\"").nth(1)?.split('"').next()?;
                let rgb = line.split("rgb(").nth(1)?.split(')').next()?;
                let channels: Vec<u8> = rgb.split(',').map(|c| c.trim().parse().unwrap()).collect();
                Some((
                    offset.parse().unwrap(),
                    [channels[0], channels[1], channels[2]],
                ))
            })
            .collect();
        assert_eq!(stops.len(), 7, "{svg}");
        for (t, colour) in stops {
            assert_eq!(jet(t), colour, "legend stop at {t}");
        }
    }

    #[test]
    fn ply_has_a_header_and_19_bytes_per_point() {
        let ply = heatmap_ply(&[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], &[0.0, 1.0], &[]);
        let text = String::from_utf8_lossy(&ply);
        let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 2"));
        assert_eq!(ply.len() - header_end, 2 * 19);
        assert_eq!(&ply[header_end + 12..header_end + 15], &[0, 0, 128]);
    }

    #[test]
    fn grasp_markers_follow_the_map_points() {
        let grasp = crate::grasp::grasp_from_points(
            &[
                [0.0, 0.0, 0.0],
                [0.0, 0.02, 0.0],
                [0.04, 0.02, 0.0],
                [0.0, 0.02, 0.1],
                [0.04, 0.02, 0.1],
            ],
            &crate::grasp::GraspParams::default(),
        )
        .unwrap();
        let markers = gripper_vertices(&grasp);
        assert!(markers.iter().any(|m| m.1 == [255, 255, 255]));
        assert!(markers.iter().any(|m| m.1 == [255, 0, 255]));
        let ply = heatmap_ply(&[[0.0; 3]], &[0.5], &markers);
        let text = String::from_utf8_lossy(&ply);
        let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains(&format!("element vertex {}", 1 + markers.len())));
        assert!(text.contains("draw the grasp"));
        assert_eq!(ply.len() - header_end, (1 + markers.len()) * 19);
        let last = &ply[ply.len() - 4..];
        assert_eq!(last, &MARKER_SIMILARITY.to_le_bytes());
    }
}
