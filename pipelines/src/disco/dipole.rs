//! The dipole diffusion approximation of Jensen et al. 2001 ("A practical model for subsurface
//! light transport"): the diffuse reflectance `Rd(r)` of a homogeneous half-space between two
//! surface points `r` apart, and the Fresnel transmittance at its boundary. The virtual rig's
//! object is rendered with it; the fit's local kernels are compared with its fall-off.

use std::f64::consts::PI;

/// A homogeneous scattering medium: reduced scattering and absorption per colour channel (the
/// lasers' red, green, blue), mm⁻¹, and the relative index of refraction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    /// Name, as in Jensen et al.'s table.
    pub name: &'static str,
    /// σs′, mm⁻¹.
    pub sigma_s: [f64; 3],
    /// σa, mm⁻¹.
    pub sigma_a: [f64; 3],
    /// η.
    pub eta: f64,
}

/// Jensen et al. 2001, table of measured parameters (η = 1.3): marble.
pub const MARBLE: Medium =
    Medium { name: "marble", sigma_s: [2.19, 2.62, 3.00], sigma_a: [0.0021, 0.0041, 0.0071], eta: 1.3 };
/// Jensen et al. 2001: skin 1.
pub const SKIN1: Medium =
    Medium { name: "skin1", sigma_s: [0.74, 0.88, 1.01], sigma_a: [0.032, 0.17, 0.48], eta: 1.3 };
/// Jensen et al. 2001: skim milk.
pub const SKIM_MILK: Medium =
    Medium { name: "skimmilk", sigma_s: [0.70, 1.22, 1.90], sigma_a: [0.0014, 0.0025, 0.0142], eta: 1.3 };

/// Diffuse Fresnel reflectance, Jensen et al.'s fit (their eq. 4 after Egan and Hilgeman).
pub fn fresnel_diffuse(eta: f64) -> f64 {
    -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta
}

/// Fresnel transmittance `Ft(η, ω)` into (or out of) a medium of relative index `eta` for light
/// at `cos_theta` to the normal: one minus the unpolarised Fresnel reflectance.
pub fn fresnel_transmittance(eta: f64, cos_theta: f64) -> f64 {
    let ci = cos_theta.clamp(0.0, 1.0);
    let si2 = 1.0 - ci * ci;
    let st2 = si2 / (eta * eta);
    if st2 >= 1.0 {
        return 0.0;
    }
    let ct = (1.0 - st2).sqrt();
    let rs = (ci - eta * ct) / (ci + eta * ct);
    let rp = (eta * ci - ct) / (eta * ci + ct);
    1.0 - 0.5 * (rs * rs + rp * rp)
}

/// Per channel, the dipole's constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dipole {
    /// Reduced albedo α′.
    pub alpha: f64,
    /// Effective transport coefficient σtr, mm⁻¹.
    pub sigma_tr: f64,
    /// Depth of the real source, mm.
    pub z_r: f64,
    /// Height of the virtual source, mm.
    pub z_v: f64,
}

impl Dipole {
    /// Channel `c` of `m`.
    pub fn new(m: &Medium, c: usize) -> Self {
        let st = m.sigma_s[c] + m.sigma_a[c];
        let alpha = m.sigma_s[c] / st;
        let sigma_tr = (3.0 * m.sigma_a[c] * st).sqrt();
        let fdr = fresnel_diffuse(m.eta);
        let a = (1.0 + fdr) / (1.0 - fdr);
        let z_r = 1.0 / st;
        Dipole { alpha, sigma_tr, z_r, z_v: z_r * (1.0 + 4.0 * a / 3.0) }
    }

    /// `Rd`'s integral over the surface: the total diffuse reflectance of a half-space under a
    /// broad light (Jensen et al.'s eq. 6 analogue, with `A` from the sources' depths).
    pub fn total_reflectance(&self) -> f64 {
        let big_a = 0.75 * (self.z_v / self.z_r - 1.0);
        let s3 = (3.0 * (1.0 - self.alpha)).sqrt();
        self.alpha / 2.0 * (1.0 + (-4.0 / 3.0 * big_a * s3).exp()) * (-s3).exp()
    }

    /// `Rd(r)`, mm⁻²: the radiant exitance at distance `r` (mm) per unit incident flux.
    pub fn rd(&self, r: f64) -> f64 {
        let term = |z: f64| {
            let d = (r * r + z * z).sqrt();
            z * (1.0 + self.sigma_tr * d) * (-self.sigma_tr * d).exp() / (d * d * d)
        };
        self.alpha / (4.0 * PI) * (term(self.z_r) + term(self.z_v))
    }
}

impl Medium {
    /// The three channels' dipoles.
    pub fn dipoles(&self) -> [Dipole; 3] {
        [0, 1, 2].map(|c| Dipole::new(self, c))
    }
}

/// The inhomogeneous object's `Rd(xi, xo)` between points of media `a` and `b`: the mean of the
/// two dipoles, so that it is symmetric (light transport is).
pub fn rd_between(a: &Dipole, b: &Dipole, r: f64) -> f64 {
    0.5 * (a.rd(r) + b.rd(r))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresnel_transmittance_matches_the_textbook_values() {
        // Normal incidence: 1 − ((η−1)/(η+1))²; grazing: 0.
        let t0 = fresnel_transmittance(1.3, 1.0);
        assert!((t0 - (1.0 - (0.3f64 / 2.3).powi(2))).abs() < 1e-12);
        assert!(fresnel_transmittance(1.3, 0.0).abs() < 1e-12);
        // Monotone in angle.
        assert!(fresnel_transmittance(1.3, 0.5) < t0);
        assert!((fresnel_diffuse(1.3) - 0.4446).abs() < 1e-3);
    }

    #[test]
    fn the_dipole_integrates_to_the_total_diffuse_reflectance() {
        // ∫ Rd(r) 2πr dr equals Jensen et al.'s closed form
        // Rd = α′/2 (1 + e^{−4/3 A √(3(1−α′))}) e^{−√(3(1−α′))}.
        for m in [MARBLE, SKIN1] {
            for (c, d) in m.dipoles().iter().enumerate() {
                let (mut sum, mut r, dr) = (0.0, 0.0, 1e-3);
                while r < 400.0 {
                    let h = if r < 5.0 { dr } else { 0.05 };
                    sum += d.rd(r + h / 2.0) * 2.0 * PI * (r + h / 2.0) * h;
                    r += h;
                }
                let fdr = fresnel_diffuse(m.eta);
                let a = (1.0 + fdr) / (1.0 - fdr);
                let s = (3.0 * (1.0 - d.alpha)).sqrt();
                let closed = d.alpha / 2.0 * (1.0 + (-4.0 / 3.0 * a * s).exp()) * (-s).exp();
                assert!((sum / closed - 1.0).abs() < 2e-3, "{} channel {c}: {sum} vs {closed}", m.name);
            }
        }
    }
}
