//! The rig: every peripheral's behaviour, the sequencer and the safety state machine, driven by
//! integer ticks. [`crate::controller::Controller`] puts the protocol in front of it.
//!
//! The rig is a deterministic state machine. [`Rig::next_due`] says when it next has work;
//! [`Rig::poll`] does all work due up to a tick, in tick order, passing every output change its
//! exact tick. A board's run loop sleeps until the earlier of `next_due` and the next input;
//! the simulation jumps straight there. Nothing here reads a clock, so the same sequence gives
//! the same edges, to the tick, on the MCU, in the virtual rig and in tests.
//!
//! Work due at the same tick runs in this order: exposure captures, steps, galvo line updates,
//! trigger pulse ends, laser timers, the heartbeat check, sequence items (in sequence order),
//! then voice-coil blocks. A trigger's snapshot therefore sees every step and galvo update of
//! its own tick and every earlier item of its sequence.
//!
//! Safety (the safe state, entered on any fault, e-stop, lapsed heartbeat or underrun): lasers
//! off and disarmed; galvos parked; steppers and filter wheels decelerate to a stop (stop at
//! once on e-stop or limit switch); synthesis fades to silence over [`FADE_MS`]; the sequence
//! is dropped; the fault stays latched until `ClearFault`.
//!
//! This module keeps the rig's state, the commands, the dispatch of configuration items and
//! actions, the schedule (`next_due` / `poll` and the order above), the events, the heartbeat
//! and the safe state. Each peripheral kind's behaviour is an `impl Rig` block of its own, one
//! driver per kind:
//! - `galvos`: galvo pairs: park, point jumps blanking the lasers, line sweeps;
//! - `lasers`: arming, on and off with the interlock, outputs under blanking, warm-up, on-time;
//! - `steppers`: stepper axes and filter wheels: moves, homing, limit and index switches;
//! - `cameras`: trigger pulses with the rig's snapshot, exposure captures;
//! - `coils`: voice coils: settings on their exact sample, block synthesis, the fade;
//! - `motor`: one step/dir motor's move at exact step ticks, for `steppers`;
//! - `sequencer`: the sequence buffer: chunk order, credit, the next item's due tick.

mod cameras;
mod coils;
mod galvos;
mod lasers;
mod motor;
mod sequencer;
mod steppers;

use heapless::Deque;
use lightrig_protocol::config::{ConfigItem, Polarity, Xy};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{DeviceState, Event, FaultCause};
use lightrig_protocol::sequence::{Action, AxisRef, BufferStatus, Chunk, StartAt, WaitFor};
use lightrig_protocol::session::Capabilities;
use lightrig_protocol::{
    Error, MAX_CAMERAS, MAX_FILTER_WHEELS, MAX_GALVOS, MAX_LASERS, MAX_PARTIALS, MAX_STEPPERS,
    MAX_VOICE_COILS,
};

use crate::hal::Board;
use crate::synth::Synth;
use cameras::Camera;
use coils::Coil;
pub use coils::{VOICE_COIL_BLOCK, VOICE_COIL_LATENCY_BLOCKS};
use galvos::{check_galvo_point, Galvo};
use lasers::Laser;
use motor::Motor;
pub use sequencer::SEQUENCE_BUFFER;
use sequencer::{Phase, Sequencer, Waiting};
use steppers::{Axis, Wheel};

/// Events the rig holds until the controller hands them to the link.
pub const EVENT_QUEUE: usize = 64;
/// Fade to silence in the safe state, milliseconds.
pub const FADE_MS: u32 = 20;
/// Heartbeat timeout until the host configures one, milliseconds.
pub const DEFAULT_HEARTBEAT_MS: u32 = 1000;
/// Slots kept free in the event queue for the overflow fault's own `Fault` and `State`.
const EVENT_RESERVE: usize = 2;

/// Who asked for an action: a sequence item (with its index) or an `Immediate` command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Origin {
    Sequence(u32),
    Immediate,
}

/// Sequence id reported by triggers and markers fired by `Immediate`.
pub const IMMEDIATE_SEQUENCE: u32 = u32::MAX;

struct Heartbeat {
    timeout: u64,
    last: u64,
    watching: bool,
}

/// Outgoing events, with room kept for the overflow fault.
struct Events {
    /// Each event with the number dropped just before it, so that the event numbers the host
    /// sees skip exactly where events were lost.
    queue: Deque<(u32, Event), EVENT_QUEUE>,
    dropped: u32,
    /// Dropped since the last event queued.
    gap: u32,
}

impl Events {
    fn drop_one(&mut self) {
        self.dropped = self.dropped.saturating_add(1);
        self.gap = self.gap.saturating_add(1);
    }

    fn push(&mut self, event: Event) -> bool {
        let ok = self.queue.push_back((self.gap, event)).is_ok();
        if ok {
            self.gap = 0;
        }
        ok
    }
}

/// Kinds of work in [`Rig::run_at`]'s order, one bit each (a bit per motor): what is due at
/// the earliest due tick, so that a wake-up skips the sections with nothing to do.
mod work {
    use lightrig_protocol::{MAX_FILTER_WHEELS, MAX_GALVOS, MAX_STEPPERS};
    /// Stepper axis `i` is bit `i`.
    pub const AXES: u32 = (1 << MAX_STEPPERS) - 1;
    /// Filter wheel `i` is bit `WHEEL0 + i`.
    pub const WHEEL0: u32 = MAX_STEPPERS as u32;
    pub const WHEELS: u32 = ((1 << MAX_FILTER_WHEELS) - 1) << WHEEL0;
    pub const LINES: u32 = 1 << (WHEEL0 + MAX_FILTER_WHEELS as u32);
    pub const PULSES: u32 = LINES << 1;
    pub const LASERS: u32 = LINES << 2;
    pub const BLANK: u32 = LINES << 3;
    pub const HEARTBEAT: u32 = LINES << 4;
    pub const WAIT: u32 = LINES << 5;
    pub const SEQUENCE: u32 = LINES << 6;
    pub const COILS: u32 = LINES << 7;
    const _: () = assert!(MAX_GALVOS <= 32 && COILS != 0);
}

/// The earliest due tick and what is due then ([`work`] bits; none when 0).
#[derive(Clone, Copy)]
struct Due {
    at: u64,
    what: u32,
}

impl Due {
    const NOTHING: Self = Self { at: 0, what: 0 };

    #[inline(always)]
    fn add(&mut self, t: Option<u64>, what: u32) {
        let Some(t) = t else { return };
        if self.what == 0 || t < self.at {
            *self = Self { at: t, what };
        } else if t == self.at {
            self.what |= what;
        }
    }

    fn tick(self) -> Option<u64> {
        (self.what != 0).then_some(self.at)
    }
}

/// The rig controller's behaviour over a [`Board`].
pub struct Rig<B: Board> {
    board: B,
    tick_hz: u32,
    caps: Capabilities,
    galvos: [Galvo; MAX_GALVOS],
    lasers: [Laser; MAX_LASERS],
    axes: [Axis; MAX_STEPPERS],
    wheels: [Wheel; MAX_FILTER_WHEELS],
    coils: [Coil; MAX_VOICE_COILS],
    cameras: [Camera; MAX_CAMERAS],
    heartbeat: Heartbeat,
    /// Lasers are blanked (galvo jump settling) until this tick.
    blank_until: u64,
    /// A blank is in progress: the lasers that are on come back at `blank_until`.
    blanking: bool,
    armed: u8,
    fault: Option<FaultCause>,
    seq: Sequencer,
    events: Events,
    /// The `now` of the poll in progress: how late due work runs.
    polled_at: u64,
    /// [`Rig::next_due`] as of the end of the last `poll`, valid while `due_fresh`. A board's
    /// run loop asks for it between polls and `poll` asks again on entry: scanning every
    /// peripheral each time was most of the cost of a step or an item. Every public method
    /// that changes the rig's state clears `due_fresh`; the board's inputs are not part of it.
    due: Due,
    due_fresh: bool,
}

/// The bit of channel `ch` in a laser mask (none for a channel beyond the mask).
fn bit(ch: u8) -> u8 {
    1u8.checked_shl(u32::from(ch)).unwrap_or(0)
}

fn level(polarity: Polarity, active: bool) -> bool {
    active == (polarity == Polarity::ActiveHigh)
}

/// How late a sequence item may run before the rig gives up on the schedule: 1 ms. Outputs
/// still carry their exact tick, so hardware-timed outputs stay exact within this slack.
fn late_limit(tick_hz: u32) -> u64 {
    u64::from(tick_hz / 1000)
}

fn ms_to_ticks(ms: u32, tick_hz: u32) -> u64 {
    u64::from(ms) * u64::from(tick_hz) / 1000
}

impl<B: Board> Rig<B> {
    /// A rig in the safe state, nothing configured, with the capabilities of `caps` (clamped
    /// to the protocol's maxima) at `tick_hz`.
    pub fn new(board: B, caps: Capabilities, tick_hz: u32) -> Self {
        let caps = Capabilities {
            galvos: caps.galvos.min(MAX_GALVOS as u8),
            lasers: caps.lasers.min(MAX_LASERS as u8),
            steppers: caps.steppers.min(MAX_STEPPERS as u8),
            filter_wheels: caps.filter_wheels.min(MAX_FILTER_WHEELS as u8),
            voice_coils: caps.voice_coils.min(MAX_VOICE_COILS as u8),
            partials_per_coil: caps.partials_per_coil.min(MAX_PARTIALS as u8),
            cameras: caps.cameras.min(MAX_CAMERAS as u8),
            ..caps
        };
        let laser = Laser { config: None, on: false, emitting: false, on_since: 0, ready: false };
        Self {
            board,
            tick_hz,
            caps,
            galvos: core::array::from_fn(|_| Galvo { config: None, pos: Xy::default(), line: None }),
            lasers: [laser; MAX_LASERS],
            axes: core::array::from_fn(|i| Axis {
                config: None,
                motor: Motor::new(AxisRef::Stepper(i as u8)),
                homed: false,
            }),
            wheels: core::array::from_fn(|i| Wheel {
                config: None,
                motor: Motor::new(AxisRef::FilterWheel(i as u8)),
                homed: false,
                slot: None,
            }),
            coils: core::array::from_fn(|_| Coil {
                config: None,
                synth: Synth::new(48_000),
                t0: 0,
                next_sample: 0,
                pending: Deque::new(),
            }),
            cameras: core::array::from_fn(|_| Camera {
                config: None,
                pulse_end: None,
                last_edge: None,
                exposure_active: false,
                exposure_ended: false,
            }),
            heartbeat: Heartbeat {
                timeout: ms_to_ticks(DEFAULT_HEARTBEAT_MS, tick_hz),
                last: 0,
                watching: false,
            },
            blank_until: 0,
            blanking: false,
            armed: 0,
            fault: None,
            seq: Sequencer::new(),
            events: Events { queue: Deque::new(), dropped: 0, gap: 0 },
            polled_at: 0,
            due: Due::NOTHING,
            due_fresh: false,
        }
    }

    /// The board, for inspection (the simulation's record) and for input changes.
    pub fn board(&self) -> &B {
        &self.board
    }

    /// The board, mutably.
    pub fn board_mut(&mut self) -> &mut B {
        &mut self.board
    }

    /// The latched fault, if any.
    pub fn fault(&self) -> Option<FaultCause> {
        self.fault
    }

    /// Armed lasers, one bit per channel.
    pub fn armed(&self) -> u8 {
        self.armed
    }

    /// The sequence state, `None` when no sequence is running.
    pub fn running(&self) -> Option<u32> {
        (self.seq.phase == Phase::Running).then_some(self.seq.id)
    }

    /// The sequence buffer, if a sequence is loaded or running.
    pub fn buffer(&self) -> Option<BufferStatus> {
        (self.seq.phase != Phase::Idle).then(|| self.seq.status())
    }

    /// The state the protocol reports (the controller adds the handshake state).
    pub fn state(&self) -> DeviceState {
        match (self.fault, self.running()) {
            (Some(cause), _) => DeviceState::Faulted(cause),
            (None, Some(sequence)) => DeviceState::Running { sequence },
            (None, None) => DeviceState::Ready,
        }
    }

    /// Takes the oldest event for the host.
    pub fn pop_event(&mut self) -> Option<Event> {
        self.pop_event_after_gap().map(|(_, e)| e)
    }

    /// The next event for the host and how many events were dropped just before it (the
    /// queue was full): the controller skips that many event numbers.
    pub fn pop_event_after_gap(&mut self) -> Option<(u32, Event)> {
        self.events.queue.pop_front()
    }

    /// Events dropped because the queue was full (after the overflow fault).
    pub fn dropped_events(&self) -> u32 {
        self.events.dropped
    }

    // ---------------------------------------------------------------- host contact & safety

    /// The host spoke at `now` (any command counts as a heartbeat). `watch` starts the
    /// heartbeat watchdog (the session is open).
    pub fn host_seen(&mut self, now: u64, watch: bool) {
        self.due_fresh = false;
        self.heartbeat.last = now;
        self.heartbeat.watching |= watch;
    }

    /// Every moving motor decelerates to a stop (a firmware update begins: nothing moves
    /// until it ends).
    pub fn stop_motion(&mut self, now: u64) {
        self.due_fresh = false;
        self.stop_motors(now, false);
    }

    /// Emergency stop: safe state at once, motors without deceleration.
    pub fn emergency_stop(&mut self, now: u64) {
        self.due_fresh = false;
        self.enter_safe_state(FaultCause::EmergencyStop, now);
    }

    /// Clears a latched fault. Lasers stay disarmed.
    pub fn clear_fault(&mut self, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        if self.fault.take().is_some() {
            self.heartbeat.last = now;
            self.emit_state(now);
        }
        Ok(())
    }

    fn emit(&mut self, event: Event, now: u64) {
        if self.events.queue.len() + EVENT_RESERVE >= EVENT_QUEUE {
            self.events.drop_one();
            if self.fault.is_none() {
                self.enter_safe_state(FaultCause::EventOverflow, now);
            }
            return;
        }
        self.events.push(event);
    }

    /// For the safe state's own events: may use the reserved slots.
    fn emit_reserved(&mut self, event: Event) {
        if !self.events.push(event) {
            self.events.drop_one();
        }
    }

    fn emit_state(&mut self, now: u64) {
        let event = Event::State { state: self.state(), armed: self.armed, tick: now };
        self.emit(event, now);
    }

    /// Enters the safe state and latches `cause` (the first cause stays latched).
    fn enter_safe_state(&mut self, cause: FaultCause, now: u64) {
        let hard = matches!(cause, FaultCause::EmergencyStop | FaultCause::Limit { .. });
        warn!("safe state at tick {}", now);
        // Latch first: stopping a homing seek below would otherwise report a second fault.
        // The first cause stays, but an emergency stop replaces it: a person asked for the
        // stop, and a host must not clear it as it may clear the other (a lapsed heartbeat).
        if self.fault.is_none() || cause == FaultCause::EmergencyStop {
            self.fault = Some(cause);
        }
        self.armed = 0;
        for ch in 0..MAX_LASERS {
            self.laser_off(ch as u8, now);
        }
        for g in 0..MAX_GALVOS {
            self.park(g as u8, now);
        }
        self.stop_motors(now, hard);
        for c in 0..MAX_VOICE_COILS {
            self.coil_fade(c as u8, now);
        }
        self.seq.clear();
        self.emit_reserved(Event::Fault { cause, tick: now });
        self.emit_reserved(Event::State { state: self.state(), armed: 0, tick: now });
    }

    // ---------------------------------------------------------------- configuration

    /// Applies a configuration item (validated by the caller against the device's
    /// capabilities). Refused while a sequence runs or an axis moves.
    pub fn configure(&mut self, item: &ConfigItem, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        if let Some(sequence) = self.running() {
            return Err(Error::InvalidState(DeviceState::Running { sequence }));
        }
        match *item {
            ConfigItem::Galvo(c) => self.configure_galvo(c, now),
            ConfigItem::Laser(c) => self.configure_laser(c, now),
            ConfigItem::Stepper(c) => self.configure_stepper(c, now),
            ConfigItem::FilterWheel(c) => self.configure_wheel(c, now),
            ConfigItem::VoiceCoil(c) => self.configure_coil(c, now),
            ConfigItem::Camera(c) => self.configure_camera(c, now),
            ConfigItem::Safety(s) => {
                self.heartbeat.timeout = u64::from(s.heartbeat_timeout_ticks);
                Ok(())
            }
        }
    }

    // ---------------------------------------------------------------- commands

    fn check_not_faulted(&self) -> Result<(), Error> {
        self.fault.map_or(Ok(()), |c| Err(Error::Faulted(c)))
    }

    /// Executes one action now (jog, park, test shot).
    pub fn immediate(&mut self, action: &Action, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        if let Some(sequence) = self.running() {
            return Err(Error::InvalidState(DeviceState::Running { sequence }));
        }
        if matches!(action, Action::Wait { .. }) {
            return Err(Error::InvalidState(self.state()));
        }
        self.check_action(action)?;
        if let Action::Laser { channel, on: true } = *action {
            if self.armed & bit(channel) == 0 {
                return Err(Error::NotArmed { channel });
            }
        }
        if let Some(axis) = self.busy_axis(action) {
            return Err(Error::Busy { axis });
        }
        self.execute(action, now, Origin::Immediate);
        Ok(())
    }

    /// Loads a chunk of a sequence; answers the buffer after it.
    pub fn load(&mut self, chunk: &Chunk) -> Result<BufferStatus, Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        self.seq.check_chunk(chunk)?;
        for item in &chunk.items {
            self.check_item(&item.action)?;
        }
        self.seq.append(chunk);
        Ok(self.seq.status())
    }

    /// A sequence item against the configuration and arming as they are now.
    fn check_item(&self, action: &Action) -> Result<(), Error> {
        self.check_action(action)?;
        if let Action::Laser { channel, on: true } = *action {
            if self.armed & bit(channel) == 0 {
                return Err(Error::NotArmed { channel });
            }
        }
        Ok(())
    }

    /// Starts the loaded sequence `sequence`.
    pub fn start(&mut self, sequence: u32, at: StartAt, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        if self.seq.phase != Phase::Loaded || self.seq.id != sequence {
            if let Some(running) = self.running() {
                return Err(Error::InvalidState(DeviceState::Running { sequence: running }));
            }
            return Err(Error::NoSuchSequence { sequence });
        }
        let start = match at {
            StartAt::Now => now,
            StartAt::Tick(t) if t < now => return Err(Error::StartInPast { now }),
            StartAt::Tick(t) => t,
        };
        // The configuration may have changed since the items were loaded (a narrower galvo
        // range, new stepper limits, a disarm): they must hold under what holds now. Items
        // loaded after the start are checked as they arrive, and nothing is configured while
        // a sequence runs.
        for item in self.seq.items() {
            self.check_item(&item.action)?;
        }
        self.seq.start(start);
        self.emit_state(now);
        // A sequence loaded without items ends at once; one loaded short is an underrun.
        self.check_sequence_end(now);
        Ok(())
    }

    /// Stops the running (or loaded) sequence: lasers off, axes decelerate, galvos park.
    pub fn abort(&mut self, sequence: u32, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        if self.seq.phase == Phase::Idle || self.seq.id != sequence {
            return Err(Error::NoSuchSequence { sequence });
        }
        let was_running = self.seq.phase == Phase::Running;
        self.seq.clear();
        if was_running {
            for ch in 0..MAX_LASERS {
                self.laser_off(ch as u8, now);
            }
            for g in 0..MAX_GALVOS {
                self.park(g as u8, now);
            }
            self.stop_motors(now, false);
            self.emit_state(now);
        }
        Ok(())
    }

    // ---------------------------------------------------------------- checks

    /// Whether `action` is acceptable for the configuration (not the timing): the peripheral
    /// exists and is configured, and every value lies in its configured range.
    fn check_action(&self, action: &Action) -> Result<(), Error> {
        match *action {
            Action::GalvoPoint { galvo, to } => {
                let c = self.galvo_config(galvo)?;
                check_galvo_point(&c, to)
            }
            Action::GalvoLine { galvo, to, duration, steps } => {
                self.check_galvo_line(galvo, to, duration, steps)
            }
            Action::Laser { channel, .. } => self.laser_config(channel).map(|_| ()),
            Action::StepperMove { axis, target, profile } => self.check_stepper_move(axis, target, profile),
            Action::FilterWheel { wheel, slot } => self.check_wheel_to(wheel, slot),
            Action::VoiceCoil { channel, ref partials, .. } => self.check_coil(channel, partials),
            Action::Trigger { camera, .. } => self.camera_config(camera).map(|_| ()),
            Action::Wait { until, .. } => match until {
                WaitFor::MoveDone(AxisRef::Stepper(i)) => self.stepper_config(i).map(|_| ()),
                WaitFor::MoveDone(AxisRef::FilterWheel(i)) => self.wheel_config(i).map(|_| ()),
                WaitFor::LaserReady(ch) => self.laser_config(ch).map(|_| ()),
                WaitFor::ExposureEnd(cam) => self.camera_config(cam).map(|_| ()),
            },
            Action::Marker { .. } => Ok(()),
        }
    }

    // ---------------------------------------------------------------- execution

    fn execute(&mut self, action: &Action, t: u64, origin: Origin) {
        match *action {
            Action::GalvoPoint { galvo, to } => self.galvo_point(galvo, to, t),
            Action::GalvoLine { galvo, to, duration, steps } => {
                self.galvo_line(galvo, to, duration, steps, t)
            }
            Action::Laser { channel, on } => self.switch_laser(channel, on, t),
            Action::StepperMove { axis, target, profile } => self.stepper_move(axis, target, profile, t),
            Action::FilterWheel { wheel, slot } => self.wheel_to(wheel, slot, t),
            Action::VoiceCoil { channel, ramp, ref partials } => self.coil_set(channel, partials, ramp, t),
            Action::Trigger { camera, exposure } => self.trigger(camera, exposure, t, origin),
            Action::Wait { until, timeout } => {
                if let Origin::Sequence(item) = origin {
                    self.seq.waiting =
                        Some(Waiting { until, deadline: t.saturating_add(u64::from(timeout)), item });
                    // It may already hold.
                    self.check_wait(t);
                }
            }
            Action::Marker { id } => {
                let (sequence, item) = match origin {
                    Origin::Sequence(i) => (self.seq.id, i),
                    Origin::Immediate => (IMMEDIATE_SEQUENCE, 0),
                };
                self.emit(Event::Marker { sequence, item, id, tick: t }, t);
            }
        }
    }

    // ---------------------------------------------------------------- the schedule

    /// The earliest tick at which the rig has work, if any.
    pub fn next_due(&self) -> Option<u64> {
        if self.due_fresh {
            self.due.tick()
        } else {
            self.compute_due().tick()
        }
    }

    fn compute_due(&self) -> Due {
        let mut due = Due::NOTHING;
        for (i, a) in self.axes.iter().enumerate() {
            due.add(a.motor.next_due(), 1 << i);
        }
        for (i, w) in self.wheels.iter().enumerate() {
            due.add(w.motor.next_due(), 1 << (work::WHEEL0 + i as u32));
        }
        for g in &self.galvos {
            if let Some(l) = &g.line {
                due.add(Some(l.tick_of(l.done.saturating_add(1))), work::LINES);
            }
        }
        for k in &self.cameras {
            due.add(k.pulse_end, work::PULSES);
        }
        for l in &self.lasers {
            due.add(self.laser_deadline(l), work::LASERS);
        }
        if self.blanking {
            due.add(Some(self.blank_until), work::BLANK);
        }
        if self.heartbeat.watching && self.fault.is_none() {
            due.add(Some(self.heartbeat.last.saturating_add(self.heartbeat.timeout)), work::HEARTBEAT);
        }
        due.add(self.seq.next_due(), work::SEQUENCE);
        due.add(self.seq.waiting.map(|w| w.deadline), work::WAIT);
        for k in &self.coils {
            due.add(self.coil_due(k), work::COILS);
        }
        due
    }

    /// Does all work due at or before `now`, in tick order.
    pub fn poll(&mut self, now: u64) {
        self.polled_at = now;
        let mut due = if self.due_fresh { self.due } else { self.compute_due() };
        while let Some(t) = due.tick().filter(|&t| t <= now) {
            self.run_at(t, due.what);
            due = self.compute_due();
        }
        let captured = self.take_captures(now);
        // An interlock seen open now acts now, after the work that was due before.
        let tripped = self.check_interlocks(now);
        // Either may change the schedule (a wait that ends, the safe state).
        self.due = due;
        self.due_fresh = !captured && !tripped;
    }

    /// Does the work due at `t`, the earliest due tick, where `what` ([`work`] bits) says what
    /// was due when `t` was found. A section not in `what` has nothing to do at `t`: nothing
    /// before it in this order can make it due (only the sequence's section can become due
    /// mid-way, through a wait that ends, and `poll` comes back for it at the same tick), so
    /// skipping it changes nothing but the cost.
    fn run_at(&mut self, t: u64, what: u32) {
        let _ = self.take_captures(t);
        // Steps.
        if what & work::AXES != 0 {
            for i in 0..MAX_STEPPERS {
                let Some(a) = self.axes.get_mut(i).filter(|_| what & (1 << i) != 0) else { continue };
                if a.motor.next_due() == Some(t) {
                    let r = a.motor.step(&mut self.board, t);
                    self.after_step(AxisRef::Stepper(i as u8), r, t);
                }
            }
        }
        if what & work::WHEELS != 0 {
            for i in 0..MAX_FILTER_WHEELS {
                let bit = 1 << (work::WHEEL0 + i as u32);
                let Some(w) = self.wheels.get_mut(i).filter(|_| what & bit != 0) else { continue };
                if w.motor.next_due() == Some(t) {
                    let r = w.motor.step(&mut self.board, t);
                    self.after_step(AxisRef::FilterWheel(i as u8), r, t);
                }
            }
        }
        if what & work::LINES != 0 {
            self.run_lines(t);
        }
        if what & work::PULSES != 0 {
            self.run_pulse_ends(t);
        }
        if what & work::LASERS != 0 {
            self.run_laser_timers(t);
        }
        if what & work::BLANK != 0 && self.blanking && t >= self.blank_until {
            self.blanking = false;
            self.update_laser_outputs(t);
        }
        if what & work::HEARTBEAT != 0
            && self.heartbeat.watching
            && self.fault.is_none()
            && t >= self.heartbeat.last.saturating_add(self.heartbeat.timeout)
        {
            self.enter_safe_state(FaultCause::HeartbeatLost, t);
        }
        if what & work::WAIT != 0 {
            if let Some(w) = self.seq.waiting {
                if t >= w.deadline {
                    let cause = FaultCause::WaitTimeout { sequence: self.seq.id, item: w.item };
                    self.enter_safe_state(cause, t);
                }
            }
        }
        if what & work::SEQUENCE != 0 {
            self.run_items(t);
        }
        if what & work::COILS != 0 {
            for c in 0..MAX_VOICE_COILS {
                let due = self.coils.get(c).and_then(|k| self.coil_due(k));
                if due == Some(t) {
                    self.coil_block(c as u8, t);
                }
            }
        }
    }

    fn run_items(&mut self, t: u64) {
        while self.seq.next_due() == Some(t) {
            if self.polled_at.saturating_sub(t) > late_limit(self.tick_hz) {
                // The run loop woke too late to honour the schedule: stop rather than drift.
                // Stamped with the item's tick, so outputs and events stay in tick order with
                // the rest of this catch-up (the pins change now, as late as the wake-up).
                let cause = FaultCause::Late { sequence: self.seq.id, item: self.seq.executed };
                self.enter_safe_state(cause, t);
                break;
            }
            let Some((index, item)) = self.seq.pop(t) else { break };
            self.execute(&item.action, t, Origin::Sequence(index));
            if self.seq.phase != Phase::Running {
                break; // the item ended the sequence (a fault)
            }
            if let Some(status) = self.seq.take_report() {
                self.emit(Event::Buffer(status), t);
            }
            self.check_sequence_end(t);
        }
    }

    /// After an item (or at the start): done if the buffer is dry after the last chunk, an
    /// underrun if it is dry before.
    fn check_sequence_end(&mut self, t: u64) {
        if !self.seq.is_dry() {
            return;
        }
        let sequence = self.seq.id;
        if self.seq.complete {
            let items = self.seq.executed;
            self.seq.clear();
            // Lasers never outlive their sequence.
            for ch in 0..MAX_LASERS {
                self.laser_off(ch as u8, t);
            }
            self.emit(Event::SequenceDone { sequence, items, tick: t }, t);
            self.emit_state(t);
        } else {
            let item = self.seq.executed;
            self.emit(Event::Underrun { sequence, item, tick: t }, t);
            self.enter_safe_state(FaultCause::Underrun { sequence }, t);
        }
    }

    fn check_wait(&mut self, t: u64) {
        let Some(w) = self.seq.waiting else { return };
        let holds = match w.until {
            WaitFor::MoveDone(AxisRef::Stepper(i)) => {
                self.axes.get(usize::from(i)).is_some_and(|a| !a.motor.is_moving())
            }
            WaitFor::MoveDone(AxisRef::FilterWheel(i)) => {
                self.wheels.get(usize::from(i)).is_some_and(|w| !w.motor.is_moving())
            }
            WaitFor::LaserReady(ch) => self.lasers.get(usize::from(ch)).is_some_and(|l| l.on && l.ready),
            WaitFor::ExposureEnd(cam) => self.cameras.get(usize::from(cam)).is_some_and(|k| k.exposure_ended),
        };
        if holds {
            self.seq.waiting = None;
            self.seq.last_due = t;
            self.check_sequence_end(t);
        }
    }
}

/// A peripheral's configuration, or the error that says why there is none: an index beyond
/// the device's `count`, or one never configured.
fn configured<T>(kind: Peripheral, index: u8, count: u8, config: Option<T>) -> Result<T, Error> {
    if index >= count {
        return Err(Error::NoSuchPeripheral { kind, index, count });
    }
    config.ok_or(Error::NotConfigured { kind, index })
}
