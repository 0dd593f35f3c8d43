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

pub mod brrdf;
pub mod disco;
pub mod display;
pub mod firs;
pub mod from_rig;
pub mod lls;

use lightrig_protocol::sequence::{Action, AxisRef, Item, Profile, WaitFor};
use std::sync::Arc;

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
///
/// A step keeps what it is (id, name, `meta`, duration, trigger counts) and *how to build* its
/// items and shots, not the items themselves: those are built when the step runs
/// ([`Step::items`], [`Step::body`]) and dropped after. A full DISCO plan (72 views × 64² spots
/// × 3 lasers, 885 k triggers) would otherwise hold about 200 MB of items and labels before its
/// first frame; planned lazily it holds its step heads only (`host/tests/plan_memory.rs`).
#[derive(Clone, Serialize)]
pub struct Step {
    /// Stable id within the plan (the session journal refers to steps by it).
    pub id: u32,
    /// Human-readable name ("view 3", "pass laser").
    pub name: String,
    /// Duration if every wait ends at once, ticks: a lower bound.
    pub min_ticks: u64,
    /// Triggers per camera, cameras in the order of their first trigger.
    pub triggers: Vec<(u8, u32)>,
    /// Laser channels the step switches on (bit `n`: channel `n`), for arming.
    pub lasers: u8,
    /// Method-specific description of the step, for the pipeline.
    pub meta: serde_json::Value,
    /// Builds the items and shots, without the closing marker.
    #[serde(skip)]
    make: Arc<dyn Fn(&mut StepBuilder) + Send + Sync>,
    /// For a step whose content the acquisition decides when it gets there (the PCA-steered
    /// bispectral plan's chosen pairs): gives the step to run, from the session directory.
    #[serde(skip)]
    resolve: Option<Resolver>,
}

/// Decides a step when the acquisition reaches it: the session directory in, the step to run
/// (same id, trigger counts and lasers) or why not out.
pub type Resolver = Arc<dyn Fn(&std::path::Path) -> Result<Step, String> + Send + Sync>;

/// A step's sequence, built: its items and the triggers they fire.
#[derive(Debug, Clone, PartialEq)]
pub struct Body {
    /// The sequence items, ending with `Marker { id }`.
    pub items: Vec<Item>,
    /// The triggers, in the order they fire.
    pub shots: Vec<Shot>,
}

impl Step {
    /// A step whose sequence `make` builds, now once (for the duration and trigger counts) and
    /// again each time the step runs. `make` must build the same sequence every time: it is a
    /// plain function of what it captures.
    pub fn new(
        id: u32,
        name: impl Into<String>,
        meta: serde_json::Value,
        make: impl Fn(&mut StepBuilder) + Send + Sync + 'static,
    ) -> Step {
        let mut b = StepBuilder::default();
        make(&mut b);
        let min_ticks = b.ticks + u64::from(b.pending_delta);
        let mut triggers: Vec<(u8, u32)> = Vec::new();
        for shot in &b.shots {
            match triggers.iter_mut().find(|(c, _)| *c == shot.camera) {
                Some((_, n)) => *n += 1,
                None => triggers.push((shot.camera, 1)),
            }
        }
        let lasers = b.items.iter().fold(0u8, |mask, i| match i.action {
            Action::Laser { channel, on: true } => mask | 1u8.checked_shl(u32::from(channel)).unwrap_or(0),
            _ => mask,
        });
        Step { id, name: name.into(), min_ticks, triggers, lasers, meta, make: Arc::new(make), resolve: None }
    }

    /// This step, decided when the acquisition reaches it by `resolve` (see [`Resolver`]).
    pub fn resolved_by(mut self, resolve: Resolver) -> Step {
        self.resolve = Some(resolve);
        self
    }

    /// The step to run: this one, or what its resolver decides for the session in `dir`. A
    /// decision that changes the step's id, triggers or lasers is refused.
    pub fn resolve(&self, dir: &std::path::Path) -> Result<Option<Step>, String> {
        let Some(r) = &self.resolve else { return Ok(None) };
        let step = r(dir)?;
        if step.id != self.id || step.triggers != self.triggers || step.lasers != self.lasers {
            return Err(format!(
                "step {} ({}): its resolved form fires other triggers or lasers than planned",
                self.id, self.name
            ));
        }
        Ok(Some(step))
    }

    /// The step's items and shots, built now.
    pub fn body(&self) -> Body {
        let mut b = StepBuilder::default();
        (self.make)(&mut b);
        b.then(Action::Marker { id: self.id });
        Body { items: b.items, shots: b.shots }
    }

    /// The sequence items, built now; the last is `Marker { id }`, after any pending delay, so
    /// a delay after the last trigger (exposure, readout) still separates this step from the
    /// next.
    pub fn items(&self) -> Vec<Item> {
        self.body().items
    }

    /// The triggers, in firing order, built now.
    pub fn shots(&self) -> Vec<Shot> {
        self.body().shots
    }

    /// How many triggers the step fires, all cameras together.
    pub fn shot_count(&self) -> usize {
        self.triggers.iter().map(|&(_, n)| n as usize).sum()
    }
}

impl std::fmt::Debug for Step {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Step")
            .field("id", &self.id)
            .field("name", &self.name)
            .field("min_ticks", &self.min_ticks)
            .field("triggers", &self.triggers)
            .field("lasers", &self.lasers)
            .field("meta", &self.meta)
            .finish_non_exhaustive()
    }
}

/// Steps are equal when they say the same and build the same sequence.
impl PartialEq for Step {
    fn eq(&self, other: &Step) -> bool {
        self.id == other.id
            && self.name == other.name
            && self.min_ticks == other.min_ticks
            && self.triggers == other.triggers
            && self.lasers == other.lasers
            && self.meta == other.meta
            && self.body() == other.body()
    }
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
    /// Method-specific description shared by every step (DISCO's spot grid), for the
    /// pipeline; `Null` if none.
    pub meta: serde_json::Value,
    /// How often a step whose camera lost some of its frames is acquired again at once, before
    /// its lost frames are recorded missing ([`LOST_RETRIES`] unless the rig file's `[plan]
    /// lost_frame_retries` says otherwise).
    pub lost_retries: u32,
}

/// A step that lost frames (a GigE Vision frame short of packets, a trigger the camera missed)
/// is acquired again up to twice: a loss that repeats three times in a row is no accident of
/// the wire, and is recorded for a person to look at.
pub const LOST_RETRIES: u32 = 2;

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
        let triggers: usize = self.steps.iter().map(Step::shot_count).sum();
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

    /// Fires every camera in `cameras` on the same tick (in that order, one item each), all
    /// with `exposure` ticks: one frame of the same scene state from each camera.
    pub fn shoot_all(&mut self, cameras: &[u8], exposure: u32, label: impl Into<String>) -> &mut Self {
        let label = label.into();
        for &camera in cameras {
            self.shoot(camera, exposure, label.clone());
        }
        self
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
