//! Slope statistics of a surface made of sine waves (thesis section 5.3): one sine's
//! reflection angles follow the arcsine law of Eq. 5.6; a sum of several independent ones
//! approaches a Gaussian (figure 5.8). Distances here are Kolmogorov–Smirnov: the largest gap
//! between two cumulative distributions.

use std::f64::consts::PI;

/// Eq. 5.6: the density of reflection angles `δ` off one sine wave of roughness `rho`, light
/// incident at `beta` (small-angle model); zero outside `|δ + β| < 2ρ`.
pub fn arcsine_pdf(delta: f64, rho: f64, beta: f64) -> f64 {
    let d2 = 4.0 * rho * rho - (delta + beta).powi(2);
    if d2 <= 0.0 {
        0.0
    } else {
        1.0 / (PI * d2.sqrt())
    }
}

/// The cumulative distribution of Eq. 5.6.
pub fn arcsine_cdf(delta: f64, rho: f64, beta: f64) -> f64 {
    let u = ((delta + beta) / (2.0 * rho)).clamp(-1.0, 1.0);
    0.5 + u.asin() / PI
}

/// The error function (Abramowitz & Stegun 7.1.26, |error| < 1.5·10⁻⁷).
pub fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let y = 1.0 - poly * (-x * x).exp();
    y.copysign(x)
}

/// The normal distribution's cumulative distribution.
pub fn normal_cdf(x: f64, mean: f64, sd: f64) -> f64 {
    0.5 * (1.0 + erf((x - mean) / (sd * std::f64::consts::SQRT_2)))
}

/// Mean and variance of `samples`.
pub fn moments(samples: &[f64]) -> (f64, f64) {
    let n = samples.len().max(1) as f64;
    let mean = samples.iter().sum::<f64>() / n;
    let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / n;
    (mean, var)
}

/// Kolmogorov–Smirnov distance between the samples' distribution and `cdf`.
pub fn ks_distance(samples: &[f64], cdf: impl Fn(f64) -> f64) -> f64 {
    let mut s = samples.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len() as f64;
    s.iter()
        .enumerate()
        .map(|(i, &x)| {
            let f = cdf(x);
            (f - i as f64 / n).abs().max((f - (i + 1) as f64 / n).abs())
        })
        .fold(0.0, f64::max)
}

/// Kolmogorov–Smirnov distance of the samples from the Gaussian of their own mean and variance.
pub fn ks_to_gaussian(samples: &[f64]) -> f64 {
    let (mean, var) = moments(samples);
    ks_distance(samples, |x| normal_cdf(x, mean, var.sqrt()))
}

/// The standard deviation of the Gaussian that fits the samples' histogram best by least
/// squares (bins of a tenth of their standard deviation over ±4 of them, centred on their
/// mean): what fitting a bell to a picture of them finds. For a Gaussian's samples it is their
/// standard deviation; a flatter-topped distribution (a sum of few sines) fits wider.
pub fn fitted_gaussian_sd(samples: &[f64]) -> f64 {
    let (mean, var) = moments(samples);
    let sd = var.sqrt();
    if sd.is_nan() || sd <= 0.0 {
        return 0.0;
    }
    let (bins, width) = (80usize, sd / 10.0);
    let mut hist = vec![0.0; bins];
    for s in samples {
        let b = ((s - mean) / width + bins as f64 / 2.0).floor();
        if (0.0..bins as f64).contains(&b) {
            hist[b as usize] += 1.0;
        }
    }
    let centres: Vec<f64> = (0..bins).map(|i| (i as f64 + 0.5 - bins as f64 / 2.0) * width).collect();
    // The residual after the best scale, for a trial width.
    let cost = |s: f64| {
        let g: Vec<f64> = centres.iter().map(|x| (-x * x / (2.0 * s * s)).exp()).collect();
        let a = g.iter().zip(&hist).map(|(g, h)| g * h).sum::<f64>() / g.iter().map(|g| g * g).sum::<f64>();
        g.iter().zip(&hist).map(|(g, h)| (h - a * g).powi(2)).sum::<f64>()
    };
    // Golden-section search over half to twice the standard deviation.
    let (mut lo, mut hi) = (0.5 * sd, 2.0 * sd);
    let r = (5f64.sqrt() - 1.0) / 2.0;
    let (mut c, mut d) = (hi - r * (hi - lo), lo + r * (hi - lo));
    for _ in 0..80 {
        if cost(c) < cost(d) {
            hi = d;
        } else {
            lo = c;
        }
        c = hi - r * (hi - lo);
        d = lo + r * (hi - lo);
    }
    0.5 * (lo + hi)
}

/// The same for a 2-D distribution of independent axes, as a picture shows it: each axis
/// scaled by its standard deviation, the width (in those units) of the round Gaussian that
/// fits the 2-D histogram best by least squares (bins of an eighth over ±4).
pub fn fitted_gaussian_sd_2d(xs: &[f64], ys: &[f64]) -> f64 {
    let ((mx, vx), (my, vy)) = (moments(xs), moments(ys));
    if vx.is_nan() || vy.is_nan() || vx <= 0.0 || vy <= 0.0 {
        return 0.0;
    }
    let (sx, sy) = (vx.sqrt(), vy.sqrt());
    let (side, width) = (64usize, 1.0 / 8.0);
    let mut hist = vec![0.0; side * side];
    for (x, y) in xs.iter().zip(ys) {
        let bx = ((x - mx) / sx / width + side as f64 / 2.0).floor();
        let by = ((y - my) / sy / width + side as f64 / 2.0).floor();
        if (0.0..side as f64).contains(&bx) && (0.0..side as f64).contains(&by) {
            hist[by as usize * side + bx as usize] += 1.0;
        }
    }
    let r2: Vec<f64> = (0..side * side)
        .map(|i| {
            let c = |k: usize| (k as f64 + 0.5 - side as f64 / 2.0) * width;
            c(i % side).powi(2) + c(i / side).powi(2)
        })
        .collect();
    let cost = |s: f64| {
        let g: Vec<f64> = r2.iter().map(|r| (-r / (2.0 * s * s)).exp()).collect();
        let a = g.iter().zip(&hist).map(|(g, h)| g * h).sum::<f64>() / g.iter().map(|g| g * g).sum::<f64>();
        g.iter().zip(&hist).map(|(g, h)| (h - a * g).powi(2)).sum::<f64>()
    };
    let (mut lo, mut hi) = (0.5, 2.0);
    let r = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..60 {
        let (c, d) = (hi - r * (hi - lo), lo + r * (hi - lo));
        if cost(c) < cost(d) {
            hi = d;
        } else {
            lo = c;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reflection angles off a sum of sines, sampled evenly over a long time (the display's
    /// time average).
    fn sines(rhos: &[f64], freqs: &[f64], n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 1e-4;
                rhos.iter()
                    .zip(freqs)
                    .enumerate()
                    .map(|(j, (r, f))| {
                        2.0 * r * (2.0 * PI * (f * t + crate::display::mapping::golden_phase(j))).cos()
                    })
                    .sum()
            })
            .collect()
    }

    #[test]
    fn the_arcsine_law_is_a_density_with_the_single_sines_variance() {
        let rho = 0.05;
        let (lo, hi, m) = (-2.0 * rho, 2.0 * rho, 200_000);
        let h = (hi - lo) / m as f64;
        // Midpoint rule (the density's singularities at the ends are integrable).
        let (mut mass, mut var) = (0.0, 0.0);
        for i in 0..m {
            let d = lo + (i as f64 + 0.5) * h;
            mass += arcsine_pdf(d, rho, 0.0) * h;
            var += d * d * arcsine_pdf(d, rho, 0.0) * h;
        }
        assert!((mass - 1.0).abs() < 5e-3, "{mass}");
        assert!((var / (2.0 * rho * rho) - 1.0).abs() < 5e-3, "σ₀² = 2ρ²: {var}");
        assert!((arcsine_cdf(0.0, rho, 0.0) - 0.5).abs() < 1e-15);
        assert_eq!(arcsine_pdf(0.2, rho, 0.0), 0.0);
    }

    #[test]
    fn one_sine_follows_eq_5_6_and_seven_approach_a_gaussian() {
        let one = sines(&[0.05], &[131.0], 200_000);
        assert!(ks_distance(&one, |d| arcsine_cdf(d, 0.05, 0.0)) < 0.01);
        assert!(ks_to_gaussian(&one) > 0.05, "one sine is far from a bell");
        let freqs = crate::display::mapping::X_FREQUENCIES;
        let seven = sines(&[0.02; 7], &freqs, 200_000);
        let (_, var) = moments(&seven);
        assert!((var / (7.0 * 2.0 * 0.02f64.powi(2)) - 1.0).abs() < 0.01, "σ² = n·2ρ²");
        assert!(ks_to_gaussian(&seven) < 0.015, "{}", ks_to_gaussian(&seven));
        // Frequencies with repeated pairwise sums (110 + 190 = 130 + 170) correlate their
        // waves' fourth moments: the same seven amplitudes give a worse bell.
        let resonant = sines(&[0.02; 7], &[110.0, 130.0, 170.0, 190.0, 230.0, 290.0, 310.0], 200_000);
        assert!(ks_to_gaussian(&resonant) > 2.0 * ks_to_gaussian(&seven));
    }

    #[test]
    fn erf_matches_known_values() {
        for (x, want) in [(0.0, 0.0), (0.5, 0.520_499_877_8), (1.0, 0.842_700_792_9), (2.0, 0.995_322_265)] {
            assert!((erf(x) - want).abs() < 2e-7 && (erf(-x) + want).abs() < 2e-7, "{x}");
        }
    }

    #[test]
    fn a_gaussians_fitted_width_is_its_standard_deviation_and_a_sines_is_wider() {
        // A Gaussian's quantiles, evenly spaced in probability (inverse cdf by bisection).
        let inv = |p: f64| {
            let (mut lo, mut hi) = (-10.0, 10.0);
            for _ in 0..80 {
                let mid = 0.5 * (lo + hi);
                if normal_cdf(mid, 0.0, 2.0) < p {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            0.5 * (lo + hi)
        };
        let g: Vec<f64> = (0..50_000).map(|i| inv((f64::from(i) + 0.5) / 50_000.0)).collect();
        assert!((fitted_gaussian_sd(&g) / 2.0 - 1.0).abs() < 0.01, "{}", fitted_gaussian_sd(&g));
        // Paired with a scrambled copy (a stride coprime to the count): independent axes.
        let ys: Vec<f64> = (0..g.len()).map(|i| g[(i * 7919) % g.len()]).collect();
        let xs = &g[..];
        assert!((fitted_gaussian_sd_2d(xs, &ys) - 1.0).abs() < 0.02, "{}", fitted_gaussian_sd_2d(xs, &ys));
        // One sine: flatter-topped, fitted wider than its standard deviation.
        let s: Vec<f64> = (0..50_000).map(|i| (f64::from(i) * 0.001).sin()).collect();
        let (_, var) = moments(&s);
        assert!(fitted_gaussian_sd(&s) / var.sqrt() > 1.2);
    }
}
