//! The marching-cubes case table: for each of the 256 inside/outside patterns of a cell's eight
//! corners, the triangles (as triples of cell edges) of the surface through the cell.
//!
//! The table is built once, from the cube's geometry, rather than typed in: on each face of the
//! cell the sign changes are joined by segments (on a face with four sign changes, each inside
//! corner is cut off by its own segment, so two cells sharing a face always agree and the mesh
//! has no cracks), the segments are chained into closed loops around the inside corners, and
//! each loop is fanned into triangles. Triangles wind counter-clockwise seen from outside
//! (positive TSDF, free space), so their right-hand normals point out of the surface. This is
//! Lorensen and Cline's marching cubes with the face ambiguity resolved consistently.

use std::sync::LazyLock;

/// Corner `c` of a cell sits at offset `(c & 1, c >> 1 & 1, c >> 2 & 1)` voxels from its base.
/// Edge `e` joins corners `EDGE_CORNERS[e] = [a, b]`, where `b = a + (1 << axis)` and
/// `axis = e / 4`.
pub(crate) const EDGE_CORNERS: [[u8; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7],
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

/// Offset of corner `c` from the cell base.
#[inline]
pub(crate) fn corner_offset(c: u8) -> [usize; 3] {
    [
        usize::from(c & 1),
        usize::from(c >> 1 & 1),
        usize::from(c >> 2 & 1),
    ]
}

/// Triangles per case, flattened.
pub(crate) struct CaseTable {
    /// Case `m`'s triangles are `triangles[start[m]..start[m + 1]]`.
    start: [u16; 257],
    triangles: Vec<[u8; 3]>,
}

impl CaseTable {
    /// The triangles of case `mask` (bit `c` set when corner `c` is inside, TSDF < 0).
    #[inline]
    pub(crate) fn triangles(&self, mask: u8) -> &[[u8; 3]] {
        let m = usize::from(mask);
        self.triangles
            .get(usize::from(self.start[m])..usize::from(self.start[m + 1]))
            .unwrap_or(&[])
    }
}

/// The table, built on first use.
pub(crate) static TABLE: LazyLock<CaseTable> = LazyLock::new(|| {
    let mut start = [0_u16; 257];
    let mut triangles = Vec::new();
    for mask in 0..=255_u8 {
        triangles.extend(case_triangles(mask));
        // At most 256 cases x 12 triangles: fits u16.
        start[usize::from(mask) + 1] = triangles.len() as u16;
    }
    CaseTable { start, triangles }
});

/// The edge joining corners `a` and `b` (which differ in one bit).
fn edge_between(a: u8, b: u8) -> u8 {
    let (lo, hi) = (a.min(b), a.max(b));
    EDGE_CORNERS
        .iter()
        .position(|&[x, y]| x == lo && y == hi)
        .unwrap_or(0) as u8
}

/// Twice a corner's position (integers).
fn corner_pos2(c: u8) -> [i32; 3] {
    corner_offset(c).map(|x| 2 * x as i32)
}

/// Twice the midpoint of edge `e`.
fn edge_mid2(e: u8) -> [i32; 3] {
    let [a, b] = EDGE_CORNERS[usize::from(e)];
    let (pa, pb) = (corner_pos2(a), corner_pos2(b));
    [
        (pa[0] + pb[0]) / 2,
        (pa[1] + pb[1]) / 2,
        (pa[2] + pb[2]) / 2,
    ]
}

fn sub(a: [i32; 3], b: [i32; 3]) -> [i32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [i32; 3], b: [i32; 3]) -> [i32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [i32; 3], b: [i32; 3]) -> i32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The closed loops of cell edges that the surface of case `mask` crosses, each ordered
/// counter-clockwise around the inside as seen from outside the cell.
pub(crate) fn case_loops(mask: u8) -> Vec<Vec<u8>> {
    let inside = |c: u8| mask >> c & 1 == 1;
    // next[e]: the edge after e along its loop.
    let mut next = [u8::MAX; 12];
    for axis in 0..3_u8 {
        for side in 0..2_u8 {
            let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
            let q0 = side << axis;
            let q = [q0, q0 | 1 << b, q0 | 1 << b | 1 << c, q0 | 1 << c];
            let mut normal = [0; 3];
            normal[usize::from(axis)] = if side == 1 { 1 } else { -1 };
            let crossing: Vec<usize> = (0..4)
                .filter(|&k| inside(q[k]) != inside(q[(k + 1) % 4]))
                .collect();
            // (edge, edge, an inside corner on the segment's inside side)
            let mut segments = Vec::new();
            match crossing.as_slice() {
                &[k0, k1] => {
                    let n = q.iter().copied().find(|&c| inside(c)).unwrap_or(q0);
                    segments.push((
                        edge_between(q[k0], q[(k0 + 1) % 4]),
                        edge_between(q[k1], q[(k1 + 1) % 4]),
                        n,
                    ));
                }
                [_, _, _, _] => {
                    for k in 0..4 {
                        if inside(q[k]) {
                            segments.push((
                                edge_between(q[(k + 3) % 4], q[k]),
                                edge_between(q[k], q[(k + 1) % 4]),
                                q[k],
                            ));
                        }
                    }
                }
                _ => {}
            }
            for (ea, eb, n) in segments {
                let (pa, pb, pn) = (edge_mid2(ea), edge_mid2(eb), corner_pos2(n));
                // Seen from outside the face, the inside corner is to the left of a -> b.
                let (ea, eb) = if dot(cross(sub(pb, pa), sub(pn, pa)), normal) >= 0 {
                    (ea, eb)
                } else {
                    (eb, ea)
                };
                next[usize::from(ea)] = eb;
            }
        }
    }
    let mut used = [false; 12];
    let mut loops = Vec::new();
    for first in 0..12_u8 {
        if next[usize::from(first)] == u8::MAX || used[usize::from(first)] {
            continue;
        }
        let mut ring = Vec::new();
        let mut e = first;
        while !used[usize::from(e)] && e != u8::MAX {
            used[usize::from(e)] = true;
            ring.push(e);
            e = next[usize::from(e)];
        }
        loops.push(ring);
    }
    loops
}

/// The triangles of case `mask`: each loop fanned from its first edge, wound so that the normal
/// points to the outside.
fn case_triangles(mask: u8) -> Vec<[u8; 3]> {
    let mut triangles = Vec::new();
    for ring in case_loops(mask) {
        for pair in ring.windows(2).skip(1) {
            triangles.push([ring[0], pair[1], pair[0]]);
        }
    }
    triangles
}
