//! Spectral scaling (thesis §4.4.2): camera values become bispectral BRRDF entries through a
//! measurement on a flat Spectralon target.
//!
//! Spectralon preserves the wavelength and reflects 99 % quasi-Lambertian, so its bispectral
//! matrix is `ρ/π` on the diagonal and zero elsewhere; what the camera sees off the diagonal
//! is the filters' crosstalk. From the Spectralon rows (`S(λo, λi)`, camera rate per unit
//! `cos θi`, measured within a few bands of each diagonal):
//!
//! - the diagonal scale `d(λ) = (ρ/π) / S(λ, λ)`;
//! - the leakage `L(λo, λi) = S(λo, λi) / S(λi, λi)`: the share of a wavelength-preserving
//!   reflection that the crosstalk puts into a neighbouring pair, subtracted from a sample's
//!   off-diagonal values so that they hold only reradiated light;
//! - the row scale `a(λi)`: the rows, each band weighted by the detection branch's known
//!   sensitivity `c(λo) = Δλ / W(λo)` (`W`: the camera filter × sensor's integral, from the
//!   manufacturers' curves), sum to `ρ/π` ("the rows add up to 0.99"). An off-diagonal entry is
//!   `a(λi) · c(λo) · (m(λo, λi) − L · m(λi, λi))`: the light reradiated into the band `Δλ` wide
//!   at `λo` per unit of light in the band at `λi`, per steradian.
//!
//! The row sums stand for each band's light only as far as the camera's bands tile the
//! spectrum: with 15 nm bands 20 nm apart the off-diagonal entries keep a few per cent of
//! ripple (under 5 % against the band-limited truth in the tests below), and the first band
//! off the diagonal shares the filters' overlap with the diagonal reflection, so it is exact
//! only for a flat albedo across the two bands.

use std::collections::BTreeMap;

/// A wavelength pair `(excitation, emission)`, nm.
pub type PairNm = (u16, u16);

/// Why the Spectralon rows do not scale a pair.
#[derive(Debug, Clone, PartialEq)]
pub enum ScalingError {
    /// The Spectralon session has no diagonal pair for this excitation (for example an LED
    /// below the camera filter's range).
    NoDiagonal { excitation: u16 },
    /// The diagonal was measured but holds no light (dark, or every exposure clipped).
    Dark { excitation: u16, value: f64 },
}

impl std::fmt::Display for ScalingError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ScalingError::NoDiagonal { excitation } => write!(
                f,
                "excitation {excitation} nm: the Spectralon session has no {excitation}→{excitation} nm pair to \
                 scale it by (is the excitation inside the camera filter's range?)"
            ),
            ScalingError::Dark { excitation, value } => write!(
                f,
                "excitation {excitation} nm: Spectralon's {excitation}→{excitation} nm value is {value:.3e}: no \
                 light to scale by (check the source and the exposure series)"
            ),
        }
    }
}

impl std::error::Error for ScalingError {}

/// The scale of every pair the Spectralon session measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Scaling {
    /// Spectralon's reflectance `ρ` (0.99).
    pub reflectance: f64,
    /// `d(λ)`, per excitation.
    pub diagonal: BTreeMap<u16, f64>,
    /// `a(λi)`, per excitation.
    pub row: BTreeMap<u16, f64>,
    /// `L(λo, λi)` of the measured off-diagonal pairs.
    pub leak: BTreeMap<PairNm, f64>,
    /// `c(λo)`, per emission band measured.
    pub detection: BTreeMap<u16, f64>,
}

impl Scaling {
    /// From the Spectralon values `rows` (`(pair, S)`), the detection branch's band integral
    /// `band_integral(λo)` (`W`, any unit), the emission grid's step `step_nm` and the target's
    /// reflectance.
    pub fn new(
        rows: &[(PairNm, f64)],
        band_integral: impl Fn(u16) -> f64,
        step_nm: f64,
        reflectance: f64,
    ) -> Result<Scaling, ScalingError> {
        let white = reflectance / std::f64::consts::PI;
        let mut by_pair: BTreeMap<PairNm, f64> = BTreeMap::new();
        for &(p, v) in rows {
            by_pair.insert(p, v);
        }
        let excitations: Vec<u16> =
            by_pair.keys().map(|p| p.0).collect::<std::collections::BTreeSet<_>>().into_iter().collect();
        let mut s = Scaling {
            reflectance,
            diagonal: BTreeMap::new(),
            row: BTreeMap::new(),
            leak: BTreeMap::new(),
            detection: BTreeMap::new(),
        };
        for &(p, _) in rows {
            s.detection.entry(p.1).or_insert_with(|| step_nm / band_integral(p.1));
        }
        for ex in excitations {
            let diag = *by_pair.get(&(ex, ex)).ok_or(ScalingError::NoDiagonal { excitation: ex })?;
            if diag.is_nan() || diag <= 0.0 || !diag.is_finite() {
                return Err(ScalingError::Dark { excitation: ex, value: diag });
            }
            s.diagonal.insert(ex, white / diag);
            let mut total = 0.0;
            for (&(e, o), &v) in by_pair.range((ex, 0)..=(ex, u16::MAX)) {
                debug_assert_eq!(e, ex);
                total += s.detection[&o] * v.max(0.0);
                if o != ex {
                    s.leak.insert((ex, o), v / diag);
                }
            }
            s.row.insert(ex, white / total);
        }
        Ok(s)
    }

    /// A sample's scaled values: `values[j]` measured at `pairs[j]` (camera rate per unit
    /// `cos θi`), written to `out[j]` (sr⁻¹). Off-diagonal pairs lose the leakage of their
    /// excitation's diagonal value when the sample has it. A pair this scaling lacks is an
    /// error naming it.
    pub fn apply(&self, pairs: &[PairNm], values: &[f64], out: &mut [f64]) -> Result<(), ScalingError> {
        for (j, &(ex, em)) in pairs.iter().enumerate() {
            let v = values[j];
            out[j] = if ex == em {
                v * self.diagonal.get(&ex).ok_or(ScalingError::NoDiagonal { excitation: ex })?
            } else {
                let a = *self.row.get(&ex).ok_or(ScalingError::NoDiagonal { excitation: ex })?;
                let c = self.c(em);
                let leak = match (self.leak.get(&(ex, em)), pairs.iter().position(|&p| p == (ex, ex))) {
                    (Some(l), Some(d)) => l * values[d],
                    _ => 0.0,
                };
                a * c * (v - leak)
            };
        }
        Ok(())
    }

    /// `c(λo)`: measured on Spectralon, or (for an emission band far from every diagonal) the
    /// nearest band's.
    fn c(&self, em: u16) -> f64 {
        if let Some(c) = self.detection.get(&em) {
            return *c;
        }
        let below = self.detection.range(..em).next_back();
        let above = self.detection.range(em..).next();
        match (below, above) {
            (Some((a, ca)), Some((b, cb))) => {
                let t = f64::from(em - a) / f64::from(b - a);
                ca + t * (cb - ca)
            }
            (Some((_, c)), None) | (None, Some((_, c))) => *c,
            (None, None) => 1.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::brrdf::spectra::{ccd, sums, xenon, Lctf, Material};

    fn band_integral(f: &Lctf, em: u16) -> f64 {
        (340..=780).map(|nm| f.transmission(f64::from(em), f64::from(nm)) * ccd(f64::from(nm))).sum()
    }

    #[test]
    fn spectralon_rows_scale_a_matte_diagonal_and_the_reradiation_to_their_band_limited_truth() {
        let f = Lctf::default();
        // Excitation through the light filter from 440 nm, the camera from 400: every Spectralon
        // row reaches two bands either side of its diagonal.
        let grid: Vec<u16> = (440..=680).step_by(20).collect();
        let camera_grid: Vec<u16> = (400..=720).step_by(20).collect();
        let source = |ex: u16| move |nm: f64| xenon(nm) * f.transmission(f64::from(ex), nm);
        let camera = |em: u16| move |nm: f64| f.transmission(f64::from(em), nm) * ccd(nm);
        let white = Material::spectralon();
        let mut rows = Vec::new();
        for &ex in &grid {
            for &em in camera_grid.iter().filter(|&&em| (i32::from(em) - i32::from(ex)).abs() <= 40) {
                rows.push(((ex, em), sums(&white, &source(ex), &camera(em)).diffuse));
            }
        }
        let scaling = Scaling::new(&rows, |em| band_integral(&f, em), 20.0, 0.99).unwrap();
        // Spectralon itself: its diagonal reads ρ/π exactly, its off-diagonal nothing.
        let pairs: Vec<PairNm> = rows.iter().map(|r| r.0).collect();
        let values: Vec<f64> = rows.iter().map(|r| r.1).collect();
        let mut out = vec![0.0; pairs.len()];
        scaling.apply(&pairs, &values, &mut out).unwrap();
        for (p, v) in pairs.iter().zip(&out) {
            let want = if p.0 == p.1 { 0.99 / std::f64::consts::PI } else { 0.0 };
            assert!((v - want).abs() < 1e-12, "{p:?}: {v}");
        }
        // The fluorescent paint's upper triangle (no specular: lit and seen head-on).
        let m = Material { specular: None, ..Material::fluorescent_yellow() };
        let pairs: Vec<PairNm> = grid
            .iter()
            .flat_map(|&ex| camera_grid.iter().filter(move |&&em| em >= ex).map(move |&em| (ex, em)))
            .collect();
        let values: Vec<f64> = pairs
            .iter()
            .map(|&(ex, em)| {
                let s = sums(&m, &source(ex), &camera(em));
                s.diffuse + s.reradiated * Material::reradiation_angular(1.0)
            })
            .collect();
        let mut out = vec![0.0; pairs.len()];
        scaling.apply(&pairs, &values, &mut out).unwrap();
        // Diagonal entries and those two or more bands off it above 1 % of the diagonal: relative
        // error (weaker ones are within the crosstalk's mismatch, below); the first band
        // off the diagonal shares the filters' overlap with the diagonal reflection, whose
        // leakage is Spectralon's (flat albedo) share: its error is held against the row's diagonal.
        let (mut worst, mut worst_near): ((f64, PairNm), (f64, PairNm)) = ((0.0, (0, 0)), (0.0, (0, 0)));
        for (j, &(ex, em)) in pairs.iter().enumerate() {
            let diag = m.band_diagonal(&source(ex), &camera(ex));
            let truth = if ex == em {
                m.band_diagonal(&source(ex), &camera(em))
            } else {
                m.band_reradiation(&source(ex), &camera(em), 20.0) * Material::reradiation_angular(1.0)
            };
            if em == ex + 20 || (em != ex && truth <= 0.01 * diag) {
                let e = (out[j] - truth).abs() / diag;
                if e > worst_near.0 {
                    worst_near = (e, (ex, em));
                }
            } else if truth > 0.01 * diag {
                let e = (out[j] / truth - 1.0).abs();
                if e > worst.0 {
                    worst = (e, (ex, em));
                }
            }
        }
        assert!(worst.0 < 0.05, "worst relative error {:.4} at {:?}", worst.0, worst.1);
        assert!(
            worst_near.0 < 0.05,
            "first band off the diagonal and weak entries: {:.4} of the diagonal at {:?}",
            worst_near.0,
            worst_near.1
        );
    }

    #[test]
    fn an_excitation_without_its_diagonal_is_named() {
        let rows = [((420, 440), 1.0), ((440, 440), 2.0)];
        let e = Scaling::new(&rows, |_| 1.0, 20.0, 0.99).unwrap_err();
        assert_eq!(e, ScalingError::NoDiagonal { excitation: 420 });
        assert!(e.to_string().contains("420→420 nm"), "{e}");
        let dark = [((440, 440), 0.0)];
        assert!(matches!(
            Scaling::new(&dark, |_| 1.0, 20.0, 0.99),
            Err(ScalingError::Dark { excitation: 440, .. })
        ));
    }
}
