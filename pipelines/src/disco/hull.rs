//! Coarse pose guesses for registration when the scan's own frame is far from how the object
//! stands: the object's visual hull carved from the registration views' silhouettes, its
//! centroid and principal axes matched with the scanned mesh's.
//!
//! Silhouette registration ([`super::register::register`]) descends from a guess and reaches
//! some 20° and 10 mm; a scanner's frame can be anywhere. The hull is a superset of the object
//! (concavities are not carved, few views leave corners), so its moments place the mesh to a
//! few millimetres and degrees, which the descent then refines. A principal axis is known up to
//! its sign, so there are four proper rotations per match; where two of the hull's axes are
//! about as long as each other (an object round about an axis), the turn about the third is not
//! fixed by the moments, and the guesses include turns about it in [`SPIN_STEP_DEG`] steps.
//!
//! **Choice:** the mesh's moments are its solid's (signed tetrahedra from the origin), right
//! for a closed scan; a scan with holes gives rougher guesses.

use lightrig_imaging::calib::rodrigues_inv;
use lightrig_imaging::linalg::sym_eigen;

use super::optics::{turn, Pinhole};
use super::register::Pose;
use crate::firs::mesh::Mesh;
use crate::vec3::{add, cross, dot, norm, normalize, scale, sub, V3};

/// Cells along each side of the carved cube.
pub const HULL_CELLS: usize = 48;
/// Two axes are taken as equally long when their variances differ by less than this fraction.
pub const ROUND: f64 = 0.15;
/// The turn about an object's round axis between guesses, degrees.
pub const SPIN_STEP_DEG: f64 = 30.0;

/// A solid's volume, centroid and covariance about the centroid (mm³, mm, mm²).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Moments {
    pub volume: f64,
    pub centroid: V3,
    pub covariance: [[f64; 3]; 3],
}

impl Moments {
    /// From Σ1, Σx, Σxxᵀ (each times the volume element).
    fn from_sums(v: f64, s: V3, ss: [[f64; 3]; 3]) -> Option<Moments> {
        if v == 0.0 || !v.is_finite() {
            return None;
        }
        let c = scale(s, 1.0 / v);
        let covariance = std::array::from_fn(|i| std::array::from_fn(|j| ss[i][j] / v - c[i] * c[j]));
        Some(Moments { volume: v.abs(), centroid: c, covariance })
    }

    /// Principal axes as columns of a proper rotation, variances descending.
    pub fn axes(&self) -> ([f64; 3], [[f64; 3]; 3]) {
        let flat: Vec<f64> = self.covariance.iter().flatten().copied().collect();
        let (vals, vecs) = sym_eigen(&flat, 3);
        let mut e: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| vecs[i * 3 + j]));
        // Right-handed: the third axis the cross product of the first two.
        let (a, b) = (column(&e, 0), column(&e, 1));
        let c = cross(a, b);
        for (i, row) in e.iter_mut().enumerate() {
            row[2] = c[i];
        }
        ([vals[0], vals[1], vals[2]], e)
    }
}

fn column(m: &[[f64; 3]; 3], j: usize) -> V3 {
    [m[0][j], m[1][j], m[2][j]]
}

/// The closed mesh's solid moments (signed tetrahedra from the origin; `None` for a mesh that
/// encloses no volume).
pub fn mesh_moments(mesh: &Mesh) -> Option<Moments> {
    let (mut v, mut s, mut ss) = (0.0, [0.0; 3], [[0.0; 3]; 3]);
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let vol = dot(a, cross(b, c)) / 6.0;
        let sum = add(add(a, b), c);
        v += vol;
        s = add(s, scale(sum, vol / 4.0));
        // ∫xxᵀ over a tetrahedron with a vertex at the origin: V/20·(Σ vᵢvᵢᵀ + (Σ vᵢ)(Σ vᵢ)ᵀ).
        for (i, row) in ss.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x += vol / 20.0 * (a[i] * a[j] + b[i] * b[j] + c[i] * c[j] + sum[i] * sum[j]);
            }
        }
    }
    Moments::from_sums(v, s, ss)
}

/// One view for carving: camera, turntable angle, silhouette (row-major, the camera's size).
pub struct HullView<'a> {
    pub camera: &'a Pinhole,
    pub turntable_deg: f64,
    pub mask: &'a [bool],
}

/// The point nearest (least squares) to every view's ray through its silhouette's centre, in
/// the turntable's frame: where the object stands. `None` without views or when all rays are
/// parallel.
pub fn silhouette_centre(views: &[HullView]) -> Option<V3> {
    let (mut a, mut b) = ([[0.0; 3]; 3], [0.0; 3]);
    for v in views {
        let w = v.camera.width as usize;
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0usize);
        for (i, _) in v.mask.iter().enumerate().filter(|p| *p.1) {
            sx += (i % w) as f64 + 0.5;
            sy += (i / w) as f64 + 0.5;
            n += 1;
        }
        if n == 0 {
            continue;
        }
        let d = turn(v.camera.ray(sx / n as f64, sy / n as f64), -v.turntable_deg);
        let e = turn(v.camera.eye, -v.turntable_deg);
        // Σ (I − ddᵀ) p = Σ (I − ddᵀ) e.
        for i in 0..3 {
            for j in 0..3 {
                let m = f64::from(u8::from(i == j)) - d[i] * d[j];
                a[i][j] += m;
                b[i] += m * e[j];
            }
        }
    }
    crate::vec3::solve3(a, b)
}

/// The visual hull's moments: cells of a cube `2·half` mm across about `centre` (turntable
/// frame) kept where every view sees the cell's centre inside its silhouette (a cell outside a
/// frame is carved: the object stands clear of the frames' edges). `None` when nothing is left.
pub fn hull_moments(views: &[HullView], centre: V3, half: f64) -> Option<Moments> {
    let n = HULL_CELLS;
    let cell = 2.0 * half / n as f64;
    let (mut v, mut s, mut ss) = (0.0, [0.0; 3], [[0.0; 3]; 3]);
    let vol = cell * cell * cell;
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let p = add(centre, [i, j, k].map(|q| (q as f64 + 0.5) * cell - half));
                let inside = views.iter().all(|view| {
                    let Some((px, _)) = view.camera.project(turn(p, view.turntable_deg)) else {
                        return false;
                    };
                    let (w, h) = (view.camera.width as f64, view.camera.height as f64);
                    if px[0] < 0.0 || px[1] < 0.0 || px[0] >= w || px[1] >= h {
                        return false;
                    }
                    view.mask[px[1] as usize * view.camera.width as usize + px[0] as usize]
                });
                if inside {
                    v += vol;
                    s = add(s, scale(p, vol));
                    for (a, row) in ss.iter_mut().enumerate() {
                        for (b, x) in row.iter_mut().enumerate() {
                            *x += vol * p[a] * p[b];
                        }
                    }
                }
            }
        }
    }
    Moments::from_sums(v, s, ss)
}

/// Poses (mesh frame → turntable frame) that put the mesh's centroid on the hull's and its
/// principal axes on the hull's: the four sign choices, each also turned about an axis the
/// moments leave free (see the module's docs). Empty where the mesh or the hull has no volume.
pub fn guesses(mesh: &Mesh, views: &[HullView]) -> Vec<Pose> {
    let Some(m) = mesh_moments(mesh) else { return Vec::new() };
    let radius = mesh.vertices.iter().map(|&v| norm(sub(v, m.centroid))).fold(0.0, f64::max);
    let Some(centre) = silhouette_centre(views) else { return Vec::new() };
    // Room for the object and for the centre's error (the silhouettes' centres are not the
    // centroid's projections).
    let Some(h) = hull_moments(views, centre, 1.5 * radius + 5.0) else { return Vec::new() };
    let (lm, em) = m.axes();
    let (lh, eh) = h.axes();
    let round = |a: f64, b: f64| (a - b).abs() <= ROUND * a.max(b);
    // The axis the turn is about: the one whose variance stands apart from the other two.
    let free = if round(lh[0], lh[1]) || round(lm[0], lm[1]) {
        Some(2)
    } else if round(lh[1], lh[2]) || round(lm[1], lm[2]) {
        Some(0)
    } else {
        None
    };
    let spins = if free.is_some() { (360.0 / SPIN_STEP_DEG).round() as usize } else { 1 };
    let mut out = Vec::new();
    for signs in [[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]] {
        // R = E_h · S · E_mᵀ.
        let r: [[f64; 3]; 3] = std::array::from_fn(|i| {
            std::array::from_fn(|j| (0..3).map(|k| eh[i][k] * signs[k] * em[j][k]).sum())
        });
        for s in 0..spins {
            let r = match free {
                Some(a) => mul(&axis_turn(column(&eh, a), (s as f64 * SPIN_STEP_DEG).to_radians()), &r),
                None => r,
            };
            let rotation = rodrigues_inv(&r);
            let rotate = Pose { rotation, translation: [0.0; 3] };
            out.push(Pose { rotation, translation: sub(h.centroid, rotate.apply(m.centroid)) });
        }
    }
    out
}

fn mul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// The rotation by `angle` rad about unit axis `u`.
fn axis_turn(u: V3, angle: f64) -> [[f64; 3]; 3] {
    let u = normalize(u);
    lightrig_imaging::calib::rodrigues(scale(u, angle))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;
    use crate::disco::register::tests::{about_centre, rig_views};

    #[test]
    fn a_closed_meshs_moments_are_its_solids() {
        // The egg without its taper is an ellipsoid: volume 4/3·π·abc, centroid at its centre,
        // variances a²/5 (the icosphere's facets make it a little smaller).
        let e = crate::disco::mesh::icosphere(4);
        let (a, b, c) = (24.0, 20.0, 30.0);
        let mesh = Mesh {
            vertices: e.vertices.iter().map(|v| [a * v[0] + 5.0, b * v[1] - 3.0, c * v[2] + 30.0]).collect(),
            triangles: e.triangles.clone(),
        };
        let m = mesh_moments(&mesh).unwrap();
        let exact = 4.0 / 3.0 * std::f64::consts::PI * a * b * c;
        assert!((m.volume / exact - 1.0).abs() < 0.01, "{} against {exact}", m.volume);
        assert!(norm(sub(m.centroid, [5.0, -3.0, 30.0])) < 1e-9, "{:?}", m.centroid);
        for (i, r) in [a, b, c].iter().enumerate() {
            assert!((m.covariance[i][i] / (r * r / 5.0) - 1.0).abs() < 0.02, "{:?}", m.covariance);
            for j in 0..3 {
                if j != i {
                    assert!(m.covariance[i][j].abs() < 1e-9);
                }
            }
        }
        let (vals, axes) = m.axes();
        assert!(vals[0] > vals[1] && vals[1] > vals[2]);
        // The longest axis is z, the shortest y, as a proper rotation.
        assert!(column(&axes, 0)[2].abs() > 0.999 && column(&axes, 2)[1].abs() > 0.999);
        let det = dot(column(&axes, 0), cross(column(&axes, 1), column(&axes, 2)));
        assert!((det - 1.0).abs() < 1e-9);
        // An open surface (a triangle) encloses nothing.
        assert!(mesh_moments(&Mesh { vertices: vec![[0.0; 3]; 3], triangles: vec![[0, 1, 2]] }).is_none());
    }

    #[test]
    fn the_hull_stands_where_the_object_does() {
        let mesh = pebble(3, [24.0, 20.0, 30.0]);
        let truth = about_centre([1.2, -0.4, 0.9], [14.0, -9.0, 0.0]);
        let placed = truth.place(&mesh);
        let sil = rig_views(&mesh, &truth);
        // The egg stands clear of every frame's edges.
        for v in &sil {
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            assert!(v
                .mask
                .iter()
                .enumerate()
                .all(|(i, &m)| !m || (i % w > 2 && i % w < w - 3 && i / w > 2 && i / w < h - 3)));
        }
        let views: Vec<HullView> = sil
            .iter()
            .map(|v| HullView { camera: &v.camera, turntable_deg: v.turntable_deg, mask: &v.mask })
            .collect();
        let truth_m = mesh_moments(&placed).unwrap();
        let c = silhouette_centre(&views).unwrap();
        assert!(norm(sub(c, truth_m.centroid)) < 1.0, "{c:?} against {:?}", truth_m.centroid);
        let h = hull_moments(&views, c, 60.0).unwrap();
        // A superset (2.8 % larger here, from eight views), centred within 0.2 mm.
        assert!(
            h.volume > truth_m.volume && h.volume < 1.1 * truth_m.volume,
            "{} {}",
            h.volume,
            truth_m.volume
        );
        assert!(norm(sub(h.centroid, truth_m.centroid)) < 0.5);
        // One of the guesses puts every vertex within 3 mm of the truth (1.3 mm here).
        let g = guesses(&mesh, &views);
        assert_eq!(g.len(), 4, "the egg's axes are distinct: no turns");
        let best = g
            .iter()
            .map(|p| super::super::register::max_displacement(p, &truth, &mesh.vertices))
            .fold(f64::MAX, f64::min);
        assert!(best < 3.0, "nearest guess {best} mm off at some vertex");
        // No silhouettes, no guesses.
        assert!(guesses(&mesh, &[]).is_empty());
    }
}
