//! The live state of a running acquisition, for whoever watches it from elsewhere (the
//! `lightrig-serve` endpoint, docs/live-api.md): what the engine, the client and the journal
//! report as they go. Writers take a short lock and never wait on a reader; readers copy out.
//!
//! Frames are kept only while someone watches ([`Live::watch`]), at most one per camera per
//! [`FRAME_EVERY`], as the bytes the source delivered: decoding and scaling are the reader's.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use lightrig_protocol::link::LinkStats;
use serde::Serialize;

use crate::acquire::{Captured, Progress};
use crate::client::Interrupt;
use crate::clock::ClockMap;
use crate::plan::Step;
use crate::session::Trigger;

/// Journal records kept for readers (older ones are in the session's journal file).
pub const RECORDS_KEPT: usize = 4096;
/// A camera's latest frame is copied at most this often.
pub const FRAME_EVERY: Duration = Duration::from_millis(200);
/// A reader of the frames counts as watching for this long after it read them.
pub const WATCH_FOR: Duration = Duration::from_secs(10);
/// Triggers of the running step kept per camera, to name a late frame's trigger.
const TRIGGERS_KEPT: usize = 4096;
/// The window the rates are measured over.
const RATE_WINDOW: Duration = Duration::from_secs(10);

/// What the run is, as `status.run` says.
#[derive(Debug, Clone, Serialize, Default)]
pub struct RunInfo {
    /// `acquire`, `resume`, `demo`.
    pub command: String,
    pub pid: u32,
    /// The session directory.
    pub session: String,
    /// The device, as its transport describes itself.
    pub device: String,
    /// The plan's method (`lls`, `disco`, …).
    pub method: String,
    /// Wall clock at start, RFC 3339 UTC.
    pub started: String,
    /// Where the endpoint serves it (set by the endpoint).
    pub address: String,
}

/// The device as the host knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceState {
    Connecting,
    Ready,
    Running,
    Faulted,
    Lost,
    Stopped,
}

/// A camera's latest frame, as delivered.
#[derive(Debug, Clone)]
pub struct LiveFrame {
    pub camera: u8,
    /// Counts the frames this camera showed, from 1.
    pub seq: u64,
    /// The step it belongs to.
    pub step: Option<u32>,
    /// Its number in the step, if the source numbers them.
    pub frame: Option<u32>,
    /// File extension (`png`, `exr`, …) and bytes.
    pub ext: String,
    pub data: Arc<[u8]>,
    pub host_us: f64,
    /// The trigger it will be paired with (its camera's `frame`-th of the step), if known.
    pub trigger: Option<Trigger>,
}

#[derive(Debug, Clone, Serialize)]
struct StepNow {
    number: usize,
    of: usize,
    id: u32,
    name: String,
    attempt: u32,
    triggers: u64,
    triggered: u64,
    frames: u64,
    #[serde(skip)]
    sequence: u32,
    /// Stored: its frames are in the progress's count now.
    #[serde(skip)]
    stored: bool,
}

#[derive(Debug)]
struct State {
    run: RunInfo,
    /// `None` while running; `Some(Ok)` finished, `Some(Err(why))` failed.
    ended: Option<Result<(), String>>,
    started: bool,
    paused: bool,
    step: Option<StepNow>,
    progress: Option<Progress>,
    device: DeviceState,
    fault: Option<String>,
    boot_id: Option<u32>,
    lasers: u8,
    link: LinkStats,
    clock: serde_json::Value,
    records: VecDeque<(u64, Arc<str>)>,
    next_record: u64,
    frames: BTreeMap<u8, LiveFrame>,
    frame_seq: BTreeMap<u8, u64>,
    last_copy: BTreeMap<u8, Duration>,
    triggers: BTreeMap<u8, VecDeque<Trigger>>,
    /// (time, triggered, frames) samples for the rates.
    samples: VecDeque<(Duration, u64, u64)>,
    start_time: Duration,
    /// When the first progress of the run's steps came.
    steps_began: Option<Duration>,
    watched_until: Duration,
    /// Bumped on every change, for readers waiting on one.
    version: u64,
}

impl State {
    /// The running step's arrivals until it is stored (then the progress counts them).
    fn unstored_frames(&self) -> u64 {
        self.step.as_ref().filter(|st| !st.stored).map_or(0, |st| st.frames)
    }
}

/// A clock for [`Live`]: time since some fixed start (tests give their own).
pub type LiveClock = Arc<dyn Fn() -> Duration + Send + Sync>;

/// The live state of one run; shared as `Arc<Live>` by the engine and the endpoint.
pub struct Live {
    state: Mutex<State>,
    changed: Condvar,
    interrupt: Arc<Interrupt>,
    pause: AtomicBool,
    sockets: AtomicUsize,
    clock: LiveClock,
}

impl std::fmt::Debug for Live {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Live").field("run", &self.lock().run).finish()
    }
}

impl Live {
    /// The state of a run described by `run`, stopped through `interrupt` (the one its client
    /// obeys), on the process's monotonic clock.
    pub fn new(run: RunInfo, interrupt: Arc<Interrupt>) -> Arc<Live> {
        let epoch = std::time::Instant::now();
        Live::with_clock(run, interrupt, Arc::new(move || epoch.elapsed()))
    }

    /// [`Live::new`] on `clock`.
    pub fn with_clock(run: RunInfo, interrupt: Arc<Interrupt>, clock: LiveClock) -> Arc<Live> {
        let now = clock();
        Arc::new(Live {
            state: Mutex::new(State {
                run,
                ended: None,
                started: false,
                paused: false,
                step: None,
                progress: None,
                device: DeviceState::Connecting,
                fault: None,
                boot_id: None,
                lasers: 0,
                link: LinkStats::default(),
                clock: serde_json::json!({"residual_us": null, "rate": null, "min_rtt_us": null, "samples": 0}),
                records: VecDeque::new(),
                next_record: 0,
                frames: BTreeMap::new(),
                frame_seq: BTreeMap::new(),
                last_copy: BTreeMap::new(),
                triggers: BTreeMap::new(),
                samples: VecDeque::new(),
                start_time: now,
                steps_began: None,
                watched_until: Duration::ZERO,
                version: 0,
            }),
            changed: Condvar::new(),
            interrupt,
            pause: AtomicBool::new(false),
            sockets: AtomicUsize::new(0),
            clock,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding it leaves counters, not invariants: go on reading them.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs `f` on the state, then wakes readers waiting for a change.
    fn update(&self, f: impl FnOnce(&mut State)) {
        let mut s = self.lock();
        f(&mut s);
        s.version += 1;
        drop(s);
        self.changed.notify_all();
    }

    // --- writers: the engine, the client, the journal -------------------------------------

    /// A journal record was written: its JSON (the journal line without CRC and tab).
    pub fn record(&self, json: &[u8]) {
        let text: Arc<str> = String::from_utf8_lossy(json).into();
        self.update(|s| {
            s.records.push_back((s.next_record, text));
            s.next_record += 1;
            while s.records.len() > RECORDS_KEPT {
                s.records.pop_front();
            }
        });
    }

    /// Sets what the endpoint's address is, for `status.run.address`.
    pub fn set_address(&self, address: &str) {
        self.update(|s| s.run.address = address.to_string());
    }

    /// Sets the plan's method, once planned.
    pub fn set_method(&self, method: &str) {
        self.update(|s| s.run.method = method.to_string());
    }

    /// Sets the device the run talks to (after a connection).
    pub fn set_device(&self, device: &str, boot_id: u32) {
        self.update(|s| {
            s.run.device = device.to_string();
            s.boot_id = Some(boot_id);
            s.device = DeviceState::Ready;
            s.fault = None;
        });
    }

    /// The device's state changed, as the host saw it; `fault` in words when faulted.
    pub fn device(&self, state: DeviceState, fault: Option<String>) {
        self.update(|s| {
            s.device = state;
            if state == DeviceState::Faulted || fault.is_some() {
                s.fault = fault;
            } else if state == DeviceState::Ready {
                s.fault = None;
            }
        });
    }

    /// The device said its state and armed lasers (a `State` event).
    pub fn reported(&self, state: &lightrig_protocol::event::DeviceState, armed: u8) {
        use lightrig_protocol::event::DeviceState as D;
        let (word, fault) = match state {
            D::AwaitingHello => (DeviceState::Connecting, None),
            D::Ready => (DeviceState::Ready, None),
            D::Running { .. } => (DeviceState::Running, None),
            D::Faulted(cause) => (DeviceState::Faulted, Some(crate::client::describe_fault(cause))),
        };
        self.update(|s| {
            s.device = word;
            s.lasers = armed;
            if word == DeviceState::Faulted || word == DeviceState::Ready {
                s.fault = fault;
            }
        });
    }

    /// The lasers the host has armed now (bit `i`: laser `i`).
    pub fn lasers(&self, mask: u8) {
        self.update(|s| s.lasers = mask);
    }

    /// The link's counters and the clock mapping, now.
    pub fn link(&self, stats: &LinkStats, clock: &ClockMap) {
        let rate = clock.rate();
        // The residual is in ticks; ticks per µs turn it into µs.
        let residual_us = clock.residual().zip(rate).map(|(r, k)| if k > 0.0 { r / k } else { r });
        let json = serde_json::json!({
            "residual_us": residual_us,
            "rate": rate,
            "min_rtt_us": clock.min_rtt_us(),
            "samples": clock.counts().0,
        });
        self.update(|s| {
            s.link = *stats;
            s.clock = json;
        });
    }

    /// The run has begun its steps.
    pub fn started(&self) {
        self.update(|s| s.started = true);
    }

    /// An attempt at `step` (the `number`-th of `of` in the plan) began as device sequence
    /// `sequence`.
    pub fn step_started(&self, number: usize, of: usize, step: &Step, attempt: u32, sequence: u32) {
        let triggers = step.triggers.iter().map(|t| u64::from(t.1)).sum();
        self.update(|s| {
            s.step = Some(StepNow {
                number,
                of,
                id: step.id,
                name: step.name.clone(),
                attempt,
                triggers,
                triggered: 0,
                frames: 0,
                sequence,
                stored: false,
            });
            s.triggers.clear();
            s.device = DeviceState::Running;
        });
    }

    /// The running step's sequence is done (its frames are being collected).
    pub fn sequence_done(&self) {
        self.update(|s| {
            if s.device == DeviceState::Running {
                s.device = DeviceState::Ready;
            }
        });
    }

    /// The device fired a trigger of the running step.
    pub fn triggered(&self, t: Trigger) {
        self.update(|s| {
            if let Some(step) = s.step.as_mut().filter(|st| st.sequence == t.sequence) {
                step.triggered += 1;
                let kept = s.triggers.entry(t.camera).or_default();
                kept.push_back(t);
                while kept.len() > TRIGGERS_KEPT {
                    kept.pop_front();
                }
            }
        });
    }

    /// Frames of the running step arrived: counted, and the latest of each camera kept if
    /// someone watches and its last copy is [`FRAME_EVERY`] old.
    pub fn arrived(&self, frames: &[Captured]) {
        if frames.is_empty() {
            return;
        }
        let now = (self.clock)();
        let watched = self.watched_at(now);
        self.update(|s| {
            if let Some(step) = s.step.as_mut() {
                step.frames += frames.iter().filter(|c| !c.before_step).count() as u64;
            }
            if let (Some(p), Some(&(_, triggered, _))) = (&s.progress, s.samples.back()) {
                let at = p.frames + s.unstored_frames();
                s.samples.push_back((now, triggered, at));
            }
            if !watched {
                s.frames.clear();
                return;
            }
            // The newest of each camera only.
            let mut newest: BTreeMap<u8, &Captured> = BTreeMap::new();
            for c in frames.iter().filter(|c| !c.before_step) {
                newest.insert(c.camera, c);
            }
            for (camera, c) in newest {
                if s.last_copy.get(&camera).is_some_and(|&t| now < t + FRAME_EVERY) {
                    continue;
                }
                s.last_copy.insert(camera, now);
                let seq = s.frame_seq.entry(camera).or_insert(0);
                *seq += 1;
                let seq = *seq;
                let trigger =
                    c.frame.and_then(|n| s.triggers.get(&camera)?.iter().find(|t| t.frame == n).cloned());
                let step = s.step.as_ref().map(|st| st.id);
                let frame = LiveFrame {
                    camera,
                    seq,
                    step,
                    frame: c.frame,
                    ext: c.ext.clone(),
                    data: Arc::from(c.data.as_slice()),
                    host_us: c.host_us,
                    trigger,
                };
                s.frames.insert(camera, frame);
            }
        });
    }

    /// The running step was stored (its frames are in the next progress's count).
    pub fn step_stored(&self) {
        self.update(|s| {
            if let Some(st) = s.step.as_mut() {
                st.stored = true;
            }
        });
    }

    /// The engine's progress.
    pub fn progress(&self, p: &Progress) {
        let now = (self.clock)();
        self.update(|s| {
            let frames = p.frames + s.unstored_frames();
            s.samples.push_back((now, p.triggered, frames));
            s.steps_began.get_or_insert(now);
            while s.samples.len() > 2
                && s.samples.front().is_some_and(|f| now.saturating_sub(f.0) > RATE_WINDOW)
            {
                s.samples.pop_front();
            }
            s.progress = Some(p.clone());
        });
    }

    /// The run ended: `Ok` every step done, else why not.
    pub fn ended(&self, result: Result<(), String>) {
        self.update(|s| {
            s.ended = Some(result);
            if s.device == DeviceState::Running {
                s.device = DeviceState::Ready;
            }
        });
    }

    /// Whether a pause was asked for (the engine pauses at its next step boundary).
    pub fn pause_requested(&self) -> bool {
        self.pause.load(Ordering::SeqCst)
    }

    /// The engine is paused (or goes on again).
    pub fn set_paused(&self, paused: bool) {
        self.update(|s| s.paused = paused);
    }

    /// Waits until a resume or stop is asked for, at most `timeout`.
    pub fn wait_unpaused(&self, timeout: Duration) {
        let s = self.lock();
        let _ = self
            .changed
            .wait_timeout_while(s, timeout, |_| self.pause_requested() && !self.interrupt.requested());
    }

    // --- commands: the endpoint ---------------------------------------------------------

    /// Asks for an emergency stop (as Ctrl-C does).
    pub fn stop(&self) {
        self.interrupt.request();
        self.update(|_| {});
    }

    /// The stop's progress: asked for, sent, answered by the device.
    pub fn stop_state(&self) -> (bool, bool, bool) {
        (self.interrupt.requested(), self.interrupt.stopped(), self.interrupt.answered())
    }

    /// Asks the run to pause at its next step boundary; `Err` if it has ended or is stopping.
    pub fn pause(&self) -> Result<&'static str, String> {
        self.command_allowed()?;
        self.pause.store(true, Ordering::SeqCst);
        let paused = self.lock().paused;
        self.update(|_| {});
        Ok(if paused { "paused" } else { "pausing" })
    }

    /// Takes a pause back.
    pub fn resume(&self) -> Result<&'static str, String> {
        self.command_allowed()?;
        self.pause.store(false, Ordering::SeqCst);
        self.update(|_| {});
        Ok("running")
    }

    fn command_allowed(&self) -> Result<(), String> {
        if self.interrupt.requested() {
            return Err("the run is emergency-stopped; it ends now".into());
        }
        match &self.lock().ended {
            Some(Ok(())) => Err("the run has finished".into()),
            Some(Err(why)) => Err(format!("the run has ended: {why}")),
            None => Ok(()),
        }
    }

    // --- readers ------------------------------------------------------------------------

    /// A reader watches the frames: kept for [`WATCH_FOR`] from now.
    pub fn watch(&self) {
        let until = (self.clock)() + WATCH_FOR;
        self.update(|s| s.watched_until = s.watched_until.max(until));
    }

    /// A WebSocket watcher came (`true`) or went: frames are kept while one is open.
    pub fn socket(&self, open: bool) {
        if open {
            self.sockets.fetch_add(1, Ordering::SeqCst);
        } else {
            self.sockets.fetch_sub(1, Ordering::SeqCst);
        }
    }

    /// Watchers now: open WebSockets, plus one if frames were read within [`WATCH_FOR`].
    pub fn watchers(&self) -> usize {
        let recent = (self.clock)() < self.lock().watched_until;
        self.sockets.load(Ordering::SeqCst) + usize::from(recent)
    }

    fn watched_at(&self, now: Duration) -> bool {
        self.sockets.load(Ordering::SeqCst) > 0 || now < self.lock().watched_until
    }

    /// The run's state word (docs/live-api.md: `state`) and its reason.
    pub fn state_word(&self) -> (&'static str, Option<String>) {
        let s = self.lock();
        self.word_of(&s)
    }

    fn word_of(&self, s: &State) -> (&'static str, Option<String>) {
        let (asked, _, answered) = self.stop_state();
        if answered {
            return ("stopped", Some("emergency stop".into()));
        }
        match &s.ended {
            Some(Ok(())) => return ("finished", None),
            Some(Err(why)) if asked => return ("stopped", Some(format!("stop unconfirmed: {why}"))),
            Some(Err(why)) => return ("failed", Some(why.clone())),
            None => {}
        }
        if asked {
            ("stopping", None)
        } else if s.paused {
            ("paused", None)
        } else if self.pause_requested() {
            ("pausing", None)
        } else if s.started {
            ("running", None)
        } else {
            ("starting", None)
        }
    }

    /// Whether the run has ended (finished, failed, or stopped and gone).
    pub fn has_ended(&self) -> bool {
        self.lock().ended.is_some()
    }

    /// The version of the state: it changes with every update.
    pub fn version(&self) -> u64 {
        self.lock().version
    }

    /// Waits up to `timeout` for the state to change from `version`; returns the version now.
    pub fn wait_change(&self, version: u64, timeout: Duration) -> u64 {
        let s = self.lock();
        let (s, _) = self
            .changed
            .wait_timeout_while(s, timeout, |s| s.version == version)
            .unwrap_or_else(|p| p.into_inner());
        s.version
    }

    /// The status document (docs/live-api.md, STATUS).
    pub fn status(&self) -> serde_json::Value {
        let now = (self.clock)();
        let watchers = self.watchers();
        let s = self.lock();
        let (word, reason) = self.word_of(&s);
        let (requested, sent, answered) = self.stop_state();
        let progress = s.progress.as_ref().map(|p| {
            let frames = p.frames + s.unstored_frames();
            let (trigger_rate, frame_rate) = match (s.samples.front(), s.samples.back()) {
                (Some(a), Some(b)) if b.0 > a.0 => {
                    let dt = (b.0 - a.0).as_secs_f64();
                    (Some((b.1 - a.1) as f64 / dt), Some((b.2.saturating_sub(a.2)) as f64 / dt))
                }
                _ => (None, None),
            };
            // Paced from the first progress of the run's steps (connecting and homing are not
            // the plan's work).
            let began = s.steps_began.unwrap_or(now);
            let (eta, bound) = p.time_left_s(now.saturating_sub(began).as_secs_f64());
            serde_json::json!({
                "steps_done": p.steps_done,
                "steps": p.steps,
                "triggered": p.triggered,
                "to_trigger": p.to_trigger,
                "frames": frames,
                "missing": p.missing,
                "elapsed_s": now.saturating_sub(s.start_time).as_secs_f64(),
                "trigger_rate_hz": trigger_rate,
                "frame_rate_hz": frame_rate,
                "eta_s": eta,
                "eta_is_bound": bound,
            })
        });
        let device = if answered { DeviceState::Stopped } else { s.device };
        serde_json::json!({
            "api": 1,
            "run": s.run,
            "state": word,
            "reason": reason,
            "step": s.step,
            "progress": progress,
            "device": {"state": device, "fault": s.fault, "lasers_armed": s.lasers, "boot_id": s.boot_id},
            "link": s.link,
            "clock": s.clock,
            "stop": {"requested": requested, "sent": sent, "answered": answered},
            "journal": {"next": s.next_record},
            "watchers": watchers,
        })
    }

    /// Journal records with `seq >= since`, at most `limit`: `(first kept, next, records)`.
    pub fn records(&self, since: u64, limit: usize) -> (u64, u64, Vec<(u64, Arc<str>)>) {
        let s = self.lock();
        let first = s.records.front().map_or(s.next_record, |r| r.0);
        let skip = since.saturating_sub(first) as usize;
        let out = s.records.iter().skip(skip).take(limit).cloned().collect();
        (first, s.next_record, out)
    }

    /// The latest frame of each camera (kept while watched).
    pub fn frames(&self) -> Vec<LiveFrame> {
        self.lock().frames.values().cloned().collect()
    }

    /// Whether the rig projects a laser spot the page should mark (DISCO).
    pub fn marks_spot(&self) -> bool {
        self.lock().run.method == "disco"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicU64;

    fn clocked() -> (Arc<Live>, Arc<AtomicU64>, Arc<Interrupt>) {
        let ms = Arc::new(AtomicU64::new(0));
        let t = ms.clone();
        let interrupt = Arc::new(Interrupt::default());
        let run = RunInfo { command: "acquire".into(), method: "lls".into(), ..RunInfo::default() };
        let live = Live::with_clock(
            run,
            interrupt.clone(),
            Arc::new(move || Duration::from_millis(t.load(Ordering::SeqCst))),
        );
        (live, ms, interrupt)
    }

    fn captured(camera: u8, frame: u32) -> Captured {
        Captured {
            camera,
            frame: Some(frame),
            ext: "pgm".into(),
            data: vec![camera, frame as u8],
            host_us: f64::from(frame),
            before_step: false,
            stamp: None,
        }
    }

    #[test]
    fn records_are_kept_up_to_their_limit_and_read_from_a_seq() {
        let (live, _, _) = clocked();
        for i in 0..RECORDS_KEPT + 10 {
            live.record(format!("{{\"n\":{i}}}").as_bytes());
        }
        let (first, next, got) = live.records(0, 3);
        assert_eq!((first, next), (10, RECORDS_KEPT as u64 + 10));
        assert_eq!(got.iter().map(|r| r.0).collect::<Vec<_>>(), vec![10, 11, 12]);
        assert_eq!(&*got[0].1, "{\"n\":10}");
        let (_, _, tail) = live.records(next - 2, 100);
        assert_eq!(tail.len(), 2);
        assert_eq!(live.records(next, 100).2.len(), 0);
        assert_eq!(live.status()["journal"]["next"], RECORDS_KEPT as u64 + 10);
    }

    #[test]
    fn frames_are_kept_only_while_watched_and_at_most_every_frame_every() {
        let (live, ms, _) = clocked();
        live.arrived(&[captured(0, 0)]);
        assert!(live.frames().is_empty(), "nobody watches: nothing copied");
        live.watch();
        live.arrived(&[captured(0, 1), captured(1, 1), captured(0, 2)]);
        let f = live.frames();
        assert_eq!(f.len(), 2);
        assert_eq!((f[0].camera, f[0].frame, f[0].seq, &*f[0].data), (0, Some(2), 1, &[0u8, 2][..]));
        // Within FRAME_EVERY: not copied again.
        ms.store(199, Ordering::SeqCst);
        live.arrived(&[captured(0, 3)]);
        assert_eq!(live.frames()[0].frame, Some(2));
        ms.store(200, Ordering::SeqCst);
        live.arrived(&[captured(0, 4)]);
        assert_eq!((live.frames()[0].frame, live.frames()[0].seq), (Some(4), 2));
        // The watch lapses after WATCH_FOR; the frames are dropped with it.
        ms.store(10_000, Ordering::SeqCst);
        assert_eq!(live.watchers(), 0);
        live.arrived(&[captured(0, 5)]);
        assert!(live.frames().is_empty());
        // A WebSocket open keeps them.
        live.socket(true);
        live.arrived(&[captured(0, 6)]);
        assert_eq!(live.frames()[0].frame, Some(6));
        live.socket(false);
    }

    #[test]
    fn a_frame_names_the_trigger_it_will_be_paired_with() {
        let (live, _, _) = clocked();
        let mut step = Step::new(7, "pass", serde_json::Value::Null, |_| {});
        step.triggers = vec![(0, 3)];
        live.step_started(2, 3, &step, 1, 7001);
        live.watch();
        for frame in 0..3 {
            let t = Trigger {
                sequence: 7001,
                item: frame * 2,
                camera: 0,
                frame,
                tick: 1000 + u64::from(frame),
                host_us: None,
            };
            live.triggered(t);
        }
        // A trigger of another sequence (a stale one) is not the step's.
        live.triggered(Trigger { sequence: 6001, item: 0, camera: 0, frame: 1, tick: 5, host_us: None });
        live.arrived(&[captured(0, 1)]);
        assert_eq!(live.frames()[0].trigger.as_ref().map(|t| t.tick), Some(1001));
        let st = live.status();
        assert_eq!(st["step"]["triggered"], 3);
        assert_eq!(st["step"]["frames"], 1);
        assert_eq!(st["step"]["number"], 2);
        assert_eq!(st["device"]["state"], "running");
    }

    #[test]
    fn the_devices_own_state_events_say_its_state_and_armed_lasers() {
        use lightrig_protocol::event::{DeviceState as D, FaultCause};
        let (live, _, _) = clocked();
        live.reported(&D::Running { sequence: 3 }, 0b101);
        assert_eq!(
            live.status()["device"],
            serde_json::json!({"state": "running", "fault": null, "lasers_armed": 5, "boot_id": null})
        );
        live.reported(&D::Faulted(FaultCause::EmergencyStop), 0);
        let st = live.status();
        assert_eq!(
            (st["device"]["state"].as_str(), st["device"]["lasers_armed"].as_u64()),
            (Some("faulted"), Some(0))
        );
        assert!(st["device"]["fault"].as_str().is_some_and(|f| !f.is_empty()), "{st}");
        live.reported(&D::Ready, 0);
        assert!(live.status()["device"]["fault"].is_null(), "cleared with the fault");
    }

    #[test]
    fn pause_and_resume_move_the_state_and_end_with_the_run() {
        let (live, _, interrupt) = clocked();
        assert_eq!(live.state_word().0, "starting");
        live.started();
        assert_eq!(live.state_word().0, "running");
        assert_eq!(live.pause(), Ok("pausing"));
        assert!(live.pause_requested());
        live.set_paused(true);
        assert_eq!(live.state_word().0, "paused");
        assert_eq!(live.resume(), Ok("running"));
        live.set_paused(false);
        assert_eq!(live.state_word().0, "running");
        live.stop();
        assert!(interrupt.requested());
        assert_eq!(live.state_word().0, "stopping");
        assert!(live.pause().unwrap_err().contains("emergency-stopped"));
        live.ended(Err("interrupted".into()));
        assert_eq!(live.state_word(), ("stopped", Some("stop unconfirmed: interrupted".into())));
    }

    #[test]
    fn rates_and_eta_come_from_the_progress_over_time() {
        let (live, ms, _) = clocked();
        // The plan: 20 s of work in all, every wait ending at once.
        let p = |triggered, frames, done_us: u64| Progress {
            steps_done: 0,
            steps: 1,
            frames,
            received: 0,
            bytes: 0,
            planned_done_us: done_us,
            planned_left_us: 20_000_000 - done_us,
            triggered,
            to_trigger: 1000,
            missing: 0,
            missing_now: None,
        };
        // Connecting and homing (1 s) are not the plan's work.
        ms.store(1_000, Ordering::SeqCst);
        live.progress(&p(0, 0, 0));
        let st = live.status();
        assert!(st["progress"]["trigger_rate_hz"].is_null());
        // Before any work, the plan's bound, said to be one.
        assert_eq!(
            (st["progress"]["eta_s"].clone(), st["progress"]["eta_is_bound"].clone()),
            (20.0.into(), true.into())
        );
        // 2 s later the plan's first 1 s is done: half its pace, so 38 s left, not the 19 s
        // of the plan nor the 18 s of triggers over trigger rate.
        ms.store(3_000, Ordering::SeqCst);
        live.progress(&p(100, 0, 1_000_000));
        let st = live.status();
        assert_eq!(st["progress"]["trigger_rate_hz"], 50.0);
        assert_eq!(st["progress"]["eta_s"], 38.0);
        assert_eq!(st["progress"]["eta_is_bound"], false);
        assert_eq!(st["progress"]["elapsed_s"], 3.0);
        live.ended(Ok(()));
        assert_eq!(live.state_word().0, "finished");
        assert!(live.pause().is_err());
    }
}
