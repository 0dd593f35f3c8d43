//! BRDF display: voice coils drive sums of sines with prime frequency ratios into a liquid
//! (one coil per axis; the waves travel across the surface), whose time-averaged slopes make
//! it reflect a chosen Ward-like highlight (thesis chapter 5).
//!
//! One step per target: ramp the coils to the target's partials, wait for the surface to
//! settle into its steady state, take the captures, and fade to silence (the device fades a
//! sequence's coils only on a fault, so the step does it explicitly).
//!
//! Targets come from [`calibration_targets`] (a still surface, then one sine per coil per step
//! at a known drive, sweeping the band the partials lie in: what `lightrig fit display` turns
//! into the coils' responses) or from
//! [`alpha_targets`] (Ward roughness per axis, solved through a calibration by
//! `lightrig_pipelines::display`), or as raw partials from the rig file's `[plan.patterns]`.

use lightrig_pipelines::display::mapping::golden_phase;
use lightrig_pipelines::display::{Calibration, DisplayError};
use lightrig_protocol::sequence::{Action, Partial};
use lightrig_protocol::MAX_PARTIALS;
use serde_json::json;

use std::sync::Arc;

use super::{Plan, PlanError, Step};

/// A partial at `f` Hz, `drive` of full scale, starting `phase` turns in. The amplitude is
/// rounded down: drives that sum to a coil's limit stay within it once quantised (the
/// controller refuses a sum above `max_amplitude`).
pub fn partial(f: f64, drive: f64, phase: f64) -> Partial {
    Partial {
        freq_mhz: (f * 1000.0).round().clamp(0.0, f64::from(u32::MAX)) as u32,
        amplitude: (drive.clamp(0.0, 1.0) * f64::from(u16::MAX)).floor() as u16,
        phase: (phase.rem_euclid(1.0) * 65536.0) as u16,
    }
}

/// The calibration: a still surface (the beam's own spread), then step `i` plays frequency `i`
/// of each axis' sweep alone on that axis' coil at `drive`. `axes`: each axis' coil channel and
/// sweep (`mapping::X_SWEEP`, `Y_SWEEP`; the shorter one sets the count).
pub fn calibration_targets(axes: &[(u8, Vec<f64>); 2], drive: f64) -> Vec<Target> {
    let mut out = vec![Target {
        name: "still".into(),
        channels: axes.iter().map(|(c, _)| (*c, Vec::new())).collect(),
        meta: json!({ "kind": "still" }),
    }];
    let n = axes[0].1.len().min(axes[1].1.len());
    for i in 0..n {
        let f = [axes[0].1[i], axes[1].1[i]];
        out.push(Target {
            name: format!("sines {} Hz x {} Hz", f[0], f[1]),
            channels: axes.iter().zip(f).map(|((c, _), f)| (*c, vec![partial(f, drive, 0.0)])).collect(),
            meta: json!({ "kind": "sine", "index": i, "frequencies_hz": f, "drive": drive }),
        });
    }
    out
}

/// Targets showing Ward roughness `(αx, αy)` each, solved through `cal` (asking, per axis, for
/// what the camera's earlier views say shows the target: [`AxisCalibration::asked_for`]), the
/// total slope's standard deviation bounded by `max_slope` rad.
///
/// [`AxisCalibration::asked_for`]: lightrig_pipelines::display::AxisCalibration::asked_for
pub fn alpha_targets(
    cal: &Calibration,
    alphas: &[[f64; 2]],
    max_slope: f64,
) -> Result<Vec<Target>, DisplayError> {
    let liquid = cal.liquid().map_err(DisplayError::UnknownLiquid)?;
    let axes = [cal.axes[0].axis("x", max_slope), cal.axes[1].axis("y", max_slope)];
    alphas
        .iter()
        .map(|a| {
            let asked = [cal.axes[0].asked_for(a[0]), cal.axes[1].asked_for(a[1])];
            let mut channels = Vec::new();
            for (k, axis) in axes.iter().enumerate() {
                // The range is the target's: an α the display reaches only by asking for more
                // than it can is refused as out of range.
                axis.solve(a[k], &liquid)?;
                let p = axis.solve(asked[k], &liquid).map_err(|e| match e {
                    DisplayError::OutOfRange { axis, max, limit, .. } => {
                        DisplayError::OutOfRange { axis, alpha: a[k], max: max * a[k] / asked[k], limit }
                    }
                    e => e,
                })?;
                let partials =
                    p.iter().enumerate().map(|(i, q)| partial(q.frequency, q.drive, golden_phase(i)));
                channels.push((cal.axes[k].channel, partials.collect()));
            }
            Ok(Target {
                name: format!("alpha {} x {}", a[0], a[1]),
                channels,
                meta: json!({ "kind": "display", "alpha": a, "asked": asked }),
            })
        })
        .collect()
}

/// Each axis' coil channel and the partials that show `alpha` through `cal` (what a live
/// display sends, `Immediate` `VoiceCoil` actions with a ramp).
pub fn partials_for(
    cal: &Calibration,
    alpha: [f64; 2],
    max_slope: f64,
) -> Result<Vec<(u8, Vec<Partial>)>, DisplayError> {
    Ok(alpha_targets(cal, &[alpha], max_slope)?.remove(0).channels)
}

/// `Immediate` actions that take each channel to its partials over `ramp` ticks (an empty
/// list fades the channel to silence).
pub fn coil_actions(channels: &[(u8, Vec<Partial>)], ramp: u32) -> Result<Vec<Action>, PlanError> {
    channels
        .iter()
        .map(|(channel, partials)| {
            let partials = heapless::Vec::from_slice(partials)
                .map_err(|_| PlanError(format!("voice coil {channel}: more than {MAX_PARTIALS} partials")))?;
            Ok(Action::VoiceCoil { channel: *channel, ramp, partials })
        })
        .collect()
}

/// One highlight to show.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// Name ("alpha 0.10").
    pub name: String,
    /// Partials per voice-coil channel.
    pub channels: Vec<(u8, Vec<Partial>)>,
    /// What the step shows, for the fit (merged into the step's `meta`).
    pub meta: serde_json::Value,
}

/// Everything the display planner needs, in device units.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplayParams {
    /// The highlights.
    pub targets: Vec<Target>,
    /// Amplitude ramp, ticks.
    pub ramp: u32,
    /// Time for the surface to settle after the ramp, ticks.
    pub settle: u32,
    /// Cameras, all fired at every capture (at least one).
    pub cameras: Vec<u8>,
    /// Captures per target.
    pub captures: u32,
    /// Exposure, ticks.
    pub exposure: u32,
    /// Trigger to trigger, ticks (at least the exposure: a frame never sees the next
    /// setting or the fade).
    pub frame_gap: u32,
    /// Bytes per frame.
    pub frame_bytes: u64,
    /// Device tick rate.
    pub tick_hz: u32,
    /// What the fit needs of the whole plan (the liquid, the screen's pitch); `Null` if none.
    pub meta: serde_json::Value,
}

/// The display plan: one step per target.
pub fn plan(p: &DisplayParams) -> Result<Plan, PlanError> {
    if p.targets.is_empty() || p.captures == 0 {
        return Err(PlanError("brdf-display: need at least one target and one capture".into()));
    }
    if p.cameras.is_empty() {
        return Err(PlanError("brdf-display: no camera to trigger".into()));
    }
    let shared = Arc::new(p.clone());
    let mut steps = Vec::new();
    for (t, target) in p.targets.iter().enumerate() {
        let mut settings = Vec::new();
        for (channel, partials) in &target.channels {
            let partials: heapless::Vec<Partial, MAX_PARTIALS> = heapless::Vec::from_slice(partials)
                .map_err(|_| PlanError(format!("brdf-display: {}: more than 8 partials", target.name)))?;
            settings.push((*channel, partials));
        }
        let channels: Vec<_> = target
            .channels
            .iter()
            .map(|(c, ps)| json!({ "channel": c, "partials": ps.iter().map(|q| [q.freq_mhz, u32::from(q.amplitude), u32::from(q.phase)]).collect::<Vec<_>>() }))
            .collect();
        let mut meta = json!({ "target": target.name, "channels": channels });
        if let Some(extra) = target.meta.as_object() {
            for (k, v) in extra {
                meta[k] = v.clone();
            }
        }
        let p = Arc::clone(&shared);
        steps.push(Step::new(t as u32, target.name.clone(), meta, move |b| {
            for (channel, partials) in &settings {
                b.then(Action::VoiceCoil { channel: *channel, ramp: p.ramp, partials: partials.clone() });
            }
            b.wait(p.ramp.saturating_add(p.settle));
            for k in 0..p.captures {
                b.shoot_all(&p.cameras, p.exposure, format!("capture {k}"));
                // The next capture, or the fade, only once this exposure has ended: the
                // frame must see the steady surface throughout.
                b.wait(p.frame_gap.max(p.exposure));
            }
            for (channel, _) in &settings {
                b.then(Action::VoiceCoil { channel: *channel, ramp: p.ramp, partials: heapless::Vec::new() });
            }
            b.wait(p.ramp);
        }));
    }
    Ok(Plan {
        method: "brdf-display".into(),
        tick_hz: p.tick_hz,
        steps,
        frame_bytes: p.frame_bytes,
        meta: p.meta.clone(),
        lost_retries: super::LOST_RETRIES,
    })
}
