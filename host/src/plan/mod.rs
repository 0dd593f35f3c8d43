//! Acquisition planners: each rig's capture procedure as device sequences.
//!
//! A [`Plan`] is a list of [`Step`]s. A step is the unit of acquisition and of resumption: one
//! device sequence that starts from a known state (axes moved to absolute positions, lasers
//! switched explicitly), so that re-running it after a crash gives the same frames. Each step
//! says which triggers it fires, so frames can be paired with their purpose, and the pipelines
//! read the step's `meta` to know what each frame shows.
//!
//! Planners work in device units (ticks, steps, codes); the rig file converts human units
//! before a planner sees them. Planners are plain functions of their parameters: no device, no
//! I/O, so they are tested alone and their output is deterministic.

pub mod bispectral;
pub mod brdf_display;
pub mod disco;
pub mod from_rig;
pub mod immersion;
pub mod lls;

use lightrig_protocol::sequence::{Action, AxisRef, Item, Profile, WaitFor};
use serde::Serialize;

/// One trigger a step fires, in firing order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Shot {
    /// Camera.
    pub camera: u8,
    /// What the frame shows, for the pipeline (e.g. `"pos 12"`, `"laser 1 point 3,4"`).
    pub label: String,
}

/// A unit of acquisition: one device sequence.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Step {
    /// Stable id within the plan (the session journal refers to steps by it).
    pub id: u32,
    /// Human-readable name ("view 3", "pass laser").
    pub name: String,
    /// The sequence items.
    #[serde(skip)]
    pub items: Vec<Item>,
    /// The triggers, in the order they fire.
    pub shots: Vec<Shot>,
    /// Duration if every wait ends at once, ticks: a lower bound.
    pub min_ticks: u64,
    /// Method-specific description of the step, for the pipeline.
    pub meta: serde_json::Value,
}

/// A whole acquisition.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Plan {
    /// Method name.
    pub method: String,
    /// Device tick rate the plan was made for.
    pub tick_hz: u32,
    /// The steps, in order.
    pub steps: Vec<Step>,
    /// Bytes per frame, for the data-volume estimate.
    pub frame_bytes: u64,
}

/// What a plan will cost, reported before it runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Summary {
    /// Steps.
    pub steps: usize,
    /// Triggers (= frames expected).
    pub triggers: usize,
    /// Expected duration (lower bound: waits counted as zero), µs.
    pub min_duration_us: u64,
    /// Data volume, bytes.
    pub bytes: u64,
}

impl Plan {
    /// Totals, for the user to confirm before running.
    pub fn summary(&self) -> Summary {
        let triggers: usize = self.steps.iter().map(|s| s.shots.len()).sum();
        let ticks: u64 = self.steps.iter().map(|s| s.min_ticks).sum();
        let us = u128::from(ticks) * 1_000_000 / u128::from(self.tick_hz.max(1));
        Summary {
            steps: self.steps.len(),
            triggers,
            min_duration_us: u64::try_from(us).unwrap_or(u64::MAX),
            bytes: triggers as u64 * self.frame_bytes,
        }
    }
}

/// Builds a step's items with running time bookkeeping.
#[derive(Debug, Default)]
pub struct StepBuilder {
    items: Vec<Item>,
    shots: Vec<Shot>,
    ticks: u64,
    pending_delta: u32,
    /// Axes this step has already waited on.
    settled: Vec<AxisRef>,
}

impl StepBuilder {
    /// Adds an action `delta` ticks after the previous one (plus any pending delay).
    pub fn at(&mut self, delta: u32, action: Action) -> &mut Self {
        let delta = delta.saturating_add(std::mem::take(&mut self.pending_delta));
        self.ticks += u64::from(delta);
        self.items.push(Item { delta, action });
        self
    }

    /// Adds an action right after the previous one.
    pub fn then(&mut self, action: Action) -> &mut Self {
        self.at(0, action)
    }

    /// Makes the next action come `ticks` later.
    pub fn wait(&mut self, ticks: u32) -> &mut Self {
        self.pending_delta = self.pending_delta.saturating_add(ticks);
        self
    }

    /// Waits for a condition (the next action's delta counts from when it holds).
    pub fn until(&mut self, until: WaitFor, timeout: u32) -> &mut Self {
        self.then(Action::Wait { until, timeout })
    }

    /// Waits until `axis` is at rest, the first time the step uses it: a step runs from a
    /// known state even right after an aborted one whose axes are still decelerating.
    pub fn settle(&mut self, axis: AxisRef, timeout: u32) -> &mut Self {
        if !self.settled.contains(&axis) {
            self.settled.push(axis);
            self.until(WaitFor::MoveDone(axis), timeout);
        }
        self
    }

    /// Moves a stepper and waits until it is there.
    pub fn move_to(&mut self, axis: u8, target: i32, timeout: u32) -> &mut Self {
        self.settle(AxisRef::Stepper(axis), timeout);
        self.then(Action::StepperMove { axis, target, profile: Profile::default() });
        self.until(WaitFor::MoveDone(AxisRef::Stepper(axis)), timeout)
    }

    /// Fires camera `camera` with `exposure` ticks and records what the frame shows.
    pub fn shoot(&mut self, camera: u8, exposure: u32, label: impl Into<String>) -> &mut Self {
        self.then(Action::Trigger { camera, exposure });
        self.shots.push(Shot { camera, label: label.into() });
        self
    }

    /// The finished step. It ends with a `Marker { id }` after any pending delay, so a delay
    /// after the last trigger (exposure, readout) still separates this step from the next.
    pub fn build(mut self, id: u32, name: impl Into<String>, meta: serde_json::Value) -> Step {
        self.then(Action::Marker { id });
        Step { id, name: name.into(), items: self.items, shots: self.shots, min_ticks: self.ticks, meta }
    }
}

/// Why a plan cannot be made.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlanError(pub String);

impl std::fmt::Display for PlanError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for PlanError {}
