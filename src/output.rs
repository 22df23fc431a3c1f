//! Files the `vlem` command writes (statistics JSON, the dense colour model as PLY), each written
//! atomically.

use std::path::Path;

use anyhow::Result;

/// Writes `bytes` to `path` atomically ([`vlem_core::files::write_atomically`]), for the
/// command's `anyhow` call sites.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(vlem_core::files::write_atomically(path, bytes)?)
}

/// Binary little-endian PLY of a vertex-coloured triangle mesh (a point set when it has no
/// triangles), e.g. the dense colour model of a TSDF tracker.
pub fn mesh_ply(mesh: &vlem_core::ColouredMesh) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment vlem dense colour model\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    )
    .into_bytes();
    out.reserve(mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
    for (p, colour) in mesh.vertices.iter().zip(&mesh.colours) {
        p.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        out.extend_from_slice(colour);
    }
    for triangle in &mesh.triangles {
        out.push(3);
        triangle
            .iter()
            .for_each(|i| out.extend_from_slice(&i.to_le_bytes()));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_ply_holds_vertices_then_faces() {
        let mesh = vlem_core::ColouredMesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            colours: vec![[1, 2, 3]; 3],
            triangles: vec![[0, 1, 2]],
        };
        let ply = mesh_ply(&mesh);
        let text = String::from_utf8_lossy(&ply);
        let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 3") && text.contains("element face 1"));
        assert_eq!(ply.len() - header_end, 3 * 15 + 13);
        assert_eq!(&ply[header_end + 12..header_end + 15], &[1, 2, 3]);
        assert_eq!(ply[header_end + 45], 3);
        assert_eq!(&ply[ply.len() - 4..], &2u32.to_le_bytes());
    }
}
