//! Bispectral BRRDF (Hullin et al. 2010; thesis chapter 4): the maths of the PCA-steered
//! acquisition.
//!
//! - [`pca`]: principal components of bispectral samples, greedy wavelength-pair selection by
//!   `cond(R)`, reconstruction through `R⁺`, the saturated PCA of figure 4.10.
//! - [`scaling`]: the spectral scaling `s(λo, λi)` from a Spectralon session (§4.4.2).
//! - [`geometry`]: the spheres found in a frame, each pixel's normal and `(θo, θi, φd)`.
//! - [`binning`]: samples binned in `(θo, θi, φd)`, empty bins filled by diffusion (§4.4.3).
//! - [`colorimetry`]: bispectral samples rendered under an illuminant with the CIE 1931 observer.
//! - [`spectra`]: source, filter and sensor spectra and bispectral materials in closed form
//!   (the virtual scene's truth).

pub mod binning;
pub mod colorimetry;
pub mod geometry;
pub mod pca;
pub mod scaling;
pub mod spectra;
