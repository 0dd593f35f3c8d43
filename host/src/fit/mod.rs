//! Per-rig session readers: each turns a session directory into its pipeline's inputs, runs
//! the maths in `lightrig_pipelines::<rig>` and writes the outputs.
//!
//! - [`lls`]: `lightrig fit lls`: frames with their trigger snapshots → maps, previews, relit
//!   check; [`lls::stack`] streams the passes into per-pixel traces.
//! - [`display`]: `lightrig fit display`: a BRDF display's calibration (the coils' responses)
//!   or what its targets showed.
//! - [`firs`]: `lightrig fit firs-surface` and `firs-volume`: calibration through the tank
//!   wall, surface meshes and points, or the volume and its isosurface.
//!
//! - [`brrdf`]: `lightrig fit brrdf`: a bispectral session scaled by its Spectralon session,
//!   binned per sphere, and the PCA-steered reconstruction measured on it.
//! - [`disco`]: `lightrig fit disco`: a DISCO session's frames resampled into the throughput
//!   factor matrix `F` and filled on the mesh.
//! - [`bracket`]: an exposure bracket merged through the camera's response.
//!
//! Each returns a [`FitError`]: one message that says what was wrong, where (file, step,
//! field) and what to do.

pub mod bracket;
pub mod brrdf;
pub mod disco;
pub mod display;
pub mod firs;
pub mod lls;

/// Why a fit stopped: what, where, what to do.
#[derive(Debug, Clone, PartialEq)]
pub struct FitError(pub String);

impl std::fmt::Display for FitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for FitError {}

pub(crate) fn fail(m: impl Into<String>) -> FitError {
    FitError(m.into())
}
