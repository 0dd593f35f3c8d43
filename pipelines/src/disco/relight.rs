//! The measured model under a new light: the global term of the hierarchical model (section 3.1)
//! rendered as the paper's renderer does it. Each vertex receives the flux its area takes from
//! the light through the boundary, `Φk = E·max(0, nk·l)·Ak·Ft(η, θk)`; `F` carries it to every
//! vertex, `Mr = Σk F(r, k)·Φk`; the radiance leaving towards the camera is
//! `Lr = Ft(η, θo)/π · Mr`, interpolated over each triangle (in log: the fall-off is
//! exponential) at the pixels that see it.

use rayon::prelude::*;

use crate::vec3::{dot, normalize, sub, V3};

use super::dipole::fresnel_transmittance;
use super::mesh::SurfaceMesh;
use super::optics::{point_of, surface_map, turn, turned, Pinhole};

/// A distant light: irradiance `irradiance` (per unit area across the beam) from direction
/// `towards` (unit, from the object to the light), in the object's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistantLight {
    pub towards: V3,
    pub irradiance: f64,
}

/// Each vertex's radiant exitance per channel under `light`, from `f` (`k·n + r`, any symmetric
/// or not `F` of `mesh`'s vertices).
pub fn exitance(
    mesh: &SurfaceMesh,
    f: &(dyn Fn(usize, usize) -> [f64; 3] + Sync),
    light: &DistantLight,
    eta: f64,
) -> Vec<[f64; 3]> {
    let n = mesh.vertices.len();
    let l = normalize(light.towards);
    let flux: Vec<f64> = (0..n)
        .map(|k| {
            let c = dot(mesh.normals[k], l);
            if c <= 0.0 {
                0.0
            } else {
                light.irradiance * c * mesh.areas[k] * fresnel_transmittance(eta, c)
            }
        })
        .collect();
    (0..n)
        .into_par_iter()
        .map(|r| {
            let mut m = [0.0; 3];
            for (k, &phi) in flux.iter().enumerate() {
                if phi > 0.0 {
                    let v = f(r, k);
                    for c in 0..3 {
                        m[c] += v[c] * phi;
                    }
                }
            }
            m
        })
        .collect()
}

/// Each vertex's exitance with the local term in the near field (section 3.1's hierarchy):
/// `F` carries the light from beyond vertex `r`'s one-ring; within it — where `F`'s entries are
/// means over hat functions of a response that changes by orders of magnitude — the local
/// model `m_r(d)` (the kernel of `r`'s texel, times its correction) is integrated against the
/// irradiance entering over the same hats' support: `∫ w_r(x)·m_r(|x − x_r|)·E·max(0, n·l)·Ft dx`,
/// `w_r` the sum of the hat functions of `r` and its ring (so the two terms split the surface
/// exactly as `F`'s entries did). Each triangle of the two-ring is split 8 × 8. `local(r)`
/// `None` keeps `F`'s near entries for that vertex.
pub fn exitance_local(
    mesh: &SurfaceMesh,
    f: &(dyn Fn(usize, usize) -> [f64; 3] + Sync),
    local: &(dyn Fn(usize) -> Option<(super::kernel::Profile, [f64; 3])> + Sync),
    light: &DistantLight,
    eta: f64,
) -> Vec<[f64; 3]> {
    let n = mesh.vertices.len();
    let l = normalize(light.towards);
    let global = exitance(mesh, f, light, eta);
    // Triangles per vertex, for the two-ring.
    let mut fan: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (t, tri) in mesh.triangles.iter().enumerate() {
        for &v in tri {
            fan[v as usize].push(t as u32);
        }
    }
    let split = 8u32;
    let centroids = sub_centroids(split);
    (0..n)
        .into_par_iter()
        .map(|r| {
            let Some((m, corr)) = local(r) else { return global[r] };
            let mut near: Vec<u32> =
                std::iter::once(r as u32).chain(mesh.rings[r].iter().map(|e| e.0)).collect();
            near.sort_unstable();
            // F's share from the near set, taken out.
            let mut out = global[r];
            for &k in &near {
                let c = dot(mesh.normals[k as usize], l);
                if c > 0.0 {
                    let phi = light.irradiance * c * mesh.areas[k as usize] * fresnel_transmittance(eta, c);
                    let v = f(r, k as usize);
                    for ch in 0..3 {
                        out[ch] -= v[ch] * phi;
                    }
                }
            }
            let mut tris: Vec<u32> = near.iter().flat_map(|&k| fan[k as usize].iter().copied()).collect();
            tris.sort_unstable();
            tris.dedup();
            let xr = mesh.vertices[r];
            let mut add = [0.0; 3];
            for &t in &tris {
                let tri = mesh.triangles[t as usize];
                let nrm = mesh.face_normal(t as usize);
                let c = dot(nrm, l);
                if c <= 0.0 {
                    continue;
                }
                let [a, b, cc] = tri.map(|i| mesh.vertices[i as usize]);
                let area = 0.5 * crate::vec3::norm(crate::vec3::cross(sub(b, a), sub(cc, a)));
                let e = light.irradiance * c * fresnel_transmittance(eta, c) * area / centroids.len() as f64;
                let inn = tri.map(|v| near.binary_search(&v).is_ok());
                for &(u, v) in &centroids {
                    let bary = [1.0 - u - v, u, v];
                    let w: f64 = (0..3).filter(|&j| inn[j]).map(|j| bary[j]).sum();
                    if w <= 0.0 {
                        continue;
                    }
                    let x = crate::vec3::add(
                        crate::vec3::add(crate::vec3::scale(a, bary[0]), crate::vec3::scale(b, bary[1])),
                        crate::vec3::scale(cc, bary[2]),
                    );
                    let d = crate::vec3::norm(sub(x, xr));
                    for (ch, s) in add.iter_mut().enumerate() {
                        *s += w * e * m.eval(ch, d);
                    }
                }
            }
            for ch in 0..3 {
                out[ch] = out[ch].max(0.0) + add[ch] * corr[ch];
            }
            out
        })
        .collect()
}

/// The barycentric `(u, v)` of the centroids of a triangle split `split × split` (equal areas):
/// `(i + ⅓, j + ⅓)` upright and `(i + ⅔, j + ⅔)` inverted, in units of `1/split`.
pub fn sub_centroids(split: u32) -> Vec<(f64, f64)> {
    let s = f64::from(split);
    let mut out = Vec::with_capacity((split * split) as usize);
    for i in 0..split {
        for j in 0..(split - i) {
            let (fi, fj) = (f64::from(i), f64::from(j));
            out.push(((fi + 1.0 / 3.0) / s, (fj + 1.0 / 3.0) / s));
            if i + j + 1 < split {
                out.push(((fi + 2.0 / 3.0) / s, (fj + 2.0 / 3.0) / s));
            }
        }
    }
    out
}

/// The object turned to `deg` seen by `cam` with per-vertex exitance `m`: linear RGB radiance
/// per pixel (row-major, 3 per pixel; the background 0).
pub fn render(mesh: &SurfaceMesh, m: &[[f64; 3]], cam: &Pinhole, deg: f64, eta: f64) -> Vec<f32> {
    render_detailed(mesh, m, cam, deg, eta, &|_, _| [1.0; 3])
}

/// [`render`] with each pixel's response multiplied by a detail texture at the surface point it
/// sees, `detail(triangle, barycentrics)` (section 6.3's `T_ρ`).
pub fn render_detailed(
    mesh: &SurfaceMesh,
    m: &[[f64; 3]],
    cam: &Pinhole,
    deg: f64,
    eta: f64,
    detail: &(dyn Fn(u32, [f64; 3]) -> [f64; 3] + Sync),
) -> Vec<f32> {
    let world = turned(mesh, deg);
    let map = surface_map(mesh, &world, cam);
    let mut out = vec![0.0f32; map.len() * 3];
    out.par_chunks_mut(3).zip(map.par_iter()).for_each(|(px, hit)| {
        let Some(hit) = hit else { return };
        let (p, n) = point_of(mesh, &world, deg, hit);
        let ft = fresnel_transmittance(eta, dot(n, normalize(sub(cam.eye, p))));
        let t = mesh.triangles[hit.triangle as usize];
        let skin = detail(hit.triangle, hit.bary.map(f64::from));
        for c in 0..3 {
            let vals = t.map(|v| m[v as usize][c]);
            let v = if vals.iter().all(|&x| x > 0.0) {
                (0..3).map(|j| f64::from(hit.bary[j]) * vals[j].ln()).sum::<f64>().exp()
            } else {
                (0..3).map(|j| f64::from(hit.bary[j]) * vals[j].max(0.0)).sum::<f64>()
            };
            px[c] = (ft / std::f64::consts::PI * v * skin[c]) as f32;
        }
    });
    out
}

/// The light of [`render`]'s default picture: from above and to the side of `cam`, so the lit
/// side and the light that crosses into the shadowed side are both in view (object frame, the
/// turntable at `deg`).
pub fn side_light(cam: &Pinhole, deg: f64) -> DistantLight {
    let view = normalize(sub(cam.eye, [0.0, 0.0, 30.0]));
    let side = normalize(crate::vec3::cross([0.0, 0.0, 1.0], view));
    let world =
        normalize(crate::vec3::add(crate::vec3::add(side, [0.0, 0.0, 0.6]), crate::vec3::scale(view, 0.2)));
    DistantLight { towards: turn(world, -deg), irradiance: 1.0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;

    #[test]
    fn a_lambertian_like_f_gives_the_flux_back() {
        // F(r, k) = δ(r, k)/A_r: each vertex re-emits what it takes, M_r = E·cos·Ft.
        let mesh = SurfaceMesh::new(&pebble(2, [20.0, 20.0, 30.0]));
        let light = DistantLight { towards: [0.0, 0.0, 1.0], irradiance: 2.0 };
        let f = |r: usize, k: usize| if r == k { [1.0 / mesh.areas[r]; 3] } else { [0.0; 3] };
        let m = exitance(&mesh, &f, &light, 1.3);
        for (k, mk) in m.iter().enumerate() {
            let c = mesh.normals[k][2];
            let want = if c > 0.0 { 2.0 * c * fresnel_transmittance(1.3, c) } else { 0.0 };
            assert!((mk[0] - want).abs() < 1e-12, "{k}: {mk:?} vs {want}");
        }
        // Rendered, the top is bright and the background dark.
        let cam = Pinhole::looking(64, 64, 80.0, [150.0, 0.0, 90.0], [0.0, 0.0, 30.0]);
        let img = render(&mesh, &m, &cam, 0.0, 1.3);
        assert_eq!(img[0], 0.0);
        assert!(img.iter().copied().fold(0.0f32, f32::max) > 0.1);
        // A detail texture multiplies each pixel by its value at the point the pixel sees.
        let half = render_detailed(&mesh, &m, &cam, 0.0, 1.3, &|_, _| [0.5, 1.0, 2.0]);
        for (a, b) in img.chunks(3).zip(half.chunks(3)) {
            assert_eq!([b[0], b[1], b[2]], [a[0] * 0.5, a[1], a[2] * 2.0]);
        }
    }

    #[test]
    fn the_local_term_replaces_the_near_entries_over_the_same_support() {
        // With m(d) = 1/A-like constant kernel c and F's near entries the hat means of the same
        // constant, the two exitances agree: w_r sums to the near hats' area.
        let mesh = SurfaceMesh::new(&pebble(3, [20.0, 20.0, 30.0]));
        let light = DistantLight { towards: [0.0, 0.0, 1.0], irradiance: 1.0 };
        let near = |r: usize, k: usize| r == k || mesh.rings[r].iter().any(|e| e.0 as usize == k);
        let f = |r: usize, k: usize| if near(r, k) { [0.01; 3] } else { [0.0; 3] };
        let flat =
            super::super::kernel::Profile { sigma: [1e-9, 1e-9], c1: [0.01; 3], c2: [0.0; 3], misfit: 0.0 };
        let g = exitance(&mesh, &f, &light, 1.3);
        let l = exitance_local(&mesh, &f, &|_| Some((flat, [1.0; 3])), &light, 1.3);
        // Vertices whose whole two-ring faces the light (lumped vertex vs face normals agree).
        let mut checked = 0;
        for r in 0..mesh.vertices.len() {
            if mesh.normals[r][2] > 0.95 {
                assert!((l[r][0] / g[r][0] - 1.0).abs() < 0.03, "{r}: {:?} vs {:?}", l[r], g[r]);
                checked += 1;
            }
        }
        assert!(checked > 3);
        // No local model: F's exitance unchanged.
        assert_eq!(exitance_local(&mesh, &f, &|_| None, &light, 1.3), g);
    }
}
