//! From a Ward roughness to each coil's partials (thesis sections 5.3.2–5.3.3).
//!
//! Per axis: Ward's `α` is a half-angle slope; the display spreads the *reflection* angle,
//! whose variance is `σ² ≈ 4α²`. `n` sine waves of roughness `ρ = a·k` each (amplitude `a`,
//! wave number `k`) give `σ² = n·2ρ²`, so every partial gets `ρ = α·√(2/n)`. The liquid's
//! dispersion relation gives `k` at the partial's frequency, hence the surface amplitude
//! `a = ρ/k`, and the actuator's measured response `H(f)` (surface amplitude per unit drive)
//! the drive `a/|H(f)|`. Each axis has its own coil and its own prime frequencies.
//!
//! Two limits bound `α`: the linear model of Eq. 5.1 holds while each wave's slope stays under
//! 5° (`ρ ≤ 0.0873`), and the drives of an axis must sum to at most the coil's `max_amplitude`
//! (the controller refuses more).

use super::liquid::Liquid;

/// Eq. 5.1: below 5° the small-angle model errs by less than 0.4 %, rad.
pub const LINEAR_LIMIT: f64 = 5.0 * std::f64::consts::PI / 180.0;

/// Frequencies of the x axis' partials, Hz: primes around the small setup's 200 Hz efficiency
/// peak (section 5.5.1) whose pairwise sums all differ (a Sidon set): where `f₁ + f₂ = f₃ + f₄`
/// the four waves' slopes stay in step and the time-averaged lobe departs from a Gaussian
/// (`slopes` tests it: the bell's distance to a Gaussian drops about fourfold).
pub const X_FREQUENCIES: [f64; 7] = [101.0, 103.0, 109.0, 127.0, 167.0, 263.0, 317.0];
/// Frequencies of the y axis' partials, Hz: other primes, a Sidon set too.
pub const Y_FREQUENCIES: [f64; 7] = [113.0, 211.0, 227.0, 241.0, 283.0, 307.0, 311.0];

/// Starting phase of partial `i`, turns: the golden angle apart, so no two start in step.
pub fn golden_phase(i: usize) -> f64 {
    (i as f64 * 0.381_966_011_250_105).fract()
}

/// The reflection angle's variance for Ward roughness `alpha` (section 5.3.3).
pub fn reflection_variance(alpha: f64) -> f64 {
    4.0 * alpha * alpha
}

/// Ward roughness of a reflection-angle variance (the inverse of [`reflection_variance`]).
pub fn alpha_of_variance(variance: f64) -> f64 {
    variance.max(0.0).sqrt() / 2.0
}

/// Roughness `ρ` of each of `n` equal partials that together give Ward roughness `alpha`
/// (`σ² = n·2ρ²`, section 5.3.2).
pub fn partial_roughness(alpha: f64, n: usize) -> f64 {
    alpha * (2.0 / n.max(1) as f64).sqrt()
}

/// An actuator's measured response: surface amplitude at the displayed spot per unit drive
/// (m per full scale of the coil), at frequencies in increasing order; linear in between.
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
        let ((f0, h0), (f1, h1)) = (p[i - 1], p[i]);
        Some(h0 + (h1 - h0) * (f - f0) / (f1 - f0))
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
        /// `linear limit (Eq. 5.1)` or `drive limit`.
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
        let rho = partial_roughness(1.0, n);
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
        let linear = LINEAR_LIMIT / partial_roughness(1.0, self.frequencies.len());
        let drive = self.max_drive / self.drive_per_alpha(liquid)?;
        Ok(if linear <= drive { (linear, "linear limit (Eq. 5.1)") } else { (drive, "drive limit") })
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
        let rho = partial_roughness(alpha, self.frequencies.len());
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
    fn variances_and_roughness_follow_the_thesis() {
        assert!((reflection_variance(0.1) - 0.04).abs() < 1e-16);
        assert!((alpha_of_variance(reflection_variance(0.07)) - 0.07).abs() < 1e-15);
        // n partials of roughness ρ: σ² = n·2ρ² = 4α².
        let (alpha, n) = (0.08, 7);
        let rho = partial_roughness(alpha, n);
        assert!((n as f64 * 2.0 * rho * rho - reflection_variance(alpha)).abs() < 1e-15);
    }

    #[test]
    fn responses_interpolate_and_refuse_outside_what_was_measured() {
        let r = Response { points: vec![(100.0, 2.0), (200.0, 4.0), (300.0, 1.0)] };
        assert_eq!(r.at(100.0), Some(2.0));
        assert_eq!(r.at(150.0), Some(3.0));
        assert_eq!(r.at(250.0), Some(2.5));
        assert_eq!(r.at(300.0), Some(1.0));
        assert_eq!(r.at(99.0), None);
        assert_eq!(r.at(301.0), None);
    }

    #[test]
    fn each_partial_gets_its_share_of_roughness_and_the_drive_its_response_asks() {
        let w = Liquid::WATER;
        let axis =
            Axis { name: "x", frequencies: X_FREQUENCIES.to_vec(), response: flat(1e-3), max_drive: 0.5 };
        let p = axis.solve(0.05, &w).unwrap();
        assert_eq!(p.len(), 7);
        for q in &p {
            assert!((q.rho - partial_roughness(0.05, 7)).abs() < 1e-15);
            assert!((q.amplitude_m * w.wave_number(q.frequency) - q.rho).abs() < 1e-15);
            assert!((q.drive - q.amplitude_m / 1e-3).abs() < 1e-15);
        }
        // Higher frequencies have shorter waves: the same ρ takes less amplitude.
        assert!(p.windows(2).all(|w| w[1].amplitude_m < w[0].amplitude_m));
    }

    #[test]
    fn the_reachable_range_is_the_tighter_of_the_two_limits_and_is_enforced() {
        let w = Liquid::WATER;
        let strong =
            Axis { name: "x", frequencies: X_FREQUENCIES.to_vec(), response: flat(1.0), max_drive: 0.5 };
        let (max, limit) = strong.reachable(&w).unwrap();
        assert_eq!(limit, "linear limit (Eq. 5.1)");
        assert!((max - LINEAR_LIMIT * (7.0f64 / 2.0).sqrt()).abs() < 1e-12, "{max}");
        assert!(max > 0.14, "seven partials reach the thesis's range");
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
            matches!(narrow.solve(0.01, &w), Err(DisplayError::Uncalibrated { frequency, .. }) if frequency == 263.0)
        );
    }
}
