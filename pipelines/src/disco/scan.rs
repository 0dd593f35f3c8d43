//! What the DISCO fit needs of a lab's scanned mesh, checked before it is used: a 2-manifold
//! surface (each edge in at most two triangles), oriented the same way throughout and outward,
//! in millimetres, and with triangles of roughly even area, as the paper's resampling assumes
//! ("the surface is represented as a triangular surface mesh where each triangle represents a
//! similar surface area", section 5). Holes are allowed and counted: the interpolation works on
//! an open surface, only the registration's first guess gets rougher.
//!
//! Orientation is repaired (faces flipped to agree with their neighbours, then each connected
//! piece turned outward by the sign of the volume it encloses) and vertices no triangle uses
//! are dropped; the rest is measured, and a mesh that fails is refused with the measure and
//! what to do, never silently used.

use std::collections::HashMap;

use crate::firs::mesh::{edge_defects, EdgeDefects, Mesh};
use crate::vec3::{cross, dot, norm, sub};

/// The largest [`ScanCheck::area_spread`] the fit takes. An icosphere's is ~1.3, a
/// scanner's isotropically remeshed surface 2–4; a decimated or marching-cubes mesh (slivers
/// beside large triangles) is tens to thousands.
pub const AREA_SPREAD_LIMIT: f64 = 8.0;

/// The object sizes (bounding-box diagonal, mm) a turntable DISCO rig takes: outside them the
/// file's units are almost surely not millimetres.
pub const DIAGONAL_MM: (f64, f64) = (5.0, 2000.0);

/// The vertex count the remeshing advice aims at: the paper's models have 5 000 – 8 900.
pub const ADVISED_VERTICES: f64 = 5000.0;

/// What [`orient`] changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Orientation {
    /// Triangles flipped to agree with their neighbours.
    pub flipped: usize,
    /// Connected pieces turned over because they enclosed negative volume (inside out).
    pub turned_outward: usize,
    /// Connected pieces (through edges shared by exactly two triangles).
    pub pieces: usize,
}

/// Orients `mesh` consistently and outward, in place: a breadth-first walk over each piece
/// flips every triangle that runs a shared edge the same way as its neighbour, then a piece
/// whose signed volume is negative is turned over. Edges of more than two triangles are not
/// crossed; a non-orientable piece (a Möbius band) keeps what the walk left, which
/// [`check`] reports as misoriented edges.
pub fn orient(mesh: &mut Mesh) -> Orientation {
    let nt = mesh.triangles.len();
    let mut by_edge: HashMap<(u32, u32), Vec<u32>> = HashMap::with_capacity(nt * 3 / 2);
    for (k, t) in mesh.triangles.iter().enumerate() {
        for e in 0..3 {
            let (a, b) = (t[e], t[(e + 1) % 3]);
            by_edge.entry((a.min(b), a.max(b))).or_default().push(k as u32);
        }
    }
    let runs = |t: &[u32; 3], a: u32, b: u32| (0..3).any(|e| t[e] == a && t[(e + 1) % 3] == b);
    let mut out = Orientation::default();
    let mut piece = vec![u32::MAX; nt];
    let mut queue = std::collections::VecDeque::new();
    for seed in 0..nt {
        if piece[seed] != u32::MAX {
            continue;
        }
        let id = out.pieces as u32;
        out.pieces += 1;
        piece[seed] = id;
        queue.push_back(seed);
        let mut members = vec![seed];
        while let Some(k) = queue.pop_front() {
            let t = mesh.triangles[k];
            for e in 0..3 {
                let (a, b) = (t[e], t[(e + 1) % 3]);
                let users = &by_edge[&(a.min(b), a.max(b))];
                if users.len() != 2 {
                    continue;
                }
                let j = users[0] as usize ^ users[1] as usize ^ k;
                if piece[j] != u32::MAX {
                    continue;
                }
                piece[j] = id;
                // A consistent neighbour runs the shared edge b → a.
                if runs(&mesh.triangles[j], a, b) {
                    mesh.triangles[j].swap(1, 2);
                    out.flipped += 1;
                }
                members.push(j);
                queue.push_back(j);
            }
        }
        let volume: f64 = members
            .iter()
            .map(|&k| {
                let [a, b, c] = mesh.triangles[k].map(|i| mesh.vertices[i as usize]);
                dot(a, cross(b, c))
            })
            .sum();
        if volume < 0.0 {
            for &k in &members {
                mesh.triangles[k].swap(1, 2);
            }
            out.turned_outward += 1;
        }
    }
    out
}

/// Drops the vertices no triangle uses (a scanner's stray points, what a hole's repair left
/// behind: they have no normal and no one-ring), renumbering the triangles; returns how many.
pub fn drop_unused(mesh: &mut Mesh) -> usize {
    let mut used = vec![false; mesh.vertices.len()];
    for t in &mesh.triangles {
        for &i in t {
            used[i as usize] = true;
        }
    }
    let mut new_index = vec![u32::MAX; mesh.vertices.len()];
    let mut kept = Vec::with_capacity(mesh.vertices.len());
    for (i, v) in mesh.vertices.iter().enumerate() {
        if used[i] {
            new_index[i] = kept.len() as u32;
            kept.push(*v);
        }
    }
    let dropped = mesh.vertices.len() - kept.len();
    mesh.vertices = kept;
    for t in &mut mesh.triangles {
        *t = t.map(|i| new_index[i as usize]);
    }
    dropped
}

/// A scanned mesh measured against what the fit needs.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanCheck {
    pub vertices: usize,
    pub triangles: usize,
    /// The bounding box's diagonal, in the mesh's units (mm once scaled).
    pub diagonal: f64,
    /// Total area, units².
    pub area: f64,
    /// The 95th percentile of the triangles' areas over the 5th: 1 for equal triangles.
    pub area_spread: f64,
    /// After [`orient`].
    pub defects: EdgeDefects,
}

/// Measures `mesh` (orient it first).
pub fn check(mesh: &Mesh) -> ScanCheck {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for v in &mesh.vertices {
        for c in 0..3 {
            lo[c] = lo[c].min(v[c]);
            hi[c] = hi[c].max(v[c]);
        }
    }
    let diagonal = if mesh.vertices.is_empty() { 0.0 } else { norm(sub(hi, lo)) };
    let mut areas: Vec<f64> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            0.5 * norm(cross(sub(b, a), sub(c, a)))
        })
        .collect();
    let area = areas.iter().sum();
    areas.sort_by(f64::total_cmp);
    let at = |q: f64| areas.get(((areas.len().saturating_sub(1)) as f64 * q).round() as usize).copied();
    let area_spread = match (at(0.05), at(0.95)) {
        (Some(p5), Some(p95)) if p5 > 0.0 => p95 / p5,
        (Some(_), Some(_)) => f64::INFINITY,
        _ => f64::NAN,
    };
    ScanCheck {
        vertices: mesh.vertices.len(),
        triangles: mesh.triangles.len(),
        diagonal,
        area,
        area_spread,
        defects: edge_defects(mesh),
    }
}

impl ScanCheck {
    /// The edge length an isotropic remeshing should aim at for [`ADVISED_VERTICES`]
    /// vertices (a closed mesh of equilateral triangles has twice as many triangles as
    /// vertices, each √3/4·L²).
    pub fn advised_edge(&self) -> f64 {
        (self.area / (2.0 * ADVISED_VERTICES) * 4.0 / 3f64.sqrt()).sqrt()
    }

    /// Why the fit cannot use the mesh, with what to do; `None` if it can.
    pub fn refusal(&self) -> Option<String> {
        if self.triangles < 4 {
            return Some(format!("{} triangles: not a surface", self.triangles));
        }
        let (min, max) = DIAGONAL_MM;
        if !(min..=max).contains(&self.diagonal) {
            let guess = [("m", 1000.0), ("cm", 10.0), ("in", 25.4)]
                .into_iter()
                .find(|(_, f)| (min..=max).contains(&(self.diagonal * f)))
                .map(|(u, _)| format!("; if the file is in {u}, give `--set plan.fit.mesh_unit={u}`"))
                .unwrap_or_default();
            return Some(format!(
                "the mesh is {:.4} across (bounding-box diagonal) where the fit takes millimetres and an object of {min}–{max} mm{guess}",
                self.diagonal
            ));
        }
        if self.defects.non_manifold > 0 {
            return Some(format!(
                "{} edges are shared by more than two triangles (not a 2-manifold surface): repair it (MeshLab: Filters › Cleaning and Repairing › Repair non Manifold Edges)",
                self.defects.non_manifold
            ));
        }
        if self.defects.misoriented > 0 {
            return Some(format!(
                "{} edges join triangles that cannot be oriented alike (a non-orientable surface): repair it before the fit",
                self.defects.misoriented
            ));
        }
        if self.area_spread.is_nan() || self.area_spread > AREA_SPREAD_LIMIT {
            return Some(format!(
                "its triangles' areas are uneven (95th over 5th percentile {:.1}, the fit takes up to {AREA_SPREAD_LIMIT}): DISCO resamples each frame at the vertices and needs each triangle to cover a similar area (section 5); remesh it isotropically to an edge of about {:.2} mm (~{ADVISED_VERTICES} vertices; MeshLab: Filters › Remeshing, Simplification and Reconstruction › Isotropic Explicit Remeshing)",
                self.area_spread,
                self.advised_edge()
            ));
        }
        None
    }
}

/// A length unit a mesh file may be in, and its size in millimetres.
pub fn unit_mm(unit: &str) -> Option<f64> {
    Some(match unit {
        "mm" => 1.0,
        "cm" => 10.0,
        "m" => 1000.0,
        "in" => 25.4,
        "um" | "µm" => 1e-3,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::{icosphere, pebble};

    fn scaled(m: &Mesh, s: f64) -> Mesh {
        Mesh {
            vertices: m.vertices.iter().map(|v| v.map(|c| c * s)).collect(),
            triangles: m.triangles.clone(),
        }
    }

    #[test]
    fn flipped_and_inside_out_triangles_are_repaired() {
        let good = scaled(&icosphere(2), 20.0);
        let mut m = good.clone();
        for k in [3, 17, 100, 200] {
            m.triangles[k].swap(0, 1);
        }
        let o = orient(&mut m);
        assert_eq!(o, Orientation { flipped: 4, turned_outward: 0, pieces: 1 });
        assert!(check(&m).defects.is_closed());
        assert!(crate::firs::mesh::enclosed_volume(&m) > 0.0);

        // Inside out as a whole: consistent, so the walk flips nothing; the piece is turned.
        let mut inv = good.clone();
        for t in &mut inv.triangles {
            t.swap(1, 2);
        }
        let o = orient(&mut inv);
        assert_eq!((o.flipped, o.turned_outward, o.pieces), (0, 1, 1));
        assert_eq!(inv, good);

        // Two separate spheres count as two pieces, each oriented.
        let mut two = good.clone();
        let n = two.vertices.len() as u32;
        two.vertices.extend(good.vertices.iter().map(|v| [v[0] + 100.0, v[1], v[2]]));
        two.triangles.extend(good.triangles.iter().map(|t| [t[0] + n, t[2] + n, t[1] + n]));
        let o = orient(&mut two);
        assert_eq!((o.pieces, o.turned_outward), (2, 1));
        assert!(check(&two).defects.is_closed());
    }

    #[test]
    fn the_demo_object_passes_and_its_figures_are_measured() {
        let m = pebble(3, [18.0, 14.0, 12.0]);
        let c = check(&m);
        assert_eq!(c.refusal(), None);
        assert!(c.area_spread > 1.0 && c.area_spread < 3.0, "{}", c.area_spread);
        // A 36 × 28 × 24 mm box's diagonal.
        assert!(
            (c.diagonal - (36f64.powi(2) + 28f64.powi(2) + 24f64.powi(2)).sqrt()).abs() < 0.5,
            "{}",
            c.diagonal
        );
    }

    #[test]
    fn metres_are_refused_with_the_unit_to_give() {
        let m = scaled(&icosphere(2), 0.03);
        let r = check(&m).refusal().unwrap();
        assert!(r.contains("0.1039 across") && r.contains("mesh_unit=m"), "{r}");
        assert_eq!(check(&scaled(&m, unit_mm("m").unwrap())).refusal(), None);
    }

    #[test]
    fn uneven_triangles_are_refused_naming_the_measure_and_the_edge_to_remesh_to() {
        // The triangles of a cap (a quarter of the area) split at their centroids three times:
        // a tenth of the triangles keep their area, the rest have a 27th of it.
        let mut m = scaled(&icosphere(2), 20.0);
        for _ in 0..3 {
            let mut tris = Vec::new();
            for &t in &m.triangles {
                let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                if a[2] + b[2] + c[2] > 30.0 {
                    let g = (m.vertices.len()) as u32;
                    m.vertices.push([
                        (a[0] + b[0] + c[0]) / 3.0,
                        (a[1] + b[1] + c[1]) / 3.0,
                        (a[2] + b[2] + c[2]) / 3.0,
                    ]);
                    tris.extend([[t[0], t[1], g], [t[1], t[2], g], [t[2], t[0], g]]);
                } else {
                    tris.push(t);
                }
            }
            m.triangles = tris;
        }
        let c = check(&m);
        assert!(c.area_spread > 20.0, "{}", c.area_spread);
        let r = c.refusal().unwrap();
        assert!(r.contains("95th over 5th percentile") && r.contains("Isotropic Explicit Remeshing"), "{r}");
        // An edge that gives ~5 000 vertices on the sphere's area (4π·20² mm²).
        let l = c.advised_edge();
        let vertices = 4.0 * std::f64::consts::PI * 400.0 / (3f64.sqrt() / 4.0 * l * l) / 2.0;
        assert!((vertices - ADVISED_VERTICES).abs() < 0.05 * ADVISED_VERTICES, "{vertices}");
    }

    #[test]
    fn non_manifold_edges_are_refused() {
        let mut m = scaled(&icosphere(1), 20.0);
        // A fin on an existing edge: that edge now has three triangles.
        let t = m.triangles[0];
        m.vertices.push([0.0, 0.0, 0.0]);
        m.triangles.push([t[0], t[1], (m.vertices.len() - 1) as u32]);
        orient(&mut m);
        let r = check(&m).refusal().unwrap();
        assert!(r.starts_with("1 edges are shared by more than two triangles"), "{r}");
    }

    #[test]
    fn unused_vertices_are_dropped_and_the_triangles_renumbered() {
        let good = scaled(&icosphere(1), 20.0);
        let mut m = good.clone();
        // Strays before, between and after the surface's vertices.
        m.vertices.insert(0, [99.0, 0.0, 0.0]);
        m.vertices.insert(6, [98.0, 0.0, 0.0]);
        m.vertices.push([97.0, 0.0, 0.0]);
        for t in &mut m.triangles {
            *t = t.map(|i| if i >= 5 { i + 2 } else { i + 1 });
        }
        assert_eq!(drop_unused(&mut m), 3);
        assert_eq!(m, good);
    }

    #[test]
    fn a_hole_is_allowed_and_counted() {
        let mut m = scaled(&icosphere(2), 20.0);
        m.triangles.remove(10);
        let c = check(&m);
        assert_eq!(c.defects.boundary, 3);
        assert_eq!(c.refusal(), None);
    }
}
