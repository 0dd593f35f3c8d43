//! The liquid: capillary–gravity waves on a layer of finite depth, their dispersion and their
//! viscous damping (Lamb's weak-damping result).
//!
//! `ω² = (g·k + (σ/ρ)·k³) · tanh(k·h)`, with surface tension σ, density ρ and depth h. A wave
//! of wave number `k` loses amplitude at the rate `γ = 2ν·k²` (ν the kinematic viscosity), so
//! a travelling wave decays over distance at `κ = γ / c_g`, `c_g = dω/dk` its group velocity.

use std::f64::consts::PI;

/// Standard gravity, m/s².
pub const G: f64 = 9.806_65;

/// A liquid layer.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Liquid {
    /// Name, for reports.
    pub name: &'static str,
    /// Density, kg/m³.
    pub density: f64,
    /// Surface tension against air, N/m.
    pub surface_tension: f64,
    /// Kinematic viscosity, m²/s.
    pub kinematic_viscosity: f64,
    /// Depth of the layer, m.
    pub depth: f64,
}

impl Liquid {
    /// Water at 20 °C, 5 mm deep (the thesis's small, fast setup 2).
    pub const WATER: Liquid = Liquid {
        name: "water",
        density: 998.2,
        surface_tension: 0.0728,
        kinematic_viscosity: 1.004e-6,
        depth: 0.005,
    };

    /// The eutectic gallium–indium–tin alloy of the thesis's section 5.5.4, 5 mm deep:
    /// 6440 kg/m³, 0.534 N/m (Plevachuk et al. 2014; an oxide skin raises the apparent value),
    /// 2.4 mPa·s.
    pub const GALINSTAN: Liquid = Liquid {
        name: "galinstan",
        density: 6440.0,
        surface_tension: 0.534,
        kinematic_viscosity: 2.4e-3 / 6440.0,
        depth: 0.005,
    };

    /// The preset named `name` (`water`, `galinstan`).
    pub fn preset(name: &str) -> Option<Liquid> {
        match name {
            "water" => Some(Self::WATER),
            "galinstan" => Some(Self::GALINSTAN),
            _ => None,
        }
    }

    /// Angular frequency of a wave of wave number `k` (rad/m), rad/s.
    pub fn omega(&self, k: f64) -> f64 {
        ((G * k + self.surface_tension / self.density * k.powi(3)) * (k * self.depth).tanh()).sqrt()
    }

    /// Wave number (rad/m) of the wave at frequency `f` Hz: the dispersion relation solved for
    /// `k` (ω grows with k, so bisection on a bracket is exact to rounding).
    pub fn wave_number(&self, f: f64) -> f64 {
        let w = 2.0 * PI * f;
        let (mut lo, mut hi) = (0.0, 1.0);
        while self.omega(hi) < w {
            hi *= 2.0;
        }
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if self.omega(mid) < w {
                lo = mid;
            } else {
                hi = mid;
            }
            if hi - lo <= 1e-12 * hi {
                break;
            }
        }
        0.5 * (lo + hi)
    }

    /// Group velocity `dω/dk` at wave number `k`, m/s.
    pub fn group_velocity(&self, k: f64) -> f64 {
        let (s, h) = (self.surface_tension / self.density, self.depth);
        let w = self.omega(k);
        let t = (k * h).tanh();
        let sech2 = 1.0 - t * t;
        // d(ω²)/dk = (g + 3s·k²)·tanh(kh) + (g·k + s·k³)·h·sech²(kh)
        let dw2 = (G + 3.0 * s * k * k) * t + (G * k + s * k.powi(3)) * h * sech2;
        dw2 / (2.0 * w)
    }

    /// Temporal amplitude damping rate of a wave of wave number `k`, 1/s.
    pub fn damping_rate(&self, k: f64) -> f64 {
        2.0 * self.kinematic_viscosity * k * k
    }

    /// Spatial amplitude damping of a travelling wave of wave number `k`, 1/m.
    pub fn spatial_damping(&self, k: f64) -> f64 {
        self.damping_rate(k) / self.group_velocity(k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deep_water_limits_of_the_dispersion_relation() {
        let w = Liquid { depth: 10.0, ..Liquid::WATER };
        // Long waves: gravity only, ω² = g·k: a 1 m wave has k = 2π, f = √(g·2π)/2π ≈ 1.249 Hz.
        let k = w.wave_number((G * 2.0 * PI).sqrt() / (2.0 * PI));
        assert!((k / (2.0 * PI) - 1.0).abs() < 2e-3, "{k}");
        // Short waves: capillary, ω² = (σ/ρ)k³; at 1 kHz that is k = (ω²ρ/σ)^(1/3).
        let f = 1000.0;
        let capillary = ((2.0 * PI * f).powi(2) * w.density / w.surface_tension).cbrt();
        assert!((w.wave_number(f) / capillary - 1.0).abs() < 1e-3);
        // Group velocity: ½ the phase velocity for gravity waves, 3/2 for capillary ones.
        let kg = 2.0 * PI;
        assert!((w.group_velocity(kg) / (w.omega(kg) / kg) - 0.5).abs() < 2e-3);
        let kc = capillary;
        assert!((w.group_velocity(kc) / (w.omega(kc) / kc) - 1.5).abs() < 3e-3);
    }

    #[test]
    fn the_group_velocity_is_the_derivative_of_the_dispersion_relation() {
        for liquid in [Liquid::WATER, Liquid::GALINSTAN] {
            for f in [5.0, 20.0, 200.0, 800.0] {
                let k = liquid.wave_number(f);
                assert!((liquid.omega(k) / (2.0 * PI) / f - 1.0).abs() < 1e-9);
                let dk = k * 1e-6;
                let numeric = (liquid.omega(k + dk) - liquid.omega(k - dk)) / (2.0 * dk);
                assert!((liquid.group_velocity(k) / numeric - 1.0).abs() < 1e-6, "{} {f}", liquid.name);
            }
        }
    }

    #[test]
    fn high_frequencies_die_within_centimetres_as_the_thesis_saw() {
        // Section 5.5.1: 800 Hz waves reach "a few millimetres or centimetres".
        let w = Liquid::WATER;
        let reach = |f: f64| 1.0 / w.spatial_damping(w.wave_number(f));
        assert!((0.003..0.03).contains(&reach(800.0)), "{}", reach(800.0));
        assert!(reach(200.0) > 3.0 * reach(800.0));
    }
}
