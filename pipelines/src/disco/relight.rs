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

/// The object turned to `deg` seen by `cam` with per-vertex exitance `m`: linear RGB radiance
/// per pixel (row-major, 3 per pixel; the background 0).
pub fn render(mesh: &SurfaceMesh, m: &[[f64; 3]], cam: &Pinhole, deg: f64, eta: f64) -> Vec<f32> {
    let world = turned(mesh, deg);
    let map = surface_map(mesh, &world, cam);
    let mut out = vec![0.0f32; map.len() * 3];
    out.par_chunks_mut(3).zip(map.par_iter()).for_each(|(px, hit)| {
        let Some(hit) = hit else { return };
        let (p, n) = point_of(mesh, &world, deg, hit);
        let ft = fresnel_transmittance(eta, dot(n, normalize(sub(cam.eye, p))));
        let t = mesh.triangles[hit.triangle as usize];
        for c in 0..3 {
            let vals = t.map(|v| m[v as usize][c]);
            let v = if vals.iter().all(|&x| x > 0.0) {
                (0..3).map(|j| f64::from(hit.bary[j]) * vals[j].ln()).sum::<f64>().exp()
            } else {
                (0..3).map(|j| f64::from(hit.bary[j]) * vals[j].max(0.0)).sum::<f64>()
            };
            px[c] = (ft / std::f64::consts::PI * v) as f32;
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
    }
}
