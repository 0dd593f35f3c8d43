//! Fluorescent immersion range scanning (Hullin et al. 2008): the object sits in a tank of
//! fluorescent liquid; a galvo sweeps a laser sheet through the tank front to back, one frame
//! per sheet position; the sheet glows in the liquid and is cut off where it meets the object.
//!
//! One step per turntable orientation: turn, laser on and warm, then for every sheet position:
//! jump the sheet (blanked while the mirror settles), wait out the settle time, expose. A
//! calibration step first: a dark frame (laser off) and a sweep with the calibration target in
//! the tank (the operator places it; the step's `meta` says so).
//!
//! With known target positions ([`plan_with_targets`]) the calibration is what the pipeline's
//! per-pixel rays and sheet fit need: for each position (front to back of the volume) a
//! `target-board` step (one frame of the target under the lamp, laser off: its corners) and a
//! `target-sweep` step (a dark frame and the sweep: the glow cuts off on the target, which
//! gives the sheets). Each step's `meta.pose` carries the position as the operator typed it.

use lightrig_protocol::config::Xy;
use lightrig_protocol::sequence::{Action, WaitFor};
use serde_json::json;

use std::sync::Arc;

use super::{Plan, PlanError, Step, StepBuilder};

/// Everything the immersion planner needs, in device units.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImmersionParams {
    /// Turntable axis.
    pub turntable: u8,
    /// Turntable position of each orientation, steps.
    pub orientations: Vec<i32>,
    /// Sheet laser channel.
    pub laser: u8,
    /// Galvo pair; the sheet sweeps along X, Y stays at `sheet_y`.
    pub galvo: u8,
    /// Sweep: first X code, last X code, number of sheets (≥ 2).
    pub sweep: (u16, u16, u32),
    /// Fixed Y code.
    pub sheet_y: u16,
    /// Cameras, all fired at every sheet (at least one).
    pub cameras: Vec<u8>,
    /// Exposure per sheet, ticks.
    pub exposure: u32,
    /// Mirror settle time after a jump, ticks.
    pub settle: u32,
    /// Trigger to next jump, ticks.
    pub frame_gap: u32,
    /// Add the calibration step.
    pub calibration: bool,
    /// Longest a move or warm-up may take, ticks.
    pub timeout: u32,
    /// Bytes per frame.
    pub frame_bytes: u64,
    /// Device tick rate.
    pub tick_hz: u32,
}

/// X codes of the sheets: evenly spaced, exact integers, first and last included.
pub fn sheet_codes(from: u16, to: u16, n: u32) -> Vec<u16> {
    let (a, b) = (i64::from(from), i64::from(to));
    let d = i64::from(n.max(2)) - 1;
    (0..i64::from(n)).map(|k| (a + (b - a) * k / d) as u16).collect()
}

/// The immersion plan: calibration (optional), then one step per orientation.
pub fn plan(p: &ImmersionParams) -> Result<Plan, PlanError> {
    plan_with_targets(p, &[])
}

/// The immersion plan with a calibration target at each of `targets` (the operator's
/// description of each position, e.g. `{"z_mm": -12.0}`, copied into the steps' `meta.pose`),
/// front to back; with no targets (or `calibration` off) the same as [`plan`].
pub fn plan_with_targets(p: &ImmersionParams, targets: &[serde_json::Value]) -> Result<Plan, PlanError> {
    let (from, to, n) = p.sweep;
    if n < 2 || p.orientations.is_empty() {
        return Err(PlanError("immersion: need at least 2 sheets and 1 orientation".into()));
    }
    if p.frame_gap < p.exposure {
        return Err(PlanError("immersion: frame_gap is shorter than the exposure".into()));
    }
    if p.cameras.is_empty() {
        return Err(PlanError("immersion: no camera to trigger".into()));
    }
    let codes = sheet_codes(from, to, n);
    let shared = Arc::new((p.clone(), codes.clone()));
    let mut steps: Vec<Step> = Vec::new();
    let mut push = |name: String, meta: serde_json::Value, kind: StepKind| {
        let q = Arc::clone(&shared);
        let id = steps.len() as u32;
        steps.push(Step::new(id, name, meta, move |b| build(b, &q.0, &q.1, &kind)));
    };
    if p.calibration && !targets.is_empty() {
        for (k, pose) in targets.iter().enumerate() {
            let meta = json!({
                "kind": "calibration", "pass": "target-board", "target": k, "pose": pose,
                "operator": format!("remove the object; place the calibration target at position {k} ({pose}); lamp on"),
            });
            push(format!("calibration target {k}"), meta, StepKind::TargetBoard { k });
            let meta = json!({
                "kind": "calibration", "pass": "target-sweep", "target": k, "pose": pose,
                "codes": codes, "sheet_y": p.sheet_y,
                "operator": format!("target at position {k} ({pose}); lamp off"),
            });
            push(format!("calibration sweep {k}"), meta, StepKind::DarkAndSweep);
        }
    } else if p.calibration {
        let meta = json!({ "kind": "calibration", "operator": "place the calibration target in the tank", "codes": codes });
        push("calibration".into(), meta, StepKind::DarkAndSweep);
    }
    for (o, &angle) in p.orientations.iter().enumerate() {
        let meta = json!({ "kind": "scan", "pass": "scan", "orientation": o, "turntable": angle, "codes": codes, "sheet_y": p.sheet_y });
        push(format!("orientation {o}"), meta, StepKind::Scan { angle });
    }
    Ok(Plan {
        method: "fluorescent-immersion".into(),
        tick_hz: p.tick_hz,
        steps,
        frame_bytes: p.frame_bytes,
        meta: serde_json::Value::Null,
        lost_retries: super::LOST_RETRIES,
    })
}

/// What an immersion step does (its sequence is built by [`build`] when it runs).
#[derive(Debug, Clone, Copy)]
enum StepKind {
    /// The target under the lamp, laser off, at the first orientation.
    TargetBoard { k: usize },
    /// A dark frame and a calibration sweep, at the first orientation.
    DarkAndSweep,
    /// A scan sweep at turntable position `angle`.
    Scan { angle: i32 },
}

fn build(b: &mut StepBuilder, p: &ImmersionParams, codes: &[u16], kind: &StepKind) {
    let sweep = |b: &mut StepBuilder, tag: &str| {
        b.then(Action::Laser { channel: p.laser, on: true });
        b.until(WaitFor::LaserReady(p.laser), p.timeout);
        for (k, &x) in codes.iter().enumerate() {
            b.then(Action::GalvoPoint { galvo: p.galvo, to: Xy { x, y: p.sheet_y } });
            b.wait(p.settle);
            b.shoot_all(&p.cameras, p.exposure, format!("{tag} sheet {k}"));
            b.wait(p.frame_gap);
        }
        b.then(Action::Laser { channel: p.laser, on: false });
    };
    match *kind {
        StepKind::TargetBoard { k } => {
            b.move_to(p.turntable, p.orientations[0], p.timeout);
            b.then(Action::Laser { channel: p.laser, on: false });
            b.shoot_all(&p.cameras, p.exposure, format!("target {k}"));
            b.wait(p.frame_gap);
        }
        StepKind::DarkAndSweep => {
            b.move_to(p.turntable, p.orientations[0], p.timeout);
            b.shoot_all(&p.cameras, p.exposure, "dark");
            b.wait(p.frame_gap);
            sweep(b, "calibration");
        }
        StepKind::Scan { angle } => {
            b.move_to(p.turntable, angle, p.timeout);
            sweep(b, "scan");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lightrig_protocol::sequence::Action;

    fn params() -> ImmersionParams {
        ImmersionParams {
            turntable: 0,
            orientations: vec![0, 100],
            laser: 0,
            galvo: 0,
            sweep: (1000, 2000, 6),
            sheet_y: 32768,
            cameras: vec![0],
            exposure: 100,
            settle: 10,
            frame_gap: 200,
            calibration: true,
            timeout: 1_000_000,
            frame_bytes: 1,
            tick_hz: 1_000_000,
        }
    }

    #[test]
    fn each_target_position_gets_a_board_frame_and_a_sweep() {
        let poses = [json!({ "z_mm": -12.0 }), json!({ "z_mm": 8.0 })];
        let p = plan_with_targets(&params(), &poses).unwrap();
        // Board + (dark + sweep) per target, then the two orientations.
        assert_eq!(p.steps.len(), 2 * 2 + 2);
        assert_eq!(p.summary().triggers, 2 * (1 + 1 + 6) + 2 * 6);
        for (k, pose) in poses.iter().enumerate() {
            let (board, sweep) = (&p.steps[2 * k], &p.steps[2 * k + 1]);
            assert_eq!(board.meta["pass"], "target-board");
            assert_eq!(sweep.meta["pass"], "target-sweep");
            assert_eq!((&board.meta["pose"], &sweep.meta["pose"]), (pose, pose));
            assert_eq!(board.meta["target"], k);
            assert_eq!(board.shot_count(), 1);
            assert_eq!(sweep.shots().len(), 7);
            // The board frame is taken with the laser off.
            let items = board.items();
            assert!(items.iter().any(|i| matches!(i.action, Action::Laser { on: false, .. })));
            assert!(!items.iter().any(|i| matches!(i.action, Action::Laser { on: true, .. })));
        }
        assert_eq!(p.steps[4].meta["pass"], "scan");
        // Step ids are the plan order.
        assert!(p.steps.iter().enumerate().all(|(i, s)| s.id == i as u32));
        // Without targets: the single calibration step as before.
        let old = plan_with_targets(&params(), &[]).unwrap();
        assert_eq!(old, super::plan(&params()).unwrap());
        assert_eq!(old.steps.len(), 3);
    }
}
