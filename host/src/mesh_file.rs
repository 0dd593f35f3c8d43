//! A lab's mesh file, in whatever PLY or OBJ its scanner or geometry tool wrote: PLY in ASCII
//! or binary of either byte order (through `ply-rs-bw`), with `float` or `double` positions, any
//! integer index type and extra properties (normals, colours, confidence: ignored), and OBJ
//! (through `tobj`, every object and group of the file). Polygons are split into triangle fans
//! from their first corner; corners that repeat a position exactly (an STL-style file
//! that stores each triangle's corners apart) are merged, so the surface is connected.
//!
//! What a pipeline needs of the surface (closed, oriented, even triangles) is its own check
//! (`lightrig_pipelines::disco::scan`); this module only reads.

use std::collections::HashMap;
use std::fmt;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use lightrig_pipelines::firs::mesh::Mesh;
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Encoding, Property};

/// The file formats [`read_mesh`] reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    PlyAscii,
    PlyBinaryLittleEndian,
    PlyBinaryBigEndian,
    Obj,
}

impl fmt::Display for MeshFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MeshFormat::PlyAscii => "PLY (ASCII)",
            MeshFormat::PlyBinaryLittleEndian => "PLY (binary, little-endian)",
            MeshFormat::PlyBinaryBigEndian => "PLY (binary, big-endian)",
            MeshFormat::Obj => "OBJ",
        })
    }
}

/// A mesh as read, with what reading it changed.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshFile {
    /// Triangles only; positions in the file's own units.
    pub mesh: Mesh,
    pub format: MeshFormat,
    /// Faces of more than three corners, split into fans.
    pub polygons_split: usize,
    /// Faces of fewer than three distinct corners, dropped.
    pub degenerate_dropped: usize,
    /// Vertices merged into another at exactly the same position.
    pub vertices_merged: usize,
    /// Vertex properties other than x, y, z, which are not used.
    pub ignored_properties: Vec<String>,
}

/// Why a mesh file could not be read.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshFileError {
    pub path: PathBuf,
    /// The file's line where the reader knows it.
    pub line: Option<usize>,
    pub message: String,
}

impl fmt::Display for MeshFileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(l) => write!(f, "{}:{l}: {}", self.path.display(), self.message),
            None => write!(f, "{}: {}", self.path.display(), self.message),
        }
    }
}

impl std::error::Error for MeshFileError {}

/// Reads the mesh at `path`: `.ply` or `.obj` by the file's extension (any case); a file
/// without either that starts with `ply` is read as PLY.
pub fn read_mesh(path: &Path) -> Result<MeshFile, MeshFileError> {
    let err =
        |line: Option<usize>, message: String| MeshFileError { path: path.to_path_buf(), line, message };
    let bytes = std::fs::read(path).map_err(|e| err(None, format!("{e}")))?;
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    let (faces, vertices, format, ignored) = match ext.as_deref() {
        Some("obj") => read_obj(&bytes).map_err(|(l, m)| err(l, m))?,
        Some("ply") => read_ply_any(&bytes).map_err(|(l, m)| err(l, m))?,
        _ if bytes.starts_with(b"ply") => read_ply_any(&bytes).map_err(|(l, m)| err(l, m))?,
        _ => {
            return Err(err(
                None,
                "not a mesh file lightrig reads: give a .ply (ASCII or binary) or an .obj".into(),
            ))
        }
    };
    assemble(vertices, &faces, format, ignored).map_err(|m| err(None, m))
}

type Faces = Vec<Vec<i64>>;
type Read = (Faces, Vec<[f64; 3]>, MeshFormat, Vec<String>);

fn read_ply_any(bytes: &[u8]) -> Result<Read, (Option<usize>, String)> {
    let parser = Parser::<DefaultElement>::new();
    let ply = parser
        .read_ply(&mut BufReader::new(bytes))
        .map_err(|e| (e.line(), format!("PLY: {}", ParseMessage(&e))))?;
    let format = match ply.header.encoding {
        Encoding::Ascii => MeshFormat::PlyAscii,
        Encoding::BinaryLittleEndian => MeshFormat::PlyBinaryLittleEndian,
        Encoding::BinaryBigEndian => MeshFormat::PlyBinaryBigEndian,
    };
    let vdef = ply.header.elements.get("vertex").ok_or((None, "PLY: no `element vertex`".to_string()))?;
    for axis in ["x", "y", "z"] {
        if !vdef.properties.contains_key(axis) {
            return Err((None, format!("PLY: `element vertex` has no property `{axis}`")));
        }
    }
    let ignored: Vec<String> =
        vdef.properties.keys().filter(|k| !matches!(k.as_str(), "x" | "y" | "z")).cloned().collect();
    let empty = Vec::new();
    let vertices = ply
        .payload
        .get("vertex")
        .unwrap_or(&empty)
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let c = |axis: &str| {
                v.get(axis)
                    .and_then(scalar)
                    .ok_or_else(|| (None, format!("PLY: vertex {i}: `{axis}` is not a number")))
            };
            Ok([c("x")?, c("y")?, c("z")?])
        })
        .collect::<Result<Vec<_>, _>>()?;
    let fdef = ply.header.elements.get("face").ok_or((
        None,
        "PLY: no `element face`: a point cloud is not a surface; mesh it first (e.g. Poisson reconstruction)"
            .to_string(),
    ))?;
    let key = ["vertex_indices", "vertex_index"]
        .into_iter()
        .find(|k| fdef.properties.contains_key(*k))
        .ok_or((None, "PLY: `element face` has no `vertex_indices` (or `vertex_index`) list".to_string()))?;
    let faces = ply
        .payload
        .get("face")
        .unwrap_or(&empty)
        .iter()
        .enumerate()
        .map(|(i, f)| {
            f.get(key)
                .and_then(list)
                .ok_or_else(|| (None, format!("PLY: face {i}: `{key}` is not a list of integers")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((faces, vertices, format, ignored))
}

/// ply-rs' error text, which names the line itself where it knows it.
struct ParseMessage<'a>(&'a ply_rs_bw::parser::ParseError);

impl fmt::Display for ParseMessage<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = self.0.to_string();
        // The line is reported once, in the error's position.
        let s = match self.0.line() {
            Some(l) => s.strip_prefix(&format!("Line {l}: ")).map(str::to_string).unwrap_or(s),
            None => s,
        };
        f.write_str(&s)
    }
}

fn scalar(p: &Property) -> Option<f64> {
    Some(match *p {
        Property::Char(v) => f64::from(v),
        Property::UChar(v) => f64::from(v),
        Property::Short(v) => f64::from(v),
        Property::UShort(v) => f64::from(v),
        Property::Int(v) => f64::from(v),
        Property::UInt(v) => f64::from(v),
        Property::Float(v) => f64::from(v),
        Property::Double(v) => v,
        _ => return None,
    })
}

fn list(p: &Property) -> Option<Vec<i64>> {
    Some(match p {
        Property::ListChar(v) => v.iter().map(|&i| i64::from(i)).collect(),
        Property::ListUChar(v) => v.iter().map(|&i| i64::from(i)).collect(),
        Property::ListShort(v) => v.iter().map(|&i| i64::from(i)).collect(),
        Property::ListUShort(v) => v.iter().map(|&i| i64::from(i)).collect(),
        Property::ListInt(v) => v.iter().map(|&i| i64::from(i)).collect(),
        Property::ListUInt(v) => v.iter().map(|&i| i64::from(i)).collect(),
        _ => return None,
    })
}

fn read_obj(bytes: &[u8]) -> Result<Read, (Option<usize>, String)> {
    // Polygons kept as they are (split here, the same way as PLY's); points and lines are not
    // a surface.
    let opts = tobj::LoadOptions {
        triangulate: false,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, _) = tobj::load_obj_buf(&mut BufReader::new(bytes), &opts, |_| {
        // Materials are not needed: an `mtllib` the file names is not opened.
        Err(tobj::LoadError::GenericFailure)
    })
    .map_err(|e| (None, format!("OBJ: {e}")))?;
    let mut vertices = Vec::new();
    let mut faces = Vec::new();
    for m in &models {
        let base = vertices.len() as i64;
        vertices.extend(m.mesh.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        let ix = &m.mesh.indices;
        if m.mesh.face_arities.is_empty() {
            faces.extend(ix.chunks_exact(3).map(|t| t.iter().map(|&i| base + i64::from(i)).collect()));
        } else {
            let mut at = 0usize;
            for &n in &m.mesh.face_arities {
                let n = n as usize;
                faces.push(ix[at..at + n].iter().map(|&i| base + i64::from(i)).collect());
                at += n;
            }
        }
    }
    Ok((faces, vertices, MeshFormat::Obj, Vec::new()))
}

/// Checks the indices, merges coincident vertices, splits polygons and drops degenerate faces.
fn assemble(
    vertices: Vec<[f64; 3]>,
    faces: &[Vec<i64>],
    format: MeshFormat,
    ignored_properties: Vec<String>,
) -> Result<MeshFile, String> {
    if let Some((i, v)) = vertices.iter().enumerate().find(|(_, v)| v.iter().any(|c| !c.is_finite())) {
        return Err(format!("vertex {i} is not finite ({v:?})"));
    }
    let n = vertices.len() as i64;
    if n > i64::from(u32::MAX) {
        return Err(format!("{n} vertices: more than lightrig's meshes index"));
    }
    // Exact duplicates only: welding by a tolerance would join what a scanner kept apart.
    let mut first: HashMap<[u64; 3], u32> = HashMap::with_capacity(vertices.len());
    let mut unique = Vec::with_capacity(vertices.len());
    let remap: Vec<u32> = vertices
        .iter()
        .map(|v| {
            let key = v.map(|c| (if c == 0.0 { 0.0 } else { c }).to_bits());
            *first.entry(key).or_insert_with(|| {
                unique.push(*v);
                (unique.len() - 1) as u32
            })
        })
        .collect();
    let vertices_merged = vertices.len() - unique.len();
    let mut triangles = Vec::with_capacity(faces.len());
    let (mut polygons_split, mut degenerate_dropped) = (0, 0);
    for (k, f) in faces.iter().enumerate() {
        if let Some(&bad) = f.iter().find(|&&i| i < 0 || i >= n) {
            return Err(format!("face {k}: vertex index {bad} is out of range (the file has {n} vertices)"));
        }
        let f: Vec<u32> = f.iter().map(|&i| remap[i as usize]).collect();
        if f.len() > 3 {
            polygons_split += 1;
        }
        let mut any = false;
        for j in 1..f.len().saturating_sub(1) {
            let t = [f[0], f[j], f[j + 1]];
            if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                triangles.push(t);
                any = true;
            }
        }
        if !any {
            degenerate_dropped += 1;
        }
    }
    Ok(MeshFile {
        mesh: Mesh { vertices: unique, triangles },
        format,
        polygons_split,
        degenerate_dropped,
        vertices_merged,
        ignored_properties,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, bytes: &[u8]) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lightrig-mesh-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }

    /// A unit square as two triangles in the order every reader below must give back.
    fn square() -> Mesh {
        Mesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    #[test]
    fn ascii_ply_with_extra_properties_and_a_quad() {
        let p = write(
            "quad.ply",
            b"ply\nformat ascii 1.0\ncomment from a scanner\nelement vertex 4\nproperty double x\n\
              property double y\nproperty double z\nproperty float nx\nproperty uchar red\n\
              property float confidence\nelement face 1\nproperty list uchar uint vertex_indices\n\
              end_header\n0 0 0 0 255 1\n1 0 0 0 255 1\n1 1 0 0 255 1\n0 1 0 0 255 0.5\n4 0 1 2 3\n",
        );
        let m = read_mesh(&p).unwrap();
        assert_eq!(m.mesh, square());
        assert_eq!(m.format, MeshFormat::PlyAscii);
        assert_eq!(m.polygons_split, 1);
        assert_eq!(m.ignored_properties, ["nx", "red", "confidence"]);
    }

    fn binary(big: bool) -> Vec<u8> {
        let (fmt, ord): (&str, fn(f64) -> [u8; 8]) = if big {
            ("binary_big_endian", f64::to_be_bytes)
        } else {
            ("binary_little_endian", f64::to_le_bytes)
        };
        let mut b = format!(
            "ply\nformat {fmt} 1.0\nelement vertex 4\nproperty double x\nproperty double y\n\
             property double z\nelement face 2\nproperty list uchar int vertex_index\nend_header\n"
        )
        .into_bytes();
        for v in square().vertices {
            for c in v {
                b.extend_from_slice(&ord(c));
            }
        }
        for t in square().triangles {
            b.push(3);
            for i in t {
                b.extend_from_slice(&if big { (i as i32).to_be_bytes() } else { (i as i32).to_le_bytes() });
            }
        }
        b
    }

    #[test]
    fn binary_ply_of_both_byte_orders_with_doubles() {
        let le = read_mesh(&write("le.ply", &binary(false))).unwrap();
        assert_eq!(le.mesh, square());
        assert_eq!(le.format, MeshFormat::PlyBinaryLittleEndian);
        let be = read_mesh(&write("be.PLY", &binary(true))).unwrap();
        assert_eq!(be.mesh, square());
        assert_eq!(be.format, MeshFormat::PlyBinaryBigEndian);
    }

    #[test]
    fn lightrigs_own_ply_reads_back() {
        let mut b = Vec::new();
        lightrig_pipelines::firs::mesh::write_ply(&square(), &mut b).unwrap();
        assert_eq!(read_mesh(&write("own.ply", &b)).unwrap().mesh, square());
    }

    #[test]
    fn obj_with_two_objects_a_quad_and_negative_indices() {
        let p = write(
            "two.obj",
            b"mtllib missing.mtl\no a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n\
              o b\nv 5 0 0\nv 6 0 0\nv 5 1 0\nf -3 -2 -1\n",
        );
        let m = read_mesh(&p).unwrap();
        assert_eq!(m.format, MeshFormat::Obj);
        assert_eq!(m.mesh.vertices.len(), 7);
        assert_eq!(m.mesh.triangles, [[0, 1, 2], [0, 2, 3], [4, 5, 6]]);
        assert_eq!(m.polygons_split, 1);
    }

    #[test]
    fn corners_stored_apart_are_merged_and_degenerate_faces_dropped() {
        let p = write(
            "soup.ply",
            b"ply\nformat ascii 1.0\nelement vertex 7\nproperty float x\nproperty float y\nproperty float z\n\
              element face 3\nproperty list uchar int vertex_indices\nend_header\n\
              0 0 0\n1 0 0\n1 1 0\n-0 0 0\n1 1 0\n0 1 0\n0 1 0\n3 0 1 2\n3 3 4 5\n3 5 6 0\n",
        );
        let m = read_mesh(&p).unwrap();
        assert_eq!(m.mesh, square());
        assert_eq!(m.vertices_merged, 3);
        assert_eq!(m.degenerate_dropped, 1);
    }

    #[test]
    fn errors_name_the_file_and_what_is_wrong() {
        let p = write("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 1 2\n");
        let e = read_mesh(&p).unwrap_err();
        assert_eq!(e.message, "face 0: vertex index 1 is out of range (the file has 1 vertices)");
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");

        let cloud = write("cloud.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n");
        assert!(read_mesh(&cloud).unwrap_err().message.contains("point cloud"));

        let noy = write(
            "noy.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float z\nend_header\n0 0\n",
        );
        assert_eq!(read_mesh(&noy).unwrap_err().message, "PLY: `element vertex` has no property `y`");

        let garbled = write("garbled.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n0 zero 0\n");
        let e = read_mesh(&garbled).unwrap_err();
        assert!(e.line.is_some() && e.message.starts_with("PLY: "), "{e:?}");

        let stl = write("part.stl", b"solid x\nendsolid x\n");
        assert!(read_mesh(&stl).unwrap_err().message.contains("give a .ply"));
    }
}
