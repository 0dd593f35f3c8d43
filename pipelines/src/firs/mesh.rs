//! Triangle meshes and their PLY form.

use std::io::{self, Write};

use crate::vec3::V3;

/// An indexed triangle mesh, millimetres; triangles wind counter-clockwise seen from outside.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<V3>,
    /// Vertex indices, three per triangle.
    pub triangles: Vec<[u32; 3]>,
}

/// Writes `mesh` as binary little-endian PLY (float vertices, `uchar`-counted `int` faces), the
/// form MeshLab, Blender and Open3D read.
pub fn write_ply(mesh: &Mesh, out: &mut impl Write) -> io::Result<()> {
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment lightrig\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    )?;
    let mut buf = Vec::with_capacity(mesh.vertices.len() * 12 + mesh.triangles.len() * 13);
    for v in &mesh.vertices {
        for c in v {
            buf.extend_from_slice(&(*c as f32).to_le_bytes());
        }
    }
    for t in &mesh.triangles {
        buf.push(3);
        for i in t {
            buf.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    out.write_all(&buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_bytes() {
        let m = Mesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2]],
        };
        let mut out = Vec::new();
        write_ply(&m, &mut out).unwrap();
        let header_end = out.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let body = &out[header_end..];
        assert_eq!(body.len(), 3 * 12 + 13);
        assert_eq!(&body[12..16], &1.0f32.to_le_bytes());
        assert_eq!(&body[36..], &[3, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]);
    }
}
