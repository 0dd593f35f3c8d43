//! Spectra and bispectral materials in closed form: the truth the bispectral virtual scene is
//! rendered from (thesis §4.4.1–4.4.2), and what its pipeline is checked against.
//!
//! Wavelengths in nm. A bispectral BRRDF has a wavelength-preserving diagonal (a spectral
//! albedo and a white specular lobe) and, for a fluorescent material, an off-diagonal
//! reradiation `F(λo, λi) = q · ex(λi) · em(λo)` (excitation × emission spectra, quantum
//! yield `q`, emission normalised to unit area), weakly angular. A camera value is the double
//! integral of source × light filter × BRRDF × camera filter × sensor over both wavelengths,
//! on a 1 nm grid from [`GRID`]`.0` to [`GRID`]`.1`.

use crate::ward::Ward;

/// The integration grid, nm (inclusive), 1 nm apart.
pub const GRID: (u32, u32) = (340, 780);

/// A Gaussian of unit peak, full width at half maximum `fwhm`.
pub fn gauss(nm: f64, centre: f64, fwhm: f64) -> f64 {
    let s = fwhm / 2.354_820_045;
    (-0.5 * ((nm - centre) / s).powi(2)).exp()
}

/// A xenon arc through a light guide: flat across the visible, weak in the blue and near UV
/// (the thesis' reason for the LEDs), relative radiance per nm.
pub fn xenon(nm: f64) -> f64 {
    0.12 + 0.88 / (1.0 + (-(nm - 440.0) / 18.0).exp())
}

/// A near-UV/blue LED centred at `centre`, 15 nm wide, unit peak.
pub fn led(centre: f64, nm: f64) -> f64 {
    gauss(nm, centre, 15.0)
}

/// A monochrome CCD's quantum efficiency: peaks near 560 nm, a third of that at the ends.
pub fn ccd(nm: f64) -> f64 {
    0.3 + 0.7 * gauss(nm, 560.0, 280.0)
}

/// A liquid-crystal tunable filter: a band `fwhm` wide at the tuned wavelength with peak
/// transmission `peak`, and `crosstalk` of that leaking through the neighbouring bands
/// `step` nm either side (the off-diagonal light §4.4.2 sees on Spectralon).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lctf {
    pub fwhm: f64,
    pub peak: f64,
    pub crosstalk: f64,
    pub step: f64,
}

impl Default for Lctf {
    /// VariSpec-like: 15 nm bands, 45 % peak, 2 % crosstalk into the bands 20 nm away.
    fn default() -> Self {
        Lctf { fwhm: 15.0, peak: 0.45, crosstalk: 0.02, step: 20.0 }
    }
}

impl Lctf {
    /// Transmission at `nm` when tuned to `tuned`.
    pub fn transmission(&self, tuned: f64, nm: f64) -> f64 {
        let g = |c: f64| gauss(nm, c, self.fwhm);
        self.peak * (g(tuned) + self.crosstalk * (g(tuned - self.step) + g(tuned + self.step)))
    }
}

/// A material of the virtual samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// Name, for reports.
    pub name: &'static str,
    /// Diffuse spectral albedo: `low + (high − low)` logistic rising at `edge_nm`, `width_nm`.
    pub albedo: (f64, f64, f64, f64),
    /// White specular lobe (isotropic Ward): albedo, roughness; `None`: matte.
    pub specular: Option<(f64, f64)>,
    /// Fluorescence, if any.
    pub fluorescence: Option<Fluorescence>,
}

/// A fluorescent material's reradiation: `F(λo, λi) = q · ex(λi) · em(λo) / π` for `λo > λi`,
/// the emission normalised to unit area.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fluorescence {
    /// Quantum yield `q`.
    pub quantum_yield: f64,
    /// Excitation band (centre, fwhm), nm; unit peak.
    pub excitation: (f64, f64),
    /// Emission band (centre, fwhm), nm.
    pub emission: (f64, f64),
}

impl Material {
    /// A non-fluorescent orange clear-coated paint with a sharp highlight.
    pub fn orange_coat() -> Self {
        Material {
            name: "orange coat",
            albedo: (0.06, 0.78, 590.0, 14.0),
            specular: Some((0.05, 0.07)),
            fluorescence: None,
        }
    }

    /// A fluorescent yellow-green paint: absorbs blue, reradiates green-yellow.
    pub fn fluorescent_yellow() -> Self {
        Material {
            name: "fluorescent yellow",
            albedo: (0.10, 0.80, 505.0, 12.0),
            specular: Some((0.03, 0.18)),
            fluorescence: Some(Fluorescence {
                quantum_yield: 0.55,
                excitation: (440.0, 70.0),
                emission: (530.0, 45.0),
            }),
        }
    }

    /// Spectralon: 99 % Lambertian across the spectrum, wavelength-preserving.
    pub fn spectralon() -> Self {
        Material { name: "Spectralon", albedo: (0.99, 0.99, 550.0, 1.0), specular: None, fluorescence: None }
    }

    /// Diffuse albedo at `nm`.
    pub fn albedo(&self, nm: f64) -> f64 {
        let (lo, hi, edge, width) = self.albedo;
        lo + (hi - lo) / (1.0 + (-(nm - edge) / width).exp())
    }

    /// The reradiation `F(λo, λi)` per nm of `λo` (sr⁻¹ nm⁻¹, before the angular factor).
    pub fn reradiation(&self, out_nm: f64, in_nm: f64) -> f64 {
        match self.fluorescence {
            Some(Fluorescence { quantum_yield: q, excitation: ex, emission: em }) if out_nm > in_nm => {
                // Emission normalised to unit area: a Gaussian's area is fwhm · 1.0645.
                q * gauss(in_nm, ex.0, ex.1) * gauss(out_nm, em.0, em.1)
                    / (em.1 * 1.064_467)
                    / std::f64::consts::PI
            }
            _ => 0.0,
        }
    }

    /// The reradiation's weak dependence on the outgoing direction (`cos θo`).
    pub fn reradiation_angular(cos_o: f64) -> f64 {
        0.85 + 0.15 * cos_o.clamp(0.0, 1.0)
    }

    /// The diagonal entry an ideal instrument with these bands reports (the band-limited
    /// truth): the diffuse albedo over π, averaged over the light that `source` sends and
    /// `camera` sees.
    pub fn band_diagonal(&self, source: Spectrum, camera: Spectrum) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for nm in (GRID.0..=GRID.1).map(f64::from) {
            let sc = source(nm) * camera(nm);
            num += sc * self.albedo(nm) / std::f64::consts::PI;
            den += sc;
        }
        if den > 0.0 {
            num / den
        } else {
            0.0
        }
    }

    /// The off-diagonal entry an ideal instrument with these bands reports (the band-limited
    /// truth, before the angular factor): the light reradiated into an emission band `step_nm`
    /// wide per unit of exciting light, per steradian, each spectrum averaged over its band.
    pub fn band_reradiation(&self, source: Spectrum, camera: Spectrum, step_nm: f64) -> f64 {
        let Some(Fluorescence { quantum_yield: q, excitation: ex, emission: em }) = self.fluorescence else {
            return 0.0;
        };
        let grid = || (GRID.0..=GRID.1).map(f64::from);
        let (s, c): (f64, f64) = (grid().map(source).sum(), grid().map(camera).sum());
        if s <= 0.0 || c <= 0.0 {
            return 0.0;
        }
        let absorbed: f64 = grid().map(|nm| source(nm) * gauss(nm, ex.0, ex.1)).sum::<f64>() / s;
        let seen: f64 = grid().map(|nm| camera(nm) * gauss(nm, em.0, em.1)).sum::<f64>() / c;
        step_nm * q * absorbed * seen / (em.1 * 1.064_467) / std::f64::consts::PI
    }

    /// The wavelength-preserving BRDF at `nm` for unit directions `wi`, `wo` and normal `n`.
    pub fn diagonal(&self, nm: f64, wi: [f64; 3], wo: [f64; 3], n: [f64; 3]) -> f64 {
        let d = self.albedo(nm) / std::f64::consts::PI;
        let s = self.specular.map_or(0.0, |(rho, alpha)| {
            Ward { diffuse: [0.0; 3], specular: [rho; 3], alpha }.eval(n, wi, wo)[0]
        });
        d + s
    }
}

/// What lights the sample: a source spectrum (per nm) already through any filter in its path.
pub type Spectrum<'a> = &'a dyn Fn(f64) -> f64;

/// The wavelength integrals of one material under one source and camera: what every pixel of
/// a frame shares ([`Sums::value`] adds the geometry).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sums {
    /// `Σ S·C·ρ(λ)/π`: the diffuse diagonal.
    pub diffuse: f64,
    /// `Σ S·C`: what a white (specular) lobe reflects.
    pub flat: f64,
    /// `q·(Σ S·ex)·(Σ em·C)/(area·π)`: the reradiated light (0 when not fluorescent).
    pub reradiated: f64,
}

/// [`Sums`] of `m` lit by `source` and seen through `camera` (per nm, 1 nm grid over [`GRID`]).
pub fn sums(m: &Material, source: Spectrum, camera: Spectrum) -> Sums {
    let grid = || (GRID.0..=GRID.1).map(f64::from);
    let (mut diffuse, mut flat) = (0.0, 0.0);
    for nm in grid() {
        let sc = source(nm) * camera(nm);
        diffuse += sc * m.albedo(nm) / std::f64::consts::PI;
        flat += sc;
    }
    let reradiated = match m.fluorescence {
        None => 0.0,
        Some(Fluorescence { quantum_yield: q, excitation: ex, emission: em }) => {
            // F separates into ex(λi)·em(λo) over λo > λi; the two spectra overlap little,
            // so the product of the two integrals stands for the double one.
            let absorbed: f64 = grid().map(|nm| source(nm) * gauss(nm, ex.0, ex.1)).sum();
            let seen: f64 = grid().map(|nm| camera(nm) * gauss(nm, em.0, em.1)).sum();
            q * absorbed * seen / (em.1 * 1.064_467) / std::f64::consts::PI
        }
    };
    Sums { diffuse, flat, reradiated }
}

impl Sums {
    /// The camera value (relative) of a point of `m` with normal `n` lit from `wi`, seen from
    /// `wo` (unit vectors): diagonal plus reradiated light, times `cos θi`.
    pub fn value(&self, m: &Material, wi: [f64; 3], wo: [f64; 3], n: [f64; 3]) -> f64 {
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (ci, co) = (dot(n, wi), dot(n, wo));
        if ci <= 0.0 || co <= 0.0 {
            return 0.0;
        }
        let specular = m.specular.map_or(0.0, |(rho, alpha)| {
            Ward { diffuse: [0.0; 3], specular: [rho; 3], alpha }.eval(n, wi, wo)[0]
        });
        (self.diffuse + specular * self.flat + self.reradiated * Material::reradiation_angular(co)) * ci
    }
}

/// The camera value (relative) of a surface point of `m` with normal `n`, lit from `wi` by
/// `source` and seen from `wo` through `camera` (filter × sensor, per nm): the diagonal
/// integral plus the reradiated one, times `cos θi`.
pub fn camera_value(
    m: &Material,
    source: Spectrum,
    camera: Spectrum,
    wi: [f64; 3],
    wo: [f64; 3],
    n: [f64; 3],
) -> f64 {
    sums(m, source, camera).value(m, wi, wo, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_pass_their_band_and_a_little_of_the_neighbours() {
        let f = Lctf::default();
        assert!((f.transmission(550.0, 550.0) / 0.45 - 1.0).abs() < 1e-3);
        assert!((f.transmission(550.0, 557.5) / f.transmission(550.0, 550.0) - 0.5).abs() < 0.01);
        let leak = f.transmission(550.0, 570.0) / f.transmission(550.0, 550.0);
        assert!((0.015..0.03).contains(&leak), "{leak}");
        assert!(f.transmission(550.0, 620.0) < 1e-6);
    }

    #[test]
    fn spectralon_is_lambertian_and_off_diagonal_light_is_crosstalk_only() {
        let (f, s) = (Lctf::default(), Material::spectralon());
        let n = [0.0, 0.0, 1.0];
        let value = |ex: f64, em: f64, wi: [f64; 3]| {
            camera_value(
                &s,
                &|nm| xenon(nm) * f.transmission(ex, nm),
                &|nm| f.transmission(em, nm) * ccd(nm),
                wi,
                n,
                n,
            )
        };
        let head_on = value(550.0, 550.0, n);
        let a = 60f64.to_radians();
        let tilted = value(550.0, 550.0, [a.sin(), 0.0, a.cos()]);
        assert!((tilted / head_on - 0.5).abs() < 1e-9, "Lambert's cosine: {}", tilted / head_on);
        // 15 nm bands 20 nm apart overlap (and leak 2 %): the off-diagonal light §4.4.2 sees.
        let off = value(550.0, 570.0, n) / head_on;
        assert!(off > 0.05 && off < 0.2, "neighbouring band: {off}");
        assert!(value(550.0, 590.0, n) / head_on < 0.01, "two bands away");
        assert!(value(500.0, 600.0, n) / head_on < 1e-6, "far off the diagonal");
    }

    #[test]
    fn only_the_fluorescent_paint_reradiates() {
        let f = Lctf::default();
        let n = [0.0, 0.0, 1.0];
        let blue = |nm: f64| led(450.0, nm);
        let green = |nm: f64| f.transmission(540.0, nm) * ccd(nm);
        let diag_green = |nm: f64| xenon(nm) * f.transmission(540.0, nm);
        for (m, fluorescent) in [(Material::orange_coat(), false), (Material::fluorescent_yellow(), true)] {
            let off = camera_value(&m, &blue, &green, n, n, n);
            let on = camera_value(&m, &diag_green, &green, n, n, n);
            let ratio = off / on;
            if fluorescent {
                assert!(ratio > 0.2, "{}: {ratio}", m.name);
            } else {
                assert!(ratio < 1e-3, "{}: {ratio}", m.name);
            }
        }
        // Nothing reradiates to shorter wavelengths.
        assert_eq!(Material::fluorescent_yellow().reradiation(430.0, 450.0), 0.0);
    }
}
