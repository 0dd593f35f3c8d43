//! Reading the displayed lobe off the camera's picture of the screen: the reflected beam's
//! time-averaged spread, by its second moments (thesis section 5.5.1: "by deflecting a laser
//! beam, we characterised the achieved surface normal variation").
//!
//! A screen image's pixel `(x, y)` sees the reflection angles `((x + ½ − w/2)·p, (y + ½ − h/2)·p)`
//! for an angular pitch `p`. The background (the median of the image's border) is removed
//! first; noise then adds zero-mean terms only. The spread of the beam itself (a still
//! surface's picture) is subtracted from each variance.

/// Centre and variance of the reflection angles on each axis, rad and rad².
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// Mean angle on x, y.
    pub mean: [f64; 2],
    /// Variance on x, y.
    pub var: [f64; 2],
}

/// The spread of a `w × h` screen picture (row-major, linear values) of pitch `pitch` rad.
pub fn spread(pixels: &[f32], w: usize, h: usize, pitch: f64) -> Spread {
    let mut border: Vec<f32> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                border.push(pixels[y * w + x]);
            }
        }
    }
    border.sort_by(f32::total_cmp);
    let background = f64::from(border.get(border.len() / 2).copied().unwrap_or(0.0));
    // Far from the spot, pixels hold only noise and the background's error, which the
    // moments would weigh by the squared angle: after a first pass over the whole picture,
    // the moments are taken again within 5 standard deviations of the centre, twice.
    let mut window = [(f64::NEG_INFINITY, f64::INFINITY); 2];
    let mut out = Spread { mean: [0.0; 2], var: [0.0; 2] };
    for _ in 0..3 {
        let (mut m0, mut mx, mut my, mut mxx, mut myy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for y in 0..h {
            let ay = (y as f64 + 0.5 - h as f64 / 2.0) * pitch;
            if ay < window[1].0 || ay > window[1].1 {
                continue;
            }
            for x in 0..w {
                let ax = (x as f64 + 0.5 - w as f64 / 2.0) * pitch;
                if ax < window[0].0 || ax > window[0].1 {
                    continue;
                }
                let v = f64::from(pixels[y * w + x]) - background;
                m0 += v;
                mx += v * ax;
                my += v * ay;
                mxx += v * ax * ax;
                myy += v * ay * ay;
            }
        }
        let m0 = if m0 > 0.0 { m0 } else { f64::MIN_POSITIVE };
        let mean = [mx / m0, my / m0];
        out = Spread { mean, var: [mxx / m0 - mean[0] * mean[0], myy / m0 - mean[1] * mean[1]] };
        for (a, win) in window.iter_mut().enumerate() {
            // At least a few pixels either side, however narrow the spot.
            let r = 5.0 * out.var[a].max(0.0).sqrt() + 3.0 * pitch;
            *win = (out.mean[a] - r, out.mean[a] + r);
        }
    }
    out
}

/// The reflection-angle variances the surface made: `moving`'s minus the still beam's.
pub fn surface_variance(moving: &Spread, still: &Spread) -> [f64; 2] {
    [(moving.var[0] - still.var[0]).max(0.0), (moving.var[1] - still.var[1]).max(0.0)]
}

/// One sine's roughness `ρ` from its reflection-angle variance: `σ₀² = 2ρ²` (Eq. 5.6's).
pub fn single_sine_roughness(variance: f64) -> f64 {
    (variance.max(0.0) / 2.0).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gaussian_spot_on_a_noisy_background_gives_its_centre_and_variance() {
        let (w, h, p) = (96, 64, 0.01);
        let (cx, cy, sx, sy) = (0.05, -0.02, 0.06, 0.03);
        let mut px = vec![0f32; w * h];
        let mut state = 9u64;
        for y in 0..h {
            for x in 0..w {
                let ax = (x as f64 + 0.5 - w as f64 / 2.0) * p;
                let ay = (y as f64 + 0.5 - h as f64 / 2.0) * p;
                let g = (-(ax - cx).powi(2) / (2.0 * sx * sx) - (ay - cy).powi(2) / (2.0 * sy * sy)).exp();
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let noise = ((state >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.0005;
                px[y * w + x] = (0.3 + g + noise) as f32;
            }
        }
        let s = spread(&px, w, h, p);
        assert!((s.mean[0] - cx).abs() < 1e-3 && (s.mean[1] - cy).abs() < 1e-3, "{s:?}");
        // Within 2 % (the background is known to the noise's median only).
        assert!((s.var[0] / (sx * sx) - 1.0).abs() < 0.02, "{s:?}");
        assert!((s.var[1] / (sy * sy) - 1.0).abs() < 0.02, "{s:?}");
        let still = Spread { mean: [0.0; 2], var: [1e-4, 1e-4] };
        let v = surface_variance(&s, &still);
        assert!((v[0] - (s.var[0] - 1e-4)).abs() < 1e-15);
        assert!((single_sine_roughness(2.0 * 0.04 * 0.04) - 0.04).abs() < 1e-15);
    }
}
