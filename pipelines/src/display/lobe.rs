//! Reading the displayed lobe off the camera's picture of the screen ([`Screen`]): the
//! reflected beam's time-averaged distribution (thesis section 5.5.1: "by deflecting a laser
//! beam, we characterised the achieved surface normal variation").
//!
//! Two readings:
//! - [`spread`]: the moments of the facet tilts the picture holds (each pixel weighs the tilt
//!   that reaches it by its value). One sine of slope amplitude `ρ` has tilt variance `ρ²/2`
//!   ([`single_sine_roughness`]): how the calibration measures each coil's response.
//! - [`fit_ward`]: Ward's lobe as written (`crate::ward`: `exp(−tan²θh(…))/√(cosθi·cosθo)`)
//!   fitted to the picture, blurred by the still beam's own spot: the displayed `α` is the
//!   fit's, and how far the displayed bell is from Ward's shape is
//!   [`WardFit::shape_error`].
//!
//! The background (the median of the image's border) is removed first; noise then adds
//! zero-mean terms only.

use super::screen::Screen;

/// Centre and variance of a picture's distribution on each axis: facet tilts ([`spread`]) or
/// pixels ([`pixel_spread`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// Mean on x, y.
    pub mean: [f64; 2],
    /// Variance on x, y.
    pub var: [f64; 2],
}

/// The median of the picture's border pixels.
pub fn background(pixels: &[f32], w: usize, h: usize) -> f64 {
    let mut border: Vec<f32> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                border.push(pixels[y * w + x]);
            }
        }
    }
    border.sort_by(f32::total_cmp);
    f64::from(border.get(border.len() / 2).copied().unwrap_or(0.0))
}

/// Moments of `pixels` (background removed) in the coordinates `at(x, y)` over the pixels
/// `x0..x1 × y0..y1`.
fn moments(
    pixels: &[f32],
    w: usize,
    background: f64,
    (x0, x1, y0, y1): (usize, usize, usize, usize),
    at: &dyn Fn(usize, usize) -> [f64; 2],
) -> Spread {
    let (mut m0, mut m1, mut m2) = (0.0, [0.0; 2], [0.0; 2]);
    for y in y0..y1 {
        for x in x0..x1 {
            let v = f64::from(pixels[y * w + x]) - background;
            let c = at(x, y);
            m0 += v;
            for a in 0..2 {
                m1[a] += v * c[a];
                m2[a] += v * c[a] * c[a];
            }
        }
    }
    let m0 = if m0 > 0.0 { m0 } else { f64::MIN_POSITIVE };
    let mean = [m1[0] / m0, m1[1] / m0];
    Spread { mean, var: [m2[0] / m0 - mean[0] * mean[0], m2[1] / m0 - mean[1] * mean[1]] }
}

/// The pixels that hold the spot: far from it, pixels hold only noise and the background's
/// error, which moments weigh by the squared distance. After a first pass over the whole
/// picture the window is cut to 5 standard deviations (and 3 pixels) about the centre, twice.
fn window(pixels: &[f32], w: usize, h: usize, background: f64) -> (usize, usize, usize, usize) {
    let mut win = (0, w, 0, h);
    for _ in 0..2 {
        let s = moments(pixels, w, background, win, &|x, y| [x as f64 + 0.5, y as f64 + 0.5]);
        let cut = |mean: f64, var: f64, n: usize| {
            let r = 5.0 * var.max(0.0).sqrt() + 3.0;
            let lo = (mean - r).floor().clamp(0.0, n as f64) as usize;
            let hi = (mean + r).ceil().clamp(0.0, n as f64) as usize;
            if hi > lo {
                (lo, hi)
            } else {
                (0, n)
            }
        };
        let (x0, x1) = cut(s.mean[0], s.var[0], w);
        let (y0, y1) = cut(s.mean[1], s.var[1], h);
        win = (x0, x1, y0, y1);
    }
    win
}

/// The picture's spread in pixels (the still beam's spot: the blur [`fit_ward`] applies).
pub fn pixel_spread(pixels: &[f32], w: usize, h: usize) -> Spread {
    let b = background(pixels, w, h);
    let win = window(pixels, w, h, b);
    moments(pixels, w, b, win, &|x, y| [x as f64 + 0.5, y as f64 + 0.5])
}

/// The facet tilts a `w × h` screen picture (row-major, linear values) holds: their mean and
/// variance per axis.
pub fn spread(pixels: &[f32], w: usize, h: usize, screen: &Screen) -> Spread {
    let b = background(pixels, w, h);
    let win = window(pixels, w, h, b);
    moments(pixels, w, b, win, &|x, y| screen.tilt(x, y))
}

/// The tilt variances the surface made: `moving`'s minus the still beam's.
pub fn surface_variance(moving: &Spread, still: &Spread) -> [f64; 2] {
    [(moving.var[0] - still.var[0]).max(0.0), (moving.var[1] - still.var[1]).max(0.0)]
}

/// One sine's roughness (slope amplitude) `ρ` from its tilt variance `ρ²/2`.
pub fn single_sine_roughness(variance: f64) -> f64 {
    (2.0 * variance.max(0.0)).sqrt()
}

/// Ward's lobe fitted to a screen picture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WardFit {
    /// Ward's `αx`, `αy`.
    pub alpha: [f64; 2],
    /// The lobe's centre, facet tilt (a liquid not quite level moves it).
    pub centre: [f64; 2],
    /// How far the displayed bell is from Ward's: the total-variation distance between the
    /// picture and the fitted lobe, each as a distribution over the fitted pixels (0 the same
    /// shape, 1 disjoint). Noise alone adds a little.
    pub shape_error: f64,
    /// Fitted pixels.
    pub pixels: usize,
}

/// Ward's lobe for a beam at the screen's incidence, per pixel of `screen` and up to a factor:
/// `exp(−((tx−cx)²/αx² + (ty−cy)²/αy²)) · √cosθo · Ω`, with `t` the pixel's facet tilt
/// (`tan θh cos φ`, `tan θh sin φ`), `θo` its angle from the liquid's normal and `Ω` its
/// solid angle.
struct Lobe {
    /// Expanded window (the blur's margin): `x0, x1, y0, y1`.
    rect: (usize, usize, usize, usize),
    tilt: Vec<[f64; 2]>,
    weight: Vec<f64>,
    kernel: [Vec<f64>; 2],
}

impl Lobe {
    fn new(
        screen: &Screen,
        w: usize,
        h: usize,
        win: (usize, usize, usize, usize),
        beam_px: [f64; 2],
    ) -> Lobe {
        let kernel = beam_px.map(|s| {
            let s = s.max(1e-3);
            let r = (4.0 * s).ceil() as i64;
            let k: Vec<f64> = (-r..=r).map(|i| (-(i as f64).powi(2) / (2.0 * s * s)).exp()).collect();
            let sum: f64 = k.iter().sum();
            k.into_iter().map(|v| v / sum).collect::<Vec<f64>>()
        });
        let (rx, ry) = (kernel[0].len() / 2, kernel[1].len() / 2);
        let rect =
            (win.0.saturating_sub(rx), (win.1 + rx).min(w), win.2.saturating_sub(ry), (win.3 + ry).min(h));
        let mut tilt = Vec::new();
        let mut weight = Vec::new();
        for y in rect.2..rect.3 {
            for x in rect.0..rect.1 {
                tilt.push(screen.tilt(x, y));
                let cos_o = screen.direction(x, y)[2].max(0.0);
                weight.push(cos_o.sqrt() * screen.solid_angle(x, y));
            }
        }
        Lobe { rect, tilt, weight, kernel }
    }

    /// The blurred lobe over the expanded window, row-major.
    fn eval(&self, alpha: [f64; 2], centre: [f64; 2]) -> Vec<f64> {
        let raw: Vec<f64> = self
            .tilt
            .iter()
            .zip(&self.weight)
            .map(|(t, wgt)| {
                let e = ((t[0] - centre[0]) / alpha[0]).powi(2) + ((t[1] - centre[1]) / alpha[1]).powi(2);
                wgt * (-e).exp()
            })
            .collect();
        let (rw, rh) = (self.rect.1 - self.rect.0, self.rect.3 - self.rect.2);
        let blur = |src: &[f64], k: &[f64], along_x: bool| -> Vec<f64> {
            let r = (k.len() / 2) as i64;
            let mut out = vec![0.0; src.len()];
            for y in 0..rh {
                for x in 0..rw {
                    let mut acc = 0.0;
                    for (t, kv) in k.iter().enumerate() {
                        let (xx, yy) = if along_x {
                            (x as i64 + t as i64 - r, y as i64)
                        } else {
                            (x as i64, y as i64 + t as i64 - r)
                        };
                        if (0..rw as i64).contains(&xx) && (0..rh as i64).contains(&yy) {
                            acc += kv * src[yy as usize * rw + xx as usize];
                        }
                    }
                    out[y * rw + x] = acc;
                }
            }
            out
        };
        let bx = blur(&raw, &self.kernel[0], true);
        blur(&bx, &self.kernel[1], false)
    }
}

/// Fits Ward's lobe to a screen picture: `αx`, `αy` and the centre by Levenberg–Marquardt,
/// scale and background by least squares at each step. `beam_px` is the still beam's spot
/// (standard deviation in pixels, from [`pixel_spread`] of a still picture): the lobe is
/// blurred by a Gaussian of that size before it is compared. Starts from the moments.
pub fn fit_ward(pixels: &[f32], w: usize, h: usize, screen: &Screen, beam_px: [f64; 2]) -> WardFit {
    let b0 = background(pixels, w, h);
    let win = window(pixels, w, h, b0);
    let m = moments(pixels, w, b0, win, &|x, y| screen.tilt(x, y));
    let lobe = Lobe::new(screen, w, h, win, beam_px);
    let rw = lobe.rect.1 - lobe.rect.0;
    // The fitted pixels: the window, as indices into the expanded rectangle and the picture.
    let mut idx = Vec::new();
    for y in win.2..win.3 {
        for x in win.0..win.1 {
            idx.push(((y - lobe.rect.2) * rw + (x - lobe.rect.0), y * w + x));
        }
    }
    let data: Vec<f64> = idx.iter().map(|&(_, p)| f64::from(pixels[p])).collect();
    // The smallest α worth telling apart: a tenth of a pixel's tilt step at the centre.
    let cx = (screen.centre_px[0].max(0.0) as usize).min(w.saturating_sub(2));
    let cy = (screen.centre_px[1].max(0.0) as usize).min(h.saturating_sub(2));
    let step = {
        let (a, b, c) = (screen.tilt(cx, cy), screen.tilt(cx + 1, cy), screen.tilt(cx, cy + 1));
        [(b[0] - a[0]).abs(), (c[1] - a[1]).abs()]
    };
    // Parameters: ln αx, ln αy, cx, cy. Residuals after the best scale and background.
    let solve = |p: &[f64; 4]| -> (Vec<f64>, Vec<f64>, f64, f64) {
        let model = lobe.eval([p[0].exp(), p[1].exp()], [p[2], p[3]]);
        let mv: Vec<f64> = idx.iter().map(|&(i, _)| model[i]).collect();
        let n = mv.len() as f64;
        let (sm, sd) = (mv.iter().sum::<f64>(), data.iter().sum::<f64>());
        let smm: f64 = mv.iter().map(|v| v * v).sum();
        let smd: f64 = mv.iter().zip(&data).map(|(a, b)| a * b).sum();
        let det = n * smm - sm * sm;
        let (a, b) = if det.abs() > 0.0 {
            ((n * smd - sm * sd) / det, (smm * sd - sm * smd) / det)
        } else {
            (0.0, sd / n)
        };
        let r: Vec<f64> = mv.iter().zip(&data).map(|(v, d)| d - (a * v + b)).collect();
        (r, mv, a, b)
    };
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let start = [0, 1].map(|a| (2.0 * m.var[a].max(0.0)).sqrt().max(0.1 * step[a]).max(1e-6));
    let mut p = [start[0].ln(), start[1].ln(), m.mean[0], m.mean[1]];
    let (mut r, _, _, _) = solve(&p);
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    for _ in 0..60 {
        // Forward-difference Jacobian.
        let hstep = [1e-4, 1e-4, 1e-3 * start[0], 1e-3 * start[1]];
        let mut jac = vec![[0.0; 4]; r.len()];
        for k in 0..4 {
            let mut q = p;
            q[k] += hstep[k];
            let (rq, _, _, _) = solve(&q);
            for (row, (a, b)) in jac.iter_mut().zip(rq.iter().zip(&r)) {
                row[k] = (a - b) / hstep[k];
            }
        }
        let mut jtj = [[0.0; 4]; 4];
        let mut jtr = [0.0; 4];
        for (row, ri) in jac.iter().zip(&r) {
            for i in 0..4 {
                jtr[i] += row[i] * ri;
                for j in 0..4 {
                    jtj[i][j] += row[i] * row[j];
                }
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj;
            for (i, row) in a.iter_mut().enumerate() {
                row[i] += lambda * jtj[i][i].max(1e-300);
            }
            let Some(d) = crate::linalg::solve(a, jtr.map(|v| -v)) else { break };
            let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2], p[3] + d[3]];
            let (rq, _, _, _) = solve(&q);
            let cq = cost(&rq);
            if cq < c {
                let small = (c - cq) <= 1e-10 * c;
                p = q;
                r = rq;
                c = cq;
                lambda = (lambda / 3.0).max(1e-9);
                improved = !small;
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
    }
    let (_, mv, a, _) = solve(&p);
    let (sd, sm): (f64, f64) =
        (data.iter().sum::<f64>() - b0 * data.len() as f64, mv.iter().sum::<f64>() * a);
    let shape_error = if sd > 0.0 && sm.abs() > 0.0 {
        0.5 * data.iter().zip(&mv).map(|(d, v)| ((d - b0) / sd - a * v / sm).abs()).sum::<f64>()
    } else {
        1.0
    };
    WardFit { alpha: [p[0].exp(), p[1].exp()], centre: [p[2], p[3]], shape_error, pixels: idx.len() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::{add, dot, normalize};

    fn screen() -> Screen {
        Screen {
            distance_m: 0.05,
            pitch_m: 0.6e-3,
            incidence_rad: 0.2,
            tilt_rad: 0.1,
            centre_px: [96.0, 96.0],
        }
    }

    /// A picture of `value(tilt)` per unit solid angle of reflection direction, drawn by
    /// sampling each pixel 8 × 8 times, plus a background and noise.
    fn draw(s: &Screen, value: &dyn Fn([f64; 2]) -> f64) -> Vec<f32> {
        let (w, h) = (192, 192);
        let wi = s.incident();
        let mut px = vec![0f32; w * h];
        let mut state = 9u64;
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for j in 0..8 {
                    for i in 0..8 {
                        let p = s.point(
                            x as f64 + (f64::from(i) + 0.5) / 8.0,
                            y as f64 + (f64::from(j) + 0.5) / 8.0,
                        );
                        let d = normalize(p);
                        let hv = normalize(add(wi, d));
                        acc += value([hv[0] / hv[2], hv[1] / hv[2]]);
                    }
                }
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let noise = ((state >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 1e-4;
                px[y * w + x] = (0.01 + acc / 64.0 * s.solid_angle(x, y) / 1e-4 + noise) as f32;
            }
        }
        px
    }

    #[test]
    fn wards_own_lobe_is_fitted_back_with_its_alphas_and_no_shape_error() {
        let s = screen();
        let wi = s.incident();
        for (ax, ay) in [(0.03, 0.03), (0.12, 0.04), (0.14, 0.14)] {
            // Ward's lobe as `crate::ward` writes it, evaluated per direction (the tilt's half
            // vector gives θh and φ; cos θo of the reflected direction).
            let lobe = |t: [f64; 2]| {
                let n = normalize([t[0], t[1], 1.0]);
                let out = crate::vec3::sub(crate::vec3::scale(n, 2.0 * dot(wi, n)), wi);
                let tan2 = t[0] * t[0] + t[1] * t[1];
                let (c2, s2) = if tan2 > 0.0 { (t[0] * t[0] / tan2, t[1] * t[1] / tan2) } else { (1.0, 0.0) };
                (-tan2 * (c2 / (ax * ax) + s2 / (ay * ay))).exp() / (wi[2] * out[2].max(0.0)).sqrt()
                    * out[2].max(0.0)
            };
            let px = draw(&s, &lobe);
            let f = fit_ward(&px, 192, 192, &s, [1e-3, 1e-3]);
            assert!((f.alpha[0] / ax - 1.0).abs() < 0.01, "{ax}: {f:?}");
            assert!((f.alpha[1] / ay - 1.0).abs() < 0.01, "{ay}: {f:?}");
            assert!(f.centre[0].abs() < 1e-3 && f.centre[1].abs() < 1e-3, "{f:?}");
            assert!(f.shape_error < 0.01, "{f:?}");
            // The moments of the same picture: a Gaussian in tilt of variance α²/2 but for
            // Ward's √cosθo and the solid angle's cos⁴θh, a few per cent at 0.14.
            let m = spread(&px, 192, 192, &s);
            let alpha_m = (2.0 * m.var[0]).sqrt();
            assert!((alpha_m / ax - 1.0).abs() < 0.07, "{ax}: moments give {alpha_m}");
        }
    }

    #[test]
    fn a_bell_that_is_not_wards_shows_a_shape_error() {
        let s = screen();
        // A flat-topped disc of tilts: the same second moment as α = 0.08, the wrong shape.
        let r = 0.08 * 2f64.sqrt();
        let disc = |t: [f64; 2]| if t[0] * t[0] + t[1] * t[1] < r * r { 1.0 } else { 0.0 };
        let f = fit_ward(&draw(&s, &disc), 192, 192, &s, [1e-3, 1e-3]);
        assert!(f.shape_error > 0.1, "{f:?}");
    }

    #[test]
    fn the_still_beams_spot_and_one_sines_roughness() {
        let (w, h) = (96, 64);
        let (cx, cy, sx, sy) = (40.3, 30.7, 2.5, 1.5);
        let mut px = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                px[y * w + x] = (0.3 + (-dx * dx / (2.0 * sx * sx) - dy * dy / (2.0 * sy * sy)).exp()) as f32;
            }
        }
        let s = pixel_spread(&px, w, h);
        assert!((s.mean[0] - cx).abs() < 1e-3 && (s.mean[1] - cy).abs() < 1e-3, "{s:?}");
        assert!(
            (s.var[0] / (sx * sx) - 1.0).abs() < 0.01 && (s.var[1] / (sy * sy) - 1.0).abs() < 0.01,
            "{s:?}"
        );
        let still = Spread { mean: [0.0; 2], var: [1e-4, 1e-4] };
        let v = surface_variance(&s, &still);
        assert!((v[0] - (s.var[0] - 1e-4)).abs() < 1e-15);
        assert!((single_sine_roughness(0.04 * 0.04 / 2.0) - 0.04).abs() < 1e-15);
    }
}
