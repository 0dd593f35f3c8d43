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

/// `rig`'s `[plan.fit]` as `T` (`None`: the rig file has no such table). A wrong, missing or
/// unknown key is an error naming the table, its line and the key.
pub(crate) fn plan_fit<T: serde::de::DeserializeOwned>(
    rig: &crate::rigfile::RigFile,
) -> Option<Result<T, crate::rigfile::RigError>> {
    let fit = rig.plan.get("fit")?.clone();
    // serde names the field but not the sub-table it is in: the table's line is given.
    Some(fit.try_into().map_err(|e: toml::de::Error| rig.error("plan.fit", e.message().trim())))
}

/// What `lightrig acquire` checks of the fit before it connects: `rig`'s `[plan.fit]` read as
/// its rig's fit reads it, so that a wrong key is found before the acquisition, not after it.
/// A rig file without the table is no error (the acquisition needs none), but the fit will
/// refuse the session: the warning returned says so.
pub fn check_rig(rig: &crate::rigfile::RigFile) -> Result<Option<String>, FitError> {
    use crate::rigfile::Method;
    let missing = |what: &str| {
        Some(format!(
            "{}: no [plan.fit] table: the acquisition runs, but `lightrig fit` will refuse the session \
             without {what} (docs/rigs/README.md)",
            rig.path.display()
        ))
    };
    match rig.method {
        Method::LinearLightSource => match plan_fit::<lls::FitSpec>(rig) {
            None => Ok(missing("the tube's and the stripe's geometry")),
            Some(r) => r.map(|_| None).map_err(|e| fail(e.to_string())),
        },
        Method::FluorescentImmersion => match plan_fit::<firs::FirsFitSpec>(rig) {
            None => Ok(missing("the targets, the volume, the laser direction and the turntable")),
            Some(r) => r.map(|_| None).map_err(|e| fail(e.to_string())),
        },
        Method::Disco if !rig.plan.contains_key("fit") => {
            Ok(missing("the camera, the projector and the white target"))
        }
        Method::Disco => {
            crate::disco::DiscoSetup::from_rig(rig).map(|_| None).map_err(|e| fail(e.to_string()))
        }
        Method::Bispectral => brrdf::FitSpec::from_rig(rig).map(|_| None),
        Method::BrdfDisplay => Ok(None),
    }
}
