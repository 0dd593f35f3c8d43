//! The isotropic Trowbridge–Reitz (GGX) microfacet BRDF, after Walter, Marschner, Li and
//! Torrance, *Microfacet Models for Refraction through Rough Surfaces* (EGSR 2007), eqs. 20,
//! 33 and 34:
//!
//! `f(ωi, ωo) = ρd/π + ρs · D(h) G1(ωi, h) G1(ωo, h) / (4 cosθi cosθo)`
//!
//! `D(h) = α² / (π cos⁴θh (α² + tan²θh)²)`, `G1(v, h) = 2 / (1 + √(1 + α² tan²θv))` where
//! `v·h` and `v·n` agree in sign, else 0.
//!
//! with `h` the half vector. There is no Fresnel term: `ρs` is a constant reflectance, as in
//! the Ward fit, and the shadowing is the separable Smith form `G1·G1`. That is the model of
//! Mitsuba 3's `roughconductor` with `distribution = "ggx"` and `material = "none"` (and of
//! pbrt-v4's and glTF's rough conductors with the Fresnel term set to 1), so a fitted map
//! renders there as fitted. `α` is the distribution's width parameter, not a slope standard
//! deviation (GGX has none: its slopes' variance is infinite).

use crate::vec3::{add, dot, normalize, V3};

/// One material: diffuse albedo, specular albedo, GGX α.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Ggx {
    /// Diffuse albedo per colour channel.
    pub diffuse: [f64; 3],
    /// Specular albedo per colour channel (the microfacets' reflectance).
    pub specular: [f64; 3],
    /// The distribution's α.
    pub alpha: f64,
}

/// `D(h)` for `c = cosθh`.
pub fn distribution(c: f64, alpha: f64) -> f64 {
    if c <= 0.0 {
        return 0.0;
    }
    let c2 = c * c;
    let a2 = alpha * alpha;
    // α² + tan²θ = (α² cos²θ + sin²θ) / cos²θ, so D = α² / (π (α² cos²θ + 1 − cos²θ)²).
    let t = a2 * c2 + (1.0 - c2);
    a2 / (std::f64::consts::PI * t * t)
}

/// The Smith shadowing (or masking) of direction `v` for microfacet normal `h`, macro normal `n`.
pub fn smith_g1(n: V3, v: V3, h: V3, alpha: f64) -> f64 {
    let cv = dot(n, v);
    if dot(v, h) * cv <= 0.0 {
        return 0.0;
    }
    let c2 = cv * cv;
    let tan2 = (1.0 - c2).max(0.0) / c2;
    2.0 / (1.0 + (1.0 + alpha * alpha * tan2).sqrt())
}

/// The specular lobe for `ρs = 1`, `ωi` and `ωo` unit vectors away from the surface; zero when
/// either is below the horizon.
pub fn specular_lobe(n: V3, wi: V3, wo: V3, alpha: f64) -> f64 {
    let (ci, co) = (dot(n, wi), dot(n, wo));
    if ci <= 0.0 || co <= 0.0 {
        return 0.0;
    }
    let h = normalize(add(wi, wo));
    distribution(dot(n, h), alpha) * smith_g1(n, wi, h, alpha) * smith_g1(n, wo, h, alpha) / (4.0 * ci * co)
}

impl Ggx {
    /// `f(ωi, ωo)` per channel.
    pub fn eval(&self, n: V3, wi: V3, wo: V3) -> [f64; 3] {
        if dot(n, wi) <= 0.0 || dot(n, wo) <= 0.0 {
            return [0.0; 3];
        }
        let s = specular_lobe(n, wi, wo, self.alpha);
        [0, 1, 2].map(|c| self.diffuse[c] / std::f64::consts::PI + self.specular[c] * s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `∫ D(h) cosθh dω_h = 1` over the hemisphere (the normalisation of eq. 33), by the
    /// midpoint rule in `θh`: a check of `distribution` against its definition.
    #[test]
    fn the_distribution_is_normalised() {
        for alpha in [0.05, 0.2, 0.6] {
            let n = 200_000;
            let dt = std::f64::consts::FRAC_PI_2 / n as f64;
            let total: f64 = (0..n)
                .map(|i| {
                    let t = (i as f64 + 0.5) * dt;
                    distribution(t.cos(), alpha) * t.cos() * t.sin() * dt * 2.0 * std::f64::consts::PI
                })
                .sum();
            assert!((total - 1.0).abs() < 1e-6, "α {alpha}: ∫ D cos = {total}");
        }
    }

    /// Walter et al.'s G1 equals the shadowed fraction `∫ max(0, v·m) D(m) dω_m` over
    /// `v·n ∫ D(m) (m·n) dω_m`, i.e. `G1 = cosθv / ∫ max(0, v·m) D(m) dω_m` (the Smith
    /// condition, their eq. 22's normalisation); checked by integrating over `m` numerically.
    #[test]
    fn g1_satisfies_the_smith_normalisation() {
        let n = [0.0, 0.0, 1.0];
        for (alpha, theta) in [(0.1f64, 0.5f64), (0.3, 1.0), (0.5, 1.3)] {
            let v = [theta.sin(), 0.0, theta.cos()];
            let (nt, np) = (2000, 720);
            let (dt, dp) = (std::f64::consts::FRAC_PI_2 / nt as f64, 2.0 * std::f64::consts::PI / np as f64);
            let mut proj = 0.0;
            for i in 0..nt {
                let t = (i as f64 + 0.5) * dt;
                for j in 0..np {
                    let p = (j as f64 + 0.5) * dp;
                    let m = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
                    proj += dot(v, m).max(0.0) * distribution(t.cos(), alpha) * t.sin() * dt * dp;
                }
            }
            let g1 = smith_g1(n, v, n, alpha);
            let want = theta.cos() / proj;
            assert!((g1 - want).abs() < 2e-3 * want, "α {alpha} θ {theta}: G1 {g1}, ∫ gives {want}");
        }
    }

    #[test]
    fn the_lobe_is_reciprocal_and_zero_below_the_horizon() {
        let n = normalize([0.1, -0.05, 1.0]);
        let (a, b) = (normalize([0.4, 0.2, 0.8]), normalize([-0.5, 0.1, 0.7]));
        let (f, g) = (specular_lobe(n, a, b, 0.2), specular_lobe(n, b, a, 0.2));
        assert!(f > 0.0 && (f - g).abs() < 1e-15 * f);
        assert_eq!(specular_lobe(n, [0.0, 0.6, -0.8], b, 0.2), 0.0);
    }
}
