//! BRDF display: voice coils under a liquid surface, fed sums of sines with prime frequency
//! ratios (so the ripple pattern never repeats and its slopes spread evenly), make the surface
//! reflect a chosen highlight; a wider slope distribution gives a rougher-looking highlight.
//!
//! One step per target highlight: ramp the coils to the target's partials, wait for the
//! surface to settle into its steady state, take the captures, and fade to silence (the device
//! fades a sequence's coils only on a fault, so the step does it explicitly).
//!
//! The partials come from [`ward_partials`]: a first model in which each partial contributes
//! an equal share of the slope variance and a partial's slope amplitude grows with its
//! frequency (dispersion ignored). The display pipeline calibrates the scale from captures.

use lightrig_protocol::sequence::{Action, Partial};
use lightrig_protocol::MAX_PARTIALS;
use serde_json::json;

use std::sync::Arc;

use super::{Plan, PlanError, Step};

/// Primes used as frequency ratios.
pub const PRIMES: [u32; MAX_PARTIALS] = [2, 3, 5, 7, 11, 13, 17, 19];

/// Partials for a Ward roughness `alpha` (RMS slope): frequencies `base_mhz · prime`, equal
/// slope variance per partial, amplitude `alpha · scale / (prime · √n)` as a fraction of full
/// scale, phases spread by the golden angle. `n` partials (≤ 8).
pub fn ward_partials(alpha: f64, base_mhz: u32, n: usize, scale: f64) -> Vec<Partial> {
    let n = n.clamp(1, MAX_PARTIALS);
    (0..n)
        .map(|i| {
            let prime = PRIMES[i];
            let a = alpha * scale / (f64::from(prime) * (n as f64).sqrt());
            Partial {
                freq_mhz: base_mhz.saturating_mul(prime),
                amplitude: (a.clamp(0.0, 1.0) * f64::from(u16::MAX)).round() as u16,
                phase: ((i as f64 * 0.381_966_011_250_105) * 65536.0) as u16,
            }
        })
        .collect()
}

/// One highlight to show.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// Name ("alpha 0.10").
    pub name: String,
    /// Partials per voice-coil channel.
    pub channels: Vec<(u8, Vec<Partial>)>,
}

/// Everything the display planner needs, in device units.
#[derive(Debug, Clone, PartialEq, Eq)]
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
        let meta = json!({ "target": target.name, "channels": channels });
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
        meta: serde_json::Value::Null,
    })
}
