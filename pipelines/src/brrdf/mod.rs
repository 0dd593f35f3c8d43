//! Bispectral BRRDF (Hullin et al. 2010; thesis chapter 4): the maths of the PCA-steered
//! acquisition.
//!
//! - [`pca`]: principal components of bispectral samples, greedy wavelength-pair selection by
//!   `cond(R)`, reconstruction through `R⁺`, the saturated PCA of figure 4.10.

pub mod pca;
