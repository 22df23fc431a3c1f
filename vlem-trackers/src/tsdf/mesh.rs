//! Surface extraction: marching cubes (coloured triangle mesh) and zero-crossing points.
//!
//! Both run in parallel over blocks. A block's cells reach one voxel into its +x, +y and +z
//! neighbours, so each block first copies its `9³` neighbourhood. Cells (and voxel edges) with an
//! unobserved voxel (weight 0) are skipped.

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use vlem_core::ColouredMesh;

use super::TsdfVolume;
use super::block::{BLOCK_RES, Block, Voxel, voxel_index};
use super::mc_table::{EDGE_CORNERS, TABLE, corner_offset};

/// Neighbourhood edge: a block plus one voxel.
const N: usize = BLOCK_RES + 1;
/// Voxels in a neighbourhood.
const N3: usize = N * N * N;

/// Index of `(x, y, z)` (each in `0..9`) in a neighbourhood.
#[inline]
fn n_index(x: usize, y: usize, z: usize) -> usize {
    (z * N + y) * N + x
}

/// A vertex on a voxel edge: global voxel index of the edge's lower end, and its axis.
type EdgeKey = ([i32; 3], u8);

/// Points and their colours.
type ColouredPoints = (Vec<[f32; 3]>, Vec<[u8; 3]>);

/// The part of the mesh one block produced.
#[derive(Default)]
struct BlockMesh {
    vertices: Vec<[f32; 3]>,
    colours: Vec<[u8; 3]>,
    /// Vertices on an edge another block may also produce: (local index, edge).
    shared: Vec<(u32, EdgeKey)>,
    /// Triangles in local vertex indices.
    triangles: Vec<[u32; 3]>,
}

/// Per-thread scratch space of the mesh extraction.
struct Scratch {
    voxels: Vec<Voxel>,
    /// Vertex (local index) per neighbourhood edge, `u32::MAX` for none yet.
    edge_vertex: Vec<u32>,
}

impl Scratch {
    fn new() -> Self {
        Self {
            voxels: vec![Voxel::EMPTY; N3],
            edge_vertex: vec![u32::MAX; N3 * 3],
        }
    }
}

/// The point where the TSDF crosses zero between voxels `a` (at `pa`) and `b` (at `pb`), with
/// its interpolated colour.
#[inline]
fn crossing(a: &Voxel, b: &Voxel, pa: [f32; 3], pb: [f32; 3]) -> ([f32; 3], [u8; 3]) {
    let denom = a.tsdf - b.tsdf;
    let t = if denom.abs() > 1e-12 {
        (a.tsdf / denom).clamp(0.0, 1.0)
    } else {
        0.5
    };
    let p = [
        pa[0] + t * (pb[0] - pa[0]),
        pa[1] + t * (pb[1] - pa[1]),
        pa[2] + t * (pb[2] - pa[2]),
    ];
    let (ca, cb) = (a.colour(), b.colour());
    // Clamped to [0, 255] first, so the casts are exact.
    let c = [0, 1, 2].map(|i| (ca[i] + t * (cb[i] - ca[i]) + 0.5).clamp(0.0, 255.0) as u8);
    (p, c)
}

/// Whether the TSDF changes sign between `a` and `b` (inside is `< 0`).
#[inline]
fn sign_change(a: &Voxel, b: &Voxel) -> bool {
    (a.tsdf < 0.0) != (b.tsdf < 0.0)
}

impl TsdfVolume {
    /// The fused surface as a coloured triangle mesh (marching cubes), world coordinates.
    ///
    /// Vertices lie on voxel edges where the TSDF changes sign, interpolated linearly, with the
    /// colour interpolated the same way; vertices are shared between the triangles (and blocks)
    /// that meet at them. Triangles wind counter-clockwise seen from free space. Cells with an
    /// unobserved voxel are skipped.
    pub fn extract_mesh(&self) -> ColouredMesh {
        let parts: Vec<BlockMesh> = self
            .blocks
            .par_iter()
            .map_init(Scratch::new, |scratch, block| {
                self.mesh_block(block, scratch)
            })
            .collect();
        let vertex_count: usize = parts.iter().map(|p| p.vertices.len()).sum();
        let triangle_count: usize = parts.iter().map(|p| p.triangles.len()).sum();
        let mut mesh = ColouredMesh {
            vertices: Vec::with_capacity(vertex_count),
            colours: Vec::with_capacity(vertex_count),
            triangles: Vec::with_capacity(triangle_count),
        };
        let mut shared: FxHashMap<EdgeKey, u32> = FxHashMap::default();
        let mut global = Vec::new();
        for part in parts {
            global.clear();
            global.extend((0..part.vertices.len()).map(|_| u32::MAX));
            for &(local, key) in &part.shared {
                if let Some(&g) = shared.get(&key)
                    && let Some(slot) = global.get_mut(local as usize)
                {
                    *slot = g;
                }
            }
            for (i, slot) in global.iter_mut().enumerate() {
                if *slot != u32::MAX {
                    continue;
                }
                *slot = index_u32(mesh.vertices.len());
                mesh.vertices.push(part.vertices[i]);
                mesh.colours.push(part.colours[i]);
            }
            for &(local, key) in &part.shared {
                if let Some(&g) = global.get(local as usize) {
                    shared.entry(key).or_insert(g);
                }
            }
            mesh.triangles.extend(
                part.triangles
                    .iter()
                    .map(|t| t.map(|i| global.get(i as usize).copied().unwrap_or(0))),
            );
        }
        mesh
    }

    /// The fused surface as points (triangles empty): one point per voxel edge where the TSDF
    /// changes sign between two observed voxels, interpolated linearly, with colour.
    pub fn extract_points(&self) -> ColouredMesh {
        let parts: Vec<ColouredPoints> = self
            .blocks
            .par_iter()
            .map_init(Scratch::new, |scratch, block| {
                self.gather(block, &mut scratch.voxels);
                let voxels = &scratch.voxels;
                let mut points = Vec::new();
                let mut colours = Vec::new();
                let vs = self.config.voxel_size;
                let base = block.coord.map(|c| c * BLOCK_RES as i32);
                let pos = |x: usize, y: usize, z: usize| {
                    [
                        (base[0] + x as i32) as f32 * vs,
                        (base[1] + y as i32) as f32 * vs,
                        (base[2] + z as i32) as f32 * vs,
                    ]
                };
                for z in 0..BLOCK_RES {
                    for y in 0..BLOCK_RES {
                        for x in 0..BLOCK_RES {
                            let a = &voxels[n_index(x, y, z)];
                            if a.weight == 0 {
                                continue;
                            }
                            for (dx, dy, dz) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                                let b = &voxels[n_index(x + dx, y + dy, z + dz)];
                                if b.weight == 0 || !sign_change(a, b) {
                                    continue;
                                }
                                let (p, c) =
                                    crossing(a, b, pos(x, y, z), pos(x + dx, y + dy, z + dz));
                                points.push(p);
                                colours.push(c);
                            }
                        }
                    }
                }
                (points, colours)
            })
            .collect();
        let mut mesh = ColouredMesh::default();
        for (points, colours) in parts {
            mesh.vertices.extend(points);
            mesh.colours.extend(colours);
        }
        mesh
    }

    /// Copies `block`'s voxels and the first layer of its +x, +y, +z neighbours into `out`
    /// (`9³`, see [`n_index`]); missing neighbours read as unobserved.
    fn gather(&self, block: &Block, out: &mut [Voxel]) {
        let mut neighbours: [Option<&Block>; 8] = [None; 8];
        for (o, slot) in neighbours.iter_mut().enumerate() {
            *slot = if o == 0 {
                Some(block)
            } else {
                let c = block.coord;
                let coord = [
                    c[0] + (o & 1) as i32,
                    c[1] + (o >> 1 & 1) as i32,
                    c[2] + (o >> 2) as i32,
                ];
                self.index
                    .get(&coord)
                    .and_then(|&i| self.blocks.get(i as usize))
                    .map(|b| &**b)
            };
        }
        for z in 0..N {
            for y in 0..N {
                for x in 0..N {
                    let slot = (x / BLOCK_RES) | ((y / BLOCK_RES) << 1) | ((z / BLOCK_RES) << 2);
                    let voxel = neighbours[slot].map_or(Voxel::EMPTY, |b| {
                        b.voxel(voxel_index(x % BLOCK_RES, y % BLOCK_RES, z % BLOCK_RES))
                    });
                    if let Some(o) = out.get_mut(n_index(x, y, z)) {
                        *o = voxel;
                    }
                }
            }
        }
    }

    /// Marching cubes over the cells whose base voxel lies in `block`.
    fn mesh_block(&self, block: &Block, scratch: &mut Scratch) -> BlockMesh {
        self.gather(block, &mut scratch.voxels);
        scratch.edge_vertex.fill(u32::MAX);
        let voxels = &scratch.voxels;
        let vs = self.config.voxel_size;
        let base = block.coord.map(|c| c * BLOCK_RES as i32);
        let mut out = BlockMesh::default();
        for z in 0..BLOCK_RES {
            for y in 0..BLOCK_RES {
                for x in 0..BLOCK_RES {
                    let corners: [Voxel; 8] = std::array::from_fn(|c| {
                        let [ox, oy, oz] = corner_offset(c as u8);
                        voxels[n_index(x + ox, y + oy, z + oz)]
                    });
                    if corners.iter().any(|v| v.weight == 0) {
                        continue;
                    }
                    let mask = corners
                        .iter()
                        .enumerate()
                        .fold(0_u8, |m, (c, v)| m | u8::from(v.tsdf < 0.0) << c);
                    if mask == 0 || mask == u8::MAX {
                        continue;
                    }
                    for triangle in TABLE.triangles(mask) {
                        let t = triangle.map(|edge| {
                            let [a, b] = EDGE_CORNERS[usize::from(edge)];
                            let axis = usize::from(edge / 4);
                            let [ox, oy, oz] = corner_offset(a);
                            let lower = [x + ox, y + oy, z + oz];
                            let slot = n_index(lower[0], lower[1], lower[2]) * 3 + axis;
                            let existing = scratch.edge_vertex[slot];
                            if existing != u32::MAX {
                                return existing;
                            }
                            let g = [
                                base[0] + lower[0] as i32,
                                base[1] + lower[1] as i32,
                                base[2] + lower[2] as i32,
                            ];
                            let pa = g.map(|i| i as f32 * vs);
                            let mut pb = pa;
                            pb[axis] += vs;
                            let (p, c) = crossing(
                                &corners[usize::from(a)],
                                &corners[usize::from(b)],
                                pa,
                                pb,
                            );
                            let local = index_u32(out.vertices.len());
                            out.vertices.push(p);
                            out.colours.push(c);
                            if lower.iter().any(|&l| l == 0 || l == BLOCK_RES) {
                                out.shared.push((local, (g, axis as u8)));
                            }
                            scratch.edge_vertex[slot] = local;
                            local
                        });
                        out.triangles.push(t);
                    }
                }
            }
        }
        out
    }
}

/// A vertex count as a `u32` index (saturating; meshes of 4 billion vertices do not fit memory).
fn index_u32(i: usize) -> u32 {
    u32::try_from(i).unwrap_or(u32::MAX)
}
