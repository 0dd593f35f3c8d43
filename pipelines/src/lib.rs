//! The fitting pipelines' maths, free of sessions, devices and files: plain functions on
//! numbers and images, each testable alone.
//!
//! - [`vec3`]: the small vector algebra everything here uses.
//! - [`quad`]: Gauss–Legendre quadrature.
//! - [`linalg`]: small dense linear systems.
//! - [`ward`]: the isotropic Ward (1992) BRDF.
//! - [`lls`]: the linear light source reflectometry fit (Gardner et al. 2003), and
//!   [`lls::linear_light`], a cylindrical light source's diffuse and specular response at a
//!   surface point integrated numerically over its width and length (the virtual camera
//!   renders with it; the fit's faster [`lls::TraceModel`] is tested against it).
//! - [`firs`]: fluorescent immersion range scanning (Hullin et al. 2008).
//! - [`brrdf`]: the bispectral BRRDF's PCA-steered acquisition maths (Hullin et al. 2010).
//! - [`disco`]: DISCO, translucent objects measured with a laser spot (Goesele et al. 2004).
//! - [`display`]: the BRDF display's wave maths (Hullin et al. 2011).

pub mod brrdf;
pub mod disco;
pub mod display;
pub mod firs;
pub mod ggx;
pub mod linalg;
pub mod lls;
pub mod quad;
pub mod vec3;
pub mod ward;
