//! A DISCO rig's geometry, read from its rig file: what the calibration gave (camera
//! intrinsics, each camera position's pose, the laser projector's pose, the white target's)
//! in the units of `lightrig_pipelines::disco::optics`. The planner reads the camera
//! positions, the fit and the virtual rig all of it, so every layer sees one geometry.
//!
//! ```toml
//! [plan]
//! camera_positions = [
//!   { name = "front", eye_mm = [300, 0, 90], look_at_mm = [0, 0, 30] },
//!   { name = "left", eye_mm = [230, 190, 150], look_at_mm = [0, 0, 30] },
//! ]
//! [plan.fit]
//! mesh = "object.ply"        # the scanned object, relative to the session directory
//! image = [768, 496]         # the camera's image, pixels
//! focal_px = 1800            # its calibrated focal length, pixels (principal point: centre)
//! projector = { eye_mm = [280, -120, 60], look_at_mm = [0, 0, 30] }  # at the zero codes
//! white_target = { point_mm = [0, 0, 30], normal = [1, 0, 0], albedo = 0.99 }
//! ```

use std::path::PathBuf;

use lightrig_pipelines::disco::optics::{Pinhole, Projector};
use lightrig_pipelines::disco::resample::WhiteTarget;
use lightrig_pipelines::vec3::{normalize, V3};
use serde::Deserialize;

use crate::rigfile::{RigError, RigFile};

/// One camera position (`[plan] camera_positions`): the camera is moved there by hand.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPosition {
    pub name: String,
    /// Centre of projection, world mm.
    pub eye_mm: V3,
    /// The point at the image centre, world mm.
    pub look_at_mm: V3,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct Pose {
    eye_mm: V3,
    look_at_mm: V3,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct White {
    point_mm: V3,
    normal: V3,
    albedo: f64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct FitSpec {
    #[serde(default)]
    mesh: Option<String>,
    #[serde(default)]
    mesh_unit: Option<String>,
    image: [u32; 2],
    focal_px: f64,
    projector: Pose,
    white_target: White,
    #[serde(default)]
    eta: Option<f64>,
    #[serde(default)]
    held_out: Option<usize>,
}

/// The geometry of a DISCO rig.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscoSetup {
    /// Each camera position's name and calibrated camera.
    pub cameras: Vec<(String, Pinhole)>,
    /// The laser projector (the first galvo pair's codes).
    pub projector: Projector,
    /// The white target, where the operator places it for the white balance.
    pub white: WhiteTarget,
    /// The object's mesh file as written in the rig file (relative to the session directory).
    pub mesh: Option<PathBuf>,
    /// The mesh file's length unit in mm (`[plan.fit] mesh_unit`: mm, cm, m, in, um; mm if
    /// not given).
    pub mesh_unit_mm: f64,
    /// Relative index of refraction for the Fresnel terms (1.3, as the paper).
    pub eta: f64,
    /// Every `held_out`-th spot is left out of the fit and predicted (0: none).
    pub held_out: usize,
}

/// The camera positions' names (`[plan] camera_positions`), or one unnamed position.
pub fn camera_positions(rig: &RigFile) -> Result<Vec<CameraPosition>, RigError> {
    let Some(v) = rig.plan.get("camera_positions") else {
        return Ok(vec![CameraPosition { name: "camera".into(), eye_mm: [0.0; 3], look_at_mm: [0.0; 3] }]);
    };
    let list: Vec<CameraPosition> = v.clone().try_into().map_err(|e| {
        rig.error(
            "plan.camera_positions",
            format!("{e}; each is {{ name, eye_mm = [x, y, z], look_at_mm = [x, y, z] }}"),
        )
    })?;
    if list.is_empty() {
        return Err(rig.error("plan.camera_positions", "is empty: give at least one camera position"));
    }
    Ok(list)
}

impl DiscoSetup {
    /// From `rig`'s `[plan] camera_positions` and `[plan.fit]`; a missing or malformed key is an
    /// error naming it.
    pub fn from_rig(rig: &RigFile) -> Result<Self, RigError> {
        let spec: FitSpec = crate::fit::plan_fit(rig).ok_or_else(|| {
            rig.error(
                "plan.fit",
                "a DISCO fit needs [plan.fit] with image, focal_px, projector and white_target (see docs/rigs/disco.toml)",
            )
        })??;
        let positions = camera_positions(rig)?;
        if rig.plan.get("camera_positions").is_none() {
            return Err(rig
                .error("plan.camera_positions", "a DISCO fit needs each camera position's calibrated pose"));
        }
        let [w, h] = spec.image;
        if w < 8 || h < 8 || spec.focal_px.is_nan() || spec.focal_px <= 0.0 {
            return Err(rig.error("plan.fit", "image must be at least 8 × 8 pixels and focal_px positive"));
        }
        let cameras = positions
            .iter()
            .map(|p| (p.name.clone(), Pinhole::looking(w, h, spec.focal_px, p.eye_mm, p.look_at_mm)))
            .collect();
        let galvo = rig.galvos.first().ok_or_else(|| rig.error("galvo", "a DISCO rig needs a [[galvo]]"))?;
        let projector = Projector::aimed(
            spec.projector.eye_mm,
            spec.projector.look_at_mm,
            [f64::from(galvo.x.zero_code), f64::from(galvo.y.zero_code)],
            [galvo.x.urad_per_code * 1e-6, galvo.y.urad_per_code * 1e-6],
        );
        let wt = spec.white_target;
        if wt.albedo.is_nan() || wt.albedo <= 0.0 || wt.albedo > 1.0 {
            return Err(rig.error("plan.fit.white_target.albedo", "must be in (0, 1]"));
        }
        let mesh_unit_mm = match spec.mesh_unit.as_deref() {
            None => 1.0,
            Some(u) => lightrig_pipelines::disco::scan::unit_mm(u).ok_or_else(|| {
                rig.error(
                    "plan.fit.mesh_unit",
                    format!("`{u}` is not a length unit lightrig knows: give mm, cm, m, in or um"),
                )
            })?,
        };
        Ok(DiscoSetup {
            cameras,
            projector,
            mesh_unit_mm,
            white: WhiteTarget { point: wt.point_mm, normal: normalize(wt.normal), albedo: wt.albedo },
            mesh: spec.mesh.map(PathBuf::from),
            eta: spec.eta.unwrap_or(1.3),
            held_out: spec.held_out.unwrap_or(0),
        })
    }
}
