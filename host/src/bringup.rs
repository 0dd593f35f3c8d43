//! Bringing a rig up: connect, recover what an earlier run left, upload the rig file's
//! configuration, home; and how long to wait for a device that went away.

use std::sync::Arc;

use lightrig_protocol::config::{AxisKind, HomingMode};
use lightrig_protocol::event::{Event, FaultCause};
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::Command;

use crate::acquire;
use crate::client::{describe_fault, fresh_nonce, Client, ClientError, Interrupt};
use crate::rigfile::{RigFile, Stepper};
use crate::transport::Transport;

/// Why a rig could not be brought up.
#[derive(Debug)]
pub enum BringUpError {
    /// The device could not be reached, refused, or failed (homing).
    Device(String),
    /// The rig file does not fit the device.
    RigFile(String),
    /// Bring-up ended on a client error that whoever drives it acts on by its kind: a stop
    /// asked for (Ctrl-C: [`ClientError::Interrupted`]), a fault that needs a person
    /// ([`ClientError::NeedsConfirmation`]).
    Client(ClientError),
}

impl std::fmt::Display for BringUpError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BringUpError::Device(m) | BringUpError::RigFile(m) => f.write_str(m),
            BringUpError::Client(e) => e.fmt(f),
        }
    }
}

/// A client error during bring-up: kept whole where its kind decides what happens next.
fn device(e: ClientError) -> BringUpError {
    match e {
        ClientError::Interrupted { .. } | ClientError::NeedsConfirmation { .. } => BringUpError::Client(e),
        other => BringUpError::Device(other.to_string()),
    }
}

impl std::error::Error for BringUpError {}

/// What bring-up asks of, and tells, whoever drives it.
pub trait BringUpHooks {
    /// What is happening, in words (homing can take minutes).
    fn say(&mut self, _what: &str) {}

    /// Whether the fault the device has latched may be cleared now. By default any but
    /// those that need a person's word ([`acquire::needs_a_person`]).
    fn may_clear(&mut self, cause: &FaultCause) -> bool {
        !acquire::needs_a_person(cause)
    }

    /// A stop request (Ctrl-C) the client is to obey from its connection on.
    fn interrupt(&self) -> Option<Arc<Interrupt>> {
        None
    }
}

/// Bring-up that says nothing and clears what needs no person.
pub struct Quiet;

impl BringUpHooks for Quiet {}

/// [`bring_up_with`], quietly.
pub fn bring_up_on(
    rig: &RigFile,
    transport: Box<dyn Transport>,
) -> Result<Client<Box<dyn Transport>>, BringUpError> {
    bring_up_with(rig, transport, &mut Quiet)
}

/// Connects over `transport`, readies a device an earlier run left mid-sequence or faulted
/// ([`acquire::recover`], asking `hooks` before clearing a fault), uploads the rig's
/// configuration, sets the heartbeat from the rig file's `[safety]`, and homes what has a
/// homing procedure. Events that arrive meanwhile stay queued on the client, for the session
/// to journal.
pub fn bring_up_with(
    rig: &RigFile,
    transport: Box<dyn Transport>,
    hooks: &mut dyn BringUpHooks,
) -> Result<Client<Box<dyn Transport>>, BringUpError> {
    let mut client = Client::connect(transport, fresh_nonce()).map_err(device)?;
    if let Some(i) = hooks.interrupt() {
        client.set_interrupt(i);
    }
    // A device an earlier run left mid-sequence or faulted takes no configuration until then.
    let found = acquire::recover(&mut client, &mut |c: &FaultCause| hooks.may_clear(c)).map_err(device)?;
    if let Some(sequence) = found.aborted {
        hooks.say(&format!("the device was still running sequence {sequence} of an earlier run: aborted"));
    }
    if let Some(cause) = found.cleared {
        hooks.say(&format!("the device had latched a fault: {}; cleared", describe_fault(&cause)));
    }
    // Events of what came before (the fault just cleared, an earlier run's homing) may still
    // be on their way: homing goes by the events after this.
    client.fence().map_err(device)?;
    if let Some(s) = &rig.safety {
        client.set_heartbeat_us((s.heartbeat_timeout_ms * 1000.0 / 4.0) as u64);
    }
    let items = rig.config_items(client.info()).map_err(|e| BringUpError::RigFile(e.to_string()))?;
    for item in items {
        client.request(Command::Configure(item)).map_err(device)?;
    }
    let mut homing: Vec<AxisRef> = rig
        .steppers
        .iter()
        .filter(|s| s.homing.mode != HomingMode::None)
        .map(|s| AxisRef::Stepper(s.axis))
        .chain(rig.filter_wheels.iter().map(|w| AxisRef::FilterWheel(w.wheel)))
        .collect();
    if homing.is_empty() {
        return Ok(client);
    }
    for &a in &homing {
        client.request(Command::Home(a)).map_err(device)?;
    }
    let deadline_us = homing_timeout_us(rig);
    let started = client.transport().now_us();
    let give_up = started.saturating_add(deadline_us);
    let names: Vec<String> = homing.iter().map(|a| axis_name(rig, a)).collect();
    hooks.say(&format!("homing {} (at most {:.0} s)", names.join(", "), deadline_us as f64 / 1e6));
    // Events stay queued (the session journals them); `seen` is how far this loop has read.
    let mut seen = 0;
    while !homing.is_empty() {
        let left = give_up.saturating_sub(client.transport().now_us());
        if !client.wait_for_events(seen, left).map_err(device)? {
            return Err(BringUpError::Device(format!(
                "homing did not finish within {:.0} s (1.5 × the longest seek at the rig file's homing speed, \
                 + 10 s): {} still homing; check the switches and the homing speed",
                deadline_us as f64 / 1e6,
                homing.iter().map(|a| axis_name(rig, a)).collect::<Vec<_>>().join(", ")
            )));
        }
        let e = client.queued()[seen].clone();
        seen += 1;
        if client.before_fence(&e) {
            continue;
        }
        match e.event {
            Event::Homed { axis, .. } if homing.contains(&axis) => {
                homing.retain(|a| *a != axis);
                let secs = client.transport().now_us().saturating_sub(started) as f64 / 1e6;
                hooks.say(&format!("homed {} after {secs:.1} s", axis_name(rig, &axis)));
            }
            Event::Fault { cause, .. } => {
                let advice = match cause {
                    FaultCause::HomingFailed { .. } | FaultCause::Limit { .. } => {
                        "; check the switches, their wiring and polarity in the rig file"
                    }
                    _ => "",
                };
                return Err(BringUpError::Device(format!(
                    "homing stopped: {}{advice}",
                    describe_fault(&cause)
                )));
            }
            _ => {}
        }
    }
    Ok(client)
}

/// An axis by its rig-file name, else by kind and number.
fn axis_name(rig: &RigFile, axis: &AxisRef) -> String {
    let named = match *axis {
        AxisRef::Stepper(i) => rig.steppers.iter().find(|s| s.axis == i).and_then(|s| s.name.clone()),
        AxisRef::FilterWheel(i) => {
            rig.filter_wheels.iter().find(|w| w.wheel == i).and_then(|w| w.name.clone())
        }
    };
    named.unwrap_or_else(|| match *axis {
        AxisRef::Stepper(i) => format!("stepper {i}"),
        AxisRef::FilterWheel(i) => format!("filter wheel {i}"),
    })
}

/// How long homing may take, µs: 1.5 × the longest seek (a linear axis' whole travel between
/// its limits, else 1 m, plus twice its back-off; two turns of a rotary axis or a filter wheel)
/// at the axis' homing speed, + 10 s. The axes home together.
pub fn homing_timeout_us(rig: &RigFile) -> u64 {
    let seek_s = |s: &Stepper| -> f64 {
        if s.homing.mode == HomingMode::None || s.homing.speed <= 0.0 {
            return 0.0;
        }
        let travel = match s.kind {
            AxisKind::Rotary => 720.0,
            AxisKind::Linear => s.limits.map_or(1000.0, |(lo, hi)| hi - lo),
        };
        (travel + 2.0 * s.homing.backoff.abs()) / s.homing.speed
    };
    // A wheel's max_speed is in rev/s.
    let wheels = rig.filter_wheels.iter().map(|w| 2.0 / w.max_speed.max(1e-3));
    let longest = rig.steppers.iter().map(seek_s).chain(wheels).fold(0.0, f64::max);
    ((1.5 * longest + 10.0) * 1e6).min(u64::MAX as f64 / 2.0) as u64
}

/// How many times `acquire` and `resume` try to get a lost device back, waiting 1, 2, 4, 8,
/// then 10 s before each: about 1.5 minutes to plug the cable back in.
pub const RECONNECT_ATTEMPTS: u32 = 12;

/// The wait before reconnection attempt `k` (1, 2, …), ms.
pub fn reconnect_backoff_ms(k: u32) -> u64 {
    1000u64.saturating_mul(1 << k.saturating_sub(1).min(4)).min(10_000)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn example(name: &str) -> RigFile {
        RigFile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs").join(name)).unwrap()
    }

    #[test]
    fn homing_may_take_one_and_a_half_seeks_plus_ten_seconds() {
        // Gantry: limits ±200 mm, back-off 2 mm, 20 mm/s: (400 + 4) / 20 = 20.2 s.
        assert_eq!(homing_timeout_us(&example("lls-gantry.toml")), 40_300_000);
        // Turntable seeking its index at 2 deg/s: two turns, 360 s.
        assert_eq!(homing_timeout_us(&example("fluorescent-immersion.toml")), 550_000_000);
    }

    #[test]
    fn reconnection_waits_double_up_to_ten_seconds() {
        let waits: Vec<u64> = (1..=7).map(reconnect_backoff_ms).collect();
        assert_eq!(waits, [1_000, 2_000, 4_000, 8_000, 10_000, 10_000, 10_000]);
        let total: u64 = (1..=RECONNECT_ATTEMPTS).map(reconnect_backoff_ms).sum();
        assert_eq!(total, 95_000);
    }
}
