//! A pixel's model traces over a whole pass, integrated in direction space: every frame's
//! diffuse response `D_k` and specular response `S_k(α)` for the price of one integration per
//! trial `(n, α)` instead of one per frame (which is what [`crate::lls::linear_light::response`]
//! costs, and why the fit used to take minutes).
//!
//! **Why it works.** Seen from a point `p`, parametrise directions in the tube's frame (axis
//! along `y`) by the angle `θ` in the `xz`-plane and the elevation `u` out of it:
//! `ω = (cos u cos θ, sin u, cos u sin θ)`, `dω = cos u du dθ`. A ray's projection onto the
//! `xz`-plane meets the tube's circular cross-section exactly when `θ` lies within
//! `θ_k ± asin(r/d_k)` of the direction to the axis, whatever `u` is; it then meets the
//! cylinder between the ends when `u` lies between `atan((y0 − p_y)/ρ)` and
//! `atan((y1 − p_y)/ρ)`, `ρ` the distance to the cylinder in that plane. So frame `k` sees a
//! band `[θ_k − a_k, θ_k + a_k] × [u0_k, u1_k]` of one and the same integrand
//! `g(θ, u) = lobe(n, ω, v, α) · (n·ω) · cos u`, which does not depend on the frame. We
//! evaluate `g` once on a grid of Gauss–Legendre panels around the mirror direction, sized by
//! `α`, and each frame's `S_k` is a weighted sum over the nodes in its band: whole panels with
//! their own weights, the panels a band edge cuts with the integrals of their Lagrange basis
//! polynomials up to the edge.
//!
//! **Approximations**, each tested against [`crate::lls::linear_light::response`] at high order:
//! - `ρ` varies across a band (from `d − r` at its centre to `√(d² − r²)` at its edges), so
//!   the `u` limits do too; we use their mean over the band, which makes the error second
//!   order. It matters only where the lobe reaches the tube's ends (broad lobes).
//! - The grid stops `12α` from the mirror direction, where the lobe is below `e⁻³⁶`.
//! - The diffuse lobe uses the same mean limits and is then closed form per frame:
//!   `∫ cos²u du = (u + sin u cos u)/2`, `∫ sin u cos u du = sin²u/2`, and the `θ` integrals
//!   of `cos θ`, `sin θ`; as in [`crate::lls::linear_light::diffuse_vector`], `D = n·E`.

use std::f64::consts::{FRAC_1_PI, PI};
use std::sync::OnceLock;

use super::table::{lobe_geometry, AlphaLobes, LobeTables, PixelLobes, TableLobe};
use crate::lls::linear_light::{hides_local, mirror, turn, Tube};
use crate::quad::gauss_legendre;
use crate::vec3::{dot, normalize, V3};

/// Nodes per panel.
const N: usize = 8;
/// Panel edges around the mirror direction, in units of `α`.
const EDGES: [f64; 6] = [-12.0, -5.0, -2.0, 2.0, 5.0, 12.0];
/// The GGX lobe's panels: a core `±α`, then edges in a ratio of 2.5 out to `250α` (beyond any
/// band union for α ≥ 0.02): the tails' `1/θ⁴` is smooth on each.
const GGX_EDGES: [f64; 14] =
    [-250.0, -100.0, -40.0, -16.0, -6.0, -2.5, -1.0, 1.0, 2.5, 6.0, 16.0, 40.0, 100.0, 250.0];

/// The reference rule on `[−1, 1]` and the Legendre coefficients of its Lagrange basis:
/// `ℓ_i(τ) = Σ_q c[i][q] P_q(τ)` with `c[i][q] = (2q + 1)/2 · w_i · P_q(t_i)` (the rule is
/// exact for `ℓ_i P_q`, of degree ≤ 2N − 2).
struct Rule {
    t: [f64; N],
    w: [f64; N],
    c: [[f64; N]; N],
}

fn rule() -> &'static Rule {
    static RULE: OnceLock<Rule> = OnceLock::new();
    RULE.get_or_init(|| {
        let gl = gauss_legendre(N);
        let mut r = Rule { t: [0.0; N], w: [0.0; N], c: [[0.0; N]; N] };
        for (i, &(t, w)) in gl.iter().enumerate() {
            r.t[i] = t;
            r.w[i] = w;
            let p = legendre(t);
            for (q, c) in r.c[i].iter_mut().enumerate() {
                *c = (2 * q + 1) as f64 / 2.0 * w * p[q];
            }
        }
        r
    })
}

/// `P_0(τ) … P_N(τ)` by the three-term recurrence.
fn legendre(t: f64) -> [f64; N + 1] {
    let mut p = [0.0; N + 1];
    p[0] = 1.0;
    p[1] = t;
    for k in 2..=N {
        p[k] = ((2 * k - 1) as f64 * t * p[k - 1] - (k - 1) as f64 * p[k - 2]) / k as f64;
    }
    p
}

/// `∫_{-1}^{τ} P_q` for `q < N`: `τ + 1`, then `(P_{q+1} − P_{q−1})/(2q + 1)`.
fn legendre_integrals(t: f64) -> [f64; N] {
    let p = legendre(t.clamp(-1.0, 1.0));
    let mut out = [0.0; N];
    out[0] = t.clamp(-1.0, 1.0) + 1.0;
    for q in 1..N {
        out[q] = (p[q + 1] - p[q - 1]) / (2 * q + 1) as f64;
    }
    out
}

/// One Gauss–Legendre panel on `[a, b]`.
#[derive(Debug, Clone, Copy)]
struct Panel {
    a: f64,
    b: f64,
}

impl Panel {
    fn node(&self, i: usize) -> (f64, f64) {
        let r = rule();
        let (m, h) = ((self.a + self.b) / 2.0, (self.b - self.a) / 2.0);
        (m + h * r.t[i], h * r.w[i])
    }

    /// `∫_x0^x1 ℓ_i` over the panel for every node `i`, `x0 ≤ x1` inside the panel.
    fn partial(&self, x0: f64, x1: f64) -> [f64; N] {
        let h = (self.b - self.a) / 2.0;
        if h <= 0.0 {
            return [0.0; N];
        }
        let m = (self.a + self.b) / 2.0;
        let (i0, i1) = (legendre_integrals((x0 - m) / h), legendre_integrals((x1 - m) / h));
        let r = rule();
        let mut out = [0.0; N];
        for (i, o) in out.iter_mut().enumerate() {
            *o = h * (0..N).map(|q| r.c[i][q] * (i1[q] - i0[q])).sum::<f64>();
        }
        out
    }
}

/// Panels around `centre` (edges at `centre + edges·α`), clipped to `[lo, hi]`.
fn panels(centre: f64, alpha: f64, edges: &[f64], lo: f64, hi: f64) -> Vec<Panel> {
    edges
        .windows(2)
        .map(|e| Panel { a: (centre + e[0] * alpha).max(lo), b: (centre + e[1] * alpha).min(hi) })
        .filter(|p| p.b > p.a)
        .collect()
}

/// The panel holding `x` (the last whose start is at or below it).
fn panel_of(panels: &[Panel], x: f64) -> usize {
    panels.partition_point(|p| p.a <= x).saturating_sub(1)
}

/// One frame as a band of directions, in its segment's tube frame.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Band {
    /// `θ` range; empty (`lo == hi`) when the point is inside the tube.
    lo: f64,
    hi: f64,
    /// Mean `u` limits over the band.
    u0: f64,
    u1: f64,
}

/// A run of frames with one tube yaw: the point and view in that tube frame.
#[derive(Debug, Clone)]
struct Segment {
    yaw: f64,
    start: usize,
    end: usize,
    v: V3,
    /// The union of the bands, `θ` and `u`.
    theta: (f64, f64),
    u: (f64, f64),
    /// Whether the bands' `θ` limits both rise (`Some(true)`) or both fall (`Some(false)`)
    /// from frame to frame, as in a gantry pass: then the frames a lobe reaches are found by
    /// bisection.
    order: Option<bool>,
    /// Where the tube moves by equal steps from frame to frame (so that a trace is a smooth
    /// function of the frame index) and every band is non-empty: the bands' largest step in
    /// `θ` and in `u` between neighbouring frames. A broad lobe's trace is then looked up
    /// every few frames and interpolated ([`TabledTraces::specular_into`]).
    steps: Option<(f64, f64)>,
    /// Where its diffuse vectors start in [`TraceModel`]'s, and the frames from one to the
    /// next (1: every frame's; more: the computed frames', from two strides before the
    /// segment's start, the frames between interpolated).
    e_start: usize,
    e_stride: usize,
}

/// One pixel's view of a pass (or several passes): the bands of every frame, built once,
/// then [`TraceModel::diffuse`] and [`TraceModel::specular`] for any normal and roughness.
#[derive(Debug, Clone)]
pub struct TraceModel {
    bands: Vec<Band>,
    segments: Vec<Segment>,
    /// The diffuse vectors in the world frame (`D = n·e`), per segment as it says.
    es: Vec<V3>,
}

/// The mean `u` limits' rule: four-node Gauss–Legendre in `ψ` on `[−π/2, π/2]`, where
/// `sin φ = (r/d)·sin ψ`; its nodes come in pairs `±ψ` that give the same `ρ`, so the two with
/// `ψ > 0` as `(sin ψ, cos ψ, weight)`.
fn mean_rule() -> &'static [(f64, f64, f64); 2] {
    static R: OnceLock<[(f64, f64, f64); 2]> = OnceLock::new();
    R.get_or_init(|| {
        let mut out = [(0.0, 0.0, 0.0); 2];
        let pos = gauss_legendre(4).into_iter().filter(|&(x, _)| x > 0.0);
        for (o, (x, w)) in out.iter_mut().zip(pos) {
            let psi = x * PI / 2.0;
            *o = (psi.sin(), psi.cos(), w * PI / 2.0);
        }
        out
    })
}

/// `(sin x, cos x)` by their Taylor series for `|x| ≤ 0.2` (error below 1e-15), else `sin_cos`.
fn sin_cos_small(x: f64) -> (f64, f64) {
    if x.abs() > 0.2 {
        return x.sin_cos();
    }
    // Products with the reciprocals, not divisions (a division costs several products).
    let x2 = x * x;
    let s = x
        * (1.0
            - x2 * (1.0 / 6.0)
                * (1.0 - x2 * (1.0 / 20.0) * (1.0 - x2 * (1.0 / 42.0) * (1.0 - x2 * (1.0 / 72.0)))));
    let c = 1.0
        - x2 * 0.5
            * (1.0
                - x2 * (1.0 / 12.0)
                    * (1.0 - x2 * (1.0 / 30.0) * (1.0 - x2 * (1.0 / 56.0) * (1.0 - x2 * (1.0 / 90.0)))));
    (s, c)
}

/// `A(ū) = (ū + sin ū cos ū)/2` and `B(ū) = sin²ū/2` for `ū = atan(q) + δ`, without
/// trigonometric calls: `sin 2u`, `cos 2u` of `atan q` are rational in `q` (`iq = 1/(1 + q²)`),
/// and `δ` (the mean limit's distance from one node's) is small.
fn limit_terms(u: f64, q: f64, iq: f64, delta: f64) -> (f64, f64) {
    let (s2, c2) = (2.0 * q * iq, (1.0 - q * q) * iq);
    let (sd, cd) = sin_cos_small(2.0 * delta);
    let (s, c) = (s2 * cd + c2 * sd, c2 * cd - s2 * sd);
    ((u + s / 2.0) / 2.0, (1.0 - c) / 4.0)
}

/// `atan x` by its series for `|x| ≤` [`SMALL_TURN`] (the next term is below 1e-19 of `x`).
/// The series in `y = x²` summed by Estrin's scheme (pairs, then pairs of pairs): the terms'
/// chains of products are a few deep instead of ten, and a model's frames wait on them.
fn atan_small(x: f64) -> f64 {
    let y = x * x;
    let (y2, c) = (y * y, |k: f64| 1.0 / (2.0 * k + 1.0));
    let y4 = y2 * y2;
    let pair = |k: f64| c(k) - y * c(k + 1.0); // the terms 2k and 2k + 1 over y^2k
    let (a0, a1, a2, a3, a4) = (pair(0.0), pair(2.0), pair(4.0), pair(6.0), pair(8.0));
    let (b0, b1, b2) = (a0 + y2 * a1, a2 + y2 * a3, a4 + y2 * c(10.0));
    x * (b0 + y4 * (b1 + y4 * b2))
}

/// The largest `tan` of an angle step taken by [`atan_small`] (large enough for the steps
/// between the exactly computed frames of an interpolated pass, see [`BAND_SPAN`]).
const SMALL_TURN: f64 = 0.15;

/// Frames between exact (`atan2`, `asin`, `atan`) evaluations of a band's angles; in between,
/// each angle is the previous frame's plus the small step between them. The steps are exact to
/// rounding (see [`atan_small`]); re-anchoring keeps the rounding from adding up (measured:
/// within 1e-15 of the exact angles, see the tests).
const ANCHOR: usize = 32;

/// `atan(num/den)` for a small angle: `den > 0` and `|num| ≤ SMALL_TURN·den`.
fn small(num: f64, den: f64) -> bool {
    den > 0.0 && num.abs() <= SMALL_TURN * den
}

/// A frame's angles, for the next frame's steps: the tangent directions (unnormalised) and
/// their angles, and `q = y/ρ̄` and `atan q` at both ends.
#[derive(Debug, Clone, Copy)]
struct Carry {
    vlo: [f64; 2],
    vhi: [f64; 2],
    lo: f64,
    hi: f64,
    q: [f64; 2],
    atan_q: [f64; 2],
}

/// The angle steps from `p` to this frame's tangent directions `vlo`, `vhi` and to `atan q`
/// (`atan(a × b / a · b)` and `atan((q1 − q0)/(1 + q0·q1))`), with one division for the four;
/// `None` unless every one is small.
fn steps(p: &Carry, vlo: [f64; 2], vhi: [f64; 2], q: [f64; 2]) -> Option<[f64; 4]> {
    let turn = |a: [f64; 2], b: [f64; 2]| (a[0] * b[1] - a[1] * b[0], a[0] * b[0] + a[1] * b[1]);
    let at = |q0: f64, q1: f64| (q1 - q0, 1.0 + q0 * q1);
    let f = [turn(p.vlo, vlo), turn(p.vhi, vhi), at(p.q[0], q[0]), at(p.q[1], q[1])];
    if !f.iter().all(|&(n, d)| small(n, d)) {
        return None;
    }
    let (d01, d23) = (f[0].1 * f[1].1, f[2].1 * f[3].1);
    let inv = 1.0 / (d01 * d23);
    let (i01, i23) = (d23 * inv, d01 * inv); // 1/(d0·d1), 1/(d2·d3)
    Some([
        atan_small(f[0].0 * f[1].1 * i01),
        atan_small(f[1].0 * f[0].1 * i01),
        atan_small(f[2].0 * f[3].1 * i23),
        atan_small(f[3].0 * f[2].1 * i23),
    ])
}

/// A mean `u` limit `ū` from `q = y/ρ̄`, `iq = 1/(1 + q²)` and `u = atan q`: by the Taylor
/// series of `atan(y/ρ)` about the weighted mean `ρ̄` to the third central moment (one
/// `atan` instead of one per node) when the nodes lie close together (`close`), else node by
/// node (nodes `ρ`, weights `w`).
#[allow(clippy::too_many_arguments)]
fn mean_atan(
    y: f64,
    q: f64,
    iq: f64,
    u: f64,
    inv_mean: f64,
    moments: (f64, f64),
    rho_w: ([f64; 2], [f64; 2]),
    close: bool,
) -> f64 {
    if close {
        let (m2, m3) = moments;
        // d/dρ of atan(y/ρ), second and third, at ρ̄ (with y = q·ρ̄).
        let f2 = 2.0 * q * iq * iq * inv_mean * inv_mean;
        let f3 = 2.0 * q * (q * q - 3.0) * iq * iq * iq * inv_mean * inv_mean * inv_mean;
        return u + f2 * m2 / 2.0 + f3 * m3 / 6.0;
    }
    let (rho, w) = rho_w;
    (w[0] * (y / rho[0]).atan() + w[1] * (y / rho[1]).atan()) / (w[0] + w[1])
}

/// Frame `tube`'s band seen from `pl` (the tube's frame); its diffuse vector `e` also in the
/// tube's frame. `prev`: the previous frame's angles in the same segment, to step from (the
/// angles are then found without trigonometric calls where the steps are small), and this
/// frame's for the next. Divisions are shared (`1/(ab)` gives `1/a` and `1/b`): they, not the
/// additions, bound the time a frame takes.
fn band_of(pl: V3, t: &Tube, prev: Option<&Carry>) -> (Band, V3, Option<Carry>) {
    let (cx, cz) = (t.x - pl[0], t.z - pl[2]);
    let d2 = cx * cx + cz * cz;
    let r = t.radius;
    if d2 <= r * r {
        return (Band { lo: 0.0, hi: 0.0, u0: 0.0, u1: 0.0 }, [0.0; 3], None);
    }
    let d = d2.sqrt();
    let inv_d = 1.0 / d;
    let sa = r * inv_d;
    // The tangent directions from the point to the cross-section: the direction to the axis
    // turned by ∓a, with sin a = r/d, cos a = l/d; scaled by d².
    let l = (d2 - r * r).sqrt();
    let (vlo, vhi) = ([cx * l + cz * r, cz * l - cx * r], [cx * l - cz * r, cz * l + cx * r]);
    // The mean over φ ∈ [−a, a] of the u limits, with sin φ = (r/d)·sin ψ so that the square
    // root's edge behaviour becomes smooth: ρ = d·cos φ − r·cos ψ, dφ ∝ cos ψ / cos φ dψ
    // (the weights scaled by cos φ0·cos φ1, which the mean divides out).
    let [(sp0, cp0, wr0), (sp1, cp1, wr1)] = *mean_rule();
    let (s0, s1) = (sa * sp0, sa * sp1);
    let (c0, c1) = ((1.0 - s0 * s0).sqrt(), (1.0 - s1 * s1).sqrt());
    let rho = [d * c0 - r * cp0, d * c1 - r * cp1];
    let w = [wr0 * cp0 * c1, wr1 * cp1 * c0];
    let (wsum, wrho) = (w[0] + w[1], w[0] * rho[0] + w[1] * rho[1]);
    let inv = 1.0 / (wsum * wrho);
    let (inv_wsum, inv_mean) = (wrho * inv, wsum * wsum * inv);
    let mean = wrho * inv_wsum;
    let (d0, d1) = (rho[0] - mean, rho[1] - mean);
    let m2 = (w[0] * d0 * d0 + w[1] * d1 * d1) * inv_wsum;
    let m3 = (w[0] * d0 * d0 * d0 + w[1] * d1 * d1 * d1) * inv_wsum;
    let (y0, y1) = (t.y0 - pl[1], t.y1 - pl[1]);
    let q = [y0 * inv_mean, y1 * inv_mean];
    let (p0, p1) = (1.0 + q[0] * q[0], 1.0 + q[1] * q[1]);
    let inv_p = 1.0 / (p0 * p1);
    let (iq0, iq1) = (p1 * inv_p, p0 * inv_p);
    // Stepping is only done above the point (cz > 0), where `atan2(cz, cx)` does not wrap.
    let stepped = prev.filter(|_| cz > 0.0).and_then(|p| {
        let s = steps(p, vlo, vhi, q)?;
        Some([p.lo + s[0], p.hi + s[1], p.atan_q[0] + s[2], p.atan_q[1] + s[3]])
    });
    let [lo, hi, a0, a1] = stepped.unwrap_or_else(|| {
        let (centre, a) = (cz.atan2(cx), sa.asin());
        [centre - a, centre + a, q[0].atan(), q[1].atan()]
    });
    let a = (hi - lo) / 2.0;
    // The series' next term is below (r/d)⁴ of the limits' curvature scale: 1e-9 rad at the
    // rigs' r/d ≈ 0.1; node by node beyond r/d = 0.3.
    let close = sa <= 0.3;
    let u0 = mean_atan(y0, q[0], iq0, a0, inv_mean, (m2, m3), (rho, w), close);
    let u1 = mean_atan(y1, q[1], iq1, a1, inv_mean, (m2, m3), (rho, w), close);
    let ((big_a0, big_b0), (big_a1, big_b1)) =
        (limit_terms(u0, q[0], iq0, u0 - a0), limit_terms(u1, q[1], iq1, u1 - a1));
    let (da, db) = (big_a1 - big_a0, big_b1 - big_b0);
    // sin(c + a) − sin(c − a) = 2 cos c sin a, cos(c − a) − cos(c + a) = 2 sin c sin a.
    let k = 2.0 * r * inv_d * inv_d * FRAC_1_PI;
    let e = [da * k * cx, db * 2.0 * a * FRAC_1_PI, da * k * cz];
    let carry = Carry { vlo, vhi, lo, hi, q, atan_q: [a0, a1] };
    (Band { lo, hi, u0, u1 }, e, Some(carry))
}

/// The larger of two numbers, not NaN (a plain comparison, unlike `f64::max`).
fn most(a: f64, b: f64) -> f64 {
    if b > a {
        b
    } else {
        a
    }
}

/// The smaller of two numbers, not NaN.
fn least(a: f64, b: f64) -> f64 {
    if b < a {
        b
    } else {
        a
    }
}

/// Whether the tubes differ from frame to frame by one and the same step (to 1e-9 mm).
fn evenly_spaced(tubes: &[Tube]) -> bool {
    let delta = |a: &Tube, b: &Tube| [b.x - a.x, b.z - a.z, b.radius - a.radius, b.y0 - a.y0, b.y1 - a.y1];
    let Some(first) = tubes.windows(2).next().map(|w| delta(&w[0], &w[1])) else { return false };
    tubes.windows(2).all(|w| delta(&w[0], &w[1]).iter().zip(&first).all(|(a, b)| (a - b).abs() <= 1e-9))
}

/// How far (in the lobe's scaled coordinates, `t` and `s` of [`super::table`]) the bands may
/// move between two looked-up frames of an interpolated trace, and the most frames between
/// them. The cubic interpolation's error is then below 1e-5 of the pass' peak (see the tests).
const SAMPLE_STEP: f64 = 0.25;
const MAX_STRIDE: usize = 16;

/// `S_k` for the frames `a..b` of a segment of `len` frames (`out` the segment's, one slice
/// per value `look(k)` gives: the trace, and where asked its derivatives), looked up at every
/// `stride`-th frame and interpolated by cubics in between (the frames a cubic cannot be
/// centred on looked up too). The trace (`out[0]`) is kept non-negative.
fn interpolated<const K: usize>(
    mut look: impl FnMut(usize) -> [f64; K],
    len: usize,
    (a, b): (usize, usize),
    stride: usize,
    samples: &mut Vec<[f64; K]>,
    mut out: [&mut [f64]; K],
) {
    let put = |out: &mut [&mut [f64]; K], k: usize, v: [f64; K]| {
        for (o, v) in out.iter_mut().zip(v) {
            o[k] = v;
        }
    };
    if stride <= 1 || b <= a {
        for k in a..b {
            put(&mut out, k, look(k));
        }
        return;
    }
    // Samples at a + (j − 1)·stride inside the segment, one either side of a..b where there
    // is room.
    let first = usize::from(a >= stride);
    let last = (len - 1 - a) / stride + 1; // j of the last frame in the segment, +1
    let want = (b - 1 - a) / stride + 3;
    let (j0, j1) = (1 - first, last.min(want)); // sample j held for j0 ≤ j ≤ j1
    let count = j1 + 1 - j0;
    if count < 4 {
        for k in a..b {
            put(&mut out, k, look(k));
        }
        return;
    }
    samples.clear();
    samples.extend((j0..=j1).map(|j| look(a + j * stride - stride)));
    let inv = 1.0 / stride as f64;
    // The weights at x (in sample units from the stencil's first sample).
    let cubic = |x: f64| {
        [
            -(x - 1.0) * (x - 2.0) * (x - 3.0) / 6.0,
            x * (x - 2.0) * (x - 3.0) / 2.0,
            -x * (x - 1.0) * (x - 3.0) / 2.0,
            x * (x - 1.0) * (x - 2.0) / 6.0,
        ]
    };
    // Those of the frames between the middle two samples, once per trial.
    let mut inner = [[0.0; 4]; MAX_STRIDE];
    for (f, w) in inner.iter_mut().enumerate().take(stride) {
        *w = cubic(1.0 + f as f64 * inv);
    }
    // Frames past the last sample (at the segment's end): looked up.
    let end = b.min(a + (j1 - 1) * stride + 1);
    for k in end..b {
        put(&mut out, k, look(k));
    }
    // Interval by interval (sample j at frame a + (j − 1)·stride and the stride − 1 frames
    // after it): no division per frame (two integer divisions had cost more than the cubic).
    let (mut k, mut j) = (a, 1);
    while k < end {
        put(&mut out, k, samples[j - j0]);
        let stop = (k + stride).min(end);
        // The four samples around, shifted inwards at the ends.
        let base = (j - 1).max(j0).min(j1 - 3);
        let v = &samples[base - j0..base - j0 + 4];
        for (f, kf) in (k + 1..stop).enumerate() {
            let w = if base + 1 == j {
                inner[f + 1]
            } else {
                cubic(((kf - a) as f64 * inv + 1.0) - base as f64) // in sample units from `base`
            };
            for (q, o) in out.iter_mut().enumerate() {
                let x = w[0] * v[0][q] + w[1] * v[1][q] + w[2] * v[2][q] + w[3] * v[3][q];
                o[kf] = if q == 0 { x.max(0.0) } else { x };
            }
        }
        (k, j) = (stop, j + 1);
    }
}

/// How far the tube may move between two exactly computed frames of an evenly stepped pass,
/// as a fraction of its closest approach to the point (the distance over which the bands
/// bend): the frames between are interpolated by quintics through the six nearest computed
/// ones, whose error scales as the sixth power of this (measured: below 1e-9 rad, see the
/// tests).
const BAND_SPAN: f64 = 0.1;
/// The most frames from one computed frame to the next.
const MAX_BAND_STRIDE: usize = 8;
/// The least step a frame (radians, the mean between computed frames) for an interpolated
/// segment's bands to count as ordered: 25 times the quintics' largest error (4e-7, see the
/// tests), so that the frames between rise or fall with them. The rigs' steps are near 1e-3.
const ORDERED_STEP: f64 = 1e-5;

/// Where `run` (frames of one yaw, the tube moving by equal steps: [`evenly_spaced`]) stays
/// clear of the point `pl` (its frame): the frames between computed ones (≥ 2) that [`BAND_SPAN`] allows, and
/// the step from frame to frame (`x`, `z`, radius, `y0`, `y1`). `None`: compute every frame.
fn band_stride(pl: V3, run: &[Tube], span: f64) -> Option<(usize, [f64; 5])> {
    if run.len() < 8 || span <= 0.0 {
        return None;
    }
    let (t0, t1) = (&run[0], &run[1]);
    let step = [t1.x - t0.x, t1.z - t0.z, t1.radius - t0.radius, t1.y0 - t0.y0, t1.y1 - t0.y1];
    // The computed frames reach up to three strides beyond either end (quintic stencils
    // centred on every interval). The bands are smooth where the tube stays above the point
    // (`cz > r`, also what keeps `atan2` from wrapping); the height above it less the radius
    // bounds the distance over which they bend. `cz` and the radius move linearly, so the
    // ends tell.
    let reach = (3 * MAX_BAND_STRIDE) as f64;
    let last = (run.len() - 1) as f64;
    let clear = |k: f64| (t0.z + k * step[1] - pl[2]) - (t0.radius + k * step[2]);
    let a = clear(-reach).min(clear(last + reach));
    let len = step.iter().map(|s| s * s).sum::<f64>().sqrt();
    if a <= 0.0 || len <= 0.0 {
        return None;
    }
    let stride = ((span * a / len) as usize).min(MAX_BAND_STRIDE);
    (stride >= 2).then_some((stride, step))
}

/// Every frame of `run` computed ([`band_of`]), angles stepped between anchors.
fn exact_bands(
    pl: V3,
    run: &[Tube],
    anchor: usize,
    yaw: (f64, f64),
    bands: &mut Vec<Band>,
    es: &mut Vec<V3>,
) {
    let mut carry: Option<Carry> = None;
    for (k, t) in run.iter().enumerate() {
        let from = carry.as_ref().filter(|_| !k.is_multiple_of(anchor));
        let (b, e, next) = band_of(pl, t, from);
        carry = next;
        bands.push(b);
        es.push(to_world(e, yaw));
    }
}

/// A diffuse vector from a tube's frame to the world's (`yaw`: the tube's `(sin, cos)`).
fn to_world(e: V3, (sn, cs): (f64, f64)) -> V3 {
    [cs * e[0] - sn * e[1], sn * e[0] + cs * e[1], e[2]]
}

/// The Lagrange weights of the six nodes `−2 … 3` at `x`.
fn quintic(x: f64) -> [f64; 6] {
    std::array::from_fn(|i| {
        let xi = i as f64 - 2.0;
        (0..6).filter(|&j| j != i).map(|j| (x - (j as f64 - 2.0)) / (xi - (j as f64 - 2.0))).product()
    })
}

/// The bands of an evenly stepped `run`: computed at every `stride`-th frame (and up to three
/// strides beyond the ends, the tube moved on by its `step`, so that every frame's stencil is
/// centred), quintics in between, appended to `bands`; the computed frames' diffuse vectors,
/// turned to the world by `yaw` (`sin`, `cos`), to `es`. `samples`: scratch.
#[multiversion::multiversion(targets("x86_64+avx2+fma"))]
fn interpolated_bands(
    pl: V3,
    run: &[Tube],
    (stride, step): (usize, [f64; 5]),
    anchor: usize,
    yaw: (f64, f64),
    samples: &mut Vec<Band>,
    (bands, es): (&mut Vec<Band>, &mut Vec<V3>),
) {
    let n = run.len();
    // Computed frames j·stride for j in −2 ..= (n − 1)/stride + 3, held at j + 2.
    let last = (n - 1) / stride + 3;
    let t0 = run[0];
    samples.clear();
    let mut carry: Option<Carry> = None;
    for (i, j) in (-2..=last as isize).enumerate() {
        let k = j * stride as isize;
        let t = match usize::try_from(k) {
            Ok(k) if k < n => run[k],
            _ => {
                let f = k as f64;
                Tube {
                    x: t0.x + f * step[0],
                    z: t0.z + f * step[1],
                    radius: t0.radius + f * step[2],
                    y0: t0.y0 + f * step[3],
                    y1: t0.y1 + f * step[4],
                    yaw: t0.yaw,
                }
            }
        };
        let from = carry.as_ref().filter(|_| !i.is_multiple_of(anchor));
        let (b, e, next) = band_of(pl, &t, from);
        carry = next;
        samples.push(b);
        // The diffuse vectors only at the computed frames: a trace `n·e` is interpolated
        // when the normal is known (the same quintics, a quarter of the work).
        es.push(to_world(e, yaw));
    }
    let weights = quintic_weights(stride);
    let start = bands.len();
    bands.resize(start + n, Band { lo: 0.0, hi: 0.0, u0: 0.0, u1: 0.0 });
    // Interval j: frame j·stride (computed: its weights pick it exactly) and the next
    // stride − 1.
    for (j, chunk) in bands[start..].chunks_mut(stride).enumerate() {
        let s = &samples[j..j + 6];
        for (b, w) in chunk.iter_mut().zip(weights) {
            let mut acc = [0.0; 4];
            for (w, s) in w.iter().zip(s) {
                for (a, s) in acc.iter_mut().zip([s.lo, s.hi, s.u0, s.u1]) {
                    *a += w * s;
                }
            }
            *b = Band { lo: acc[0], hi: acc[1], u0: acc[2], u1: acc[3] };
        }
    }
}

/// The quintics' weights at each frame between two computed ones `stride` apart
/// (`1 ..= MAX_BAND_STRIDE`), worked out once.
fn quintic_weights(stride: usize) -> &'static [[f64; 6]; MAX_BAND_STRIDE] {
    static W: OnceLock<[[[f64; 6]; MAX_BAND_STRIDE]; MAX_BAND_STRIDE + 1]> = OnceLock::new();
    let all = W.get_or_init(|| {
        std::array::from_fn(|stride| {
            let mut weights = [[0.0; 6]; MAX_BAND_STRIDE];
            for (f, w) in weights.iter_mut().enumerate().take(stride) {
                *w = quintic(f as f64 / stride as f64);
            }
            weights
        })
    });
    &all[stride.min(MAX_BAND_STRIDE)]
}

/// What [`Segment`] says of its bands `b` (every frame's): their union (`θ`, `u`), whether
/// their limits rise or fall throughout, and, where every band is non-empty, their largest
/// steps (`θ`, `u`) from frame to frame.
#[allow(clippy::type_complexity)]
fn every_band(b: &[Band]) -> ((f64, f64), (f64, f64), Option<bool>, Option<(f64, f64)>) {
    // Plain comparisons on scalars: `f64::max`'s NaN handling, and tuples the compiler kept in
    // memory, made these chains cost as much as the interpolation.
    let (mut t_lo, mut t_hi, mut u_lo, mut u_hi) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    let (mut nonempty, mut rising, mut falling, mut dt, mut du) = (true, true, true, 0f64, 0f64);
    for (k, x) in b.iter().enumerate() {
        // Empty bands left out by selects, not branches (which kept the chains in memory).
        let some = x.hi > x.lo;
        nonempty &= some;
        let pick = |v: f64, none: f64| if some { v } else { none };
        t_lo = least(t_lo, pick(x.lo, f64::MAX));
        t_hi = most(t_hi, pick(x.hi, f64::MIN));
        u_lo = least(u_lo, pick(x.u0, f64::MAX));
        u_hi = most(u_hi, pick(x.u1, f64::MIN));
        if k > 0 {
            let w = &b[k - 1];
            let (dlo, dhi) = (x.lo - w.lo, x.hi - w.hi);
            rising &= dlo >= 0.0 && dhi >= 0.0;
            falling &= dlo <= 0.0 && dhi <= 0.0;
            dt = most(dt, most(dlo.abs(), dhi.abs()));
            du = most(du, most((x.u0 - w.u0).abs(), (x.u1 - w.u1).abs()));
        }
    }
    let order = order_of(nonempty, rising, falling);
    ((t_lo, t_hi), (u_lo, u_hi), order, nonempty.then_some((dt, du)))
}

/// A segment's order (see [`Segment`]): rising (`Some(true)`), else falling, where every band
/// is non-empty; `None` otherwise.
fn order_of(nonempty: bool, rising: bool, falling: bool) -> Option<bool> {
    match (nonempty, rising, falling) {
        (true, true, _) => Some(true),
        (true, false, true) => Some(false),
        _ => None,
    }
}

/// [`every_band`] for an interpolated segment (`b`, every frame's bands) from its `computed`
/// frames (every `stride`-th, from two strides before the first) and the frames of a few
/// intervals between them: around the computed frames where each limit is least or most (for
/// the union), and around the interval where each limit's mean step is largest (for the
/// largest steps). Where a limit and its step each peak once along the pass (as where the
/// tube passes over the point) the peaks lie there: the same as every frame's (tested), for
/// a few dozen frames' work instead of all. Rising or falling where every computed frame
/// steps the same way by more than [`ORDERED_STEP`] a frame, far above the quintics' error,
/// so that the frames between are ordered too.
#[allow(clippy::type_complexity)]
fn computed_bands(
    computed: &[Band],
    b: &[Band],
    stride: usize,
) -> ((f64, f64), (f64, f64), Option<bool>, Option<(f64, f64)>) {
    let n = b.len();
    let limits = |b: &Band| [b.lo, b.hi, b.u0, b.u1];
    // The frames between intervals: the computed ones inside the segment, and the last.
    let intervals = (n - 1).div_ceil(stride);
    let at = |i: usize| (i * stride).min(n - 1);
    let least_step = ORDERED_STEP * stride as f64;
    let rising =
        computed.windows(2).all(|w| w[1].lo - w[0].lo > least_step && w[1].hi - w[0].hi > least_step);
    let falling =
        computed.windows(2).all(|w| w[0].lo - w[1].lo > least_step && w[0].hi - w[1].hi > least_step);
    // One pass over those frames: the union there, where each limit is least or most, and
    // the interval where its mean step is largest.
    let (mut lower, mut upper) = ([f64::MAX; 4], [f64::MIN; 4]);
    let (mut ext, mut top, mut steepest) = ([0usize; 4], [0usize; 4], [f64::MIN; 4]);
    let mut nonempty = true;
    let mut prev = limits(&b[0]);
    for i in 0..=intervals {
        let x = limits(&b[at(i)]);
        nonempty &= x[1] > x[0];
        for q in 0..4 {
            // Lower limits least, upper ones most.
            if (q % 2 == 0 && x[q] < lower[q]) || (q % 2 == 1 && x[q] > upper[q]) {
                ext[q] = i;
            }
            (lower[q], upper[q]) = (least(lower[q], x[q]), most(upper[q], x[q]));
        }
        if i > 0 {
            let inv = 1.0 / (at(i) - at(i - 1)) as f64;
            for q in 0..4 {
                let mean = (x[q] - prev[q]).abs() * inv;
                if mean > steepest[q] {
                    (steepest[q], top[q]) = (mean, i - 1);
                }
            }
        }
        prev = x;
    }
    let order = order_of(nonempty, rising, falling);
    // The intervals to look into frame by frame: either side of each extreme frame, and each
    // steepest one with its neighbours; merged, then every frame of them.
    // (As the frames between: intervals `from..to`.)
    let mut ranges: [(usize, usize); 8] = std::array::from_fn(|r| {
        let (i, after) = if r < 4 { (ext[r], 1) } else { (top[r - 4], 2) };
        (i.saturating_sub(1), (i + after).min(intervals))
    });
    ranges.sort_unstable();
    let mut largest = [0f64; 4];
    let mut done = 0;
    for &(from, to) in &ranges {
        let from = from.max(done);
        if from >= to {
            continue;
        }
        let mut w = limits(&b[at(from)]);
        for x in b[at(from) + 1..=at(to)].iter().map(limits) {
            for q in 0..4 {
                (lower[q], upper[q]) = (least(lower[q], x[q]), most(upper[q], x[q]));
                largest[q] = most(largest[q], (x[q] - w[q]).abs());
            }
            w = x;
        }
        done = to;
    }
    let steps = (most(largest[0], largest[1]), most(largest[2], largest[3]));
    ((lower[0], upper[1]), (lower[2], upper[3]), order, nonempty.then_some(steps))
}

/// The frames' tubes of one pass (or several) as [`TraceModel`] takes them: split into runs of
/// one yaw, each run's spacing checked, once for every pixel of the pass (the checks had
/// taken a sixth of each pixel's model).
#[derive(Debug, Clone)]
pub struct Sweep {
    tubes: Vec<Tube>,
    /// `(start, end, evenly spaced)` of each run of frames with one yaw.
    runs: Vec<(usize, usize, bool)>,
}

impl Sweep {
    /// The sweep of the frames' `tubes`.
    pub fn new(tubes: &[Tube]) -> Self {
        let mut runs = Vec::new();
        let mut start = 0;
        while start < tubes.len() {
            let yaw = tubes[start].yaw;
            let end = tubes[start..].iter().position(|t| t.yaw != yaw).map_or(tubes.len(), |n| start + n);
            runs.push((start, end, evenly_spaced(&tubes[start..end])));
            start = end;
        }
        Sweep { tubes: tubes.to_vec(), runs }
    }

    /// The frames' tubes.
    pub fn tubes(&self) -> &[Tube] {
        &self.tubes
    }

    /// Whether each frame's tube, widened by `margin` (mm), hides point `p` from a camera in
    /// unit direction `v`: [`crate::lls::linear_light::hidden_by`]'s flags, tested only on the
    /// frames where the tube comes near the view ray (a few of an evenly spaced run; the
    /// test on every frame of every pass had been a thirtieth of the fit).
    pub fn hidden(&self, p: V3, v: V3, margin: f64) -> Vec<bool> {
        let mut out = vec![false; self.tubes.len()];
        for &(start, end, even) in &self.runs {
            let run = &self.tubes[start..end];
            let (pl, vl) = (run[0].local(p), run[0].local(v));
            let (from, to) = if even { near_ray(pl, vl, run, margin) } else { (0, run.len()) };
            for (k, t) in run.iter().enumerate().take(to).skip(from) {
                out[start + k] = hides_local(pl, vl, &Tube { radius: t.radius + margin, ..*t });
            }
        }
        out
    }
}

/// The frames of an evenly spaced `run` outside which no tube (widened by `margin`) can hide
/// `pl` from the view `vl` (both in the run's frame), as a range `from..to`. A tube hides the
/// point only where the view ray's line passes within its radius of the axis: in the
/// xz-plane, `|(pl − axis) × v| < r·|v|`. Along the run the axis and the radius move by equal
/// steps, so both sides are linear in the frame `k` and the frames where it holds are one
/// interval; two frames of margin either side absorb rounding (and the spacing's 1e-9 mm).
fn near_ray(pl: V3, vl: V3, run: &[Tube], margin: f64) -> (usize, usize) {
    let len = run.len();
    if len < 2 {
        return (0, len);
    }
    let (t0, t1) = (&run[0], &run[1]);
    let (vx, vz) = (vl[0], vl[2]);
    let norm = (vx * vx + vz * vz).sqrt();
    // |c0 + c1·k| < r0 + dr·k, everything times |v|.
    let c0 = (pl[0] - t0.x) * vz - (pl[2] - t0.z) * vx;
    let c1 = -(t1.x - t0.x) * vz + (t1.z - t0.z) * vx;
    let (r0, dr) = ((t0.radius + margin) * norm, (t1.radius - t0.radius) * norm);
    // Both `c0 + c1·k < r0 + dr·k` and `−(c0 + c1·k) < r0 + dr·k`: `m·k < b` each.
    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
    for (m, b) in [(c1 - dr, r0 - c0), (-c1 - dr, r0 + c0)] {
        if m > 0.0 {
            hi = hi.min(b / m);
        } else if m < 0.0 {
            lo = lo.max(b / m);
        } else if b <= 0.0 {
            return (0, 0);
        }
    }
    // NaN (a degenerate view) leaves the bound open: every frame is tested.
    let from = (lo.floor() - 2.0).max(0.0);
    let to = (hi.ceil() + 3.0).min(len as f64);
    if from >= to {
        return (0, 0);
    }
    (from as usize, to as usize)
}

impl TraceModel {
    /// The model for point `p` seen from unit direction `v` (towards the camera) under the
    /// frames' `tubes` ([`TraceModel::of`] a [`Sweep`] made for it alone).
    pub fn new(p: V3, v: V3, tubes: &[Tube]) -> Self {
        Self::of(p, v, &Sweep::new(tubes))
    }

    /// The model for point `p` seen from unit direction `v` (towards the camera) under the
    /// `sweep`'s tubes.
    pub fn of(p: V3, v: V3, sweep: &Sweep) -> Self {
        Self::built(p, v, sweep, ANCHOR, BAND_SPAN)
    }

    /// [`TraceModel::of`] with exact angles every `anchor` computed frames (1: every one),
    /// and evenly stepped passes computed every few frames as `span` allows (0: every frame).
    fn built(p: V3, v: V3, sweep: &Sweep, anchor: usize, span: f64) -> Self {
        let tubes = &sweep.tubes;
        let mut bands = Vec::with_capacity(tubes.len());
        let mut segments: Vec<Segment> = Vec::new();
        let mut samples = Vec::new();
        let mut es = Vec::with_capacity(tubes.len());
        for &(start, end, even) in &sweep.runs {
            let run = &tubes[start..end];
            let yaw = run[0].yaw;
            let pl = turn(p, -yaw);
            let e_start = es.len();
            let e_stride = match band_stride(pl, run, span).filter(|_| even) {
                Some(stride) => {
                    interpolated_bands(
                        pl,
                        run,
                        stride,
                        anchor,
                        yaw.sin_cos(),
                        &mut samples,
                        (&mut bands, &mut es),
                    );
                    stride.0
                }
                None => {
                    exact_bands(pl, run, anchor, yaw.sin_cos(), &mut bands, &mut es);
                    1
                }
            };
            let b = &bands[start..end];
            let (theta, u, order, steps) =
                if e_stride == 1 { every_band(b) } else { computed_bands(&samples, b, e_stride) };
            segments.push(Segment {
                yaw,
                start,
                end,
                v: turn(v, -yaw),
                theta,
                u,
                order,
                steps: steps.filter(|_| even),
                e_start,
                e_stride,
            });
        }
        TraceModel { bands, segments, es }
    }

    /// The frames of segment `s` (relative to its start) whose bands meet the `θ` range
    /// `window`: every frame but where the bands are ordered.
    fn frames_meeting(&self, s: &Segment, window: (f64, f64)) -> (usize, usize) {
        let b = &self.bands[s.start..s.end];
        let (lo, hi) = window;
        match s.order {
            // hi > lo_window holds on a suffix, lo < hi_window on a prefix.
            Some(true) => (b.partition_point(|b| b.hi <= lo), b.partition_point(|b| b.lo < hi)),
            // And the other way round.
            Some(false) => (b.partition_point(|b| b.lo >= hi), b.partition_point(|b| b.hi > lo)),
            None => (0, b.len()),
        }
    }

    /// Frames.
    pub fn len(&self) -> usize {
        self.bands.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.bands.is_empty()
    }

    /// `D_k` for unit normal `n` (world frame): the diffuse lobe for `ρd = 1`.
    pub fn diffuse(&self, n: V3) -> Vec<f64> {
        let mut out = vec![0.0; self.bands.len()];
        self.diffuse_into([n], [&mut out]);
        out.iter_mut().for_each(|o| *o = o.max(0.0));
        out
    }

    /// `n·E_k` for each of the vectors `ns` into its slice of `out` (`len()` values each, not
    /// clipped at zero: linear in `n`, so that for a tangent `dn` of the normal it is the
    /// derivative of [`TraceModel::diffuse`] where that is positive). Several at once share
    /// the interpolation's weights and loop.
    pub fn diffuse_into<const K: usize>(&self, ns: [V3; K], mut out: [&mut [f64]; K]) {
        for s in &self.segments {
            let (frames, es) = (s.end - s.start, &self.es[s.e_start..]);
            if s.e_stride == 1 {
                for (k, e) in es[..frames].iter().enumerate() {
                    for (o, n) in out.iter_mut().zip(&ns) {
                        o[s.start + k] = dot(*n, *e);
                    }
                }
                continue;
            }
            // The computed frames' traces, then the same quintics as the bands', trace by
            // trace (contiguous, no bounds checks in the loop).
            let stride = s.e_stride;
            let weights = quintic_weights(stride);
            let computed = &es[..(frames - 1) / stride + 6];
            for (o, n) in out.iter_mut().zip(&ns) {
                let d: Vec<f64> = computed.iter().map(|e| dot(*n, *e)).collect();
                // Interval j: frame j·stride (computed: its weights pick it exactly) and the
                // next stride − 1.
                for (j, chunk) in o[s.start..s.end].chunks_mut(stride).enumerate() {
                    let d = &d[j..j + 6];
                    for (x, w) in chunk.iter_mut().zip(weights) {
                        *x =
                            w[0] * d[0] + w[1] * d[1] + w[2] * d[2] + w[3] * d[3] + w[4] * d[4] + w[5] * d[5];
                    }
                }
            }
        }
    }

    /// The segment holding frame `k` and `D_k` for unit normal `n` (not clipped at zero;
    /// [`TraceModel::diffuse_into`]'s `k`-th value, bit for bit); `None` past the last frame.
    fn diffuse_at(&self, k: usize, n: V3) -> Option<(usize, f64)> {
        let at = self.segments.iter().position(|s| (s.start..s.end).contains(&k))?;
        let s = &self.segments[at];
        let (i, es) = (k - s.start, &self.es[s.e_start..]);
        if s.e_stride == 1 {
            return Some((at, dot(n, es[i])));
        }
        // As `diffuse_into`: interval `i / stride`, the computed frames from two before.
        let (j, w) = (i / s.e_stride, quintic_weights(s.e_stride)[i % s.e_stride]);
        Some((at, w.iter().zip(&es[j..j + 6]).map(|(w, e)| w * dot(n, *e)).sum()))
    }

    /// `S_k(α)` for unit normal `n`: the specular lobe for `ρs = 1`.
    pub fn specular(&self, n: V3, alpha: f64) -> Vec<f64> {
        let mut out = vec![0.0; self.bands.len()];
        for s in &self.segments {
            self.specular_segment(s, n, alpha, &mut out[s.start..s.end]);
        }
        out
    }

    /// `S_k(α)` from the shared [`LobeTables`]: a lookup per frame. A segment whose geometry
    /// or `α` the tables do not cover falls back to [`TraceModel::specular`]'s integration.
    pub fn specular_tabled(&self, n: V3, alpha: f64, tables: &LobeTables) -> Vec<f64> {
        let mut out = vec![0.0; self.bands.len()];
        self.tabled(n, tables).specular_into(alpha, &mut out);
        out
    }

    /// The traces for normal `n` from the tables, for several `α` (what they share kept).
    pub fn tabled<'a>(&'a self, n: V3, tables: &'a LobeTables) -> TabledTraces<'a> {
        let lobes = self
            .segments
            .iter()
            .map(|s| lobe_geometry(turn(n, -s.yaw), s.v).map(|g| PixelLobes::new(tables, g)))
            .collect();
        TabledTraces { model: self, n, lobes, samples: Vec::new() }
    }

    fn specular_segment(&self, s: &Segment, n: V3, alpha: f64, out: &mut [f64]) {
        let (nl, vl) = (turn(n, -s.yaw), s.v);
        let co = dot(nl, vl);
        if co <= 0.0 || alpha <= 0.0 {
            return;
        }
        let a2 = alpha * alpha;
        let k = 1.0 / (4.0 * PI * a2 * co.sqrt());
        // Ward's lobe times cos θi (the u Jacobian is applied by the caller).
        self.lobe_segment(s, nl, alpha, &EDGES, out, |wi, ci| {
            let h = normalize([wi[0] + vl[0], wi[1] + vl[1], wi[2] + vl[2]]);
            let c = dot(nl, h);
            let c2 = c * c;
            k * (-(1.0 - c2) / (c2 * a2)).exp() * ci.sqrt()
        });
    }

    /// `S_k(α)` for the GGX lobe ([`crate::ggx::specular_lobe`]) instead of Ward's, on a grid
    /// reaching the whole band union: GGX's tails fall as the fourth power of the angle, and a
    /// few per cent of the lobe lies beyond Ward's grid.
    pub fn specular_ggx(&self, n: V3, alpha: f64) -> Vec<f64> {
        let mut out = vec![0.0; self.bands.len()];
        for s in &self.segments {
            let (nl, vl) = (turn(n, -s.yaw), s.v);
            let co = dot(nl, vl);
            if co <= 0.0 || alpha <= 0.0 {
                continue;
            }
            let g1o = |h: V3| crate::ggx::smith_g1(nl, vl, h, alpha);
            self.lobe_segment(s, nl, alpha, &GGX_EDGES, &mut out[s.start..s.end], |wi, _ci| {
                let h = normalize([wi[0] + vl[0], wi[1] + vl[1], wi[2] + vl[2]]);
                crate::ggx::distribution(dot(nl, h), alpha) * crate::ggx::smith_g1(nl, wi, h, alpha) * g1o(h)
                    / (4.0 * co)
            });
        }
        out
    }

    /// The bands' integrals of `lobe(ωi, n·ωi)` (a lobe times `n·ωi`, in the segment's tube
    /// frame, `nl` the normal there) on panels with `edges` (in units of `α`) around the
    /// mirror direction.
    fn lobe_segment(
        &self,
        s: &Segment,
        nl: V3,
        alpha: f64,
        edges: &[f64],
        out: &mut [f64],
        lobe: impl Fn(V3, f64) -> f64,
    ) {
        let vl = s.v;
        if s.theta.1 <= s.theta.0 {
            return;
        }
        let m = normalize(mirror(nl, vl));
        let (tm, um) = (m[2].atan2(m[0]), m[1].atan2(m[0].hypot(m[2])));
        let tp = panels(tm, alpha, edges, s.theta.0, s.theta.1);
        let up = panels(um, alpha, edges, s.u.0, s.u.1);
        if tp.is_empty() || up.is_empty() {
            return;
        }
        let (nt, nu) = (tp.len() * N, up.len() * N);
        // g at every node, premultiplied by the u weight; and per θ node the sums over each
        // u panel.
        let unodes: Vec<(f64, f64, f64, f64)> = up
            .iter()
            .flat_map(|p| {
                (0..N).map(move |j| {
                    let (u, w) = p.node(j);
                    let (su, cu) = u.sin_cos();
                    (u, w, su, cu)
                })
            })
            .collect();
        let mut g = vec![0.0; nt * nu];
        let mut panel_sums = vec![0.0; nt * up.len()];
        for (pi, p) in tp.iter().enumerate() {
            for i in 0..N {
                let (th, _) = p.node(i);
                let (st, ct) = th.sin_cos();
                let row = pi * N + i;
                for (j, &(_, _, su, cu)) in unodes.iter().enumerate() {
                    let wi = [cu * ct, su, cu * st];
                    let ci = dot(nl, wi);
                    if ci <= 0.0 {
                        continue;
                    }
                    let val = lobe(wi, ci) * cu;
                    g[row * nu + j] = val;
                    panel_sums[row * up.len() + j / N] += val * unodes[j].1;
                }
            }
        }
        // Per θ node, the running sums over the u panels: `cum[row][q]` = Σ of panels < q.
        let np = up.len();
        let mut cum = vec![0.0; nt * (np + 1)];
        for row in 0..nt {
            for q in 0..np {
                cum[row * (np + 1) + q + 1] = cum[row * (np + 1) + q] + panel_sums[row * np + q];
            }
        }
        let (t_lo, t_hi) = (tp[0].a, tp[tp.len() - 1].b);
        let (u_lo, u_hi) = (up[0].a, up[up.len() - 1].b);
        for (o, b) in out.iter_mut().zip(&self.bands[s.start..s.end]) {
            let (lo, hi) = (b.lo.max(t_lo), b.hi.min(t_hi));
            if hi <= lo || b.u1 <= u_lo || b.u0 >= u_hi {
                continue;
            }
            // This frame's u range [u0, u1] on the grid: the whole panels strictly inside, and
            // the partial weights of the panels its ends cut (one panel when both ends fall
            // in it).
            // Usually (narrow lobes) the frame's u range holds the whole grid: no ends to cut.
            let (a0, a1) = (b.u0.max(u_lo), b.u1.min(u_hi));
            let (q0, q1) = (panel_of(&up, a0), panel_of(&up, a1));
            let ends: [(usize, [f64; N]); 2] = if a0 == u_lo && a1 == u_hi {
                [(0, [0.0; N]), (0, [0.0; N])]
            } else if q0 == q1 {
                [(q0, up[q0].partial(a0, a1)), (q0, [0.0; N])]
            } else {
                [(q0, up[q0].partial(a0, up[q0].b)), (q1, up[q1].partial(up[q1].a, a1))]
            };
            let uncut = a0 == u_lo && a1 == u_hi;
            let mut total = 0.0;
            let first = panel_of(&tp, lo);
            for (pi, p) in tp.iter().enumerate().skip(first) {
                if p.a >= hi {
                    break;
                }
                let whole = lo <= p.a && hi >= p.b;
                let partial = if whole { [0.0; N] } else { p.partial(lo.max(p.a), hi.min(p.b)) };
                for (i, &part) in partial.iter().enumerate() {
                    let w = if whole { p.node(i).1 } else { part };
                    let row = pi * N + i;
                    let c = &cum[row * (np + 1)..(row + 1) * (np + 1)];
                    let grow = &g[row * nu..(row + 1) * nu];
                    let val = if uncut {
                        c[np]
                    } else {
                        let mut val = if q1 > q0 { c[q1] - c[q0 + 1] } else { 0.0 };
                        for (q, v) in &ends {
                            val += (0..N).map(|j| v[j] * grow[q * N + j]).sum::<f64>();
                        }
                        val
                    };
                    total += w * val;
                }
            }
            *o = total.max(0.0);
        }
    }
}

/// [`TraceModel::tabled`].
pub struct TabledTraces<'a> {
    model: &'a TraceModel,
    n: V3,
    lobes: Vec<Option<PixelLobes<'a>>>,
    /// The looked-up frames of an interpolated trace (kept between trials).
    samples: Vec<[f64; 1]>,
}

impl TabledTraces<'_> {
    /// The model the traces are of.
    pub fn model(&self) -> &TraceModel {
        self.model
    }

    /// The normal the traces are for.
    pub fn normal(&self) -> V3 {
        self.n
    }

    /// `(D_k, S_k(α))` of frame `k` alone: one frame's prediction from fitted maps (the fit's
    /// check frame) without the whole traces, from what a fit through these traces has kept
    /// (its trials' `α` nodes combined). `D_k` is [`TraceModel::diffuse`]'s `k`-th value;
    /// `S_k` one lookup, which is [`TabledTraces::specular_into`]'s where that looks up every
    /// frame (between its lookups it interpolates, within 1e-5 of the pass' peak), or the
    /// segment integrated where the tables do not reach. `None` past the last frame.
    pub fn frame(&mut self, k: usize, alpha: f64) -> Option<(f64, f64)> {
        let m = self.model;
        let (at, d) = m.diffuse_at(k, self.n)?;
        let (s, b) = (&m.segments[at], &m.bands[k]);
        let sp = match self.lobes[at].as_mut().and_then(|l| l.lobe(alpha)) {
            Some(mut lobe) => lobe.band(b.lo, b.hi, b.u0, b.u1),
            None => {
                let mut o = vec![0.0; s.end - s.start];
                m.specular_segment(s, self.n, alpha, &mut o);
                o[k - s.start]
            }
        };
        Some((d.max(0.0), sp.max(0.0)))
    }

    /// `S_k(α)` into `out` (`len()` values); returns the range of frames outside which they
    /// are zero (the lobe's reach; a narrow lobe is looked up only in the frames it reaches).
    pub fn specular_into(&mut self, alpha: f64, out: &mut [f64]) -> std::ops::Range<usize> {
        let m = self.model;
        let (mut first, mut last) = (out.len(), 0);
        for (s, lobes) in m.segments.iter().zip(&mut self.lobes) {
            let o = &mut out[s.start..s.end];
            let (a, b) = match lobes.as_mut().and_then(|l| l.lobe(alpha)) {
                Some(lobe) => m.looked_up(s, lobe, &mut self.samples, o),
                None => {
                    o.fill(0.0);
                    m.specular_segment(s, self.n, alpha, o);
                    (0, o.len())
                }
            };
            if b > a {
                first = first.min(s.start + a);
                last = last.max(s.start + b);
            }
        }
        first..last.max(first)
    }
}

impl TraceModel {
    /// `S_k` for unit normal `n` at the roughness of `lobes` into `out` (`len()` values): the
    /// normal search's lookups, one new geometry per call ([`AlphaLobes`]). A segment the
    /// tables do not cover is integrated ([`TraceModel::specular`]).
    pub fn specular_alpha(&self, n: V3, lobes: &mut AlphaLobes, out: &mut [f64]) {
        let mut samples = Vec::new();
        for s in &self.segments {
            let o = &mut out[s.start..s.end];
            match lobe_geometry(turn(n, -s.yaw), s.v).and_then(|g| lobes.lobe(g)) {
                Some(lobe) => {
                    self.looked_up(s, lobe, &mut samples, o);
                }
                None => {
                    o.fill(0.0);
                    self.specular_segment(s, n, lobes.alpha(), o);
                }
            }
        }
    }

    /// Segment `s`'s `S_k` from `lobe` into `o` (the segment's frames), zero outside the
    /// frames the lobe reaches, which it returns (relative to the segment's start).
    fn looked_up(
        &self,
        s: &Segment,
        lobe: TableLobe,
        samples: &mut Vec<[f64; 1]>,
        o: &mut [f64],
    ) -> (usize, usize) {
        self.looked_up_with(s, lobe, samples, [o], |l, b| [l.band(b.lo, b.hi, b.u0, b.u1)])
    }

    /// [`TraceModel::looked_up`] for any values `look` gives per band (the trace first), each
    /// into its own slice of `out`.
    fn looked_up_with<const K: usize>(
        &self,
        s: &Segment,
        mut lobe: TableLobe,
        samples: &mut Vec<[f64; K]>,
        mut out: [&mut [f64]; K],
        look: impl Fn(&mut TableLobe, &Band) -> [f64; K],
    ) -> (usize, usize) {
        let (a, b) = self.frames_meeting(s, lobe.theta_window());
        let b = b.max(a);
        for o in out.iter_mut() {
            o[..a].fill(0.0);
            o[b..].fill(0.0);
        }
        let bands = &self.bands[s.start..s.end];
        let stride = sample_stride(s, &lobe, b > a);
        interpolated(|k| look(&mut lobe, &bands[k]), bands.len(), (a, b), stride, samples, out);
        (a, b)
    }

    /// [`TraceModel::specular_alpha`] and the traces' derivatives in the two directions
    /// `dn` of the normal (tangent to the sphere at `n`) into `d_out`: the lobe's position
    /// moved, its shape held ([`TableLobe::band_slopes`]). A segment the tables do not cover
    /// is integrated, its derivatives by differences.
    pub fn specular_alpha_slopes(
        &self,
        n: V3,
        dn: [V3; 2],
        lobes: &mut AlphaLobes,
        out: &mut [f64],
        d_out: [&mut [f64]; 2],
    ) {
        let [dx_out, dy_out] = d_out;
        let mut samples = Vec::new();
        let moved = |i: usize, h: f64| normalize(std::array::from_fn(|q| n[q] + h * dn[i][q]));
        for s in &self.segments {
            let range = s.start..s.end;
            let (o, dx, dy) = (&mut out[range.clone()], &mut dx_out[range.clone()], &mut dy_out[range]);
            let geo_of = |n: V3| lobe_geometry(turn(n, -s.yaw), s.v);
            let Some(lobe) = geo_of(n).and_then(|g| lobes.lobe(g)) else {
                o.fill(0.0);
                self.specular_segment(s, n, lobes.alpha(), o);
                const H: f64 = 1e-4;
                for (i, d) in [dx, dy].into_iter().enumerate() {
                    let (mut up, mut down) = (vec![0.0; d.len()], vec![0.0; d.len()]);
                    self.specular_segment(s, moved(i, H), lobes.alpha(), &mut up);
                    self.specular_segment(s, moved(i, -H), lobes.alpha(), &mut down);
                    for ((d, u), w) in d.iter_mut().zip(up).zip(down) {
                        *d = (u - w) / (2.0 * H);
                    }
                }
                continue;
            };
            // How the lobe's position moves with the normal (central differences of a few
            // products: exact to 1e-10).
            const H: f64 = 1e-6;
            let mut dpos = [[0.0; 2]; 2];
            for (i, dp) in dpos.iter_mut().enumerate() {
                let (Some(up), Some(down)) = (geo_of(moved(i, H)), geo_of(moved(i, -H))) else { continue };
                let wrap = |x: f64| (x + PI).rem_euclid(2.0 * PI) - PI;
                *dp = [wrap(up.theta - down.theta) / (2.0 * H), (up.u - down.u) / (2.0 * H)];
            }
            // The derivatives in the lobe's position (θ, u) into dx and dy, then turned into
            // the normal's two directions in place.
            self.looked_up_with(s, lobe, &mut samples, [o, &mut *dx, &mut *dy], |l, b| {
                l.band_slopes(b.lo, b.hi, b.u0, b.u1)
            });
            let ([xt, xu], [yt, yu]) = (dpos[0], dpos[1]);
            for (x, y) in dx.iter_mut().zip(dy.iter_mut()) {
                let (t, u) = (*x, *y);
                (*x, *y) = (t * xt + u * xu, t * yt + u * yu);
            }
        }
    }
}

/// The frames between looked-up ones for `lobe` on segment `s` (1 where its bands do not
/// step evenly, or `any` is false: nothing to look up).
fn sample_stride(s: &Segment, lobe: &TableLobe, any: bool) -> usize {
    if !any {
        return 1;
    }
    s.steps.map_or(1, |(dt, du)| {
        let (scale, inv_alpha) = lobe.scales();
        let per_frame = (dt * scale).max(du * inv_alpha);
        if per_frame > 0.0 {
            ((SAMPLE_STEP / per_frame) as usize).clamp(1, MAX_STRIDE)
        } else {
            MAX_STRIDE
        }
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::lls::linear_light::{response, Quadrature};

    #[test]
    fn partial_weights_integrate_polynomials() {
        let p = Panel { a: 0.3, b: 1.7 };
        // ∫ x^5 from 0.5 to 1.2 through the node values.
        let w = p.partial(0.5, 1.2);
        let got: f64 = (0..N).map(|i| w[i] * p.node(i).0.powi(5)).sum();
        let want = (1.2f64.powi(6) - 0.5f64.powi(6)) / 6.0;
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        // The whole panel: the rule's weights.
        let whole = p.partial(p.a, p.b);
        for (i, wi) in whole.iter().enumerate() {
            assert!((wi - p.node(i).1).abs() < 1e-13);
        }
    }

    #[test]
    fn tabled_traces_are_looked_up_only_where_the_lobe_reaches() {
        let (p, n, v) = ([1.0, 2.0, 0.3], normalize([0.02, -0.03, 1.0]), normalize([-0.5, 0.02, 0.866]));
        let tables = LobeTables::new();
        // A pass forwards (θ rising), backwards (falling), and one frame out of order.
        let forwards: Vec<Tube> =
            (0..300).map(|k| Tube::through([-140.0 + 0.8 * k as f64, 0.0, 50.0], 0.0, 6.0, 300.0)).collect();
        let backwards: Vec<Tube> = forwards.iter().rev().copied().collect();
        let mut shuffled = forwards.clone();
        shuffled.swap(100, 200);
        for (tubes, ordered) in [(&forwards, true), (&backwards, true), (&shuffled, false)] {
            let model = TraceModel::new(p, v, tubes);
            assert_eq!(model.segments.iter().all(|s| s.order.is_some()), ordered);
            let mut full = model.clone();
            full.segments.iter_mut().for_each(|s| s.order = None);
            for alpha in [0.03, 0.08, 0.3] {
                let (mut got, mut want) = (vec![1.0; tubes.len()], vec![1.0; tubes.len()]);
                let reach = model.tabled(n, &tables).specular_into(alpha, &mut got);
                let all = full.tabled(n, &tables).specular_into(alpha, &mut want);
                // The same values; zero outside the reach, which for a narrow lobe is a small
                // part of the pass.
                assert_eq!(got, want, "α {alpha}");
                assert!(got[..reach.start].iter().chain(&got[reach.end..]).all(|&s| s == 0.0));
                assert!(want[..all.start].iter().chain(&want[all.end..]).all(|&s| s == 0.0));
                assert!(got[reach.clone()].iter().any(|&s| s > 0.0));
                if ordered && alpha < 0.05 {
                    assert!(reach.len() < tubes.len() / 3, "α {alpha}: {reach:?}");
                }
            }
        }
    }

    #[test]
    fn one_frame_is_the_traces_value_there() {
        // Two passes (turned either way: two segments) over the rig's geometries: every
        // frame's pair is the traces' (the specular one looked up at every frame), bit for
        // bit; past the last frame, none.
        let tables = LobeTables::new();
        for (p, n, v, yaw) in crate::lls::table::tests::rig_cases().into_iter().step_by(3) {
            let tubes: Vec<Tube> = [yaw + 0.26, yaw - 0.26]
                .iter()
                .flat_map(|&y| {
                    (0..120).map(move |k| Tube::through([-100.0 + 1.5 * k as f64, 0.0, 50.0], y, 6.0, 300.0))
                })
                .collect();
            let mut model = TraceModel::new(p, v, &tubes);
            assert_eq!(model.segments.len(), 2);
            assert!(model.segments.iter().all(|s| s.e_stride > 1), "the diffuse vectors interpolated");
            model.segments.iter_mut().for_each(|s| s.steps = None);
            let d = model.diffuse(n);
            for alpha in [0.04, 0.13, 0.3] {
                let s = model.specular_tabled(n, alpha, &tables);
                for k in 0..tubes.len() {
                    assert_eq!(
                        model.tabled(n, &tables).frame(k, alpha),
                        Some((d[k], s[k])),
                        "frame {k}, α {alpha}"
                    );
                }
                assert_eq!(model.tabled(n, &tables).frame(tubes.len(), alpha), None);
            }
        }
    }

    #[test]
    fn interpolated_traces_match_the_looked_up_ones() {
        // Broad lobes looked up every few frames and interpolated, and looked up at every
        // frame, both against the direct integration, over the rig's geometries; passes of
        // 300 frames at 0.8 mm and 600 at 0.4 mm. Relative to the pass' peak.
        let tables = LobeTables::new();
        let alphas = [0.02, 0.03, 0.05, 0.08, 0.12, 0.16, 0.22, 0.3, 0.45, 0.6];
        let mut worst = vec![(0f64, 0f64, 0f64); alphas.len()];
        let mut strided = 0;
        for (p, n, v, yaw) in crate::lls::table::tests::rig_cases() {
            for (frames, step) in [(300, 0.8), (600, 0.4)] {
                let tubes: Vec<Tube> = (0..frames)
                    .map(|k| Tube::through([-140.0 + step * k as f64, 0.0, 50.0], yaw, 6.0, 300.0))
                    .collect();
                let model = TraceModel::new(p, v, &tubes);
                assert!(model.segments.iter().all(|s| s.steps.is_some()));
                let mut every = model.clone();
                every.segments.iter_mut().for_each(|s| s.steps = None);
                for (w, &alpha) in worst.iter_mut().zip(&alphas) {
                    let (mut got, mut want) = (vec![0.0; frames], vec![0.0; frames]);
                    let r = model.tabled(n, &tables).specular_into(alpha, &mut got);
                    let r2 = every.tabled(n, &tables).specular_into(alpha, &mut want);
                    assert_eq!(r, r2);
                    let direct = model.specular(n, alpha);
                    let peak = direct.iter().fold(0f64, |a, &b| a.max(b));
                    let err = |x: &[f64], y: &[f64]| {
                        x.iter().zip(y).map(|(a, b)| (a - b).abs()).fold(0f64, f64::max) / peak
                    };
                    *w = (
                        w.0.max(err(&got, &direct)),
                        w.1.max(err(&want, &direct)),
                        w.2.max(err(&got, &want)),
                    );
                    strided += usize::from(got != want);
                }
            }
        }
        for (&a, &(interpolated, looked_up, between)) in alphas.iter().zip(&worst) {
            // Against the direct integration, the tables' own bounds (`lls::table` tests);
            // measured: no worse than looking up every frame. Against that, measured: 0 up
            // to α 0.05 (every frame looked up), 4.1e-5 at 0.12, 8.4e-5 at 0.22, 1.3e-4 at
            // 0.3, 7.1e-4 at 0.6 (a tenth of the tables' own error there).
            // The tables' own error up to α 0.16 (≤ 2.9e-4) is at the steepest geometries (see
            // `tabled_traces_match_the_direct_integration`).
            let (tol, tol_between) = match a {
                a if a <= 0.12 => (3e-4, 5e-5),
                a if a <= 0.16 => (3.5e-4, 8e-5),
                a if a <= 0.22 => (4e-4, 1e-4),
                a if a <= 0.3 => (2.5e-3, 2e-4),
                _ => (1e-2, 1e-3),
            };
            assert!(
                interpolated < tol && between < tol_between && interpolated < looked_up * 1.05 + 2e-5,
                "α {a}: {interpolated:e} (every frame looked up: {looked_up:e}; apart {between:e})"
            );
        }
        assert!(strided > 0);
    }

    /// Model traces against the high-order tube integration, over a whole pass, relative to
    /// the pass' peak.
    fn worst(p: V3, n: V3, v: V3, yaw: f64, alpha: f64) -> (f64, f64) {
        let tubes: Vec<Tube> =
            (0..300).map(|k| Tube::through([-140.0 + 0.8 * k as f64, 0.0, 50.0], yaw, 6.0, 300.0)).collect();
        let model = TraceModel::new(p, v, &tubes);
        let (d, s) = (model.diffuse(n), model.specular(n, alpha));
        let q = Quadrature::render();
        let want: Vec<_> = tubes.iter().map(|t| response(p, n, v, t, Some(alpha), &q)).collect();
        let dpeak = want.iter().map(|r| r.diffuse).fold(0.0, f64::max);
        let speak = want.iter().map(|r| r.specular).fold(0.0, f64::max);
        let mut err = (0f64, 0f64);
        for k in 0..tubes.len() {
            err.0 = err.0.max((d[k] - want[k].diffuse).abs() / dpeak);
            err.1 = err.1.max((s[k] - want[k].specular).abs() / speak);
        }
        err
    }

    #[test]
    fn stepped_angles_match_the_exact_ones() {
        // The bands with angles stepped between anchors against exact angles at every frame,
        // over the rig's geometries (straight and diagonal mounts), and a pass with steps too
        // large to take (every fifth frame: exact again).
        let mut worst = 0f64;
        for (p, _, v, yaw) in crate::lls::table::tests::rig_cases() {
            for step in [0.8, 4.0] {
                let tubes: Vec<Tube> = (0..300)
                    .map(|k| Tube::through([-140.0 + step * k as f64, 0.0, 50.0], yaw, 6.0, 300.0))
                    .collect();
                let (a, b) = (
                    TraceModel::built(p, v, &Sweep::new(&tubes), ANCHOR, 0.0),
                    TraceModel::built(p, v, &Sweep::new(&tubes), 1, 0.0),
                );
                assert_eq!((a.es.len(), b.es.len()), (tubes.len(), tubes.len()));
                for ((x, y), (ex, ey)) in a.bands.iter().zip(&b.bands).zip(a.es.iter().zip(&b.es)) {
                    let diff = [x.lo - y.lo, x.hi - y.hi, x.u0 - y.u0, x.u1 - y.u1];
                    let de = (0..3).map(|k| (ex[k] - ey[k]).abs()).fold(0f64, f64::max);
                    worst = diff.iter().fold(worst, |w, d| w.max(d.abs())).max(de);
                }
            }
        }
        // Measured: 4e-16 (radians; the diffuse vector's entries are below 0.2).
        assert!(worst < 1e-14, "{worst:e}");
    }

    #[test]
    fn slopes_follow_the_normal() {
        // The traces of specular_alpha_slopes are specular_alpha's; their derivatives (the
        // lobe's position moved, its shape held) against central differences of the looked-up
        // traces in the same directions of the normal (the shape moved too), over the rig's
        // geometries. The normal search needs a Jacobian good enough to converge, not exact.
        let tables = LobeTables::new();
        let mut worst = [0f64; 3];
        for (p, n, v, yaw) in crate::lls::table::tests::rig_cases().into_iter().step_by(3) {
            let tubes: Vec<Tube> = (0..300)
                .map(|k| Tube::through([-140.0 + 0.8 * k as f64, 0.0, 50.0], yaw, 6.0, 300.0))
                .collect();
            let model = TraceModel::new(p, v, &tubes);
            // Two tangents of the normal.
            let t0 = normalize(crate::vec3::cross(n, [0.0, 1.0, 0.0]));
            let dn = [t0, crate::vec3::cross(n, t0)];
            for (w, alpha) in worst.iter_mut().zip([0.04, 0.13, 0.3]) {
                let mut lobes = crate::lls::AlphaLobes::new(&tables, alpha).unwrap();
                let len = model.len();
                let (mut s, mut dx, mut dy) = (vec![0.0; len], vec![0.0; len], vec![0.0; len]);
                model.specular_alpha_slopes(n, dn, &mut lobes, &mut s, [&mut dx, &mut dy]);
                let mut plain = vec![0.0; len];
                model.specular_alpha(n, &mut lobes, &mut plain);
                assert_eq!(s, plain);
                let peak = s.iter().fold(0f64, |a, &b| a.max(b));
                if peak < 1e-3 {
                    continue;
                }
                // Errors against the largest derivative in either direction (one direction
                // may move the trace little: along the tube's axis).
                let h = 1e-4;
                let (mut err, mut largest) = (0f64, 0f64);
                for (i, got) in [dx, dy].iter().enumerate() {
                    let mut at = |h: f64| {
                        let mut o = vec![0.0; len];
                        let m = normalize(std::array::from_fn(|q| n[q] + h * dn[i][q]));
                        model.specular_alpha(m, &mut lobes, &mut o);
                        o
                    };
                    let (up, down) = (at(h), at(-h));
                    for ((u, d), g) in up.iter().zip(&down).zip(got) {
                        let want = (u - d) / (2.0 * h);
                        largest = largest.max(want.abs());
                        err = err.max((g - want).abs());
                    }
                }
                *w = w.max(err / largest);
            }
        }
        // Measured: 0.051, 0.105, 0.160 of the largest derivative at α 0.04, 0.13, 0.3 (the
        // lobe's mass changes with its tilt, more so for broad lobes): Gauss–Newton then
        // gains about a decimal a step.
        for (w, (alpha, tol)) in worst.iter().zip([(0.04, 0.07), (0.13, 0.13), (0.3, 0.2)]) {
            assert!(*w < tol, "α {alpha}: the position-only slopes are {w:.3} of the largest off");
        }
    }

    #[test]
    fn the_sweep_hides_what_every_tube_does() {
        // The frames near the view ray alone tested, against every frame: the same flags,
        // over the rig's points, mounts and steps, a sweep of several runs, a run not evenly
        // spaced, and a view straight down (the tube passes over the point).
        let mut hidden = 0;
        let mut cases: Vec<(V3, V3)> =
            crate::lls::table::tests::rig_cases().into_iter().map(|(p, _, v, _)| (p, v)).collect();
        cases.push(([3.0, -2.0, 0.0], [0.0, 0.0, 1.0]));
        cases.push(([-60.0, 10.0, 0.0], normalize([0.3, -0.2, 1.0])));
        for (p, v) in cases {
            for (frames, step) in [(300, 0.8), (401, 0.6)] {
                let mut tubes = Vec::new();
                for yaw in [0.0, 15f64.to_radians(), -15f64.to_radians()] {
                    tubes.extend(
                        (0..frames)
                            .map(|k| Tube::through([-140.0 + step * k as f64, 0.0, 50.0], yaw, 6.0, 300.0)),
                    );
                }
                // A run with uneven steps (every frame tested there).
                tubes.extend((0..50).map(|k| {
                    let x = -140.0 + 5.0 * f64::from(k) + if k % 3 == 0 { 0.4 } else { 0.0 };
                    Tube::through([x, 0.0, 50.0], 0.3, 6.0, 300.0)
                }));
                let sweep = Sweep::new(&tubes);
                assert_eq!(sweep.runs.iter().filter(|r| !r.2).count(), 1);
                for margin in [0.0, 1.0] {
                    let got = sweep.hidden(p, v, margin);
                    assert_eq!(got, crate::lls::linear_light::hidden_by(p, v, &tubes, margin), "{p:?} {v:?}");
                    hidden += got.iter().filter(|&&h| h).count();
                }
                // The frames tested: those where the widened tube (14 mm across) meets the view
                // ray's line, seen across it, and a few more either side.
                let (pl, vl) = (tubes[0].local(p), tubes[0].local(v));
                let (from, to) = near_ray(pl, vl, &tubes[..frames], 1.0);
                let across = 14.0 * vl[0].hypot(vl[2]) / (step * vl[2]);
                assert!(to - from <= across.ceil() as usize + 7, "{from}..{to} {p:?} {v:?}");
            }
        }
        assert!(hidden > 1000, "{hidden}");
    }

    #[test]
    fn interpolated_bands_match_the_computed_ones() {
        // Evenly stepped passes computed every few frames and interpolated, against every
        // frame computed: the bands at every frame (radians; the diffuse vector's entries),
        // and the traces, relative to the pass' peak. The rig's geometries, its step sizes,
        // and the tube nearer the sample than on the rig (30 mm above the reference plane).
        let tables = LobeTables::new();
        let (mut bands, mut traces, mut diffuse, mut strided) = (0f64, 0f64, 0f64, 0usize);
        for (p, n, v, yaw) in crate::lls::table::tests::rig_cases() {
            for (frames, step, height) in
                [(300, 0.8, 50.0), (600, 0.4, 50.0), (400, 0.6, 50.0), (300, 0.8, 30.0)]
            {
                let tubes: Vec<Tube> = (0..frames)
                    .map(|k| Tube::through([-140.0 + step * k as f64, 0.0, height], yaw, 6.0, 300.0))
                    .collect();
                let (a, b) = (
                    TraceModel::new(p, v, &tubes),
                    TraceModel::built(p, v, &Sweep::new(&tubes), ANCHOR, 0.0),
                );
                strided += usize::from(a.bands != b.bands);
                assert_eq!((a.segments.len(), b.segments.len()), (1, 1));
                assert_eq!(a.segments[0].order, b.segments[0].order);
                for (x, y) in a.bands.iter().zip(&b.bands) {
                    let diff = [x.lo - y.lo, x.hi - y.hi, x.u0 - y.u0, x.u1 - y.u1];
                    bands = diff.iter().fold(bands, |w, d| w.max(d.abs()));
                }
                // What the segment says of its bands (union, order, largest steps), from the
                // computed frames and a few intervals' frames, against every frame: the same,
                // but that where u's steps are flat the quintics' error (below 1e-6 of the
                // step; measured 3e-8) may decide which frame's is largest.
                let sa = &a.segments[0];
                let (theta, u, order, all) = every_band(&a.bands);
                let case = format!("{p:?}, yaw {yaw}, {frames} frames of {step} mm");
                assert!(sa.e_stride > 1, "{case}");
                assert_eq!((sa.theta, sa.u, sa.order), (theta, u, order), "{case}");
                let ((dt, du), (et, eu)) = (sa.steps.unwrap(), all.unwrap());
                assert!(dt == et && (du / eu - 1.0).abs() < 1e-6, "{case}: {:?} {all:?}", sa.steps);
                // The diffuse traces (interpolated from the computed frames' `n·e`).
                let (got, want) = (a.diffuse(n), b.diffuse(n));
                let peak = want.iter().fold(0f64, |m, &x| m.max(x));
                let err = got.iter().zip(&want).map(|(g, w)| (g - w).abs()).fold(0f64, f64::max) / peak;
                diffuse = diffuse.max(err);
                for alpha in [0.02, 0.04, 0.3] {
                    let (got, want) =
                        (a.specular_tabled(n, alpha, &tables), b.specular_tabled(n, alpha, &tables));
                    let peak = want.iter().fold(0f64, |m, &x| m.max(x));
                    let err = got.iter().zip(&want).map(|(g, w)| (g - w).abs()).fold(0f64, f64::max) / peak;
                    traces = traces.max(err);
                }
            }
        }
        // Every pass is interpolated. Measured: bands within 2.1e-7, specular traces within
        // 2.5e-6 of the peak, diffuse within 1.4e-6 (a hundredth of the tables' own error, see `lls::table`); with BAND_SPAN
        // 0.05: 2.4e-9 and 3e-8, at 0.15: 2.1e-6 and 3e-5 (the sixth power).
        assert_eq!(strided, crate::lls::table::tests::rig_cases().len() * 4);
        assert!(bands < 4e-7 && traces < 5e-6 && diffuse < 3e-6, "{bands:e}, {traces:e}, {diffuse:e}");
    }

    /// The GGX lobe over the tube by brute force, shared with nothing of the model: the
    /// midpoint rule over the tube's surface in the elevation `u` and the angle `φ` around its
    /// axis (fine steps: 0.001 rad and 1/256 of the visible arc).
    pub(crate) fn ggx_brute(p: V3, n: V3, v: V3, tube: &Tube, alpha: f64) -> f64 {
        let (pl, nl, vl) = (tube.local(p), tube.local(n), tube.local(v));
        let (dx, dz) = (pl[0] - tube.x, pl[2] - tube.z);
        let d = dx.hypot(dz);
        let (u0, u1) = (((tube.y0 - pl[1]) / d).atan(), ((tube.y1 - pl[1]) / d).atan());
        let (phi0, half) = (dz.atan2(dx), (tube.radius / d).acos());
        let (nu, np) = (((u1 - u0) / 1e-3).ceil() as usize, 256);
        let (du, dp) = ((u1 - u0) / nu as f64, 2.0 * half / np as f64);
        let mut total = 0.0;
        for i in 0..nu {
            let u = u0 + (i as f64 + 0.5) * du;
            let y = pl[1] + d * u.tan();
            let dy = d / (u.cos() * u.cos());
            for j in 0..np {
                let phi = phi0 - half + (j as f64 + 0.5) * dp;
                let q = [tube.x + tube.radius * phi.cos(), y, tube.z + tube.radius * phi.sin()];
                let to = crate::vec3::sub(q, pl);
                let dist2 = dot(to, to);
                let wi = normalize(to);
                let cos_q = -(phi.cos() * wi[0] + phi.sin() * wi[2]);
                if cos_q <= 0.0 {
                    continue;
                }
                let domega = du * dp * tube.radius * dy * cos_q / dist2;
                total += crate::ggx::specular_lobe(nl, wi, vl, alpha) * dot(nl, wi).max(0.0) * domega;
            }
        }
        total
    }

    #[test]
    fn ggx_traces_match_a_brute_force_integration() {
        let cases = [
            ([1.0, 2.0, 0.3], [0.02, -0.03, 1.0], [-0.5, 0.02, 0.866]),
            ([-30.0, 35.0, -1.5], [-0.08, 0.05, 1.0], [-0.45, -0.12, 0.88]),
        ];
        let mut worst = 0f64;
        for (p, n, v) in cases {
            let (n, v) = (normalize(n), normalize(v));
            for yaw in [0.0, 15f64.to_radians()] {
                let tubes: Vec<Tube> = (0..300)
                    .map(|k| Tube::through([-140.0 + 0.8 * k as f64, 0.0, 50.0], yaw, 6.0, 300.0))
                    .collect();
                let model = TraceModel::new(p, v, &tubes);
                for alpha in [0.03, 0.1, 0.3] {
                    let s = model.specular_ggx(n, alpha);
                    let peak = s.iter().fold(0f64, |a, &b| a.max(b));
                    let top = s.iter().position(|&x| x == peak).unwrap();
                    // The peak, its flanks and the far tails (the tails are GGX's difference).
                    for k in [
                        0,
                        40,
                        top.saturating_sub(12),
                        top.saturating_sub(3),
                        top,
                        top + 3,
                        top + 12,
                        260,
                        299,
                    ] {
                        let k = k.min(299);
                        let want = ggx_brute(p, n, v, &tubes[k], alpha);
                        let err = (s[k] - want).abs() / peak;
                        worst = worst.max(err);
                        // Measured: 5.4e-6 of the pass' peak at worst.
                        assert!(err < 2e-5, "p {p:?} yaw {yaw} α {alpha} frame {k}: {} against {want}", s[k]);
                    }
                }
            }
        }
        eprintln!("GGX traces against brute force: worst {worst:e} of the pass' peak");
    }

    #[test]
    fn model_traces_match_the_tube_integration() {
        let cases = [
            ([1.0, 2.0, 0.3], [0.02, -0.03, 1.0], [-0.5, 0.02, 0.866]),
            ([-30.0, 35.0, -1.5], [-0.08, 0.05, 1.0], [-0.45, -0.12, 0.88]),
            ([40.0, -38.0, 2.0], [0.0, 0.0, 1.0], [-0.6, 0.1, 0.8]),
        ];
        for (p, n, v) in cases {
            let (n, v) = (normalize(n), normalize(v));
            for yaw in [0.0, 15f64.to_radians(), -15f64.to_radians()] {
                for alpha in [0.025, 0.04, 0.08, 0.16, 0.3, 0.5] {
                    let (ed, es) = worst(p, n, v, yaw, alpha);
                    // Measured: diffuse ≤ 2.2e-5, specular ≤ 8.4e-5 of the pass' peak (the
                    // mean u limits, at the broad lobes that reach the tube's ends).
                    assert!(
                        ed < 5e-5 && es < 1.5e-4,
                        "p {p:?} yaw {yaw} α {alpha}: diffuse {ed:e}, specular {es:e}"
                    );
                }
            }
        }
    }
}
