//! Pairing a step's camera triggers with the frames a frame source delivered.
//!
//! A pure function: no I/O, no clock. Frames are matched to triggers by camera and frame number
//! (`TriggerEvent::frame`: the count of triggers on that camera since the sequence started).

use std::collections::HashMap;

use lightrig_protocol::event::TriggerEvent;
use serde::{Deserialize, Serialize};

use crate::client::EventRecord;
use lightrig_protocol::Event;

/// A camera trigger as the pairing needs it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Trigger {
    /// Sequence the trigger item belongs to.
    pub sequence: u32,
    /// Index of the trigger item within the sequence.
    pub item: u32,
    /// Camera output.
    pub camera: u8,
    /// Frame number on this camera, from 0 at the sequence start.
    pub frame: u32,
    /// Device tick of the leading edge.
    pub tick: u64,
    /// Host time of the tick (µs), if the clock was mapped.
    pub host_us: Option<f64>,
}

impl Trigger {
    /// From a trigger event and its host time.
    pub fn from_event(t: &TriggerEvent, host_us: Option<f64>) -> Self {
        Trigger {
            sequence: t.sequence,
            item: t.item,
            camera: t.camera,
            frame: t.frame,
            tick: t.tick,
            host_us,
        }
    }

    /// From an event as the client delivers it, if it is a trigger.
    pub fn from_record(e: &EventRecord) -> Option<Self> {
        match &e.event {
            Event::Trigger(t) => Some(Self::from_event(t, e.host_us)),
            _ => None,
        }
    }
}

/// A frame that arrived from a frame source.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// Camera it came from.
    pub camera: u8,
    /// Its frame number counted from the sequence start, when the source reports one; `None`:
    /// numbered by arrival order among this camera's arrivals (0, 1, …), which cannot tell a
    /// dropped frame from a late one.
    pub frame: Option<u32>,
    /// Host time it arrived (µs, on the same clock as [`Trigger::host_us`]).
    pub host_us: f64,
}

/// A trigger and its frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pair {
    /// The trigger.
    pub trigger: Trigger,
    /// Index of the frame in the arrivals.
    pub arrival: usize,
    /// When the frame arrived (µs).
    pub arrived_us: f64,
    /// Arrival minus the trigger's host time (µs), when the trigger has one.
    pub delay_us: Option<f64>,
    /// The frame arrived more than the tolerance after its trigger. It is still paired.
    pub late: bool,
}

/// Why a frame has no trigger.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ExtraReason {
    /// An earlier frame already answered this trigger.
    Duplicate,
    /// No trigger of this step has the frame's camera and number.
    NoTrigger,
    /// The camera made it before the step began: a straggler of an earlier attempt (its
    /// `frame` is the camera's own number). Never paired (format 3).
    BeforeStep,
}

/// A frame without a trigger.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extra {
    /// Index of the frame in the arrivals.
    pub arrival: usize,
    /// Its camera.
    pub camera: u8,
    /// Its frame number (reported, or from arrival order).
    pub frame: u32,
    /// When it arrived (µs).
    pub arrived_us: f64,
    /// Why it is extra.
    pub reason: ExtraReason,
}

/// The outcome of [`pair`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pairing {
    /// Triggers with their frame, in trigger order.
    pub pairs: Vec<Pair>,
    /// Triggers without a frame, in trigger order.
    pub missing: Vec<Trigger>,
    /// Frames without a trigger, in arrival order.
    pub extra: Vec<Extra>,
}

impl Pairing {
    /// The pairs whose frame came late.
    pub fn late(&self) -> impl Iterator<Item = &Pair> {
        self.pairs.iter().filter(|p| p.late)
    }
}

/// Pairs `triggers` with `arrivals` by (camera, frame number). The first arrival for a trigger
/// wins; a later one for the same trigger is a [`ExtraReason::Duplicate`], one matching no
/// trigger is [`ExtraReason::NoTrigger`]. A trigger matched by no arrival is missing. A pair is
/// late when the frame arrived more than `tolerance_us` after the trigger's host time (never
/// when the trigger has no host time). A trigger repeating an earlier one's camera and frame
/// number (the device never sends one) is ignored.
pub fn pair(triggers: &[Trigger], arrivals: &[Arrival], tolerance_us: f64) -> Pairing {
    // (camera, frame) -> first arrival index, and every arrival's resolved number.
    let mut first: HashMap<(u8, u32), usize> = HashMap::new();
    let mut order: HashMap<u8, u32> = HashMap::new();
    let mut numbers = Vec::with_capacity(arrivals.len());
    for (i, a) in arrivals.iter().enumerate() {
        let seen = order.entry(a.camera).or_insert(0);
        let n = a.frame.unwrap_or(*seen);
        *seen += 1;
        numbers.push(n);
        first.entry((a.camera, n)).or_insert(i);
    }
    let mut out = Pairing::default();
    let mut used: HashMap<(u8, u32), bool> = HashMap::new();
    for t in triggers {
        let key = (t.camera, t.frame);
        if used.contains_key(&key) {
            continue;
        }
        used.insert(key, first.contains_key(&key));
        match first.get(&key) {
            Some(&i) => {
                let arrived_us = arrivals[i].host_us;
                let delay_us = t.host_us.map(|h| arrived_us - h);
                let late = delay_us.is_some_and(|d| d > tolerance_us);
                out.pairs.push(Pair { trigger: *t, arrival: i, arrived_us, delay_us, late });
            }
            None => out.missing.push(*t),
        }
    }
    for (i, a) in arrivals.iter().enumerate() {
        let key = (a.camera, numbers[i]);
        let reason = match used.get(&key) {
            Some(true) if first[&key] == i => continue,
            Some(true) => ExtraReason::Duplicate,
            _ => ExtraReason::NoTrigger,
        };
        out.extra.push(Extra { arrival: i, camera: a.camera, frame: key.1, arrived_us: a.host_us, reason });
    }
    out
}
