//! Section 7.1's local term: the impulse response near a laser spot as
//! `m(d) = c1·e^(−σ1·d) + c2·e^(−σ2·d)` (σ1, σ2 shared by the colour channels, c1, c2 per
//! channel), fitted in the paper's stages, and the multiplicative correction that keeps what the
//! fit cannot say (surface detail).
//!
//! **Choice (beyond the paper):** the data near the spot are the response blurred by the beam
//! (σ ≈ 0.85 mm for the paper's 2 mm spot, as wide as the fast term), so the fit compares the data
//! with `m` convolved with the beam's Gaussian ([`Blur`]), not with `m` itself: the kernel it
//! returns is the object's, not the beam's. With no beam (σ = 0) the fit is the paper's.

use std::f64::consts::PI;

use super::dipole::Dipole;

/// `e^(−x)·I0(x)`, x ≥ 0 (Abramowitz & Stegun 9.8.1–2, relative error < 2e-7).
pub fn i0e(x: f64) -> f64 {
    let x = x.abs();
    if x <= 3.75 {
        let t = (x / 3.75).powi(2);
        let i0 = 1.0
            + t * (3.5156229
                + t * (3.0899424 + t * (1.2067492 + t * (0.2659732 + t * (0.0360768 + t * 0.0045813)))));
        i0 * (-x).exp()
    } else {
        let t = 3.75 / x;
        let p = 0.39894228
            + t * (0.01328592
                + t * (0.00225319
                    + t * (-0.00157565
                        + t * (0.00916281
                            + t * (-0.02057706 + t * (0.02635537 + t * (-0.01647633 + t * 0.00392377)))))));
        p / x.sqrt()
    }
}

/// `e^(−s·r)` on the surface (radial, `r` from the spot) convolved with an isotropic Gaussian of
/// σ `beam` mm, at distance `d` mm: `∫ e^(−s r) (r/b²) e^(−(r−d)²/2b²) I0e(r d/b²) dr`.
pub fn blurred_exp(s: f64, d: f64, beam: f64) -> f64 {
    if beam <= 0.0 {
        return (-s * d).exp();
    }
    let b2 = beam * beam;
    let (lo, hi) = ((d - 7.0 * beam).max(0.0), d + 7.0 * beam);
    // Simpson over [lo, hi].
    let n = 160;
    let h = (hi - lo) / n as f64;
    let f = |r: f64| (-s * r).exp() * r / b2 * (-(r - d) * (r - d) / (2.0 * b2)).exp() * i0e(r * d / b2);
    let mut sum = f(lo) + f(hi);
    for i in 1..n {
        sum += f(lo + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
    }
    sum * h / 3.0
}

/// [`blurred_exp`] tabulated for one beam: `ln` of it on a grid of `ln s` × `d`, interpolated.
#[derive(Debug, Clone)]
pub struct Blur {
    pub beam: f64,
    ln_s: (f64, f64, usize),
    d: (f64, usize),
    table: Vec<f64>,
}

/// Rounds of the staged fit (see [`fit`]).
pub const ROUNDS: usize = 4;

/// Fall-off rates the fit considers, mm⁻¹.
pub const RATES: (f64, f64) = (0.01, 30.0);

impl Blur {
    /// The table for a beam of σ `beam` mm, distances up to `d_max` mm.
    pub fn new(beam: f64, d_max: f64) -> Self {
        let (ns, nd) = (192usize, ((d_max / 0.05).ceil() as usize).max(2) + 1);
        let (a, b) = (RATES.0.ln(), RATES.1.ln());
        let step = (b - a) / (ns - 1) as f64;
        let dd = d_max / (nd - 1) as f64;
        let mut table = vec![0.0; ns * nd];
        for i in 0..ns {
            let s = (a + i as f64 * step).exp();
            for j in 0..nd {
                table[i * nd + j] = blurred_exp(s, j as f64 * dd, beam).max(1e-300).ln();
            }
        }
        Blur { beam, ln_s: (a, step, ns), d: (dd, nd), table }
    }

    /// `ln` of the blurred `e^(−s·d)` (beyond the table, the unblurred slope continues it).
    pub fn ln(&self, s: f64, d: f64) -> f64 {
        let (a, step, ns) = self.ln_s;
        let (dd, nd) = self.d;
        let x = ((s.max(RATES.0).min(RATES.1).ln() - a) / step).clamp(0.0, (ns - 1) as f64);
        let d_top = (nd - 1) as f64 * dd;
        let y = (d.max(0.0).min(d_top)) / dd;
        let (i, j) = ((x as usize).min(ns - 2), (y as usize).min(nd - 2));
        let (fx, fy) = (x - i as f64, y - j as f64);
        let t = |i: usize, j: usize| self.table[i * nd + j];
        let v = (1.0 - fx) * ((1.0 - fy) * t(i, j) + fy * t(i, j + 1))
            + fx * ((1.0 - fy) * t(i + 1, j) + fy * t(i + 1, j + 1));
        v - s * (d - d_top).max(0.0)
    }

    pub fn eval(&self, s: f64, d: f64) -> f64 {
        self.ln(s, d).exp()
    }
}

/// One data point near a spot: distance from the spot's centre (mm), colour channel, the
/// response there (the same units as `F`: mm⁻²).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub d: f64,
    pub channel: u8,
    pub value: f64,
}

/// The stages' distance limits (section 7.1: δ1 = 3 mm, δ2 = 1 mm in the paper's example).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stages {
    /// Stage 1 fits σ1, c1 to the points beyond δ1.
    pub delta1: f64,
    /// Stage 2 fits σ2, c2 to the points within δ2.
    pub delta2: f64,
}

impl Default for Stages {
    fn default() -> Self {
        Stages { delta1: 3.0, delta2: 1.0 }
    }
}

/// A fitted `m(d)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    /// σ1 (slow), σ2 (fast), mm⁻¹.
    pub sigma: [f64; 2],
    pub c1: [f64; 3],
    pub c2: [f64; 3],
    /// Relative RMS misfit over the data.
    pub misfit: f64,
}

impl Profile {
    /// `m(d)` in channel `c`: the object's kernel, no beam.
    pub fn eval(&self, c: usize, d: f64) -> f64 {
        self.c1[c] * (-self.sigma[0] * d).exp() + self.c2[c] * (-self.sigma[1] * d).exp()
    }

    /// `m(d)` as a beam of `blur` sees it.
    pub fn eval_blurred(&self, blur: &Blur, c: usize, d: f64) -> f64 {
        self.c1[c] * blur.eval(self.sigma[0], d) + self.c2[c] * blur.eval(self.sigma[1], d)
    }
}

/// Minimises `cost(ln s)` over `[a, b]`: a scan, then golden section around the best.
fn minimise(a: f64, b: f64, cost: &dyn Fn(f64) -> f64) -> Option<f64> {
    if b.partial_cmp(&a) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let n = 48;
    let xs: Vec<f64> = (0..=n).map(|i| a + (b - a) * i as f64 / n as f64).collect();
    let (best, _) = xs
        .iter()
        .enumerate()
        .map(|(i, &x)| (i, cost(x)))
        .filter(|p| p.1.is_finite())
        .min_by(|p, q| p.1.total_cmp(&q.1))?;
    let (mut lo, mut hi) = (xs[best.saturating_sub(1)], xs[(best + 1).min(n)]);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x1, mut x2) = (hi - g * (hi - lo), lo + g * (hi - lo));
    let (mut f1, mut f2) = (cost(x1), cost(x2));
    for _ in 0..40 {
        if f1 < f2 {
            hi = x2;
            (x2, f2) = (x1, f1);
            x1 = hi - g * (hi - lo);
            f1 = cost(x1);
        } else {
            lo = x1;
            (x1, f1) = (x2, f2);
            x2 = lo + g * (hi - lo);
            f2 = cost(x2);
        }
    }
    Some(0.5 * (lo + hi))
}

/// Per channel, non-negative least squares of `v ≈ a·p + b·q` with relative weights `1/v`.
fn two_terms(rows: &[(f64, f64, f64)]) -> [f64; 2] {
    let (mut spp, mut spq, mut sqq, mut spv, mut sqv) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(p, q, v) in rows {
        let w = 1.0 / (v * v);
        spp += w * p * p;
        spq += w * p * q;
        sqq += w * q * q;
        spv += w * p * v;
        sqv += w * q * v;
    }
    let det = spp * sqq - spq * spq;
    let (a, b) = if det.abs() > 1e-300 {
        ((sqq * spv - spq * sqv) / det, (spp * sqv - spq * spv) / det)
    } else {
        (-1.0, -1.0)
    };
    if a >= 0.0 && b >= 0.0 {
        return [a, b];
    }
    // One term at zero: the better of the two single-term fits.
    let one = |pick: &dyn Fn(&(f64, f64, f64)) -> f64| -> (f64, f64) {
        let (mut sxx, mut sxv) = (0.0, 0.0);
        for r in rows {
            let w = 1.0 / (r.2 * r.2);
            sxx += w * pick(r) * pick(r);
            sxv += w * pick(r) * r.2;
        }
        let k = if sxx > 0.0 { (sxv / sxx).max(0.0) } else { 0.0 };
        let e: f64 = rows.iter().map(|r| ((r.2 - k * pick(r)) / r.2).powi(2)).sum();
        (k, e)
    };
    let (ka, ea) = one(&|r| r.0);
    let (kb, eb) = one(&|r| r.1);
    if ea <= eb {
        [ka, 0.0]
    } else {
        [0.0, kb]
    }
}

/// Fits `m(d)` to `samples` (positive values; the beam's blur in `blur`) in section 7.1's
/// stages: (1) c2 = 0, σ1 and c1 in log space to the points beyond δ1; (2) σ1, c1 fixed, σ2 > σ1
/// and c2 to the points within δ2; (3) σ1, σ2 fixed, c1 and c2 to all points. `None` with too
/// few points in a stage (fewer than 3 per channel beyond δ1, or 3 in all within δ2). The
/// stages run [`ROUNDS`] times, stage 1 on the data less the previous round's fast term: with a
/// beam, the fast term's blurred tail reaches past δ1 and biased σ1 by 10 % in one round.
pub fn fit(samples: &[Sample], blur: &Blur, stages: &Stages) -> Option<Profile> {
    fit_shared(&[(samples, blur)], stages).and_then(|v| v.into_iter().next())
}

/// One spot's data as the stages see them.
struct Spot<'a> {
    blur: &'a Blur,
    pts: Vec<Sample>,
    far: Vec<Sample>,
    near: Vec<Sample>,
}

/// [`fit`] over several spots at once: σ1, σ2 shared, each spot's own c1, c2 — the stages'
/// costs summed over the spots. On one medium the rates are the medium's, and a spot's
/// data within δ2 (a dozen texels, through a blur as wide as the fast term) fix the fast
/// term's energy `c2/σ2²` far better than σ2 itself; spots landing at other places between
/// the texels pin σ2 together. `None` when any spot has too few points (as in [`fit`]).
/// Profiles in the order given, each with its own misfit.
pub fn fit_shared(spots: &[(&[Sample], &Blur)], stages: &Stages) -> Option<Vec<Profile>> {
    let mut set: Vec<Spot> = Vec::with_capacity(spots.len());
    for &(samples, blur) in spots {
        let pts: Vec<Sample> = samples
            .iter()
            .copied()
            .filter(|s| s.value > 0.0 && s.value.is_finite() && s.d >= 0.0 && s.channel < 3)
            .collect();
        let far: Vec<Sample> = pts.iter().copied().filter(|s| s.d > stages.delta1).collect();
        let near: Vec<Sample> = pts.iter().copied().filter(|s| s.d < stages.delta2).collect();
        let per = |v: &[Sample], c: u8| v.iter().filter(|s| s.channel == c).count();
        if (0..3).any(|c| per(&far, c) < 3) || near.len() < 3 {
            return None;
        }
        set.push(Spot { blur, pts, far, near });
    }
    if set.is_empty() {
        return None;
    }
    let k = set.len();
    // The fast term's blurred tail reaches past δ1 (the paper's stages assume it does not): the
    // stages are repeated with stage 1 fitted to the data less the last round's fast term.
    let (mut s1, mut s2) = (0.0, 0.0);
    let (mut c1o, mut c2o) = (vec![[0.0; 3]; k], vec![[0.0; 3]; k]);
    for _round in 0..ROUNDS {
        let far_rest: Vec<Vec<(f64, Sample)>> = set
            .iter()
            .zip(&c2o)
            .map(|(sp, c2)| {
                let fast = |p: &Sample| {
                    if s2 > 0.0 {
                        c2[usize::from(p.channel)] * sp.blur.eval(s2, p.d)
                    } else {
                        0.0
                    }
                };
                sp.far.iter().map(|p| (p.value - fast(p), *p)).filter(|(v, p)| *v > 0.05 * p.value).collect()
            })
            .collect();
        if far_rest.iter().any(|f| (0..3).any(|c| f.iter().filter(|(_, p)| p.channel == c).count() < 3)) {
            break;
        }
        // Stage 1: ln c1[c] is the mean residual of its channel, per spot.
        let ln_c1 = |i: usize, ls: f64| -> [f64; 3] {
            let s = ls.exp();
            let mut sum = [(0.0, 0usize); 3];
            for (v, p) in &far_rest[i] {
                let c = usize::from(p.channel);
                sum[c].0 += v.ln() - set[i].blur.ln(s, p.d);
                sum[c].1 += 1;
            }
            sum.map(|(a, n)| a / n.max(1) as f64)
        };
        let cost1 = |ls: f64| {
            let s = ls.exp();
            (0..k)
                .map(|i| {
                    let kc = ln_c1(i, ls);
                    far_rest[i]
                        .iter()
                        .map(|(v, p)| (v.ln() - kc[usize::from(p.channel)] - set[i].blur.ln(s, p.d)).powi(2))
                        .sum::<f64>()
                })
                .sum::<f64>()
        };
        let ls1 = minimise(RATES.0.ln(), RATES.1.ln(), &cost1)?;
        s1 = ls1.exp();
        let c1: Vec<[f64; 3]> = (0..k).map(|i| ln_c1(i, ls1).map(f64::exp)).collect();
        // Stage 2: c2 per spot and channel by least squares for each σ2.
        let c2_of = |i: usize, s2: f64| -> [f64; 3] {
            let sp = &set[i];
            let mut c2 = [0.0; 3];
            for (c, out) in c2.iter_mut().enumerate() {
                let (mut sqq, mut sqv) = (0.0, 0.0);
                for p in sp.near.iter().filter(|p| usize::from(p.channel) == c) {
                    let rest = p.value - c1[i][c] * sp.blur.eval(s1, p.d);
                    let q = sp.blur.eval(s2, p.d);
                    let w = 1.0 / (p.value * p.value);
                    sqq += w * q * q;
                    sqv += w * q * rest;
                }
                *out = if sqq > 0.0 { (sqv / sqq).max(0.0) } else { 0.0 };
            }
            c2
        };
        let cost2 = |ls: f64| {
            let s2 = ls.exp();
            (0..k)
                .map(|i| {
                    let sp = &set[i];
                    let c2 = c2_of(i, s2);
                    sp.near
                        .iter()
                        .map(|p| {
                            let c = usize::from(p.channel);
                            ((p.value - c1[i][c] * sp.blur.eval(s1, p.d) - c2[c] * sp.blur.eval(s2, p.d))
                                / p.value)
                                .powi(2)
                        })
                        .sum::<f64>()
                })
                .sum::<f64>()
        };
        s2 = minimise((s1 * 1.05).ln(), RATES.1.ln(), &cost2)?.exp();
        // Stage 3: each spot's colours on all its points.
        for (i, sp) in set.iter().enumerate() {
            for c in 0..3u8 {
                let rows: Vec<(f64, f64, f64)> = sp
                    .pts
                    .iter()
                    .filter(|p| p.channel == c)
                    .map(|p| (sp.blur.eval(s1, p.d), sp.blur.eval(s2, p.d), p.value))
                    .collect();
                let [a, b] = two_terms(&rows);
                c1o[i][usize::from(c)] = a;
                c2o[i][usize::from(c)] = b;
            }
        }
    }
    if s2 <= 0.0 {
        return None;
    }
    Some(
        set.iter()
            .enumerate()
            .map(|(i, sp)| {
                let mut prof = Profile { sigma: [s1, s2], c1: c1o[i], c2: c2o[i], misfit: 0.0 };
                let se: f64 = sp
                    .pts
                    .iter()
                    .map(|p| {
                        ((prof.eval_blurred(sp.blur, usize::from(p.channel), p.d) - p.value) / p.value)
                            .powi(2)
                    })
                    .sum();
                prof.misfit = (se / sp.pts.len() as f64).sqrt();
                prof
            })
            .collect(),
    )
}

/// The dipole's own `m(d)`: the same staged fit to a homogeneous medium's `Rd` (no beam) at the
/// distances `ds` — what the kernels measured on a homogeneous region are compared with.
pub fn dipole_profile(dipoles: &[Dipole; 3], ds: &[f64], stages: &Stages) -> Option<Profile> {
    let samples: Vec<Sample> = ds
        .iter()
        .flat_map(|&d| (0..3u8).map(move |c| Sample { d, channel: c, value: dipoles[usize::from(c)].rd(d) }))
        .collect();
    let d_max = ds.iter().copied().fold(0.0, f64::max);
    fit(&samples, &Blur::new(0.0, d_max.max(0.1)), stages)
}

/// The kernel's sample distances for a spot at the centre of a `size`×`size` grid of `texel` mm
/// pitch, offset by `(ox, oy)` texels: what [`dipole_profile`] is evaluated on.
pub fn grid_distances(size: usize, texel: f64, offset: [f64; 2]) -> Vec<f64> {
    let h = (size as f64 - 1.0) / 2.0;
    (0..size * size)
        .map(|i| {
            let (x, y) = ((i % size) as f64 - h - offset[0], (i / size) as f64 - h - offset[1]);
            texel * (x * x + y * y).sqrt()
        })
        .collect()
}

/// `2π∫ m(d) d dd` in channel `c`, no beam: the kernel's total (its diffuse reflectance).
pub fn total(p: &Profile, c: usize) -> f64 {
    2.0 * PI * (p.c1[c] / (p.sigma[0] * p.sigma[0]) + p.c2[c] / (p.sigma[1] * p.sigma[1]))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::disco::dipole::MARBLE;

    #[test]
    fn the_bessel_factor_matches_its_series() {
        // I0(x) = Σ (x/2)^{2k} / (k!)².
        for x in [0.0, 0.5, 2.0, 3.75, 5.0, 20.0] {
            let (mut term, mut sum) = (1.0f64, 1.0f64);
            for k in 1..200 {
                term *= (x / 2.0) * (x / 2.0) / (k * k) as f64;
                sum += term;
            }
            let want = sum * (-x).exp();
            assert!((i0e(x) / want - 1.0).abs() < 1e-6, "x {x}: {} vs {want}", i0e(x));
        }
    }

    #[test]
    fn blurring_keeps_the_total_and_the_far_slope() {
        // The Gaussian preserves ∫ f dA; far out the exponential keeps its rate.
        let (s, b) = (0.8, 0.85);
        let total = |f: &dyn Fn(f64) -> f64| {
            let mut sum = 0.0;
            let h = 0.005;
            let mut r = h / 2.0;
            while r < 40.0 {
                sum += f(r) * 2.0 * PI * r * h;
                r += h;
            }
            sum
        };
        let plain = total(&|r| (-s * r).exp());
        let blurred = total(&|r| blurred_exp(s, r, b));
        assert!((blurred / plain - 1.0).abs() < 2e-3, "{blurred} vs {plain}");
        let slope = (blurred_exp(s, 8.0, b) / blurred_exp(s, 9.0, b)).ln();
        assert!((slope - s).abs() < 0.02, "{slope}");
        let t = Blur::new(b, 10.0);
        for d in [0.0, 0.3, 1.7, 4.4] {
            assert!((t.eval(s, d) / blurred_exp(s, d, b) - 1.0).abs() < 1e-3);
        }
    }

    fn synthetic(p: &Profile, blur: &Blur, noise: f64) -> Vec<Sample> {
        // 9×9 texels of 1 mm, the spot off the texel centre; deterministic ±noise.
        let mut out = Vec::new();
        for (i, d) in grid_distances(9, 1.0, [0.3, -0.2]).into_iter().enumerate() {
            for c in 0..3 {
                let e = 1.0 + noise * (((i * 7 + c * 3) % 11) as f64 / 5.0 - 1.0);
                out.push(Sample { d, channel: c as u8, value: p.eval_blurred(blur, c, d) * e });
            }
        }
        out
    }

    #[test]
    fn the_staged_fit_recovers_a_blurred_profile() {
        let truth =
            Profile { sigma: [0.35, 2.5], c1: [0.02, 0.015, 0.01], c2: [0.2, 0.25, 0.3], misfit: 0.0 };
        let blur = Blur::new(0.85, 8.0);
        let p = fit(&synthetic(&truth, &blur, 0.0), &blur, &Stages::default()).unwrap();
        assert!((p.sigma[0] / 0.35 - 1.0).abs() < 0.01, "{p:?}");
        assert!((p.sigma[1] / 2.5 - 1.0).abs() < 0.03, "{p:?}");
        for c in 0..3 {
            assert!((total(&p, c) / total(&truth, c) - 1.0).abs() < 0.01, "{p:?}");
        }
        // 2 % noise: still within the 10 %.
        let p = fit(&synthetic(&truth, &blur, 0.02), &blur, &Stages::default()).unwrap();
        assert!((p.sigma[0] / 0.35 - 1.0).abs() < 0.05, "{p:?}");
        assert!((p.sigma[1] / 2.5 - 1.0).abs() < 0.10, "{p:?}");
        // Fitted without the beam, the fast rate is the beam's, not the object's.
        let flat = fit(&synthetic(&truth, &blur, 0.0), &Blur::new(0.0, 8.0), &Stages::default()).unwrap();
        assert!((flat.sigma[1] / 2.5 - 1.0).abs() > 0.2, "{flat:?}");
    }

    /// A spot's data: 0.5 mm texels within 5 mm, the spot at `offset` texels from a texel, with
    /// multiplicative noise of `noise` (RMS) from `seed`.
    pub(crate) fn spot_data(
        p: &Profile,
        blur: &Blur,
        offset: [f64; 2],
        noise: f64,
        seed: u64,
    ) -> Vec<Sample> {
        let mut x = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut gauss = move || {
            // Sum of 12 uniforms: near enough a unit normal for a test's noise.
            (0..12)
                .map(|_| {
                    x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    (x >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0
        };
        grid_distances(21, 0.5, offset)
            .into_iter()
            .filter(|&d| d <= 5.0)
            .flat_map(|d| (0..3u8).map(move |c| (d, c)))
            .map(|(d, c)| Sample {
                d,
                channel: c,
                value: p.eval_blurred(blur, usize::from(c), d) * (1.0 + noise * gauss()),
            })
            .collect()
    }

    #[test]
    fn spots_sharing_their_rates_pin_the_fast_one() {
        // Marble-like rates through a 0.85 mm beam, 3 % noise: alone, each spot's σ2 scatters
        // (here −23 % to +24 %); the eight fitted together give it within 8 % (the relative
        // weights' noise biases it up: noise-free, within 0.3 %), and each spot keeps its own
        // colours.
        let truth =
            Profile { sigma: [0.73, 3.4], c1: [0.02, 0.015, 0.01], c2: [0.3, 0.35, 0.4], misfit: 0.0 };
        let blur = Blur::new(0.85, 6.0);
        let offsets = [
            [0.0, 0.0],
            [0.4, 0.1],
            [-0.3, 0.45],
            [0.2, -0.35],
            [0.49, 0.49],
            [-0.1, -0.2],
            [0.3, 0.3],
            [-0.45, 0.05],
        ];
        let data: Vec<Vec<Sample>> = offsets
            .iter()
            .enumerate()
            .map(|(i, &o)| {
                // Each spot its own brightness: shared rates, not shared colours.
                let mut t = truth;
                let k = 1.0 + 0.1 * i as f64;
                t.c1 = t.c1.map(|c| c * k);
                t.c2 = t.c2.map(|c| c * k);
                spot_data(&t, &blur, o, 0.03, i as u64 + 1)
            })
            .collect();
        let alone: Vec<f64> =
            data.iter().map(|d| fit(d, &blur, &Stages::default()).unwrap().sigma[1] / 3.4 - 1.0).collect();
        let worst_alone = alone.iter().fold(0.0f64, |m, e| m.max(e.abs()));
        let set: Vec<(&[Sample], &Blur)> = data.iter().map(|d| (d.as_slice(), &blur)).collect();
        let shared = fit_shared(&set, &Stages::default()).unwrap();
        assert_eq!(shared.len(), 8);
        let s = shared[0].sigma;
        assert!((s[0] / 0.73 - 1.0).abs() < 0.03, "σ1 {s:?}");
        assert!((s[1] / 3.4 - 1.0).abs() < 0.08, "σ2 {s:?}; alone {alone:?}");
        assert!(worst_alone > 3.0 * (s[1] / 3.4 - 1.0).abs(), "alone {alone:?}, shared {s:?}");
        for (i, p) in shared.iter().enumerate() {
            assert_eq!(p.sigma, s);
            let k = 1.0 + 0.1 * i as f64;
            for c in 0..3 {
                let want = 2.0 * PI * k * (truth.c1[c] / (0.73f64 * 0.73) + truth.c2[c] / (3.4f64 * 3.4));
                assert!((total(p, c) / want - 1.0).abs() < 0.03, "spot {i} channel {c}: {p:?}");
            }
            assert!(p.misfit < 0.1, "{p:?}");
        }
        // One spot fitted "together" is the spot fitted alone.
        assert_eq!(
            fit_shared(&set[..1], &Stages::default()).unwrap()[0],
            fit(&data[0], &blur, &Stages::default()).unwrap()
        );
    }

    #[test]
    fn too_few_points_is_no_fit() {
        let blur = Blur::new(0.0, 8.0);
        let s = [Sample { d: 0.5, channel: 0, value: 1.0 }, Sample { d: 4.0, channel: 0, value: 0.1 }];
        assert_eq!(fit(&s, &blur, &Stages::default()), None);
    }

    /// The sample distances of a spot's data: 0.5 mm texels within 5 mm, the spot off-centre.
    fn spot_distances() -> Vec<f64> {
        grid_distances(21, 0.5, [0.3, -0.2]).into_iter().filter(|&d| d <= 5.0).collect()
    }

    #[test]
    fn the_dipole_of_marble_has_two_distinct_rates() {
        let p = dipole_profile(&MARBLE.dipoles(), &spot_distances(), &Stages::default()).unwrap();
        assert!(p.sigma[1] > 2.0 * p.sigma[0], "{p:?}");
        assert!(p.misfit < 0.2, "{p:?}");
        // The beam-blurred dipole fitted through the beam model: the rates the rig can see.
        let blur = Blur::new(0.85, 8.0);
        let d = MARBLE.dipoles();
        let samples: Vec<Sample> = spot_distances()
            .into_iter()
            .flat_map(|r| {
                (0..3u8).map(move |c| {
                    // The dipole convolved with the beam, by the same radial integral.
                    let b2 = 0.85f64 * 0.85;
                    let (lo, hi, n) = ((r - 6.0 * 0.85f64).max(0.0), r + 6.0 * 0.85, 400);
                    let h = (hi - lo) / n as f64;
                    let v: f64 = (0..n)
                        .map(|i| {
                            let x = lo + (i as f64 + 0.5) * h;
                            d[usize::from(c)].rd(x) * x / b2
                                * (-(x - r) * (x - r) / (2.0 * b2)).exp()
                                * i0e(x * r / b2)
                                * h
                        })
                        .sum();
                    Sample { d: r, channel: c, value: v }
                })
            })
            .collect();
        let q = fit(&samples, &blur, &Stages::default()).unwrap();
        // Deconvolved through the beam model, the rates are the dipole's to within 6 %.
        for k in 0..2 {
            assert!((q.sigma[k] / p.sigma[k] - 1.0).abs() < 0.06, "{p:?} {q:?}");
        }
        // The fast rate follows the blur's width steeply: told a beam 2 % narrower than the
        // data's, the fit gives σ2 about 10 % lower (the data fix the blur's and the fast
        // term's widths together); σ1 hardly moves.
        let narrow = fit(&samples, &Blur::new(0.85 / 1.02, 8.0), &Stages::default()).unwrap();
        let drop = 1.0 - narrow.sigma[1] / q.sigma[1];
        assert!(drop > 0.06 && drop < 0.16, "σ2 {} against {}", narrow.sigma[1], q.sigma[1]);
        assert!((narrow.sigma[0] / q.sigma[0] - 1.0).abs() < 0.06, "{narrow:?} {q:?}");
    }
}
