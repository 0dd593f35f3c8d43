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
//!
//! **Diagonal mounts.** Gardner et al. also sweep the tube mounted at ±15° to the gantry's
//! cross direction, which moves the lobes with the normal's `y` component. A [`Tube`] with a
//! `yaw` is described in its own frame (the world turned by `−yaw` about `z`), where its axis
//! runs along `y` again; the functions here turn the point, normal and view into that frame
//! first, so the integration is the same for every mount.

use std::f64::consts::PI;

use crate::quad::{gauss_legendre, on_interval};
use crate::vec3::{dot, normalize, sub, V3};
use crate::ward::specular_lobe;

/// The tube's placement for one frame, millimetres. `x`, `y0` and `y1` are in the tube's own
/// frame: the world turned by `−yaw` about `z` (for `yaw = 0`, the world).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tube {
    /// Axis position along the frame's `x`.
    pub x: f64,
    /// Axis height above the reference plane `z = 0`.
    pub z: f64,
    /// Radius.
    pub radius: f64,
    /// Ends of the emitting length along the frame's `y`.
    pub y0: f64,
    /// See `y0`.
    pub y1: f64,
    /// The axis' turn about `z` from the world's `y` (counter-clockwise seen from above),
    /// radians: the axis runs along `(−sin yaw, cos yaw, 0)`.
    pub yaw: f64,
}

impl Tube {
    /// The tube with axis `centre + s·(−sin yaw, cos yaw, 0)` for `s` in `±length/2`.
    pub fn through(centre: V3, yaw: f64, radius: f64, length: f64) -> Tube {
        let c = turn(centre, -yaw);
        Tube { x: c[0], z: c[2], radius, y0: c[1] - length / 2.0, y1: c[1] + length / 2.0, yaw }
    }

    /// World vector `a` in the tube's frame.
    pub(crate) fn local(&self, a: V3) -> V3 {
        if self.yaw == 0.0 {
            a
        } else {
            turn(a, -self.yaw)
        }
    }
}

/// `a` turned by `angle` about `z`.
pub(crate) fn turn(a: V3, angle: f64) -> V3 {
    let (s, c) = angle.sin_cos();
    [c * a[0] - s * a[1], s * a[0] + c * a[1], a[2]]
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

    /// The order the virtual camera renders with: within 1e-8 of the specular lobe's peak for
    /// α ≥ 0.04 (4e-6 at α = 0.025) and 1e-11 of the diffuse lobe's, against a reference of
    /// 48 × (96 + 2·64) nodes (see the tests).
    pub fn render() -> Self {
        Self::new(16, 24, 8)
    }

    /// A cheaper order for the diffuse lobe alone (relative error below 1e-4, see the tests).
    pub fn diffuse() -> Self {
        Self::new(8, 16, 8)
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
/// The specular lobe is skipped where it cannot reach the tube (below e⁻²⁵ of its peak; see
/// the tests).
pub fn response(p: V3, n: V3, v: V3, tube: &Tube, alpha: Option<f64>, q: &Quadrature) -> Response {
    integrate(p, n, v, tube, alpha, q, true)
}

fn integrate(p: V3, n: V3, v: V3, tube: &Tube, alpha: Option<f64>, q: &Quadrature, cull: bool) -> Response {
    let (p, n, v) = (tube.local(p), tube.local(n), tube.local(v));
    let (dx, dz) = (p[0] - tube.x, p[2] - tube.z);
    let d = (dx * dx + dz * dz).sqrt();
    let r = tube.radius;
    if d <= r {
        return Response::default();
    }
    let alpha = alpha.filter(|&a| !(cull && lobe_misses(p, n, v, tube, d, a)));
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

/// The diffuse lobe's vector form: `E = ∫ wi / π dω` over the visible tube, so that
/// `D = n · E` for every normal `n` that sees the whole tube above its tangent plane (the usual
/// case: the fit of normals from the diagonal passes uses it to try many normals for the price
/// of one integration). Same quadrature and parametrisation as [`response`].
pub fn diffuse_vector(p: V3, tube: &Tube, q: &Quadrature) -> V3 {
    let pl = tube.local(p);
    let (dx, dz) = (pl[0] - tube.x, pl[2] - tube.z);
    let d = (dx * dx + dz * dz).sqrt();
    let r = tube.radius;
    if d <= r {
        return [0.0; 3];
    }
    let (u0, u1) = (((tube.y0 - pl[1]) / d).atan(), ((tube.y1 - pl[1]) / d).atan());
    let phi0 = dz.atan2(dx);
    let half = (r / d).acos();
    let mut e = [0.0; 3];
    for (u, wu) in on_interval(&q.centre, u0, u1) {
        let (s, c) = u.sin_cos();
        let y = pl[1] + d * s / c;
        let dy = d / (c * c);
        for (phi, wphi) in on_interval(&q.across, phi0 - half, phi0 + half) {
            let (sp, cp) = phi.sin_cos();
            let to = sub([tube.x + r * cp, y, tube.z + r * sp], pl);
            let dist2 = dot(to, to);
            let dist = dist2.sqrt();
            let wi = [to[0] / dist, to[1] / dist, to[2] / dist];
            let cos_q = -(cp * wi[0] + sp * wi[2]);
            if cos_q <= 0.0 {
                continue;
            }
            let w = wu * wphi * r * dy * cos_q / dist2 / PI;
            for k in 0..3 {
                e[k] += w * wi[k];
            }
        }
    }
    // Back to the world frame.
    if tube.yaw == 0.0 {
        e
    } else {
        turn(e, tube.yaw)
    }
}

/// Whether the specular lobe cannot reach the tube: the angle between the mirror direction
/// and the nearest direction to the tube, halved (the half vector turns half as far), is more
/// than 5α from the normal (the lobe is below e⁻²⁵ there). `pl`, `nl`, `vl` in the tube's
/// frame, `d` the distance from `pl` to the axis.
fn lobe_misses(pl: V3, nl: V3, vl: V3, tube: &Tube, d: f64, alpha: f64) -> bool {
    let m = normalize(mirror(nl, vl));
    let us = m[1].atan2((m[0] * m[0] + m[2] * m[2]).sqrt());
    let y = (pl[1] + d * us.tan()).clamp(tube.y0, tube.y1);
    let to_axis = normalize(sub([tube.x, y, tube.z], pl));
    let gap = crate::vec3::angle(to_axis, m) - (tube.radius / d).asin();
    gap > 0.0 && (gap / 2.0).tan() > 5.0 * alpha
}

/// `S(α)` alone.
pub fn specular_response(p: V3, n: V3, v: V3, tube: &Tube, alpha: f64, q: &Quadrature) -> f64 {
    response(p, n, v, tube, Some(alpha), q).specular
}

/// Whether the tube hides point `p` from a camera in unit direction `v`: the view ray meets the
/// cylinder between its ends (the camera then sees the tube itself).
pub fn hides(p: V3, v: V3, tube: &Tube) -> bool {
    hides_local(tube.local(p), tube.local(v), tube)
}

/// [`hides`] for every tube of a pass, each widened by `margin` (mm): the point and view
/// turned into the tubes' frame once per yaw, not once per tube (a pass' tubes share one;
/// two `sin_cos` a frame had cost more than the test itself).
pub fn hidden_by(p: V3, v: V3, tubes: &[Tube], margin: f64) -> Vec<bool> {
    let mut frame: Option<(f64, V3, V3)> = None;
    tubes
        .iter()
        .map(|t| {
            let (pl, vl) = match frame {
                Some((yaw, pl, vl)) if yaw == t.yaw => (pl, vl),
                _ => {
                    let (pl, vl) = (t.local(p), t.local(v));
                    frame = Some((t.yaw, pl, vl));
                    (pl, vl)
                }
            };
            hides_local(pl, vl, &Tube { radius: t.radius + margin, ..*t })
        })
        .collect()
}

/// [`hides`] for `p` and `v` already in the tube's frame.
pub(crate) fn hides_local(p: V3, v: V3, tube: &Tube) -> bool {
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
        Tube { x, z: 50.0, radius: 6.0, y0: -1e5, y1: 1e5, yaw: 0.0 }
    }

    #[test]
    fn white_plane_under_a_long_tube_matches_the_view_factor() {
        // The closed form r·h/(h² + Δx²) for an infinitely long cylinder; 2·10⁵ mm is long
        // enough that the ends contribute below 1e-9.
        let up = [0.0, 0.0, 1.0];
        for q in [Quadrature::render(), Quadrature::new(48, 96, 64)] {
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

    /// The largest errors of rule `q` against a far higher one (48 × (96 + 2·64) nodes) over a
    /// pass of a tube, relative to the lobes' peaks: specular, diffuse.
    fn worst_against_reference(q: &Quadrature, alpha: f64) -> (f64, f64) {
        let v = normalize([-0.5, 0.05, 1.0]);
        let n = normalize([0.03, -0.02, 1.0]);
        let p = [3.0, -4.0, 0.5];
        let reference = Quadrature::new(48, 96, 64);
        let (mut speak, mut dpeak) = (0f64, 0f64);
        let mut rows = Vec::new();
        for i in -80..=80 {
            let t = Tube { x: i as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 };
            let a = integrate(p, n, v, &t, Some(alpha), q, false);
            let b = integrate(p, n, v, &t, Some(alpha), &reference, false);
            speak = speak.max(b.specular);
            dpeak = dpeak.max(b.diffuse);
            rows.push((a, b));
        }
        rows.iter().fold((0f64, 0f64), |w, (a, b)| {
            (w.0.max((a.specular - b.specular).abs() / speak), w.1.max((a.diffuse - b.diffuse).abs() / dpeak))
        })
    }

    #[test]
    fn the_render_order_agrees_with_a_far_higher_one() {
        // Measured: specular 4e-6 of its peak at α 0.025, ≤ 1e-8 from 0.04; diffuse ≤ 1e-11.
        for (alpha, tol) in
            [(0.025, 1e-5), (0.04, 1e-7), (0.08, 1e-7), (0.16, 1e-7), (0.3, 1e-7), (0.5, 1e-7)]
        {
            let (es, ed) = worst_against_reference(&Quadrature::render(), alpha);
            assert!(es < tol && ed < 1e-9, "α {alpha}: specular off by {es:e}, diffuse by {ed:e}");
        }
    }

    #[test]
    fn the_diffuse_order_is_within_1e4() {
        let up = [0.0, 0.0, 1.0];
        for dx in [0.0, 10.0, 30.0, 60.0, 120.0, 300.0] {
            let t = Tube { x: dx, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 };
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
        let q = Quadrature::render();
        for alpha in [0.03, 0.1, 0.3] {
            let mut peak = 0f64;
            let mut rows = Vec::new();
            for i in -150..=150 {
                let t = Tube { x: i as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 };
                let full = integrate([0.0; 3], n, v, &t, Some(alpha), &q, false).specular;
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
        let t = Tube { x: -50.0, z: 50.0, radius: 6.0, y0: -100.0, y1: 100.0, yaw: 0.0 };
        assert!(hides([0.0, 0.0, 0.0], v, &t));
        assert!(!hides([9.0, 0.0, 0.0], v, &t)); // ray passes 9/√2 ≈ 6.4 mm from the axis
        assert!(hides([8.0, 0.0, 0.0], v, &t)); // 5.7 mm
        assert!(!hides([0.0, 120.0, 0.0], v, &t)); // beyond the tube's end
        assert!(!hides([0.0, 0.0, 0.0], normalize([1.0, 0.0, 1.0]), &t));
    }

    #[test]
    fn a_pass_hides_where_each_widened_tube_does() {
        // Two runs of yaws (the frame turned once per run) and a tube that hides the point only
        // once widened by the margin.
        let v = normalize([-1.0, 0.2, 1.0]);
        let p = [8.5, 3.0, 0.0];
        let mut tubes = Vec::new();
        for yaw in [0.0, 15f64.to_radians(), 15f64.to_radians(), -15f64.to_radians()] {
            for x in [-70.0, -50.0, -42.0, 0.0] {
                tubes.push(Tube::through(turn([x, 0.0, 50.0], yaw), yaw, 6.0, 200.0));
            }
        }
        let margin = 1.0;
        let got = hidden_by(p, v, &tubes, margin);
        let want: Vec<bool> =
            tubes.iter().map(|t| hides(p, v, &Tube { radius: t.radius + margin, ..*t })).collect();
        assert_eq!(got, want);
        assert!(want.iter().any(|&h| h) && want.iter().any(|&h| !h));
        let unwidened: Vec<bool> = tubes.iter().map(|t| hides(p, v, t)).collect();
        assert_ne!(want, unwidened, "the margin changes nothing here: pick another point");
    }

    #[test]
    fn a_turned_tube_sees_a_turned_scene() {
        // Turning tube, point, normal and view together about z changes nothing; a tube built
        // by `through` at yaw 0 is the plain one.
        let q = Quadrature::render();
        let (p, n, v) = ([3.0, -4.0, 0.5], normalize([0.03, -0.02, 1.0]), normalize([-0.5, 0.05, 1.0]));
        let yaw = 15f64.to_radians();
        for x in [-30.0, 0.0, 12.0, 29.0, 60.0] {
            let plain = Tube { x, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 };
            assert_eq!(Tube::through([x, 0.0, 50.0], 0.0, 6.0, 300.0), plain);
            let turned = Tube { yaw, ..plain };
            let (pt, nt, vt) = (turn(p, yaw), turn(n, yaw), turn(v, yaw));
            for alpha in [0.05, 0.2] {
                let a = response(p, n, v, &plain, Some(alpha), &q);
                let b = response(pt, nt, vt, &turned, Some(alpha), &q);
                assert!((a.diffuse - b.diffuse).abs() < 1e-12 && (a.specular - b.specular).abs() < 1e-12);
                let c = specular_response(pt, nt, vt, &turned, alpha, &q);
                assert!((c - a.specular).abs() < 1e-12);
            }
            assert_eq!(hides(p, v, &plain), hides(pt, vt, &turned));
        }
        // `through`: the centre lies on the axis, the ends `length/2` along (−sin, cos, 0).
        let t = Tube::through([10.0, 5.0, 50.0], yaw, 6.0, 300.0);
        let end = turn([t.x, t.y1, t.z], yaw);
        let want = [10.0 - 150.0 * yaw.sin(), 5.0 + 150.0 * yaw.cos(), 50.0];
        assert!((0..3).all(|k| (end[k] - want[k]).abs() < 1e-9), "{end:?} vs {want:?}");
    }

    #[test]
    fn the_diffuse_vector_gives_the_diffuse_lobe() {
        let q = Quadrature::diffuse();
        let p = [3.0, -4.0, 0.5];
        for yaw in [0.0, 15f64.to_radians(), -0.3] {
            for x in [-60.0, -10.0, 0.0, 25.0, 80.0] {
                let t = Tube::through([x, 0.0, 50.0], yaw, 6.0, 300.0);
                let e = diffuse_vector(p, &t, &q);
                for n in [[0.0, 0.0, 1.0], normalize([0.05, -0.08, 1.0])] {
                    let want = response(p, n, [0.0, 0.0, 1.0], &t, None, &q).diffuse;
                    let got = dot(n, e);
                    assert!((got - want).abs() < 1e-12 * want.max(1e-9), "{got} vs {want}");
                }
            }
        }
    }
}
