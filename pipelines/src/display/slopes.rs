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
}
