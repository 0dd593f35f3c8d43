//! DISCO (Goesele et al. 2004): a galvo-steered laser spot visits points on a translucent
//! object on a turntable, for each view and each laser colour; the camera records each
//! impulse response.
//!
//! First, with `white`, the white balance (section 4.4): the operator places the white target,
//! and each laser in turn puts its spot on it at the galvo's zero codes. Then one step per view,
//! camera position by camera position (the paper's acquisition order): the first view at a
//! position asks the operator to move the camera there (`meta.operator`); the turntable goes to
//! the view's angle; a registration frame is taken under the spotlights; then for each laser:
//! on, warm up, and for every grid point: jump (the device blanks the lasers while the mirrors
//! settle), wait out the settle time, expose `frames_per_spot` frames. No frame is triggered
//! while the mirrors move.

use lightrig_protocol::config::Xy;
use lightrig_protocol::sequence::{Action, WaitFor};
use serde_json::json;

use std::sync::Arc;

use super::{Plan, PlanError, Step};

/// Everything the DISCO planner needs, in device units.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiscoParams {
    /// Turntable axis.
    pub turntable: u8,
    /// Turntable position of each view, steps.
    pub views: Vec<i32>,
    /// Laser channels, in capture order (e.g. 635, 532, 476 nm).
    pub lasers: Vec<u8>,
    /// Camera positions, by name, in capture order (at least one).
    pub positions: Vec<String>,
    /// Frames per spot (and laser).
    pub frames_per_spot: u32,
    /// The white balance step first, its spot at these codes.
    pub white: Option<Xy>,
    /// Galvo pair.
    pub galvo: u8,
    /// Spot positions, DAC codes.
    pub grid: Vec<Xy>,
    /// Cameras, all fired at every spot (at least one).
    pub cameras: Vec<u8>,
    /// Exposure per spot, ticks.
    pub exposure: u32,
    /// Mirror settle time after a jump, ticks (the galvo's `settle_ticks`).
    pub settle: u32,
    /// Time from a trigger to the next jump, ticks (at least the exposure).
    pub frame_gap: u32,
    /// Light channel of the spotlights for the registration frame, if any.
    pub spotlight: Option<u8>,
    /// Longest a move or warm-up may take, ticks.
    pub timeout: u32,
    /// Bytes per frame.
    pub frame_bytes: u64,
    /// Device tick rate.
    pub tick_hz: u32,
}

/// The DISCO plan: one step per view.
pub fn plan(p: &DiscoParams) -> Result<Plan, PlanError> {
    if p.views.is_empty() || p.lasers.is_empty() || p.grid.is_empty() {
        return Err(PlanError("disco: views, lasers and grid must not be empty".into()));
    }
    if p.frame_gap < p.exposure {
        return Err(PlanError(format!(
            "disco: frame_gap ({} ticks) is shorter than the exposure ({} ticks): the spot would move during it",
            p.frame_gap, p.exposure
        )));
    }
    if p.cameras.is_empty() {
        return Err(PlanError("disco: no camera to trigger".into()));
    }
    if p.positions.is_empty() || p.frames_per_spot == 0 {
        return Err(PlanError("disco: at least one camera position and one frame per spot".into()));
    }
    // Shared by every step's builder (the grid alone is 4096 points at 64²).
    let shared = Arc::new(p.clone());
    let mut steps = Vec::new();
    if let Some(code) = p.white {
        let p = Arc::clone(&shared);
        let meta = json!({
            "kind": "white", "camera_position": 0, "lasers": p.lasers,
            "operator": format!("camera at position `{}`; place the white target where the rig file's [plan.fit] white_target says", p.positions[0]),
        });
        steps.push(Step::new(0, "white balance".to_string(), meta, move |b| {
            for &laser in &p.lasers {
                b.then(Action::GalvoPoint { galvo: p.galvo, to: code });
                b.then(Action::Laser { channel: laser, on: true });
                b.until(WaitFor::LaserReady(laser), p.timeout);
                b.wait(p.settle);
                b.shoot_all(&p.cameras, p.exposure, format!("white laser {laser}"));
                b.wait(p.frame_gap);
                b.then(Action::Laser { channel: laser, on: false });
            }
        }));
    }
    for (c, position) in p.positions.iter().enumerate() {
        for (v, &angle) in p.views.iter().enumerate() {
            let p = Arc::clone(&shared);
            let mut meta = json!({
                "kind": "view", "view": v, "camera_position": c, "turntable": angle, "lasers": p.lasers,
                "registration": p.spotlight.is_some(), "frames_per_spot": p.frames_per_spot,
            });
            if v == 0 && (c > 0 || p.white.is_some()) {
                let mut op = String::new();
                if c == 0 {
                    op.push_str("remove the white target; place the object on the turntable");
                } else {
                    op.push_str(&format!("move the camera to position `{position}` as calibrated"));
                }
                meta["operator"] = json!(op);
            }
            let id = steps.len() as u32;
            let name =
                if p.positions.len() > 1 { format!("{position} view {v}") } else { format!("view {v}") };
            steps.push(Step::new(id, name, meta, move |b| {
                b.move_to(p.turntable, angle, p.timeout);
                if let Some(s) = p.spotlight {
                    b.then(Action::Laser { channel: s, on: true });
                    b.until(WaitFor::LaserReady(s), p.timeout);
                    b.shoot_all(&p.cameras, p.exposure, "registration");
                    b.wait(p.frame_gap);
                    b.then(Action::Laser { channel: s, on: false });
                }
                for &laser in &p.lasers {
                    b.then(Action::Laser { channel: laser, on: true });
                    b.until(WaitFor::LaserReady(laser), p.timeout);
                    for (k, &point) in p.grid.iter().enumerate() {
                        b.then(Action::GalvoPoint { galvo: p.galvo, to: point });
                        b.wait(p.settle);
                        for _ in 0..p.frames_per_spot {
                            b.shoot_all(&p.cameras, p.exposure, format!("laser {laser} point {k}"));
                            b.wait(p.frame_gap);
                        }
                    }
                    b.then(Action::Laser { channel: laser, on: false });
                }
            }));
        }
    }
    // The spot grid is the same in every view: once, in the plan's `meta`.
    let plan_meta = json!({ "grid": p.grid.iter().map(|q| [q.x, q.y]).collect::<Vec<_>>() });
    Ok(Plan {
        method: "disco".into(),
        tick_hz: p.tick_hz,
        steps,
        frame_bytes: p.frame_bytes,
        meta: plan_meta,
        lost_retries: super::LOST_RETRIES,
    })
}
