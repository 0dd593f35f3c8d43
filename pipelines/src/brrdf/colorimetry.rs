//! Colour of bispectral data (thesis §4.6: renderings under a 5600 K illuminant and near-UV
//! light): the spectral radiance a bispectral BRRDF reflects under an illuminant, integrated
//! with the CIE 1931 2° standard observer into XYZ, then linear sRGB.
//!
//! Tables: the CIE 1931 2° colour-matching functions and the CIE illuminants D65 and A,
//! 380–780 nm in 10 nm steps (CIE 015:2018; the values colour-science ships), interpolated
//! linearly in between.

/// `[x̄, ȳ, z̄, D65, A]` at 380, 390, …, 780 nm.
const TABLE: [[f64; 5]; 41] = [
    [0.001368, 0.000039, 0.006450, 49.9755, 9.7951],
    [0.004243, 0.000120, 0.020050, 54.6482, 12.0853],
    [0.014310, 0.000396, 0.067850, 82.7549, 14.7080],
    [0.043510, 0.001210, 0.207400, 91.4860, 17.6753],
    [0.134380, 0.004000, 0.645600, 93.4318, 20.9950],
    [0.283900, 0.011600, 1.385600, 86.6823, 24.6709],
    [0.348280, 0.023000, 1.747060, 104.8650, 28.7027],
    [0.336200, 0.038000, 1.772110, 117.0080, 33.0859],
    [0.290800, 0.060000, 1.669200, 117.8120, 37.8121],
    [0.195360, 0.090980, 1.287640, 114.8610, 42.8693],
    [0.095640, 0.139020, 0.812950, 115.9230, 48.2423],
    [0.032010, 0.208020, 0.465180, 108.8110, 53.9132],
    [0.004900, 0.323000, 0.272000, 109.3540, 59.8611],
    [0.009300, 0.503000, 0.158200, 107.8020, 66.0635],
    [0.063270, 0.710000, 0.078250, 104.7900, 72.4959],
    [0.165500, 0.862000, 0.042160, 107.6890, 79.1326],
    [0.290400, 0.954000, 0.020300, 104.4050, 85.9470],
    [0.433450, 0.994950, 0.008750, 104.0460, 92.9120],
    [0.594500, 0.995000, 0.003900, 100.0000, 100.0000],
    [0.762100, 0.952000, 0.002100, 96.3342, 107.1840],
    [0.916300, 0.870000, 0.001650, 95.7880, 114.4360],
    [1.026300, 0.757000, 0.001100, 88.6856, 121.7310],
    [1.062200, 0.631000, 0.000800, 90.0062, 129.0430],
    [1.002600, 0.503000, 0.000340, 89.5991, 136.3460],
    [0.854450, 0.381000, 0.000190, 87.6987, 143.6180],
    [0.642400, 0.265000, 0.000050, 83.2886, 150.8360],
    [0.447900, 0.175000, 0.000020, 83.6992, 157.9790],
    [0.283500, 0.107000, 0.000000, 80.0268, 165.0280],
    [0.164900, 0.061000, 0.000000, 80.2146, 171.9630],
    [0.087400, 0.032000, 0.000000, 82.2778, 178.7690],
    [0.046770, 0.017000, 0.000000, 78.2842, 185.4290],
    [0.022700, 0.008210, 0.000000, 69.7213, 191.9310],
    [0.011359, 0.004102, 0.000000, 71.6091, 198.2610],
    [0.005790, 0.002091, 0.000000, 74.3490, 204.4090],
    [0.002899, 0.001047, 0.000000, 61.6040, 210.3650],
    [0.001440, 0.000520, 0.000000, 69.8856, 216.1200],
    [0.000690, 0.000249, 0.000000, 75.0870, 221.6670],
    [0.000332, 0.000120, 0.000000, 63.5927, 227.0000],
    [0.000166, 0.000060, 0.000000, 46.4182, 232.1150],
    [0.000083, 0.000030, 0.000000, 66.8054, 237.0080],
    [0.000042, 0.000015, 0.000000, 63.3828, 241.6750],
];

fn lookup(nm: f64, column: usize) -> f64 {
    let t = (nm - 380.0) / 10.0;
    if !(0.0..=40.0).contains(&t) {
        return 0.0;
    }
    let i = (t.floor() as usize).min(39);
    let f = t - i as f64;
    TABLE[i][column] * (1.0 - f) + TABLE[i + 1][column] * f
}

/// The CIE 1931 2° colour-matching functions at `nm`.
pub fn cmf(nm: f64) -> [f64; 3] {
    [lookup(nm, 0), lookup(nm, 1), lookup(nm, 2)]
}

/// An illuminant's relative spectral power.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Illuminant {
    /// CIE D65 (daylight).
    D65,
    /// CIE A (tungsten, 2856 K).
    A,
    /// An LED at `centre` nm, `fwhm` wide (a near-UV or violet source).
    Led { centre: f64, fwhm: f64 },
}

impl Illuminant {
    /// Relative power at `nm`.
    pub fn power(&self, nm: f64) -> f64 {
        match *self {
            Illuminant::D65 => lookup(nm, 3),
            Illuminant::A => lookup(nm, 4),
            Illuminant::Led { centre, fwhm } => super::spectra::gauss(nm, centre, fwhm),
        }
    }

    /// A short name for files.
    pub fn name(&self) -> String {
        match self {
            Illuminant::D65 => "d65".into(),
            Illuminant::A => "a".into(),
            Illuminant::Led { centre, .. } => format!("led{centre:.0}"),
        }
    }
}

/// Renders bispectral samples on one wavelength grid under an illuminant.
#[derive(Debug, Clone)]
pub struct Renderer {
    /// The pairs `(λi, λo)` of a sample, nm.
    pairs: Vec<(f64, f64)>,
    /// Per pair: the illuminant at `λi` times the observer at `λo`, scaled.
    weights: Vec<[f64; 3]>,
}

impl Renderer {
    /// For samples over `pairs` (`(λi, λo)`, the grid `step_nm` apart) under `light`, scaled
    /// so that a white Lambertian reflector (`1/π` on the diagonal) under the same power of
    /// D65 on the same grid has `Y = 1`.
    pub fn new(pairs: &[(f64, f64)], light: Illuminant) -> Renderer {
        let mut grid: Vec<f64> = pairs.iter().map(|p| p.1).collect();
        grid.sort_by(f64::total_cmp);
        grid.dedup();
        // The same total power on the grid as D65; D65's white at Y = 1.
        let power = |l: Illuminant| grid.iter().map(|&nm| l.power(nm)).sum::<f64>();
        let equal = power(Illuminant::D65) / power(light).max(1e-300);
        let white_y: f64 = grid.iter().map(|&nm| Illuminant::D65.power(nm) * cmf(nm)[1]).sum();
        let k = std::f64::consts::PI * equal / white_y;
        let weights = pairs
            .iter()
            .map(|&(i, o)| {
                let c = cmf(o);
                let e = light.power(i) * k;
                [e * c[0], e * c[1], e * c[2]]
            })
            .collect();
        Renderer { pairs: pairs.to_vec(), weights }
    }

    /// XYZ of a sample (`values[j]` at `pairs[j]`: diagonal entries `f(λ)`, reradiated ones the
    /// light reradiated into the band at `λo` per unit of light in the band at `λi`), lit at
    /// irradiance 1 and seen along the normal.
    pub fn xyz(&self, values: &[f64]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (w, v) in self.weights.iter().zip(values) {
            for c in 0..3 {
                out[c] += w[c] * v;
            }
        }
        out
    }

    /// The pairs this renderer expects.
    pub fn pairs(&self) -> &[(f64, f64)] {
        &self.pairs
    }
}

/// CIE XYZ to linear sRGB (IEC 61966-2-1, D65 white).
pub fn xyz_to_linear_srgb(xyz: [f64; 3]) -> [f64; 3] {
    let [x, y, z] = xyz;
    [
        3.2406 * x - 1.5372 * y - 0.4986 * z,
        -0.9689 * x + 1.8758 * y + 0.0415 * z,
        0.0557 * x - 0.2040 * y + 1.0570 * z,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> Vec<(f64, f64)> {
        let mut v = Vec::new();
        for i in (400..=720).step_by(20) {
            for o in (400..=720).step_by(20).filter(|&o| o >= i) {
                v.push((f64::from(i), f64::from(o)));
            }
        }
        v
    }

    #[test]
    fn a_white_reflector_under_d65_is_white_and_under_a_is_warm() {
        let pairs = grid();
        let white: Vec<f64> =
            pairs.iter().map(|p| if p.0 == p.1 { 1.0 / std::f64::consts::PI } else { 0.0 }).collect();
        let xyz = Renderer::new(&pairs, Illuminant::D65).xyz(&white);
        assert!((xyz[1] - 1.0).abs() < 1e-12, "{xyz:?}");
        let rgb = xyz_to_linear_srgb(xyz);
        // Sampled every 20 nm from 400 to 720 nm the white point lands within 3 % of (1, 1, 1).
        for c in rgb {
            assert!((c - 1.0).abs() < 0.03, "{rgb:?}");
        }
        let warm = xyz_to_linear_srgb(Renderer::new(&pairs, Illuminant::A).xyz(&white));
        assert!(warm[0] > 1.3 * warm[2], "illuminant A is red-heavy: {warm:?}");
    }

    #[test]
    fn reradiation_shows_in_its_emission_colour_under_near_uv() {
        let pairs = grid();
        let j = pairs.iter().position(|&p| p == (400.0, 520.0)).unwrap();
        let mut v = vec![0.0; pairs.len()];
        v[j] = 0.05;
        let uv = Renderer::new(&pairs, Illuminant::Led { centre: 400.0, fwhm: 15.0 });
        let rgb = xyz_to_linear_srgb(uv.xyz(&v));
        assert!(rgb[1] > 0.0 && rgb[1] > rgb[0] && rgb[1] > rgb[2], "green glow: {rgb:?}");
        // Under D65 the same pair shows too, weaker: D65 has less of its power at 400 nm.
        let d = xyz_to_linear_srgb(Renderer::new(&pairs, Illuminant::D65).xyz(&v));
        assert!(d[1] > 0.0 && d[1] < rgb[1], "{d:?} against {rgb:?}");
    }
}
