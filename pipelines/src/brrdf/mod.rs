//! Bispectral BRRDF (Hullin et al. 2010; thesis chapter 4): the maths of the PCA-steered
//! acquisition.
//!
//! - [`pca`]: principal components of bispectral samples, greedy wavelength-pair selection by
//!   `cond(R)`, reconstruction through `R⁺`, the saturated PCA of figure 4.10.
//! - [`spectra`]: source, filter and sensor spectra and bispectral materials in closed form
//!   (the virtual scene's truth).

pub mod pca;
pub mod spectra;
