//! The object's surface as the global term sees it: vertices, triangles, per-vertex normals and
//! areas, and each vertex's one-ring with its edge lengths (the neighbourhood the interpolation
//! of section 6.2 filters over).
//!
//! [`pebble`] makes the virtual rig's test object: an egg-shaped solid from a subdivided
//! icosahedron, whose triangles have roughly even areas as the paper's resampling assumes.

use std::collections::HashMap;

use crate::firs::mesh::Mesh;
use crate::vec3::{add, cross, norm, normalize, scale, sub, V3};

/// A closed triangle mesh with what the DISCO fit needs per vertex.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceMesh {
    /// Positions, mm, in the object's frame (the turntable's at angle 0).
    pub vertices: Vec<V3>,
    /// Counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// Area-weighted vertex normals, unit, outward.
    pub normals: Vec<V3>,
    /// A third of the adjacent triangles' areas, mm².
    pub areas: Vec<f64>,
    /// One-ring: (neighbour, edge length mm), sorted by neighbour.
    pub rings: Vec<Vec<(u32, f64)>>,
}

impl SurfaceMesh {
    /// The surface of `mesh`. Triangles with an index out of range are dropped.
    pub fn new(mesh: &Mesh) -> Self {
        let n = mesh.vertices.len();
        let triangles: Vec<[u32; 3]> =
            mesh.triangles.iter().copied().filter(|t| t.iter().all(|&i| (i as usize) < n)).collect();
        let mut normals = vec![[0.0; 3]; n];
        let mut areas = vec![0.0; n];
        let mut rings: Vec<Vec<(u32, f64)>> = vec![Vec::new(); n];
        for t in &triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            let nrm = cross(sub(b, a), sub(c, a));
            let area = 0.5 * norm(nrm);
            for (k, &i) in t.iter().enumerate() {
                let i = i as usize;
                normals[i] = add(normals[i], nrm);
                areas[i] += area / 3.0;
                let j = t[(k + 1) % 3];
                let e = norm(sub(mesh.vertices[j as usize], mesh.vertices[i]));
                rings[i].push((j, e));
                rings[j as usize].push((i as u32, e));
            }
        }
        for r in &mut rings {
            r.sort_by_key(|&(j, _)| j);
            r.dedup_by_key(|&mut (j, _)| j);
        }
        SurfaceMesh {
            vertices: mesh.vertices.clone(),
            triangles,
            normals: normals.into_iter().map(normalize).collect(),
            areas,
            rings,
        }
    }

    /// As a plain [`Mesh`] (for PLY).
    pub fn mesh(&self) -> Mesh {
        Mesh { vertices: self.vertices.clone(), triangles: self.triangles.clone() }
    }

    /// Mean edge length, mm.
    pub fn mean_edge(&self) -> f64 {
        let (s, c) = self.rings.iter().flatten().fold((0.0, 0usize), |(s, c), &(_, e)| (s + e, c + 1));
        if c == 0 {
            0.0
        } else {
            s / c as f64
        }
    }

    /// Unit normal of triangle `t` (geometric, outward).
    pub fn face_normal(&self, t: usize) -> V3 {
        let [a, b, c] = self.triangles[t].map(|i| self.vertices[i as usize]);
        normalize(cross(sub(b, a), sub(c, a)))
    }
}

/// A unit icosphere: the icosahedron with every triangle split in four `level` times.
pub fn icosphere(level: u32) -> Mesh {
    let p = (1.0 + 5f64.sqrt()) / 2.0;
    let mut vertices: Vec<V3> = [
        [-1.0, p, 0.0],
        [1.0, p, 0.0],
        [-1.0, -p, 0.0],
        [1.0, -p, 0.0],
        [0.0, -1.0, p],
        [0.0, 1.0, p],
        [0.0, -1.0, -p],
        [0.0, 1.0, -p],
        [p, 0.0, -1.0],
        [p, 0.0, 1.0],
        [-p, 0.0, -1.0],
        [-p, 0.0, 1.0],
    ]
    .iter()
    .map(|&v| normalize(v))
    .collect();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut split = |a: u32, b: u32, vertices: &mut Vec<V3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                vertices.push(normalize(scale(add(vertices[a as usize], vertices[b as usize]), 0.5)));
                (vertices.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(triangles.len() * 4);
        for [a, b, c] in triangles {
            let ab = split(a, b, &mut vertices);
            let bc = split(b, c, &mut vertices);
            let ca = split(c, a, &mut vertices);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        triangles = next;
    }
    Mesh { vertices, triangles }
}

/// The virtual rig's test object: an egg `2·radii` across standing on the turntable (its lowest
/// point at `z = 0`, its axis the turntable's), narrower at the top, from an icosphere of
/// `level` (3: 642 vertices, 4: 2 562).
pub fn pebble(level: u32, radii: [f64; 3]) -> Mesh {
    let mut m = icosphere(level);
    for v in &mut m.vertices {
        // Taper the upper half by up to 15 %: an egg, not an ellipsoid, so the silhouette has a
        // top and a bottom, while the triangles stay within a few tens of percent in area.
        let taper = 1.0 - 0.15 * v[2].max(0.0);
        *v = [v[0] * radii[0] * taper, v[1] * radii[1] * taper, (v[2] + 1.0) * radii[2]];
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::firs::mesh::edge_defects;

    #[test]
    fn the_icosphere_is_closed_with_the_expected_counts_and_even_areas() {
        for (level, verts) in [(0, 12), (1, 42), (3, 642)] {
            let m = icosphere(level);
            assert_eq!(m.vertices.len(), verts);
            assert_eq!(m.triangles.len(), 20 * 4usize.pow(level));
            assert!(edge_defects(&m).is_closed());
        }
        let s = SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]));
        let (lo, hi) = s.areas.iter().fold((f64::MAX, 0.0f64), |(l, h), &a| (l.min(a), h.max(a)));
        assert!(hi / lo < 2.5, "vertex areas {lo}..{hi}");
        // Every vertex has a ring of 5 or 6, with symmetric edges.
        for (v, r) in s.rings.iter().enumerate() {
            assert!(r.len() == 5 || r.len() == 6, "vertex {v}: {}", r.len());
            for &(j, e) in r {
                let back = s.rings[j as usize].iter().find(|&&(k, _)| k as usize == v).unwrap();
                assert_eq!(back.1, e);
            }
        }
        // The pebble stands on z = 0 and its normals point outward.
        let zmin = s.vertices.iter().map(|v| v[2]).fold(f64::MAX, f64::min);
        assert!(zmin.abs() < 1e-9);
        let centre = [0.0, 0.0, 30.0];
        for (v, n) in s.vertices.iter().zip(&s.normals) {
            assert!(crate::vec3::dot(sub(*v, centre), *n) > 0.0);
        }
    }
}
