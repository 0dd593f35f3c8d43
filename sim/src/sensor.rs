//! The virtual camera's sensor: scene radiance in, stored pixel values out.
//!
//! `electrons = radiance · exposure · gain`, then shot noise (Poisson, drawn as a Gaussian of
//! variance equal to the mean: the counts here are hundreds and more) and read noise
//! (Gaussian), clipped at the full well, then the response curve and quantisation to the
//! stored bit depth. Noise comes from a counter-based generator keyed by (seed, frame, pixel),
//! so the same seed gives the same bytes however the rendering is split across threads.

/// How sensor values become stored values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Response {
    /// Stored value proportional to the collected charge (a machine-vision camera).
    Linear,
    /// `v^(1/γ)`: a camera that applies a display gamma.
    Gamma(f64),
}

impl Response {
    /// A camera with display gamma `gamma` (1: linear).
    pub fn of_gamma(gamma: f64) -> Self {
        if gamma == 1.0 {
            Response::Linear
        } else {
            Response::Gamma(gamma)
        }
    }
}

/// Stored sample format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Depth {
    /// 8-bit integers.
    U8,
    /// 12-bit integers: 4096 levels, stored in 16-bit files.
    U12,
    /// 16-bit integers.
    U16,
    /// 32-bit float (EXR), no quantisation, no clipping.
    Float,
    /// 16-bit half float (EXR): no clipping, 11 significant bits (far below shot noise at any
    /// level a camera resolves), half the bytes of `Float`: an HDR video camera's thousands
    /// of frames.
    Half,
}

/// The sensor model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensor {
    /// Electrons per unit radiance per second of exposure.
    pub gain: f64,
    /// Full-well capacity, electrons: saturation.
    pub full_well: f64,
    /// Read noise, electrons RMS.
    pub read_noise: f64,
    /// Response curve.
    pub response: Response,
    /// Stored format.
    pub depth: Depth,
    /// Noise seed.
    pub seed: u64,
    /// A monochrome sensor: one channel, the mean of the scene's three.
    pub grey: bool,
}

impl Default for Sensor {
    fn default() -> Self {
        Sensor {
            gain: 1.0e6,
            full_well: 30_000.0,
            read_noise: 4.0,
            response: Response::Linear,
            depth: Depth::U16,
            seed: 1,
            grey: false,
        }
    }
}

/// SplitMix64's finaliser: a well-mixed 64-bit hash.
pub fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Two independent standard normal numbers for key `k` (Box–Muller).
pub fn normals(k: u64) -> (f64, f64) {
    let a = mix(k);
    let b = mix(a ^ 0x5851_f42d_4c95_7f2d);
    let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
    let r = (-2.0 * u1.ln()).sqrt();
    let t = std::f64::consts::TAU * u2;
    (r * t.cos(), r * t.sin())
}

impl Sensor {
    /// The largest stored value.
    pub fn max_value(&self) -> f64 {
        match self.depth {
            Depth::U8 => 255.0,
            Depth::U12 => 4095.0,
            Depth::U16 => 65535.0,
            Depth::Float | Depth::Half => f64::INFINITY,
        }
    }

    /// The stored value, normalised to `[0, 1]` for integer formats (as image files read back),
    /// of a pixel with `radiance` exposed for `exposure_s`; `key` selects the noise draw.
    pub fn expose(&self, radiance: f64, exposure_s: f64, key: u64) -> f32 {
        let mean = (radiance * exposure_s * self.gain).max(0.0);
        let (n1, n2) = normals(mix(self.seed ^ mix(key)));
        let e = mean + mean.sqrt() * n1 + self.read_noise * n2;
        if matches!(self.depth, Depth::Float | Depth::Half) {
            return (e / self.full_well) as f32;
        }
        let v = (e / self.full_well).clamp(0.0, 1.0);
        let v = match self.response {
            Response::Linear => v,
            Response::Gamma(g) => v.powf(1.0 / g),
        };
        let max = self.max_value();
        ((v * max).round() / max) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_has_the_modelled_mean_and_variance() {
        let s = Sensor { depth: Depth::Float, ..Sensor::default() };
        let (radiance, t) = (0.01, 0.5); // 5000 e⁻
        let n = 200_000;
        let xs: Vec<f64> = (0..n).map(|k| f64::from(s.expose(radiance, t, k)) * s.full_well).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        // 5000 e⁻ of shot noise plus 16 e⁻² of read noise; standard errors ≈ 0.16 e⁻ and 16 e⁻².
        assert!((mean - 5000.0).abs() < 1.0, "mean {mean}");
        assert!((var - 5016.0).abs() < 80.0, "variance {var}");
    }

    #[test]
    fn saturates_and_quantises() {
        let s = Sensor { depth: Depth::U8, read_noise: 0.0, ..Sensor::default() };
        assert_eq!(s.expose(1.0, 1.0, 3), 1.0); // 10⁶ e⁻ ≫ full well
        let v = s.expose(0.0, 1.0, 3);
        assert_eq!(v, 0.0);
        let v = f64::from(s.expose(0.015, 1.0, 9)); // half the full well
        assert!(((v * 255.0).round() - v * 255.0).abs() < 1e-4, "{v} is not a multiple of 1/255");
        assert!((v - 0.5).abs() < 0.02, "{v}");
    }

    #[test]
    fn same_key_same_value() {
        let s = Sensor::default();
        assert_eq!(s.expose(0.003, 0.004, 77).to_bits(), s.expose(0.003, 0.004, 77).to_bits());
        assert_ne!(s.expose(0.003, 0.004, 77).to_bits(), s.expose(0.003, 0.004, 78).to_bits());
    }
}
