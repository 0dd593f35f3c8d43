//! The acquisition engine: runs a [`Plan`] on a device, step by step, journaling everything to
//! a [`Session`] as it happens, pairing every frame with its trigger.
//!
//! A step is atomic. For each pending step the engine opens a new attempt in the journal,
//! streams the step's sequence, journals each device event as it arrives, waits for the
//! step's frames, pairs them with the triggers (missing, duplicate and late frames are
//! recorded as such), stores them, and closes the attempt. An attempt whose camera lost some of
//! its frames is abandoned and the step run again at once, up to [`Plan::lost_retries`] times,
//! before its lost frames are recorded missing. Anything that stops a step midway
//! (a device fault, an unplug, the host dying) leaves the attempt open or abandoned; `resume`
//! runs the step again as the next attempt, so the finished session holds exactly one frame
//! (or one `FrameMissing`) per planned trigger.

use std::io;

use lightrig_protocol::event::{DeviceState, FaultCause, TriggerEvent};
use lightrig_protocol::sequence::StartAt;
use lightrig_protocol::{Command, Event, Reply};

use crate::client::{Client, ClientError};
use crate::frames::{DirectorySource, Pattern};
use crate::plan::{Plan, Step};
use crate::session::{pair, Arrival, CameraTriggers, Extra, ExtraReason, Pairing, PlanStep, PlanSummary};
use crate::session::{CameraStamp, Session, SessionError};
use crate::session::{StepId, Trigger};
use crate::transport::Transport;

/// A frame as a source delivers it.
#[derive(Debug, Clone, PartialEq)]
pub struct Captured {
    /// Camera.
    pub camera: u8,
    /// Frame number counted from the step's start on this camera, if the source knows it (for
    /// a frame made [`Self::before_step`], the camera's own number, for the record).
    pub frame: Option<u32>,
    /// File extension to store it under (`png`, `exr`, `pgm`…).
    pub ext: String,
    /// The file's bytes.
    pub data: Vec<u8>,
    /// Host time of arrival, µs on the transport's clock.
    pub host_us: f64,
    /// The source knows the frame was made before the step began (a straggler of an earlier
    /// attempt): kept as an extra, never paired.
    pub before_step: bool,
    /// The camera's own frame id and timestamp, if it gives them (stored with the frame).
    pub stamp: Option<CameraStamp>,
}

/// Where a camera's frames come from. Inputs are `Send`: the engine polls them on another
/// thread while it keeps a real-time device's link alive ([`Client::busy`]).
pub trait FrameInput: Send {
    /// A step is about to start: frames from now on count from 0.
    fn begin_step(&mut self, step: &Step) -> io::Result<()>;
    /// The device fired a trigger (a rendering camera renders it here).
    fn on_trigger(&mut self, _trigger: &TriggerEvent, _host_us: Option<f64>) -> io::Result<()> {
        Ok(())
    }
    /// Frames that arrived since the last call.
    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>>;
    /// Frames ready now, without waiting or reading anything slow: called while a sequence
    /// runs (the link is not kept alive meanwhile), for those watching the run. A source that
    /// cannot answer so quickly gives none; its frames come from [`Self::poll`] after the
    /// sequence as always.
    fn poll_now(&mut self, _now_us: f64) -> io::Result<Vec<Captured>> {
        Ok(Vec::new())
    }
    /// Triggers heard and not yet worked through (a source making its frames on a thread of
    /// its own): after a step's sequence its frames are waited for while this shrinks, however
    /// long past [`FRAME_WAIT_US`], until it has not shrunk for [`STUCK_US`].
    fn backlog(&self) -> usize {
        0
    }
    /// Whether its frames' timestamps follow the trigger ticks (a camera triggered by the
    /// controller's line, stamping each frame by its own clock): the engine then checks each
    /// step's frames against their triggers' ticks, and acquires a step again when the stamps
    /// say some were paired with the wrong trigger ([`crate::session::off_their_triggers`]).
    fn stamps_follow_triggers(&self) -> bool {
        false
    }
    /// Frames of the current step the source knows it lost, `(camera, frame, why)` (a camera
    /// that delivered a frame incomplete): their missing records say why. Taken once.
    fn lost(&mut self) -> Vec<(u8, u32, String)> {
        Vec::new()
    }
}

/// What a step asks of the host before its sequence runs, in words: a person's action
/// (`meta.operator`: place the board, turn the light's mount) and the settings of instruments
/// the host drives rather than the device (`meta.host`: the bispectral rig's tunable filters).
/// Empty if it asks for nothing.
pub fn step_requests(step: &Step) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(op) = step.meta.get("operator").and_then(|o| o.as_str()) {
        out.push(op.to_string());
    }
    if let Some(host) = step.meta.get("host").and_then(|h| h.as_object()) {
        for (k, v) in host {
            let k = k.replace('_', " ");
            out.push(match k.strip_suffix(" nm") {
                Some(what) => format!("set the {what} to {v} nm"),
                None => format!("set {k} to {v}"),
            });
        }
    }
    out
}

/// Carries out (or has a person carry out) a step's [`step_requests`] before its sequence
/// runs. A refusal stops the run before the step starts: the session stays resumable. It runs
/// on another thread while the engine keeps a real-time device's link alive (a person may take
/// minutes), with the lasers disarmed.
pub trait StepPreparation: Send {
    /// Prepares `step`; returns who did it (the journal's `StepPrepared.by`), or why not.
    /// Called only for steps that ask for something.
    fn prepare(&mut self, step: &Step, requests: &[String]) -> Result<String, String>;
}

/// Preparation that takes every request as done: the virtual rig (its instruments follow the
/// step's `meta`) and tests.
pub struct Unattended(pub &'static str);

impl StepPreparation for Unattended {
    fn prepare(&mut self, _step: &Step, _requests: &[String]) -> Result<String, String> {
        Ok(self.0.to_string())
    }
}

/// A camera whose software writes numbered files into a directory.
///
/// A step's frame 0 is the first file written after the step began. A file the camera wrote
/// before (a straggler of an attempt that was cut short, a test shot) would otherwise take
/// that place and shift every pairing of the step by one: it is handed over marked
/// [`Captured::before_step`], and the session keeps it as an extra (`BeforeStep`). A file is
/// from before the step if it was in the directory when the step began, or if its
/// modification time is older than the step by the directory's own clock: at each step's
/// start a mark file is written there and its modification time read back, so a network
/// share's clock or a file system's coarse timestamps (FAT: 2 s) never make a frame of the
/// step look older than the step.
pub struct DirectoryInput {
    camera: u8,
    dir: std::path::PathBuf,
    source: DirectorySource,
    ext: String,
    /// File number of the step's first frame.
    base: Option<u64>,
    /// When the step began, on the directory's clock.
    began: Option<std::time::SystemTime>,
    /// Files (not yet reported) that were there when the step began.
    there_before: std::collections::HashSet<std::path::PathBuf>,
}

/// The mark file [`DirectoryInput`] writes (and removes) to read the directory's clock.
pub const STEP_MARK: &str = ".lightrig-step-mark";

impl DirectoryInput {
    /// Watches `dir` for `pattern` (e.g. `img_{frame:06}.png`) for `camera`.
    pub fn new(camera: u8, dir: &std::path::Path, pattern: &str) -> Result<Self, String> {
        let ext =
            pattern.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase()).unwrap_or_else(|| "raw".into());
        let pattern = Pattern::parse(pattern)?;
        let source = DirectorySource::new(dir, pattern).map_err(|e| format!("{}: {e}", dir.display()))?;
        Ok(Self {
            camera,
            dir: dir.to_path_buf(),
            source,
            ext,
            base: None,
            began: None,
            there_before: Default::default(),
        })
    }

    /// Now on the directory's clock: the modification time of a file written there now. A
    /// directory the host cannot write to falls back on the host's clock.
    fn directory_now(&self) -> std::time::SystemTime {
        let mark = self.dir.join(STEP_MARK);
        let written = std::fs::write(&mark, b"").and_then(|()| std::fs::metadata(&mark)?.modified());
        let _ = std::fs::remove_file(&mark);
        written.unwrap_or_else(|_| std::time::SystemTime::now())
    }
}

impl FrameInput for DirectoryInput {
    fn begin_step(&mut self, _step: &Step) -> io::Result<()> {
        // The camera numbers its files on; the step's first file written from now on is its
        // frame 0.
        self.base = None;
        self.there_before = self.source.unreported()?;
        self.began = Some(self.directory_now());
        Ok(())
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        let mut out = Vec::new();
        for a in self.source.poll()? {
            let data = std::fs::read(&a.path)?;
            let before_step = self.there_before.remove(&a.path)
                || matches!((a.modified, self.began), (Some(w), Some(b)) if w < b);
            let frame = if before_step {
                u32::try_from(a.frame).ok()
            } else {
                let base = *self.base.get_or_insert(a.frame);
                a.frame.checked_sub(base).and_then(|f| u32::try_from(f).ok())
            };
            out.push(Captured {
                camera: self.camera,
                frame,
                ext: self.ext.clone(),
                data,
                host_us: now_us,
                before_step,
                stamp: None,
            });
        }
        Ok(out)
    }
}

/// Several cameras' inputs as one: every input hears every step and trigger (each keeps to its
/// own camera), and the frames of all of them are collected together; pairing goes by camera
/// and frame number.
pub struct Cameras(pub Vec<Box<dyn FrameInput>>);

impl FrameInput for Cameras {
    fn begin_step(&mut self, step: &Step) -> io::Result<()> {
        self.0.iter_mut().try_for_each(|c| c.begin_step(step))
    }

    fn on_trigger(&mut self, trigger: &TriggerEvent, host_us: Option<f64>) -> io::Result<()> {
        self.0.iter_mut().try_for_each(|c| c.on_trigger(trigger, host_us))
    }

    fn poll_now(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        let mut out = Vec::new();
        for c in &mut self.0 {
            out.extend(c.poll_now(now_us)?);
        }
        Ok(out)
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        let mut out = Vec::new();
        for c in &mut self.0 {
            out.extend(c.poll(now_us)?);
        }
        Ok(out)
    }

    fn lost(&mut self) -> Vec<(u8, u32, String)> {
        self.0.iter_mut().flat_map(|c| c.lost()).collect()
    }

    fn backlog(&self) -> usize {
        self.0.iter().map(|c| c.backlog()).sum()
    }

    fn stamps_follow_triggers(&self) -> bool {
        // The step's stamps are checked when every camera stamps by its trigger line.
        !self.0.is_empty() && self.0.iter().all(|c| c.stamps_follow_triggers())
    }
}

/// A frame input that works on its own thread, as a real camera does: the virtual camera
/// rendering a frame (tens of ms in a release build, far more in a debug one) or a source
/// reading large files then never holds up the link loop, whose heartbeats keep a real
/// controller from faulting (`HeartbeatLost`) while the frames are made.
///
/// Calls reach the inner input in order. `on_trigger` returns at once (its error, if any,
/// comes back from a later `poll`); `poll` hands over what the thread has produced so far,
/// waiting at most [`Background::POLL_WAIT`] for the answer to this call; `begin_step` waits
/// until every earlier call is done, and drops frames the thread produced for no one (an
/// attempt cut short), as the contract of `begin_step` says.
pub struct Background {
    /// Triggers sent to the thread.
    sent: usize,
    /// Triggers the thread had worked through when it made the latest answer taken in: the
    /// backlog is `sent - answered`, so it reaches 0 only once the frames of every trigger
    /// sent have been handed over, never between the thread's work and its answer.
    answered: std::cell::Cell<usize>,
    calls: Option<std::sync::mpsc::Sender<Call>>,
    results: std::sync::mpsc::Receiver<(Answer, usize)>,
    worker: Option<std::thread::JoinHandle<()>>,
}

enum Call {
    Begin(Step),
    Trigger(TriggerEvent, Option<f64>),
    Poll(f64),
}

enum Answer {
    Begun(io::Result<()>),
    Frames(io::Result<Vec<Captured>>),
}

impl Background {
    /// How long `poll` waits for the thread's answer before returning what it has.
    pub const POLL_WAIT: std::time::Duration = std::time::Duration::from_millis(20);

    /// Runs `inner` on a new thread.
    pub fn new(mut inner: Box<dyn FrameInput + Send>) -> Background {
        let (calls, inbox) = std::sync::mpsc::channel::<Call>();
        let (outbox, results) = std::sync::mpsc::channel::<(Answer, usize)>();
        let worker = std::thread::spawn(move || {
            // Triggers worked through, sent with every answer.
            let mut handled = 0;
            for call in inbox {
                let answer = match call {
                    Call::Begin(step) => {
                        let r = inner.poll(f64::NEG_INFINITY).and_then(|_stale| inner.begin_step(&step));
                        Answer::Begun(r)
                    }
                    Call::Trigger(t, host_us) => {
                        handled += 1;
                        match inner.on_trigger(&t, host_us) {
                            Ok(()) => continue,
                            Err(e) => Answer::Frames(Err(e)),
                        }
                    }
                    Call::Poll(now_us) => Answer::Frames(inner.poll(now_us)),
                };
                if outbox.send((answer, handled)).is_err() {
                    return;
                }
            }
        });
        Background { sent: 0, answered: 0.into(), calls: Some(calls), results, worker: Some(worker) }
    }

    fn send(&self, call: Call) -> io::Result<()> {
        self.calls
            .as_ref()
            .and_then(|c| c.send(call).ok())
            .ok_or_else(|| io::Error::other("the frame source's thread has stopped (it panicked?)"))
    }

    /// The next answer within `wait`, its count of triggers handled taken in.
    fn receive(&self, wait: std::time::Duration) -> Option<Answer> {
        let (answer, handled) = self.results.recv_timeout(wait).ok()?;
        self.answered.set(handled);
        Some(answer)
    }

    /// Takes the answers in, appending frames to `out`; the first error wins. Waits up to
    /// `wait` for the first one.
    fn gather(&self, out: &mut Vec<Captured>, wait: std::time::Duration) -> io::Result<()> {
        let mut first = self.receive(wait);
        let mut error = None;
        while let Some(answer) = first.take().or_else(|| self.receive(std::time::Duration::ZERO)) {
            match answer {
                Answer::Frames(Ok(v)) => out.extend(v),
                Answer::Frames(Err(e)) | Answer::Begun(Err(e)) => {
                    error.get_or_insert(e);
                }
                Answer::Begun(Ok(())) => {}
            }
        }
        error.map_or(Ok(()), Err)
    }
}

impl FrameInput for Background {
    fn begin_step(&mut self, step: &Step) -> io::Result<()> {
        self.send(Call::Begin(step.clone()))?;
        // Everything sent before is answered before `Begun`: drop those frames, keep errors.
        let mut error = None;
        loop {
            match self.receive(std::time::Duration::MAX) {
                Some(Answer::Begun(r)) => return error.map_or(r, Err),
                Some(Answer::Frames(Err(e))) => {
                    error.get_or_insert(e);
                }
                Some(Answer::Frames(Ok(_))) => {}
                None => return Err(io::Error::other("the frame source's thread has stopped (it panicked?)")),
            }
        }
    }

    fn on_trigger(&mut self, trigger: &TriggerEvent, host_us: Option<f64>) -> io::Result<()> {
        self.send(Call::Trigger(trigger.clone(), host_us))?;
        self.sent += 1;
        Ok(())
    }

    fn backlog(&self) -> usize {
        self.sent - self.answered.get()
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        self.send(Call::Poll(now_us))?;
        let mut out = Vec::new();
        self.gather(&mut out, Self::POLL_WAIT)?;
        Ok(out)
    }

    fn poll_now(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        // What the thread answered to earlier calls; this one's answer comes with a later call.
        self.send(Call::Poll(now_us))?;
        let mut out = Vec::new();
        self.gather(&mut out, std::time::Duration::ZERO)?;
        Ok(out)
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        // Closing the channel ends the thread's loop once it has finished its work.
        drop(self.calls.take());
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

/// What went wrong in an acquisition; each says what to do next.
#[derive(Debug)]
pub enum AcquireError {
    /// The device or the link failed; the step in progress was abandoned.
    Device(ClientError),
    /// The session could not be written.
    Session(SessionError),
    /// The frame source failed.
    Frames(io::Error),
    /// A step's preparation was refused or could not be done; the step did not start.
    Preparation(String),
}

impl std::fmt::Display for AcquireError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AcquireError::Device(e) => {
                write!(f, "{e}\nThe step in progress was abandoned; `lightrig resume` acquires it again.")
            }
            AcquireError::Session(e) => write!(f, "session: {e}"),
            AcquireError::Frames(e) => write!(f, "frame source: {e}"),
            AcquireError::Preparation(e) => {
                write!(f, "{e}\nNothing of that step was acquired; `lightrig resume` continues from it.")
            }
        }
    }
}

impl std::error::Error for AcquireError {}

impl From<SessionError> for AcquireError {
    fn from(e: SessionError) -> Self {
        AcquireError::Session(e)
    }
}

/// The session's view of a plan: steps with their triggers per camera, and each step's `meta`.
pub fn plan_summary(plan: &Plan) -> PlanSummary {
    PlanSummary {
        steps: plan
            .steps
            .iter()
            .map(|s| PlanStep {
                id: s.id,
                name: s.name.clone(),
                triggers: s
                    .triggers
                    .iter()
                    .map(|&(camera, count)| CameraTriggers { camera, count })
                    .collect(),
                extra: serde_json::json!({ "meta": s.meta }),
            })
            .collect(),
        extra: if plan.meta.is_null() {
            serde_json::json!({ "method": plan.method, "tick_hz": plan.tick_hz })
        } else {
            serde_json::json!({ "method": plan.method, "tick_hz": plan.tick_hz, "meta": plan.meta })
        },
    }
}

/// Progress of a run, for a progress bar.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Progress {
    /// Steps done (including earlier runs).
    pub steps_done: usize,
    /// Steps in the plan.
    pub steps: usize,
    /// Frames stored in this run (a step's frames are stored, paired, when it ends).
    pub frames: u64,
    /// Frames of the running step received and not yet stored.
    pub received: u64,
    /// Bytes of the frames stored in this run.
    pub bytes: u64,
    /// The plan's time for the work this run has done and has left, µs: each step's
    /// [`Step::min_ticks`] (every wait ending at once), the running step's split by its
    /// triggers. Their ratio to the time taken gives the time left at the run's own pace.
    pub planned_done_us: u64,
    pub planned_left_us: u64,
    /// Triggers fired in this run, the running step's included: progress within a step (a
    /// DISCO view is 12 288 frames).
    pub triggered: u64,
    /// Triggers of the steps this run had to do when it began.
    pub to_trigger: u64,
    /// Frames recorded missing in this run (in steps stored with them, after their retries).
    pub missing: u64,
    /// A step just stored with frames missing: which, and why, in words (to warn at once).
    pub missing_now: Option<String>,
}

impl Progress {
    /// The time left, s, `elapsed_s` into the run's steps, and whether it is the plan's bound
    /// rather than an estimate: the plan's time for the work left scaled by the pace so far
    /// (the plan's times are lower bounds, every wait ending at once); before any planned work
    /// is done, the plan's bound itself.
    pub fn time_left_s(&self, elapsed_s: f64) -> (f64, bool) {
        let left_s = self.planned_left_us as f64 / 1e6;
        if self.planned_done_us > 0 && elapsed_s > 0.0 {
            (left_s * elapsed_s / (self.planned_done_us as f64 / 1e6), false)
        } else {
            (left_s, true)
        }
    }
}

/// How long to wait for a step's next frame after its sequence ended, µs: the step's frames
/// are complete when every trigger has one, or when none has come for this long.
pub const FRAME_WAIT_US: u64 = 2_000_000;
/// A frame later than this after its trigger is flagged late (still paired), µs.
pub const LATE_US: f64 = 1_000_000.0;
/// A frame source whose backlog ([`FrameInput::backlog`]) has not shrunk for this long is
/// taken as stuck, µs.
pub const STUCK_US: u64 = 30_000_000;
/// While a sequence runs and someone watches, frames are looked for this often, µs of host time.
const LOOK_EVERY_US: f64 = 100_000.0;

/// Device sequence id of a step attempt: unique within a session.
pub fn sequence_id(step: StepId, attempt: u32) -> u32 {
    step.wrapping_mul(1_000).wrapping_add(attempt)
}

/// Runs every step the session has not finished, taking what steps ask of the host as done
/// ([`Unattended`]: the virtual rig, tests). Returns when the session is done.
pub fn run<T: Transport>(
    client: &mut Client<T>,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
    progress: impl FnMut(Progress),
) -> Result<(), AcquireError> {
    run_prepared(client, session, plan, input, &mut Unattended("virtual"), progress)
}

/// [`run`], with `prep` carrying out each step's [`step_requests`] before the step starts.
pub fn run_prepared<T: Transport>(
    client: &mut Client<T>,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
    prep: &mut dyn StepPreparation,
    mut progress: impl FnMut(Progress),
) -> Result<(), AcquireError> {
    // Every session write outside the link loop goes through `busy`: an fsync on a slow disk
    // must not hold up a real-time device's heartbeat.
    let info = *client.info();
    client.busy(|| session.device_connected(&info))?;
    // What arrived since the connection (an earlier run's last events, a fault from while no
    // host was there, homing) is journaled before anything else.
    let events = client.take_events();
    client.busy(|| events.iter().try_for_each(|e| session.record_event(e).map(|_| ())))?;
    recover(client, &mut |c: &FaultCause| !needs_a_person(c)).map_err(AcquireError::Device)?;
    // Faults cleared by asking the device's status (at bring-up or just now): their event may
    // have gone to an earlier host.
    let cleared = client.take_cleared();
    client.busy(|| {
        cleared.iter().try_for_each(|c| session.fault_cleared(info.boot_id, c, needs_a_person(c)))
    })?;
    if let Some(live) = client.live() {
        live.started();
    }
    let result = run_steps(client, session, plan, input, prep, &mut progress);
    if result.is_err() {
        // Whatever stopped the run, the lasers are left disarmed where the device still
        // listens (a device that went away disarms itself when the heartbeat lapses).
        let _ = client.request(Command::Disarm);
    }
    result
}

fn run_steps<T: Transport>(
    client: &mut Client<T>,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
    prep: &mut dyn StepPreparation,
    progress: &mut impl FnMut(Progress),
) -> Result<(), AcquireError> {
    let lasers = lasers_used(plan);
    let live = client.live().cloned();
    let armed = |mask: u8| {
        if let Some(l) = &live {
            l.lasers(mask)
        }
    };
    if lasers != 0 {
        client.request(Command::Arm { lasers }).map_err(AcquireError::Device)?;
        armed(lasers);
    }
    let mut progress = |p: Progress| {
        if let Some(l) = &live {
            l.progress(&p);
        }
        progress(p)
    };
    let total = plan.steps.len();
    let mut frames = 0u64;
    let done_before = session.steps_done();
    let to_trigger: u64 = plan
        .steps
        .iter()
        .filter(|s| !done_before.contains(&s.id))
        .flat_map(|s| s.triggers.iter().map(|t| u64::from(t.1)))
        .sum();
    let (mut triggered, mut missing, mut bytes) = (0u64, 0u64, 0u64);
    let us_of = |ticks: u64| (u128::from(ticks) * 1_000_000 / u128::from(plan.tick_hz.max(1))) as u64;
    let planned_us: u64 =
        plan.steps.iter().filter(|s| !done_before.contains(&s.id)).map(|s| us_of(s.min_ticks)).sum();
    let mut planned_done_us = 0u64;
    if let Some(l) = &live {
        // Those watching see the run's size before its first trigger.
        l.progress(&Progress {
            steps_done: done_before.len(),
            steps: total,
            frames,
            received: 0,
            bytes,
            planned_done_us,
            planned_left_us: planned_us,
            triggered,
            to_trigger,
            missing,
            missing_now: None,
        });
    }
    for (number, step) in plan.steps.iter().enumerate() {
        if session.steps_done().contains(&step.id) {
            continue;
        }
        if let Some(l) = live.as_ref().filter(|l| l.pause_requested()) {
            pause_here(client, l, lasers)?;
        }
        // A step decided now (the PCA-steered plan's chosen pairs), from what the session holds.
        let dir = session.dir().to_path_buf();
        let decided = client.busy(|| step.resolve(&dir)).map_err(AcquireError::Preparation)?;
        let step = decided.as_ref().unwrap_or(step);
        let requests = step_requests(step);
        let prepared_by = if requests.is_empty() {
            None
        } else {
            // A person may be at the rig: lasers disarmed until they are done, the link kept
            // alive meanwhile so the device does not time the host out.
            client.request(Command::Disarm).map_err(AcquireError::Device)?;
            armed(0);
            let done = client.busy(|| prep.prepare(step, &requests));
            let by = done.map_err(AcquireError::Preparation)?;
            if lasers != 0 {
                client.request(Command::Arm { lasers }).map_err(AcquireError::Device)?;
                armed(lasers);
            }
            Some(by)
        };
        let steps_done = session.steps_done().len();
        let step_start = triggered;
        let (step_us, step_shots) = (us_of(step.min_ticks), step.shot_count().max(1) as u64);
        let mut within = |n: u64, received: u64| {
            triggered = step_start + n;
            let done = planned_done_us + step_us * n.min(step_shots) / step_shots;
            progress(Progress {
                steps_done,
                steps: total,
                frames,
                received,
                bytes,
                planned_done_us: done,
                planned_left_us: planned_us.saturating_sub(done),
                triggered,
                to_trigger,
                missing,
                missing_now: None,
            });
        };
        let mut prepared = prepared_by.map(|by| (by, requests));
        let mut tries = 0;
        let stored = loop {
            let retry = tries < plan.lost_retries;
            let place = (number + 1, total);
            match run_step(client, session, step, place, input, prepared.take(), retry, &mut within)? {
                Stepped::Stored(stored) => break stored,
                // Its lost frames are acquired again with the whole step: the triggers count
                // from the step's start.
                Stepped::Lost => tries += 1,
            }
        };
        if let Some(l) = &live {
            l.step_stored();
        }
        frames += stored.frames;
        bytes += stored.bytes;
        planned_done_us += step_us;
        missing += stored.missing.len() as u64;
        let missing_now = (!stored.missing.is_empty()).then(|| missing_words(step, &stored.missing));
        // A step's shots all fired (an abandoned attempt's are not counted twice).
        triggered = step_start + step.triggers.iter().map(|t| u64::from(t.1)).sum::<u64>();
        progress(Progress {
            steps_done: session.steps_done().len(),
            steps: total,
            frames,
            received: 0,
            bytes,
            planned_done_us,
            planned_left_us: planned_us.saturating_sub(planned_done_us),
            triggered,
            to_trigger,
            missing,
            missing_now,
        });
    }
    client.request(Command::Disarm).map_err(AcquireError::Device)?;
    armed(0);
    client.busy(|| session.finish())?;
    Ok(())
}

/// A pause asked for by those watching the run ([`crate::live::Live::pause`]), at a step
/// boundary: lasers disarmed, the link kept alive, until a resume (lasers armed again) or a
/// stop (the client's interrupt ends the wait with `Interrupted`).
fn pause_here<T: Transport>(
    client: &mut Client<T>,
    live: &crate::live::Live,
    lasers: u8,
) -> Result<(), AcquireError> {
    client.request(Command::Disarm).map_err(AcquireError::Device)?;
    live.lasers(0);
    live.set_paused(true);
    while live.pause_requested() {
        if !client.transport().runs_alone() {
            // A device whose time waits for the host: wait in real time here instead.
            live.wait_unpaused(std::time::Duration::from_millis(50));
        }
        client.idle(50_000).map_err(AcquireError::Device)?;
    }
    live.set_paused(false);
    if lasers != 0 {
        client.request(Command::Arm { lasers }).map_err(AcquireError::Device)?;
        live.lasers(lasers);
    }
    Ok(())
}

/// Whether clearing the latched fault `cause` needs a person's word first: an opened laser
/// interlock (an enclosure door, a key switch) means someone may be at the beam; an emergency
/// stop (Ctrl-C, `lightrig stop`, the board's stop input) means someone wanted the rig
/// stopped, and no program may undo that on its own.
pub fn needs_a_person(cause: &FaultCause) -> bool {
    matches!(cause, FaultCause::Interlock { .. } | FaultCause::EmergencyStop)
}

/// What [`recover`] found on the device and did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Recovered {
    /// The sequence an earlier run left running: aborted.
    pub aborted: Option<u32>,
    /// The fault that was latched: cleared.
    pub cleared: Option<FaultCause>,
}

/// Readies a device a run was cut short on (host crash, unplug): stops the sequence it may
/// still be running and clears a latched fault if `may_clear` allows (else fails with
/// [`ClientError::NeedsConfirmation`], the fault still latched). Lasers stay disarmed until a
/// run arms them.
pub fn recover<T: Transport>(
    client: &mut Client<T>,
    may_clear: &mut dyn FnMut(&FaultCause) -> bool,
) -> Result<Recovered, ClientError> {
    let mut found = Recovered::default();
    if let Reply::Status(s) = client.request(Command::GetStatus)? {
        match s.state {
            DeviceState::Running { sequence } => {
                client.request(Command::SequenceAbort { sequence })?;
                found.aborted = Some(sequence);
            }
            DeviceState::Faulted(cause) => {
                if !may_clear(&cause) {
                    return Err(ClientError::NeedsConfirmation {
                        device: client.transport().describe(),
                        cause,
                    });
                }
                client.request(Command::ClearFault)?;
                client.note_cleared(cause);
                found.cleared = Some(cause);
            }
            DeviceState::AwaitingHello | DeviceState::Ready => {}
        }
    }
    Ok(found)
}

/// Whether `e` means the link to the device was lost (cable pulled, port gone, the device
/// timed the host out or restarted), rather than the device refusing or faulting on what it
/// was asked.
pub fn is_link_loss(e: &ClientError) -> bool {
    matches!(
        e,
        ClientError::Io { .. }
            | ClientError::Timeout { .. }
            | ClientError::SessionLost { .. }
            | ClientError::Fault { cause: FaultCause::HeartbeatLost, .. }
    )
}

/// [`run_prepared`] that rides out a lost device: when the link is lost mid-run
/// ([`is_link_loss`]) the step in progress is abandoned as always, then `reconnect` is called
/// (attempt 1, 2, … up to `attempts`; the first call gets the old transport, to replug it;
/// the closure does its own waiting between attempts) until it gives a connected, configured
/// client, and the run goes on from that step. Every frame is still stored exactly once:
/// the abandoned attempt is superseded and the step runs again. `notify` hears what happens.
#[allow(clippy::too_many_arguments)]
pub fn run_reconnecting<T: Transport>(
    mut client: Client<T>,
    reconnect: &mut dyn FnMut(Option<T>, u32) -> Result<Client<T>, ClientError>,
    attempts: u32,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
    prep: &mut dyn StepPreparation,
    mut progress: impl FnMut(Progress),
    mut notify: impl FnMut(&str),
) -> Result<(), AcquireError> {
    loop {
        let lost = match run_prepared(&mut client, session, plan, input, prep, &mut progress) {
            // A stop asked for while the link failed: the run ends here, never reconnects.
            Err(AcquireError::Device(e)) if is_link_loss(&e) && client.interrupted().is_some() => {
                let answered = client.interrupted().is_some_and(|i| i.answered());
                let device = client.transport().describe();
                return Err(AcquireError::Device(ClientError::Interrupted { device, answered }));
            }
            Err(AcquireError::Device(e)) if is_link_loss(&e) => e,
            other => return other,
        };
        notify(&format!("device lost: {lost}"));
        let live = client.live().cloned();
        if let Some(l) = &live {
            l.device(crate::live::DeviceState::Lost, Some(lost.to_string()));
        }
        let mut old = Some(client.into_transport());
        let mut last = lost;
        let mut back = None;
        for k in 1..=attempts {
            match reconnect(old.take(), k) {
                Ok(c) => {
                    back = Some(c);
                    break;
                }
                // A stop asked for meanwhile, or a fault that needs a person: trying again
                // cannot help.
                Err(e @ (ClientError::Interrupted { .. } | ClientError::NeedsConfirmation { .. })) => {
                    return Err(AcquireError::Device(e));
                }
                Err(e) => {
                    notify(&format!("reconnection {k}/{attempts} failed: {e}"));
                    last = e;
                }
            }
        }
        match back {
            Some(c) => {
                notify("device back; going on from the interrupted step");
                client = c;
                if let Some(l) = live {
                    if client.live().is_none() {
                        client.set_live(l);
                    }
                }
            }
            None => return Err(AcquireError::Device(last)),
        }
    }
}

fn lasers_used(plan: &Plan) -> u8 {
    plan.steps.iter().fold(0, |mask, s| mask | s.lasers)
}

/// How an attempt at a step ended.
enum Stepped {
    /// Done: its frames stored, the frames it lost recorded missing.
    Stored(Stored),
    /// Abandoned because it lost frames: to be acquired again.
    Lost,
}

/// One attempt of one step. With `retry`, an attempt that lost some of its frames (not all: a
/// camera that delivers none is miswired, not unlucky) is abandoned instead of stored.
#[allow(clippy::too_many_arguments)]
fn run_step<T: Transport>(
    client: &mut Client<T>,
    session: &mut Session,
    step: &Step,
    (number, of): (usize, usize),
    input: &mut dyn FrameInput,
    prepared: Option<(String, Vec<String>)>,
    retry: bool,
    triggered: &mut dyn FnMut(u64, u64),
) -> Result<Stepped, AcquireError> {
    let attempt = session.next_attempt(step.id);
    let seq = sequence_id(step.id, attempt);
    let live = client.live().cloned();
    // Frames still on their way from an attempt that was cut short belong to nobody now: drain
    // them, and below ignore anything stamped before this attempt began.
    let start_us = client.transport().now_us() as f64;
    // A camera's work between steps (a directory of files to look through, a GenICam camera
    // taking its new settings) keeps the link alive as every other wait of the host does.
    let _stale = client.busy(|| input.poll(start_us)).map_err(AcquireError::Frames)?;
    client.busy(|| {
        session.start_step(step.id, seq)?;
        match prepared {
            Some((by, actions)) => session.step_prepared(&by, actions),
            None => Ok(()),
        }
    })?;
    client.busy(|| input.begin_step(step)).map_err(AcquireError::Frames)?;
    if let Some(l) = &live {
        l.step_started(number, of, step, attempt, seq);
    }
    // Built now, dropped when the attempt ends: a plan holds no step's items for long.
    let items = step.items();
    let mut triggers = Vec::new();
    let mut arrivals: Vec<Captured> = Vec::new();
    let mut failure: Option<AcquireError> = None;
    // Sequence ids repeat across host sessions: an earlier session's triggers of the same id
    // (still queued on the device) are stamped before this tick (docs/protocol.md §6.4).
    let fence = client.fence().map_err(AcquireError::Device)?;
    // Frames are looked for while the sequence runs only for those watching it: quickly
    // ([`FrameInput::poll_now`]) on a device in real time, whose link must not wait; fully on
    // one whose time waits for the host.
    let mut looked_us = start_us;
    let waits_for_us = !client.transport().runs_alone();
    let result = client.run_sequence(seq, items, StartAt::Now, |e| {
        if failure.is_some() {
            return;
        }
        if let Err(err) = session.record_event(e) {
            failure = Some(err.into());
            return;
        }
        if let Event::Trigger(t) = &e.event {
            if t.sequence == seq && t.tick >= fence {
                triggers.push(Trigger::from_event(t, e.host_us));
                triggered(triggers.len() as u64, arrivals.len() as u64);
                if let Err(err) = input.on_trigger(t, e.host_us) {
                    failure = Some(AcquireError::Frames(err));
                    return;
                }
                if let Some(l) = &live {
                    l.triggered(Trigger::from_event(t, e.host_us));
                    let now = e.host_us.unwrap_or(looked_us);
                    if now >= looked_us + LOOK_EVERY_US {
                        looked_us = now;
                        let got = if waits_for_us { input.poll(now) } else { input.poll_now(now) };
                        match got {
                            Ok(got) => {
                                let fresh: Vec<Captured> =
                                    got.into_iter().filter(|c| c.host_us >= start_us).collect();
                                l.arrived(&fresh);
                                arrivals.extend(fresh);
                            }
                            Err(err) => failure = Some(AcquireError::Frames(err)),
                        }
                    }
                }
            }
        }
    });
    if let Some(l) = &live {
        l.sequence_done();
    }
    if let Some(f) = failure {
        return Err(f);
    }
    if let Err(e) = result {
        // The device is in its safe state (or gone): this attempt is void.
        let why = e.to_string();
        client.busy(|| session.abandon_step(&why))?;
        return Err(AcquireError::Device(e));
    }
    // Collect the frames: until every trigger has one, or none has come for FRAME_WAIT_US (a
    // camera still delivering a backlog is given the time it needs).
    let expected = step.shot_count();
    let mut wait_until = client.transport().now_us() + FRAME_WAIT_US;
    // A source still working through the step's triggers (a camera rendering or converting
    // on its own thread, slower than the trigger rate) is waited for as long as it gets on.
    let mut backlog = (input.backlog(), client.transport().now_us());
    loop {
        let now = client.transport().now_us() as f64;
        let before = arrivals.len();
        // Reading whole files may take a while: the link stays alive meanwhile.
        let polled = client.busy(|| input.poll(now)).map_err(AcquireError::Frames)?;
        let fresh: Vec<Captured> = polled.into_iter().filter(|c| c.host_us >= start_us).collect();
        if let Some(l) = &live {
            l.arrived(&fresh);
        }
        arrivals.extend(fresh);
        let at = client.transport().now_us();
        if arrivals.len() > before {
            wait_until = at + FRAME_WAIT_US;
            // The frames are counted as they come, not only when the step is stored.
            triggered(triggers.len() as u64, arrivals.len() as u64);
        }
        let busy = input.backlog();
        if busy < backlog.0 {
            backlog = (busy, at);
        }
        let working = busy > 0 && at < backlog.1 + STUCK_US;
        if arrivals.len() >= expected || at >= wait_until && !working {
            break;
        }
        client.idle(10_000).map_err(AcquireError::Device)?;
    }
    // Frames made before the step began are no frames of it: the others are paired, those
    // kept as extras.
    arrivals.sort_by_key(|c| c.before_step);
    let fresh = arrivals.iter().take_while(|c| !c.before_step);
    let numbered: Vec<Arrival> =
        fresh.map(|c| Arrival { camera: c.camera, frame: c.frame, host_us: c.host_us }).collect();
    let mut pairing = pair(&triggers, &numbered, LATE_US);
    for (i, c) in arrivals.iter().enumerate().skip(numbered.len()) {
        let reason = ExtraReason::BeforeStep;
        let frame = c.frame.unwrap_or(0);
        pairing.extra.push(Extra { arrival: i, camera: c.camera, frame, arrived_us: c.host_us, reason });
    }
    let lost = input.lost();
    if retry && !pairing.pairs.is_empty() {
        // Stamps first: a trigger the camera missed also leaves the last trigger without a
        // frame, but the stamps name where the frames shifted.
        let shifted = if input.stamps_follow_triggers() { shifted_reason(&pairing, &arrivals) } else { None };
        let why =
            shifted.or_else(|| (!pairing.missing.is_empty()).then(|| lost_reason(&pairing, &lost, expected)));
        if let Some(why) = why {
            client.busy(|| session.abandon_step(&why))?;
            return Ok(Stepped::Lost);
        }
    }
    let mut lost = lost;
    if input.stamps_follow_triggers() {
        // The last try: the camera's clock pairs what its numbering shifted.
        let stamps: Vec<Option<u64>> = arrivals.iter().map(|c| c.stamp.map(|s| s.time_ns)).collect();
        for (camera, frame) in crate::session::repair_by_stamps(&mut pairing, &stamps) {
            let why = "the camera missed this trigger: by its timestamps it made no frame for it".to_string();
            lost.push((camera, frame, why));
        }
    }
    // Each frame is written and fsynced with its record (hundreds in a pass): the link stays
    // alive meanwhile.
    client.busy(|| store(session, &pairing, &arrivals, &lost)).map(Stepped::Stored)
}

/// Why an attempt that lost frames is acquired again, for its `StepAbandoned` record: how
/// many, and the first few by camera and frame with the reason the source gave.
fn lost_reason(pairing: &Pairing, lost: &[(u8, u32, String)], expected: usize) -> String {
    let named: Vec<String> = pairing
        .missing
        .iter()
        .take(3)
        .map(|m| {
            let why =
                lost.iter().find(|(c, f, _)| (*c, *f) == (m.camera, m.frame)).map(|(_, _, w)| w.as_str());
            format!(
                "camera {} frame {}: {}",
                m.camera,
                m.frame,
                why.unwrap_or("no frame arrived within the wait")
            )
        })
        .collect();
    let more = pairing.missing.len().saturating_sub(named.len());
    let more = if more > 0 { format!("; {more} more") } else { String::new() };
    format!(
        "{LOST_PREFIX} {} of {expected} frames ({}{more}): the step is acquired again",
        pairing.missing.len(),
        named.join("; ")
    )
}

/// Per camera, the paired frames whose timestamps put them off their triggers' ticks (a
/// trigger the camera missed shifts the frames after it onto the trigger before their own):
/// the reason to acquire the step again, or `None` if every stamp agrees.
fn shifted_reason(pairing: &Pairing, arrivals: &[Captured]) -> Option<String> {
    let mut cameras: Vec<u8> = pairing.pairs.iter().map(|p| p.trigger.camera).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let mut named = Vec::new();
    for cam in cameras {
        let mut stamped: Vec<(u32, u64, u64)> = pairing
            .pairs
            .iter()
            .filter(|p| p.trigger.camera == cam)
            .filter_map(|p| arrivals[p.arrival].stamp.map(|s| (p.trigger.frame, p.trigger.tick, s.time_ns)))
            .collect();
        stamped.sort_unstable();
        let pts: Vec<(u64, u64)> = stamped.iter().map(|s| (s.1, s.2)).collect();
        let off = crate::session::off_their_triggers(&pts);
        if let Some(&(k, r)) = off.first() {
            named.push(format!(
                "camera {cam}: {} frames off their triggers' ticks by the camera's clock, from frame {} ({:+.1} ms)",
                off.len(),
                stamped[k].0,
                r / 1e6
            ));
        }
    }
    (!named.is_empty()).then(|| {
        format!(
            "{LOST_PREFIX} the pairing of {} (a trigger the camera missed shifts the frames after it): the step is acquired again",
            named.join("; ")
        )
    })
}

/// How the reason of an attempt abandoned for its lost frames begins.
pub const LOST_PREFIX: &str = "lost";

/// A stored step attempt: the frames stored, and those recorded missing with why.
struct Stored {
    frames: u64,
    bytes: u64,
    missing: Vec<(u8, u32, String)>,
}

/// A step's missing frames in words: how many, the first few by camera and frame with why.
fn missing_words(step: &Step, missing: &[(u8, u32, String)]) -> String {
    let named: Vec<String> =
        missing.iter().take(3).map(|(c, f, why)| format!("camera {c} frame {f}: {why}")).collect();
    let more = missing.len().saturating_sub(named.len());
    let more = if more > 0 { format!("; {more} more") } else { String::new() };
    format!(
        "step {} ({}): {} of {} frames missing ({}{more})",
        step.id,
        step.name,
        missing.len(),
        step.shot_count(),
        named.join("; ")
    )
}

/// Stores a step attempt's paired frames, records the missing ones and the extra ones, and
/// closes the attempt; returns the frames stored.
fn store(
    session: &mut Session,
    pairing: &Pairing,
    arrivals: &[Captured],
    lost: &[(u8, u32, String)],
) -> Result<Stored, AcquireError> {
    let mut stored = Stored { frames: 0, bytes: 0, missing: Vec::new() };
    for p in &pairing.pairs {
        let c = &arrivals[p.arrival];
        session.store_frame_stamped(p, &c.ext, &c.data, c.stamp)?;
        stored.frames += 1;
        stored.bytes += c.data.len() as u64;
    }
    for m in &pairing.missing {
        let why = lost.iter().find(|(c, f, _)| (*c, *f) == (m.camera, m.frame)).map(|(_, _, w)| w.as_str());
        let why = why.unwrap_or("no frame arrived within the wait");
        session.frame_missing(m, why)?;
        stored.missing.push((m.camera, m.frame, why.to_string()));
    }
    for x in &pairing.extra {
        let c = &arrivals[x.arrival];
        session.store_extra(x, &c.ext, &c.data)?;
    }
    session.finish_step()?;
    Ok(stored)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera that makes one frame per trigger on its own camera.
    struct OneCamera {
        camera: u8,
        steps: u32,
        ready: Vec<Captured>,
    }

    impl FrameInput for OneCamera {
        fn begin_step(&mut self, _step: &Step) -> io::Result<()> {
            self.steps += 1;
            Ok(())
        }
        fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> io::Result<()> {
            if t.camera == self.camera {
                let data = vec![t.camera, t.frame as u8];
                let host_us = host_us.unwrap_or(0.0);
                self.ready.push(Captured {
                    camera: t.camera,
                    frame: Some(t.frame),
                    ext: "raw".into(),
                    data,
                    host_us,
                    before_step: false,
                    stamp: None,
                });
            }
            Ok(())
        }
        fn poll(&mut self, _now_us: f64) -> io::Result<Vec<Captured>> {
            Ok(std::mem::take(&mut self.ready))
        }
    }

    #[test]
    fn several_cameras_hear_every_trigger_and_give_their_own_frames() {
        let cam = |camera| Box::new(OneCamera { camera, steps: 0, ready: Vec::new() }) as Box<dyn FrameInput>;
        let mut both = Cameras(vec![cam(0), cam(1)]);
        let step = Step::new(0, "s", serde_json::Value::Null, |_| {});
        both.begin_step(&step).unwrap();
        for (camera, frame) in [(1, 0), (0, 0), (1, 1)] {
            let snapshot = lightrig_protocol::event::Snapshot {
                galvos: Default::default(),
                axes: Default::default(),
                filters: Default::default(),
                lasers: 0,
            };
            let t = TriggerEvent { sequence: 1, item: 0, frame, camera, tick: 0, width: 1, snapshot };
            both.on_trigger(&t, Some(5.0)).unwrap();
        }
        let got: Vec<(u8, Option<u32>)> =
            both.poll(10.0).unwrap().iter().map(|c| (c.camera, c.frame)).collect();
        assert_eq!(got, [(0, Some(0)), (1, Some(0)), (1, Some(1))]);
        assert!(both.poll(11.0).unwrap().is_empty());
    }

    /// [`OneCamera`] whose every trigger waits for the test's go-ahead: a slow renderer.
    struct Gated(OneCamera, std::sync::mpsc::Receiver<()>);

    impl FrameInput for Gated {
        fn begin_step(&mut self, step: &Step) -> io::Result<()> {
            self.0.begin_step(step)
        }
        fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> io::Result<()> {
            self.1.recv().map_err(|_| io::Error::other("no go-ahead"))?;
            self.0.on_trigger(t, host_us)
        }
        fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
            self.0.poll(now_us)
        }
    }

    fn trigger(frame: u32) -> TriggerEvent {
        let snapshot = lightrig_protocol::event::Snapshot {
            galvos: Default::default(),
            axes: Default::default(),
            filters: Default::default(),
            lasers: 0,
        };
        TriggerEvent { sequence: 1, item: 0, frame, camera: 0, tick: 0, width: 1, snapshot }
    }

    #[test]
    fn a_background_input_never_holds_up_the_caller_and_keeps_its_frames_in_order() {
        let (go, gate) = std::sync::mpsc::channel();
        let mut bg =
            Background::new(Box::new(Gated(OneCamera { camera: 0, steps: 0, ready: Vec::new() }, gate)));
        let step = Step::new(0, "s", serde_json::Value::Null, |_| {});
        bg.begin_step(&step).unwrap();
        // Three triggers while the camera is stuck on the first: none of them blocks.
        for f in 0..3 {
            bg.on_trigger(&trigger(f), Some(f64::from(f))).unwrap();
        }
        assert!(bg.poll(0.0).unwrap().is_empty(), "nothing made yet");
        for _ in 0..3 {
            go.send(()).unwrap();
        }
        let mut got = Vec::new();
        while got.len() < 3 {
            got.extend(bg.poll(0.0).unwrap().into_iter().map(|c| c.frame));
        }
        assert_eq!(got, [Some(0), Some(1), Some(2)]);
        // A frame made for an attempt that was cut short is dropped by the next begin_step.
        bg.on_trigger(&trigger(3), Some(3.0)).unwrap();
        go.send(()).unwrap();
        bg.begin_step(&step).unwrap();
        assert!(bg.poll(0.0).unwrap().is_empty());
        // The input's errors come back from poll.
        drop(go);
        bg.on_trigger(&trigger(4), None).unwrap();
        let mut error = None;
        while error.is_none() {
            error = bg.poll(0.0).err();
        }
        assert!(error.unwrap().to_string().contains("no go-ahead"));
    }

    /// [`OneCamera`] that says when it has worked through a trigger, and whose `poll` waits
    /// for the test's go-ahead: frames made, not yet handed over.
    struct SlowToHand(OneCamera, std::sync::mpsc::Sender<()>, std::sync::mpsc::Receiver<()>);

    impl FrameInput for SlowToHand {
        fn begin_step(&mut self, step: &Step) -> io::Result<()> {
            self.0.begin_step(step)
        }
        fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> io::Result<()> {
            self.0.on_trigger(t, host_us)?;
            self.1.send(()).map_err(|_| io::Error::other("no one listens"))
        }
        fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
            if now_us.is_finite() {
                self.2.recv().map_err(|_| io::Error::other("no go-ahead"))?;
            }
            self.0.poll(now_us)
        }
    }

    #[test]
    fn a_background_backlog_ends_only_when_its_frames_are_handed_over() {
        let (done, worked) = std::sync::mpsc::channel();
        let (go, gate) = std::sync::mpsc::channel();
        let camera = SlowToHand(OneCamera { camera: 0, steps: 0, ready: Vec::new() }, done, gate);
        let mut bg = Background::new(Box::new(camera));
        let step = Step::new(0, "s", serde_json::Value::Null, |_| {});
        bg.begin_step(&step).unwrap();
        for f in 0..3 {
            bg.on_trigger(&trigger(f), Some(f64::from(f))).unwrap();
        }
        assert_eq!(bg.backlog(), 3);
        // The thread has made all three frames but not handed them over: the engine, seeing
        // no frame, must not take the source for idle.
        for _ in 0..3 {
            worked.recv().unwrap();
        }
        assert_eq!(bg.backlog(), 3, "frames made are not frames handed over");
        go.send(()).unwrap();
        let mut got = Vec::new();
        while got.len() < 3 {
            assert_eq!(bg.backlog(), 3, "no answer with frames yet");
            got.extend(bg.poll(1.0).unwrap().into_iter().map(|c| c.frame));
        }
        assert_eq!(got, [Some(0), Some(1), Some(2)]);
        assert_eq!(bg.backlog(), 0, "the answer with the frames ends the backlog");
        drop(go);
    }

    #[test]
    fn a_file_written_before_the_step_is_a_straggler_not_its_frame_0() {
        let dir = std::env::temp_dir().join(format!("lightrig-stragglers-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut input = DirectoryInput::new(2, &dir, "f_{frame:04}.raw").unwrap();
        // The camera was still writing frame 7 of an attempt that was cut short: the file is
        // dated a second before the next step begins, and the engine first sees it after.
        let straggler = dir.join("f_0007.raw");
        std::fs::write(&straggler, b"old").unwrap();
        let a_second_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(1);
        std::fs::File::options().write(true).open(&straggler).unwrap().set_modified(a_second_ago).unwrap();
        let step = Step::new(0, "s", serde_json::Value::Null, |_| {});
        input.begin_step(&step).unwrap();
        assert!(!dir.join(STEP_MARK).exists(), "the mark is removed");
        std::fs::write(dir.join("f_0008.raw"), b"new0").unwrap();
        std::fs::write(dir.join("f_0009.raw"), b"new1").unwrap();
        // A file that arrives during the step but was made before it (copied with its date).
        let copied = dir.join("f_0010.raw");
        std::fs::write(&copied, b"copied").unwrap();
        std::fs::File::options().write(true).open(&copied).unwrap().set_modified(a_second_ago).unwrap();
        let mut got = Vec::new();
        for _ in 0..2 {
            got.extend(input.poll(1.0).unwrap());
        }
        let seen: Vec<_> = got.iter().map(|c| (c.camera, c.frame, c.before_step, c.data.clone())).collect();
        assert_eq!(
            seen,
            [
                (2, Some(7), true, b"old".to_vec()),
                (2, Some(0), false, b"new0".to_vec()),
                (2, Some(1), false, b"new1".to_vec()),
                (2, Some(10), true, b"copied".to_vec()),
            ]
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
