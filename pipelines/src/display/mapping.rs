//! From a Ward roughness to each coil's partials (thesis sections 5.3.2–5.3.3).
//!
//! **The convention.** `α` is the roughness of Ward's lobe as written (Ward 1992; the thesis's
//! reference model, and `crate::ward`): `exp(−tan²θh·(cos²φ/αx² + sin²φ/αy²))`. At the
//! display's incidence the half vector is the reflecting facet's normal, and `tanθh·cosφ`,
//! `tanθh·sinφ` are its tilts along x and y: Ward's lobe is a Gaussian in facet tilt of
//! variance `α²/2` per axis. The thesis relates variances by `σ² ≈ 4α²` (reflection angle
//! against half-angle), which treats `α` as the half-angle's standard deviation and is √2
//! off Ward's own lobe; lightrig plans and judges by the lobe, so it uses `α²/2`.
//!
//! Per axis, `n` sine waves of roughness `ρ = a·k` each (amplitude `a`, wave number `k`: the
//! slope amplitude) make a slope whose variance is `n·ρ²/2`, so every partial gets
//! `ρ = α/√n`: exact for the slopes of a height field, with no small-angle step. The liquid's
//! dispersion relation gives `k` at the partial's frequency, hence the surface amplitude
//! `a = ρ/k`, and the actuator's measured response `H(f)` (surface amplitude per unit drive)
//! the drive `a/|H(f)|`. Each axis has its own coil and its own prime frequencies.
//!
//! Two limits bound `α`: the linear model (Eq. 5.1's small angles, and waves that superpose)
//! holds while the **total** slope stays small: its standard deviation per axis, `α/√2`, must
//! stay under `Axis::max_slope` (default [`LINEAR_LIMIT`], 5°); and the drives of an axis must
//! sum to at most the coil's `max_amplitude` (the controller refuses more).

use super::liquid::Liquid;

/// Eq. 5.1: below 5° the small-angle model errs by less than 0.4 %, rad. The default bound on
/// the total slope's standard deviation per axis (as an angle).
pub const LINEAR_LIMIT: f64 = 5.0 * std::f64::consts::PI / 180.0;

/// Frequencies of the x axis' partials, Hz: primes around the small setup's 200 Hz efficiency
/// peak (section 5.5.1), at least 4 Hz apart, chosen so that their slope's bell over its
/// period (1 s) is the same whatever their phases: where frequencies are related (`f₁ + f₂ =
/// f₃ + f₄` and higher orders) the waves' phases at the spot, which the liquid and the paddle
/// shift and the calibration does not measure, change the bell's shape. These stay within
/// 1.5 % of the bell of seven independent sines for the phases tested (where 101, 103, 109,
/// 127, 167, 263, 317 Hz moved by 1.7 % and 113, 211, 227, 241, 283, 307, 311 Hz by 2.6 %).
pub const X_FREQUENCIES: [f64; 7] = [97.0, 127.0, 193.0, 211.0, 251.0, 293.0, 313.0];
/// Frequencies of the y axis' partials, Hz: other primes, chosen alike.
pub const Y_FREQUENCIES: [f64; 7] = [109.0, 163.0, 223.0, 239.0, 271.0, 307.0, 311.0];

/// The calibration's sweep on the x coil, Hz: 90 to 330 every [`SWEEP_STEP_HZ`], none of them a
/// partial's frequency, so the display's drives come from `|H|` interpolated between measured
/// points, and the wave number `k` at a partial differs from the one the calibration divided by.
pub const X_SWEEP: [f64; 49] = sweep(90.0);
/// The calibration's sweep on the y coil, Hz: 100 to 340 every [`SWEEP_STEP_HZ`].
pub const Y_SWEEP: [f64; 49] = sweep(100.0);
/// The calibration sweep's step, Hz: a small tank's walls send waves back across the spot, a
/// ripple in `|H|` with a period of 25–40 Hz in a 2 cm tank, which 20 Hz steps alias; at 5 Hz
/// the interpolated `|H|` follows it within a few per cent.
pub const SWEEP_STEP_HZ: f64 = 5.0;

const fn sweep<const N: usize>(from: f64) -> [f64; N] {
    let mut a = [0.0; N];
    let mut i = 0;
    while i < N {
        a[i] = from + SWEEP_STEP_HZ * i as f64;
        i += 1;
    }
    a
}

/// Starting phase of partial `i`, turns: the golden angle apart, so no two start in step.
pub fn golden_phase(i: usize) -> f64 {
    (i as f64 * 0.381_966_011_250_105).fract()
}

/// The variance of the facet tilt per axis in Ward's lobe of roughness `alpha`: `α²/2`.
pub fn slope_variance(alpha: f64) -> f64 {
    alpha * alpha / 2.0
}

/// Ward roughness of a facet-tilt variance (the inverse of [`slope_variance`]).
pub fn alpha_of_slope_variance(variance: f64) -> f64 {
    (2.0 * variance.max(0.0)).sqrt()
}

/// Roughness `ρ` (slope amplitude) of each of `n` equal partials whose slopes have Ward
/// roughness `alpha`'s variance: `n·ρ²/2 = α²/2`.
pub fn partial_roughness(alpha: f64, n: usize) -> f64 {
    alpha / (n.max(1) as f64).sqrt()
}

/// The roughness `α_s` of a Gaussian facet-tilt distribution whose screen picture Ward's lobe
/// fits as `alpha`. Ward's lobe as written weighs directions by `√(cosθi·cosθo)`, where a
/// mirror's facets map into reflected directions by `1/(4·cosθd·cos³θh)`; at normal incidence
/// the two differ by `≈ 1 + 3·tan²θh`, which widens the fitted lobe to `α_s/√(1 − 3α_s²)`
/// (3 % at 0.14): so `α_s = α/√(1 + 3α²)`.
pub fn slope_roughness(alpha: f64) -> f64 {
    alpha / (1.0 + 3.0 * alpha * alpha).sqrt()
}

/// The inverse of [`slope_roughness`]: the Ward α a picture of tilts of roughness `alpha_s`
/// shows.
pub fn ward_of_slope_roughness(alpha_s: f64) -> f64 {
    alpha_s / (1.0 - 3.0 * alpha_s * alpha_s).max(1e-12).sqrt()
}

/// How much wider than its standard deviation a round bell fitted to the picture of `n` equal
/// sines of independent phases on each axis is: [`slopes::fitted_gaussian_sd_2d`] (one sine's
/// arcsine law is the flattest at 1.31, seven 1.027, the limit 1). A sum of few sines is
/// flatter-topped than a Gaussian, and Ward's lobe fitted to the screen sees the bell, not the
/// variance; the ratio does not depend on the amplitude, nor on how the two axes' widths
/// compare. Drawn once per `n`, when first asked (200 000 seeded samples, ±0.2 %).
///
/// [`slopes::fitted_gaussian_sd_2d`]: super::slopes::fitted_gaussian_sd_2d
pub fn bell_ratio(n: usize) -> f64 {
    static TABLE: [std::sync::OnceLock<f64>; lightrig_protocol_max_partials() + 1] =
        [const { std::sync::OnceLock::new() }; lightrig_protocol_max_partials() + 1];
    let Some(cell) = TABLE.get(n).filter(|_| n > 0) else { return 1.0 };
    *cell.get_or_init(|| {
        let mut state = 0x5eed_u64;
        let mut uniform = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut sines = || -> Vec<f64> {
            (0..200_000).map(|_| (0..n).map(|_| (std::f64::consts::TAU * uniform()).cos()).sum()).collect()
        };
        let (xs, ys) = (sines(), sines());
        super::slopes::fitted_gaussian_sd_2d(&xs, &ys)
    })
}

/// The most partials a coil plays (the controller's limit).
const fn lightrig_protocol_max_partials() -> usize {
    8
}

/// An actuator's measured response: surface amplitude at the displayed spot per unit drive
/// (m per full scale of the coil), at frequencies in increasing order; a cubic in between.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Response {
    /// `(frequency Hz, |H| m per full scale)`.
    pub points: Vec<(f64, f64)>,
}

impl Response {
    /// `|H(f)|`, if `f` lies within the measured range.
    pub fn at(&self, f: f64) -> Option<f64> {
        let p = &self.points;
        let i = p.partition_point(|&(g, _)| g < f);
        if i < p.len() && p[i].0 == f {
            return Some(p[i].1);
        }
        if i == 0 || i == p.len() {
            return None;
        }
        // A cubic Hermite piece with centred-difference slopes (one-sided at the ends): it
        // follows a ripple sampled a few times per period, where straight lines cut its peaks.
        let slope = |j: usize| {
            let (a, b) = (j.saturating_sub(1), (j + 1).min(p.len() - 1));
            (p[b].1 - p[a].1) / (p[b].0 - p[a].0)
        };
        let ((f0, h0), (f1, h1)) = (p[i - 1], p[i]);
        let w = f1 - f0;
        let t = (f - f0) / w;
        let (m0, m1) = (slope(i - 1) * w, slope(i) * w);
        let (t2, t3) = (t * t, t * t * t);
        let h = (2.0 * t3 - 3.0 * t2 + 1.0) * h0
            + (t3 - 2.0 * t2 + t) * m0
            + (-2.0 * t3 + 3.0 * t2) * h1
            + (t3 - t2) * m1;
        // Never below the smaller neighbour's half: a response is positive.
        Some(h.max(0.5 * h0.min(h1)))
    }
}

/// One axis of the display: its coil's frequencies, response and drive limit.
#[derive(Debug, Clone, PartialEq)]
pub struct Axis {
    /// Name for messages (`x`, `y`).
    pub name: &'static str,
    /// The partials' frequencies, Hz.
    pub frequencies: Vec<f64>,
    /// The coil's measured response.
    pub response: Response,
    /// The coil's drive limit: the partials' drives sum to at most this (fraction of full
    /// scale, the rig file's `max_amplitude`).
    pub max_drive: f64,
    /// The bound on the total slope's standard deviation, as an angle, rad (the rig file's
    /// `[plan] max_slope_deg`; [`LINEAR_LIMIT`] by default).
    pub max_slope: f64,
}

/// One partial's setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartialDrive {
    /// Frequency, Hz.
    pub frequency: f64,
    /// Its wave's roughness `ρ = a·k`.
    pub rho: f64,
    /// Surface amplitude, m.
    pub amplitude_m: f64,
    /// Drive, fraction of the coil's full scale.
    pub drive: f64,
}

/// Why an `α` cannot be shown.
#[derive(Debug, Clone, PartialEq)]
pub enum DisplayError {
    /// Above what the axis can reach; `max` is its reachable maximum and `limit` says which
    /// bound sets it.
    OutOfRange {
        /// The axis.
        axis: &'static str,
        /// The α asked for.
        alpha: f64,
        /// The reachable maximum.
        max: f64,
        /// `slope limit` (the linear model's, `max_slope`) or `drive limit`.
        limit: &'static str,
    },
    /// Negative or not a number.
    Invalid {
        /// The axis.
        axis: &'static str,
        /// The α asked for.
        alpha: f64,
    },
    /// The calibration names a liquid this build does not know (the message says which).
    UnknownLiquid(String),
    /// A partial's frequency lies outside the measured response: calibrate over it.
    Uncalibrated {
        /// The axis.
        axis: &'static str,
        /// The frequency, Hz.
        frequency: f64,
    },
}

impl std::fmt::Display for DisplayError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            // The maximum rounded down, so that the figure given can itself be asked for.
            DisplayError::OutOfRange { axis, alpha, max, limit } => write!(
                f,
                "α{axis} = {alpha} cannot be shown: this display reaches 0 < α{axis} ≤ {:.4} ({limit})",
                (max * 1e4).floor() / 1e4
            ),
            DisplayError::Invalid { axis, alpha } => write!(f, "α{axis} = {alpha}: must be a number ≥ 0"),
            DisplayError::UnknownLiquid(why) => f.write_str(why),
            DisplayError::Uncalibrated { axis, frequency } => write!(
                f,
                "the {axis} coil's response is not measured at {frequency} Hz: run the display's \
                 calibration over its partials' frequencies"
            ),
        }
    }
}

impl std::error::Error for DisplayError {}

impl Axis {
    /// `Σ drive / α`: the drive the axis needs per unit of α (all of it is linear in α).
    fn drive_per_alpha(&self, liquid: &Liquid) -> Result<f64, DisplayError> {
        let n = self.frequencies.len();
        let rho = partial_roughness(1.0, n) / bell_ratio(self.frequencies.len());
        let mut sum = 0.0;
        for &f in &self.frequencies {
            let h = self
                .response
                .at(f)
                .filter(|h| *h > 0.0)
                .ok_or(DisplayError::Uncalibrated { axis: self.name, frequency: f })?;
            sum += rho / liquid.wave_number(f) / h;
        }
        Ok(sum)
    }

    /// The largest α the axis shows, and which limit sets it.
    pub fn reachable(&self, liquid: &Liquid) -> Result<(f64, &'static str), DisplayError> {
        // Both bounds in the slopes' own roughness, then as the Ward lobe shows it. The slope's
        // standard deviation is α_s/(√2·bell ratio).
        let linear = self.max_slope.tan() * std::f64::consts::SQRT_2 * bell_ratio(self.frequencies.len());
        let drive = self.max_drive / self.drive_per_alpha(liquid)?;
        let (a, limit) = if linear <= drive { (linear, "slope limit") } else { (drive, "drive limit") };
        Ok((ward_of_slope_roughness(a), limit))
    }

    /// The partials that show `alpha` on this axis, or why not.
    pub fn solve(&self, alpha: f64, liquid: &Liquid) -> Result<Vec<PartialDrive>, DisplayError> {
        if alpha.is_nan() || alpha < 0.0 {
            return Err(DisplayError::Invalid { axis: self.name, alpha });
        }
        let (max, limit) = self.reachable(liquid)?;
        // A hair of slack so that asking for exactly the reported maximum works.
        if alpha > max * (1.0 + 1e-12) {
            return Err(DisplayError::OutOfRange { axis: self.name, alpha, max, limit });
        }
        let rho = partial_roughness(slope_roughness(alpha), self.frequencies.len())
            / bell_ratio(self.frequencies.len());
        Ok(self
            .frequencies
            .iter()
            .map(|&f| {
                let k = liquid.wave_number(f);
                let amplitude_m = rho / k;
                let h = self.response.at(f).expect("checked by reachable");
                PartialDrive { frequency: f, rho, amplitude_m, drive: amplitude_m / h }
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(h: f64) -> Response {
        Response { points: vec![(50.0, h), (400.0, h)] }
    }

    #[test]
    fn variances_and_roughness_follow_wards_lobe() {
        assert!((slope_variance(0.1) - 0.005).abs() < 1e-16);
        assert!((alpha_of_slope_variance(slope_variance(0.07)) - 0.07).abs() < 1e-15);
        // n partials of slope amplitude ρ: n·ρ²/2 = α²/2.
        let (alpha, n) = (0.08, 7);
        let rho = partial_roughness(alpha, n);
        assert!((n as f64 * rho * rho / 2.0 - slope_variance(alpha)).abs() < 1e-15);
        // Ward's lobe, sampled on a fine grid of facet tilts: its variance along x is α²/2.
        let (alpha, step) = (0.12, 0.002);
        let (mut m0, mut m2) = (0.0, 0.0);
        for i in -400..=400 {
            for j in -400..=400 {
                let (tx, ty) = (f64::from(i) * step, f64::from(j) * step);
                // tan²θh of the half vector (tx, ty, 1), per unit tilt area (the lobe's density
                // in tilt space is its value in those coordinates).
                let w = (-(tx * tx + ty * ty) / (alpha * alpha)).exp();
                m0 += w;
                m2 += w * tx * tx;
            }
        }
        assert!((m2 / m0 / slope_variance(alpha) - 1.0).abs() < 1e-6, "{}", m2 / m0);
    }

    #[test]
    fn few_sines_make_a_flatter_bell_than_a_gaussian_and_more_approach_one() {
        let r: Vec<f64> = (1..=8).map(bell_ratio).collect();
        // One sine's arcsine law is as flat-topped as a bell gets; each partial more is rounder.
        assert!(r[0] > 1.3, "{r:?}");
        assert!(r.windows(2).all(|w| w[1] < w[0]), "{r:?}");
        assert!(r[6] > 1.02 && r[6] < 1.06 && r[7] > 1.0, "{r:?}");
        // One axis alone: seven independent sines' bell, 1-D.
        let mut state = 3u64;
        let one: Vec<f64> = (0..200_000)
            .map(|_| {
                (0..7)
                    .map(|_| {
                        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                        (std::f64::consts::TAU * (state >> 11) as f64 / (1u64 << 53) as f64).cos()
                    })
                    .sum()
            })
            .collect();
        let (_, var) = crate::display::slopes::moments(&one);
        let iid = crate::display::slopes::fitted_gaussian_sd(&one) / var.sqrt();
        // The axes' frequency sets at whole hertz over their period (1 s), with the phases
        // the planner gives and with others: their bell is the independent sines' within 1.5 %.
        for set in [X_FREQUENCIES, Y_FREQUENCIES] {
            for shift in [0.0, 0.37, 0.71] {
                let s: Vec<f64> = (0..8000)
                    .map(|i| {
                        let t = f64::from(i) / 8000.0;
                        set.iter()
                            .enumerate()
                            .map(|(j, f)| {
                                let phase = golden_phase(j) + shift * (j * j) as f64;
                                (std::f64::consts::TAU * (f * t + phase)).cos()
                            })
                            .sum()
                    })
                    .collect();
                let (_, var) = crate::display::slopes::moments(&s);
                let ratio = crate::display::slopes::fitted_gaussian_sd(&s) / var.sqrt();
                assert!((ratio / iid - 1.0).abs() < 0.015, "{set:?} shift {shift}: {ratio} vs {iid}");
            }
        }
    }

    #[test]
    fn responses_interpolate_and_refuse_outside_what_was_measured() {
        let r = Response { points: vec![(100.0, 2.0), (200.0, 4.0), (300.0, 1.0)] };
        assert_eq!(r.at(100.0), Some(2.0));
        // Hermite pieces with the slopes 0.02 (one-sided), −0.005 (centred), −0.03 per Hz:
        // halfway, the mean of the ends plus an eighth of the slopes' difference times the step.
        assert_eq!(r.at(150.0), Some(3.3125));
        assert_eq!(r.at(250.0), Some(2.8125));
        assert_eq!(r.at(300.0), Some(1.0));
        assert_eq!(r.at(99.0), None);
        assert_eq!(r.at(301.0), None);
        // Centred slopes are a parabola's own: inside, it is followed exactly.
        let q = |f: f64| 1.0 + (f / 100.0).powi(2);
        let r = Response { points: (1..=5).map(|i| f64::from(i) * 100.0).map(|f| (f, q(f))).collect() };
        for f in [210.0, 250.0, 333.0, 399.0] {
            assert!((r.at(f).unwrap() - q(f)).abs() < 1e-12, "{f}");
        }
        // A ripple of period 30 Hz sampled every 5 Hz: within 3 % of its amplitude (2.6 %),
        // where straight lines between the samples miss its peaks by 13 %.
        let ripple = |f: f64| 2.0 + (std::f64::consts::TAU * f / 30.0).sin();
        let r = Response {
            points: (0..=40).map(|i| f64::from(i) * 5.0 + 100.0).map(|f| (f, ripple(f))).collect(),
        };
        let worst =
            (0..1000).map(|i| 110.0 + f64::from(i) * 0.18).map(|f| (r.at(f).unwrap() - ripple(f)).abs());
        let worst = worst.fold(0.0, f64::max);
        assert!(worst < 0.03, "{worst}");
    }

    #[test]
    fn each_partial_gets_its_share_of_roughness_and_the_drive_its_response_asks() {
        let w = Liquid::WATER;
        let axis = Axis {
            name: "x",
            frequencies: X_FREQUENCIES.to_vec(),
            response: flat(1e-3),
            max_drive: 0.5,
            max_slope: LINEAR_LIMIT,
        };
        let p = axis.solve(0.05, &w).unwrap();
        assert_eq!(p.len(), 7);
        for q in &p {
            assert!((q.rho - partial_roughness(slope_roughness(0.05), 7) / bell_ratio(7)).abs() < 1e-15);
            assert!((q.amplitude_m * w.wave_number(q.frequency) - q.rho).abs() < 1e-15);
            assert!((q.drive - q.amplitude_m / 1e-3).abs() < 1e-15);
        }
        // Higher frequencies have shorter waves: the same ρ takes less amplitude.
        assert!(p.windows(2).all(|w| w[1].amplitude_m < w[0].amplitude_m));
    }

    #[test]
    fn the_reachable_range_is_the_tighter_of_the_two_limits_and_is_enforced() {
        let w = Liquid::WATER;
        let strong = Axis {
            name: "x",
            frequencies: X_FREQUENCIES.to_vec(),
            response: flat(1.0),
            max_drive: 0.5,
            max_slope: LINEAR_LIMIT,
        };
        let (max, limit) = strong.reachable(&w).unwrap();
        assert_eq!(limit, "slope limit");
        // The slope's standard deviation at the maximum is the limit's: α_s/(√2·bell) = tan 5°.
        let a_s = slope_roughness(max);
        assert!((a_s / 2f64.sqrt() / bell_ratio(7) - LINEAR_LIMIT.tan()).abs() < 1e-12, "{max}");
        assert!((ward_of_slope_roughness(a_s) / max - 1.0).abs() < 1e-12);
        let six = Axis { max_slope: 6f64.to_radians(), ..strong.clone() };
        assert!(six.reachable(&w).unwrap().0 > 0.14, "6° reaches the thesis's range");
        let weak = Axis { response: flat(1e-6), ..strong.clone() };
        let (max, limit) = weak.reachable(&w).unwrap();
        assert_eq!(limit, "drive limit");
        let at_max: f64 = weak.solve(max, &w).unwrap().iter().map(|q| q.drive).sum();
        assert!((at_max - 0.5).abs() < 1e-9, "the drives at the maximum fill the coil: {at_max}");
        let e = weak.solve(max * 1.01, &w).unwrap_err();
        assert!(matches!(e, DisplayError::OutOfRange { limit: "drive limit", .. }));
        assert!(e.to_string().contains(&format!("0 < αx ≤ {:.4}", (max * 1e4).floor() / 1e4)), "{e}");
        assert!(matches!(weak.solve(-0.1, &w), Err(DisplayError::Invalid { .. })));
        let narrow = Axis { response: Response { points: vec![(100.0, 1.0), (200.0, 1.0)] }, ..strong };
        assert!(
            matches!(narrow.solve(0.01, &w), Err(DisplayError::Uncalibrated { frequency, .. }) if frequency == 97.0)
        );
    }
}
