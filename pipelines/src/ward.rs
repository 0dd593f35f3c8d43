//! The isotropic Ward (1992) BRDF:
//!
//! `f(ωi, ωo) = ρd/π + ρs · exp(−tan²δ/α²) / (4π α² √(cosθi cosθo))`
//!
//! with `δ` the angle between the normal and the half vector. The two lobes are kept apart
//! because the fits solve for `ρd` and `ρs` linearly once `α` is fixed.

use crate::vec3::{add, dot, normalize, V3};

/// One material: diffuse albedo, specular albedo, roughness.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Ward {
    /// Diffuse albedo per colour channel.
    pub diffuse: [f64; 3],
    /// Specular albedo per colour channel.
    pub specular: [f64; 3],
    /// Roughness α (the lobe's slope standard deviation).
    pub alpha: f64,
}

/// The specular lobe for `ρs = 1`, `ωi` and `ωo` unit vectors away from the surface; zero when
/// either is below the horizon.
pub fn specular_lobe(n: V3, wi: V3, wo: V3, alpha: f64) -> f64 {
    let (ci, co) = (dot(n, wi), dot(n, wo));
    if ci <= 0.0 || co <= 0.0 {
        return 0.0;
    }
    let h = normalize(add(wi, wo));
    let c = dot(n, h);
    let c2 = c * c;
    let tan2 = (1.0 - c2) / c2;
    (-tan2 / (alpha * alpha)).exp() / (4.0 * std::f64::consts::PI * alpha * alpha * (ci * co).sqrt())
}

impl Ward {
    /// `f(ωi, ωo)` per channel.
    pub fn eval(&self, n: V3, wi: V3, wo: V3) -> [f64; 3] {
        if dot(n, wi) <= 0.0 || dot(n, wo) <= 0.0 {
            return [0.0; 3];
        }
        let s = specular_lobe(n, wi, wo, self.alpha);
        [0, 1, 2].map(|c| self.diffuse[c] / std::f64::consts::PI + self.specular[c] * s)
    }
}
