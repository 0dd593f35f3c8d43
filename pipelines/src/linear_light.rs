//! A linear light source: a cylinder of uniform radiance whose axis runs parallel to the
//! sample plane along `y` (the gantry moves it along `x`), as in Gardner et al. 2003.
//!
//! [`response`] integrates the two Ward lobes over the part of the cylinder's surface a point
//! sees, numerically across its width and along its length:
//!
//! `L = Le · (ρd · D + ρs · S(α))`,  `D = ∫ cosθi / π dω`,  `S(α) = ∫ lobe(α) cosθi dω`,
//!
//! with `dω = cosθq dA / |q − p|²` for a point `q` on the cylinder with normal `nq`.
//!
//! **Parametrisation.** Along the tube, by the elevation angle `u` of the direction out of the
//! plane through `p` perpendicular to the axis: `y = p_y + d·tan u` (`d` the distance from `p` to
//! the axis in that plane). The specular lobe is a bump in `u` of width ≈ 2α around the mirror
//! direction's elevation `u_s`, so the `u` range is cut into three panels, the middle one
//! `u_s ± 8α` wide, each with its own Gauss–Legendre rule. Across the tube, by the angle `φ`
//! around the axis, over the visible arc `φ0 ± acos(r/d)`; the integrand vanishes smoothly at the
//! arc's ends (grazing), which Gauss–Legendre handles well.
//!
//! For a white Lambertian plane under an infinitely long tube `D` has the closed form
//! `r·h / (h² + Δx²)` (the view factor of a parallel cylinder), which the tests check.

use std::f64::consts::PI;

use crate::quad::{gauss_legendre, on_interval};
use crate::vec3::{dot, normalize, sub, V3};
use crate::ward::specular_lobe;

/// The tube's placement for one frame, millimetres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tube {
    /// Axis position along `x`.
    pub x: f64,
    /// Axis height above the reference plane `z = 0`.
    pub z: f64,
    /// Radius.
    pub radius: f64,
    /// Ends of the emitting length along `y`.
    pub y0: f64,
    /// See `y0`.
    pub y1: f64,
}

/// Quadrature orders: Gauss–Legendre nodes across the tube and per panel along it.
#[derive(Debug, Clone)]
pub struct Quadrature {
    across: Vec<(f64, f64)>,
    centre: Vec<(f64, f64)>,
    outer: Vec<(f64, f64)>,
}

impl Quadrature {
    /// `across` nodes over the visible arc, `centre` nodes on the specular panel, `outer` on
    /// each of the two outer panels.
    pub fn new(across: usize, centre: usize, outer: usize) -> Self {
        Self { across: gauss_legendre(across), centre: gauss_legendre(centre), outer: gauss_legendre(outer) }
    }

    /// The order the fit uses: error below 1e-6 of the lobe's peak for α ≥ 0.03 (see the tests).
    pub fn fit() -> Self {
        Self::new(16, 24, 8)
    }

    /// A cheaper order for the diffuse lobe alone (relative error below 1e-4, see the tests).
    pub fn diffuse() -> Self {
        Self::new(8, 16, 8)
    }

    /// The order the virtual camera renders with: well beyond the fit's.
    pub fn render() -> Self {
        Self::new(24, 48, 32)
    }

    /// Nodes per evaluation.
    pub fn nodes(&self) -> usize {
        self.across.len() * (self.centre.len() + 2 * self.outer.len())
    }
}

/// The two lobes' responses at one point for a unit-radiance tube and unit albedos.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Response {
    /// `D`: the diffuse lobe (`ρd = 1`).
    pub diffuse: f64,
    /// `S(α)`: the specular lobe (`ρs = 1`); zero when no `α` was asked for.
    pub specular: f64,
}

/// The mirror direction of `v` about `n`.
pub fn mirror(n: V3, v: V3) -> V3 {
    let c = 2.0 * dot(n, v);
    [c * n[0] - v[0], c * n[1] - v[1], c * n[2] - v[2]]
}

/// Responses at point `p` with unit normal `n`, seen from unit direction `v` (towards the
/// camera), under `tube`; the specular lobe for roughness `alpha` if given.
pub fn response(p: V3, n: V3, v: V3, tube: &Tube, alpha: Option<f64>, q: &Quadrature) -> Response {
    let (dx, dz) = (p[0] - tube.x, p[2] - tube.z);
    let d = (dx * dx + dz * dz).sqrt();
    let r = tube.radius;
    if d <= r {
        return Response::default();
    }
    let (u0, u1) = (((tube.y0 - p[1]) / d).atan(), ((tube.y1 - p[1]) / d).atan());
    // The visible arc of the cross-section, centred on the direction from the axis to p.
    let phi0 = dz.atan2(dx);
    let half = (r / d).acos();
    // Panels along u: the specular one around the mirror direction's elevation.
    let mut panels = [(u0, u1, &q.centre); 3];
    let mut count = 1;
    if let Some(a) = alpha {
        let m = normalize(mirror(n, v));
        let us = m[1].atan2((m[0] * m[0] + m[2] * m[2]).sqrt());
        let (c0, c1) = ((us - 8.0 * a).max(u0), (us + 8.0 * a).min(u1));
        if c0 < c1 {
            panels = [(u0, c0, &q.outer), (c0, c1, &q.centre), (c1, u1, &q.outer)];
            count = 3;
        }
    }
    let co = dot(n, v);
    let mut out = Response::default();
    for &(a, b, rule) in &panels[..count] {
        if b <= a {
            continue;
        }
        for (u, wu) in on_interval(rule, a, b) {
            let (s, c) = u.sin_cos();
            let y = p[1] + d * s / c;
            let dy = d / (c * c); // dy/du
            for (phi, wphi) in on_interval(&q.across, phi0 - half, phi0 + half) {
                let (sp, cp) = phi.sin_cos();
                let qp = [tube.x + r * cp, y, tube.z + r * sp];
                let to = sub(qp, p);
                let dist2 = dot(to, to);
                let dist = dist2.sqrt();
                let wi = [to[0] / dist, to[1] / dist, to[2] / dist];
                let cos_q = -(cp * wi[0] + sp * wi[2]);
                let ci = dot(n, wi);
                if cos_q <= 0.0 || ci <= 0.0 {
                    continue;
                }
                let domega = wu * wphi * r * dy * cos_q / dist2;
                out.diffuse += ci / PI * domega;
                if let (Some(al), true) = (alpha, co > 0.0) {
                    out.specular += specular_lobe(n, wi, v, al) * ci * domega;
                }
            }
        }
    }
    out
}

/// `S(α)` alone, zero without integrating when the lobe cannot reach the tube: the angle
/// between the mirror direction and the nearest direction to the tube, halved (the half vector
/// turns half as far), is more than 5α from the normal (the lobe is below e⁻²⁵ there).
pub fn specular_response(p: V3, n: V3, v: V3, tube: &Tube, alpha: f64, q: &Quadrature) -> f64 {
    let (dx, dz) = (p[0] - tube.x, p[2] - tube.z);
    let d = (dx * dx + dz * dz).sqrt();
    if d <= tube.radius {
        return 0.0;
    }
    let m = normalize(mirror(n, v));
    let us = m[1].atan2((m[0] * m[0] + m[2] * m[2]).sqrt());
    let y = (p[1] + d * us.tan()).clamp(tube.y0, tube.y1);
    let to_axis = normalize(sub([tube.x, y, tube.z], p));
    let gap = crate::vec3::angle(to_axis, m) - (tube.radius / d).asin();
    if gap > 0.0 && (gap / 2.0).tan() > 5.0 * alpha {
        return 0.0;
    }
    response(p, n, v, tube, Some(alpha), q).specular
}

/// Whether the tube hides point `p` from a camera in unit direction `v`: the view ray meets the
/// cylinder between its ends (the camera then sees the tube itself).
pub fn hides(p: V3, v: V3, tube: &Tube) -> bool {
    // Distance from the axis (a line along y) to the ray, in the xz-plane.
    let (ox, oz) = (p[0] - tube.x, p[2] - tube.z);
    let (vx, vz) = (v[0], v[2]);
    let a = vx * vx + vz * vz;
    if a <= 0.0 {
        return false;
    }
    let t = -(ox * vx + oz * vz) / a;
    if t <= 0.0 {
        return ox * ox + oz * oz < tube.radius * tube.radius;
    }
    let (cx, cz) = (ox + t * vx, oz + t * vz);
    if cx * cx + cz * cz >= tube.radius * tube.radius {
        return false;
    }
    let y = p[1] + t * v[1];
    y >= tube.y0 && y <= tube.y1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tube(x: f64) -> Tube {
        Tube { x, z: 50.0, radius: 6.0, y0: -1e5, y1: 1e5 }
    }

    #[test]
    fn white_plane_under_a_long_tube_matches_the_view_factor() {
        // The closed form r·h/(h² + Δx²) for an infinitely long cylinder; 2·10⁵ mm is long
        // enough that the ends contribute below 1e-9.
        let up = [0.0, 0.0, 1.0];
        for q in [Quadrature::fit(), Quadrature::render()] {
            for dx in [0.0, 10.0, 30.0, 60.0, 120.0, 300.0] {
                let t = tube(dx);
                let want = t.radius * t.z / (t.z * t.z + dx * dx);
                // Alone, and beside the specular lobe's panels.
                for alpha in [None, Some(0.04), Some(0.3)] {
                    let got = response([0.0, 0.0, 0.0], up, up, &t, alpha, &q).diffuse;
                    assert!((got / want - 1.0).abs() < 1e-6, "Δx {dx}, α {alpha:?}: {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn fit_order_agrees_with_render_order_on_the_specular_lobe() {
        let v = normalize([-0.5, 0.05, 1.0]);
        let n = normalize([0.03, -0.02, 1.0]);
        let p = [3.0, -4.0, 0.5];
        for alpha in [0.03, 0.04, 0.08, 0.16, 0.3, 0.5] {
            let (fit, render) = (Quadrature::fit(), Quadrature::render());
            let mut peak = 0f64;
            let mut worst = 0f64;
            let mut rows = Vec::new();
            for i in -80..=80 {
                let t = Tube { x: i as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0 };
                let a = response(p, n, v, &t, Some(alpha), &fit).specular;
                let b = response(p, n, v, &t, Some(alpha), &render).specular;
                peak = peak.max(b);
                rows.push((a, b));
            }
            for (a, b) in rows {
                worst = worst.max((a - b).abs() / peak);
            }
            assert!(worst < 1e-6, "α {alpha}: fit order off by {worst:e} of the peak");
        }
    }

    #[test]
    fn the_diffuse_order_is_within_1e4() {
        let up = [0.0, 0.0, 1.0];
        for dx in [0.0, 10.0, 30.0, 60.0, 120.0, 300.0] {
            let t = Tube { x: dx, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0 };
            let p = [0.0, 20.0, 1.0];
            let a = response(p, up, up, &t, None, &Quadrature::diffuse()).diffuse;
            let b = response(p, up, up, &t, None, &Quadrature::render()).diffuse;
            assert!((a / b - 1.0).abs() < 1e-4, "Δx {dx}: {a} vs {b}");
        }
    }

    #[test]
    fn culled_specular_is_negligible_and_the_rest_exact() {
        let v = normalize([-0.5, 0.05, 1.0]);
        let n = normalize([0.03, -0.02, 1.0]);
        let q = Quadrature::fit();
        for alpha in [0.03, 0.1, 0.3] {
            let mut peak = 0f64;
            let mut rows = Vec::new();
            for i in -150..=150 {
                let t = Tube { x: i as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0 };
                let full = response([0.0; 3], n, v, &t, Some(alpha), &q).specular;
                let culled = specular_response([0.0; 3], n, v, &t, alpha, &q);
                peak = peak.max(full);
                rows.push((full, culled));
            }
            let culled = rows.iter().filter(|r| r.1 == 0.0).count();
            // A broad lobe reaches the tube from everywhere in this range.
            assert!(culled > 0 || alpha > 0.2, "α {alpha}: nothing culled");
            for (full, c) in rows {
                assert!((full - c).abs() <= 1e-9 * peak, "α {alpha}: {full} vs {c}");
            }
        }
    }

    #[test]
    fn the_tube_hides_the_points_behind_it() {
        let v = normalize([-1.0, 0.0, 1.0]); // camera up and to −x at 45°
        let t = Tube { x: -50.0, z: 50.0, radius: 6.0, y0: -100.0, y1: 100.0 };
        assert!(hides([0.0, 0.0, 0.0], v, &t));
        assert!(!hides([9.0, 0.0, 0.0], v, &t)); // ray passes 9/√2 ≈ 6.4 mm from the axis
        assert!(hides([8.0, 0.0, 0.0], v, &t)); // 5.7 mm
        assert!(!hides([0.0, 120.0, 0.0], v, &t)); // beyond the tube's end
        assert!(!hides([0.0, 0.0, 0.0], normalize([1.0, 0.0, 1.0]), &t));
    }
}
