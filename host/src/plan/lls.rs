//! Linear light source reflectometry (Gardner et al. 2003): a gantry carries a linear light
//! (and, in another pass, a laser stripe) over a flat sample; one frame per position.
//!
//! One step per pass, each from a known start: the gantry goes to the first position, the
//! pass's light comes on and warms up, then for every position: move, settle, expose. The
//! light goes off at the end of the pass (and the device turns every laser off when a sequence
//! ends anyway).

use lightrig_protocol::sequence::{Action, WaitFor};
use serde_json::json;

use std::sync::Arc;

use super::{Plan, PlanError, Step, StepBuilder};

/// What a pass lights the sample with. `Reflectance` and `Stripe` sweep the gantry, one frame
/// (bracket) per position; the others are one frame (bracket) with the gantry at the start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    /// The calibration board on the reference plane, in the room light: the camera's pose.
    Board,
    /// The light box with nothing on it: the reference for translucency.
    LightBox,
    /// The linear light: diffuse, specular and roughness. `mount_deg` turns the light's mount
    /// about the vertical (0: across the gantry's travel; Gardner et al. add ±15° passes for
    /// the normals' other component).
    Reflectance {
        /// Degrees, counter-clockwise seen from above.
        mount_deg: i8,
    },
    /// The laser stripe: height by triangulation.
    Stripe,
    /// The light box under the sample: translucency.
    Backlit,
}

impl Pass {
    /// The reflectance pass with the light across the gantry's travel.
    pub const REFLECTANCE: Pass = Pass::Reflectance { mount_deg: 0 };

    /// The pass's name in the rig file and in the step's `meta.pass` (the mount angle goes to
    /// `meta.mount_deg`).
    pub fn name(self) -> &'static str {
        match self {
            Pass::Board => "board",
            Pass::LightBox => "light-box",
            Pass::Reflectance { .. } => "reflectance",
            Pass::Stripe => "stripe",
            Pass::Backlit => "backlit",
        }
    }

    /// Parses a rig file's pass name: `board`, `light-box`, `reflectance`, `reflectance+15`,
    /// `reflectance-15` (any whole number of degrees up to 45 either way), `stripe`, `backlit`.
    pub fn parse(name: &str) -> Option<Pass> {
        Some(match name {
            "board" => Pass::Board,
            "light-box" | "lightbox" => Pass::LightBox,
            "reflectance" => Pass::REFLECTANCE,
            "stripe" => Pass::Stripe,
            "backlit" => Pass::Backlit,
            other => {
                let deg = other.strip_prefix("reflectance")?;
                if !deg.starts_with(['+', '-']) {
                    return None;
                }
                let mount_deg: i8 = deg.parse().ok()?;
                if mount_deg.unsigned_abs() > 45 {
                    return None;
                }
                Pass::Reflectance { mount_deg }
            }
        })
    }

    /// Whether the pass sweeps the gantry.
    pub fn sweeps(self) -> bool {
        matches!(self, Pass::Reflectance { .. } | Pass::Stripe)
    }

    /// What the operator must do before the pass, if anything.
    pub fn operator(self) -> Option<String> {
        match self {
            Pass::Board => Some("place the calibration board on the reference plane".into()),
            Pass::LightBox => Some("clear the light box (no sample)".into()),
            _ => None,
        }
    }
}

/// Everything the LLS planner needs, in device units.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LlsParams {
    /// Gantry axis.
    pub axis: u8,
    /// First position, steps.
    pub start: i32,
    /// Distance between frames, steps (1 mm by default).
    pub step: i32,
    /// Frames per pass.
    pub count: u32,
    /// Cameras, all fired at every position (at least one).
    pub cameras: Vec<u8>,
    /// Exposures taken at every position (an HDR bracket), ticks.
    pub exposures: Vec<u32>,
    /// Wait after the gantry stops before exposing (vibration), ticks.
    pub settle: u32,
    /// Time from a trigger to the next trigger or move, ticks: at least the longest exposure
    /// plus readout, and the camera's shortest frame interval.
    pub frame_gap: u32,
    /// Laser channel switching the linear light.
    pub light: u8,
    /// Laser channel of the stripe laser.
    pub stripe: u8,
    /// Laser channel of the light box, if the rig has one.
    pub backlight: Option<u8>,
    /// The passes, in order.
    pub passes: Vec<Pass>,
    /// Longest a move or warm-up may take before the device gives up, ticks.
    pub timeout: u32,
    /// Bytes per frame.
    pub frame_bytes: u64,
    /// Device tick rate.
    pub tick_hz: u32,
}

/// The LLS plan: one step per pass.
pub fn plan(p: &LlsParams) -> Result<Plan, PlanError> {
    if p.count == 0 || p.step == 0 || p.exposures.is_empty() {
        return Err(PlanError("lls: count, step and exposures must be non-zero".into()));
    }
    let longest = p.exposures.iter().copied().max().unwrap_or(0);
    if p.frame_gap < longest {
        return Err(PlanError(format!(
            "lls: frame_gap ({} ticks) is shorter than the longest exposure ({longest} ticks): frames would overlap",
            p.frame_gap
        )));
    }
    let last = i64::from(p.start) + i64::from(p.step) * (i64::from(p.count) - 1);
    let last = i32::try_from(last).map_err(|_| PlanError("lls: the pass runs past the axis range".into()))?;
    if p.cameras.is_empty() {
        return Err(PlanError("lls: no camera to trigger".into()));
    }
    let shared = Arc::new(p.clone());
    let mut steps = Vec::new();
    let mut mount = 0i8;
    for (id, pass) in p.passes.iter().enumerate() {
        let channel = match pass {
            Pass::Board => None,
            Pass::Reflectance { .. } => Some(p.light),
            Pass::Stripe => Some(p.stripe),
            Pass::Backlit | Pass::LightBox => Some(
                p.backlight.ok_or_else(|| PlanError(format!("lls: a {pass:?} pass needs a backlight")))?,
            ),
        };
        let count = if pass.sweeps() { p.count } else { 1 };
        let (q, pass_now) = (Arc::clone(&shared), *pass);
        let make = move |b: &mut StepBuilder| {
            b.move_to(q.axis, q.start, q.timeout);
            if let Some(channel) = channel {
                b.then(Action::Laser { channel, on: true });
                b.until(WaitFor::LaserReady(channel), q.timeout);
            }
            for i in 0..count {
                let pos = q.start + q.step * i as i32;
                b.move_to(q.axis, pos, q.timeout);
                b.wait(q.settle);
                for (e, &exposure) in q.exposures.iter().enumerate() {
                    b.shoot_all(&q.cameras, exposure, format!("{pass_now:?} {i} e{e}").to_lowercase());
                    b.wait(q.frame_gap);
                }
            }
            if let Some(channel) = channel {
                b.then(Action::Laser { channel, on: false });
            }
        };
        let mut meta = json!({
            "pass": pass.name(), "axis": p.axis, "start": p.start, "step": p.step, "count": count,
            "last": if pass.sweeps() { last } else { p.start }, "exposures": p.exposures,
        });
        let mut operator = pass.operator();
        let mut title = format!("pass {}", pass.name());
        if let Pass::Reflectance { mount_deg } = *pass {
            meta["mount_deg"] = json!(mount_deg);
            if mount_deg != mount {
                operator = Some(format!("turn the linear light's mount to {mount_deg:+}°"));
                mount = mount_deg;
            }
            if mount_deg != 0 {
                title = format!("{title} {mount_deg:+}°");
            }
        }
        if let Some(op) = operator {
            meta["operator"] = json!(op);
        }
        steps.push(Step::new(id as u32, title, meta, make));
    }
    Ok(Plan {
        method: "linear-light-source".into(),
        tick_hz: p.tick_hz,
        steps,
        frame_bytes: p.frame_bytes,
        meta: serde_json::Value::Null,
        lost_retries: super::LOST_RETRIES,
    })
}
