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

use crate::overrides::Override;

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

thread_local! {
    /// The `--set` overrides of the fit running on this thread ([`with_overrides`]).
    static SET: std::cell::RefCell<Vec<Override>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Runs `fit` with `overrides` applied to the rig file of the session it reads
/// (`lightrig fit --set`): a fit's geometry measured wrong (the tube's height, a target's
/// depth) is corrected without acquiring again. Only what no acquisition step used may
/// change: keys under `plan.fit`, the display's `plan.screen` (where the screen stands) and a
/// camera's `response`; any other key describes how the session was taken and is refused. Every fit reads its session's rig file through
/// [`session_rig`], on the thread that calls it, so the overrides reach each pipeline
/// without a parameter of its own.
pub fn with_overrides<T>(overrides: &[Override], fit: impl FnOnce() -> T) -> Result<T, FitError> {
    for o in overrides {
        let camera_response = o
            .key
            .strip_prefix("camera[")
            .and_then(|k| k.split_once("]."))
            .is_some_and(|(_, f)| f == "response");
        if !(o.key.starts_with("plan.fit.") || o.key.starts_with("plan.screen.") || camera_response) {
            return Err(fail(format!(
                "--set {o}: a fit changes only what the fit alone reads, keys under plan.fit and \
                 plan.screen and a camera's response (camera[N].response); `{}` describes how the \
                 session was acquired: \
                 acquire again with `lightrig acquire … --set {o}`",
                o.key
            )));
        }
    }
    struct Restore(Vec<Override>);
    impl Drop for Restore {
        fn drop(&mut self) {
            SET.with(|s| *s.borrow_mut() = std::mem::take(&mut self.0));
        }
    }
    let _restore = Restore(SET.with(|s| s.replace(overrides.to_vec())));
    Ok(fit())
}

/// The rig file session `dir` was acquired with (its manifest's `rig_text`), with this
/// thread's [`with_overrides`] applied; errors point at the manifest.
pub(crate) fn session_rig(
    rig_text: &str,
    dir: &std::path::Path,
) -> Result<crate::rigfile::RigFile, FitError> {
    let manifest = dir.join("manifest.json");
    let overrides = SET.with(|s| s.borrow().clone());
    let text = crate::overrides::apply(rig_text, &overrides)
        .map_err(|e| fail(format!("{}: the session's rig file: {e}", manifest.display())))?;
    crate::rigfile::RigFile::parse(&text, &manifest)
        .map_err(|e| fail(format!("{}: the session's rig file: {e}", dir.display())))
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
