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

mod motor;
mod sequencer;

use heapless::{Deque, Vec};
use lightrig_protocol::config::{
    CameraConfig, ConfigItem, FilterWheelConfig, GalvoConfig, HomingMode, Input, LaserConfig, Polarity,
    StepperConfig, VoiceCoilConfig, Xy,
};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{DeviceState, Event, FaultCause, Snapshot, Switch, TriggerEvent};
use lightrig_protocol::sequence::{Action, AxisRef, BufferStatus, Chunk, Partial, StartAt, WaitFor};
use lightrig_protocol::session::Capabilities;
use lightrig_protocol::{
    Error, MAX_CAMERAS, MAX_FILTER_WHEELS, MAX_GALVOS, MAX_LASERS, MAX_PARTIALS, MAX_STEPPERS,
    MAX_VOICE_COILS,
};

use crate::hal::Board;
use crate::synth::Synth;
use motor::{Motor, Purpose, Stepped};
pub use sequencer::SEQUENCE_BUFFER;
use sequencer::{Phase, Sequencer, Waiting};

/// Events the rig holds until the controller hands them to the link.
pub const EVENT_QUEUE: usize = 64;
/// Samples per voice-coil DMA block.
pub const VOICE_COIL_BLOCK: usize = 64;
/// A voice-coil sample plays this many blocks after its nominal tick: the block is computed
/// once its window has passed (so every setting inside it lands on its exact sample), then
/// waits one block in the DMA double buffer. Constant, so the host plans around it.
pub const VOICE_COIL_LATENCY_BLOCKS: u64 = 2;
/// Fade to silence in the safe state, milliseconds.
pub const FADE_MS: u32 = 20;
/// Heartbeat timeout until the host configures one, milliseconds.
pub const DEFAULT_HEARTBEAT_MS: u32 = 1000;
/// Settings a voice-coil channel holds for its current block.
const COIL_PENDING: usize = 8;
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

struct Galvo {
    config: Option<GalvoConfig>,
    pos: Xy,
    line: Option<Line>,
}

/// A galvo sweep in progress.
#[derive(Clone, Copy)]
struct Line {
    from: Xy,
    to: Xy,
    start: u64,
    duration: u32,
    steps: u16,
    /// Updates made.
    done: u16,
}

impl Line {
    fn tick_of(&self, i: u16) -> u64 {
        self.start.saturating_add(u64::from(self.duration) * u64::from(i) / u64::from(self.steps.max(1)))
    }

    fn point(&self, i: u16) -> Xy {
        let lerp = |a: u16, b: u16| {
            let d = i64::from(b) - i64::from(a);
            let v = i64::from(a) + d * i64::from(i) / i64::from(self.steps.max(1));
            v.clamp(0, i64::from(u16::MAX)) as u16
        };
        Xy { x: lerp(self.from.x, self.to.x), y: lerp(self.from.y, self.to.y) }
    }
}

#[derive(Clone, Copy)]
struct Laser {
    config: Option<LaserConfig>,
    /// Asked on (by an item or `Immediate`).
    on: bool,
    /// Output level is "emit".
    emitting: bool,
    on_since: u64,
    /// Warm-up finished since the last turn-on.
    ready: bool,
}

struct Axis {
    config: Option<StepperConfig>,
    motor: Motor,
    homed: bool,
}

struct Wheel {
    config: Option<FilterWheelConfig>,
    /// Position in motor steps, 0 = centre of slot 0, kept in `0..steps_per_rev`.
    motor: Motor,
    homed: bool,
    /// The slot the wheel rests at (`None` while moving or not homed).
    slot: Option<u8>,
}

struct Camera {
    config: Option<CameraConfig>,
    /// Tick at which the trigger pulse in progress ends.
    pulse_end: Option<u64>,
    last_edge: Option<u64>,
    exposure_active: bool,
    /// The exposure input went inactive since the last trigger.
    exposure_ended: bool,
}

struct Coil {
    config: Option<VoiceCoilConfig>,
    synth: Synth,
    /// Tick of sample 0.
    t0: u64,
    /// First sample of the next block to compute.
    next_sample: u64,
    /// Settings that take effect inside the block being collected, by sample.
    pending: Deque<(u64, CoilSetting), COIL_PENDING>,
}

#[derive(Clone)]
enum CoilSetting {
    Set { partials: Vec<Partial, MAX_PARTIALS>, ramp: u32 },
    Fade { ramp: u32 },
}

struct Heartbeat {
    timeout: u64,
    last: u64,
    watching: bool,
}

/// Outgoing events, with room kept for the overflow fault.
struct Events {
    queue: Deque<Event, EVENT_QUEUE>,
    dropped: u32,
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
            events: Events { queue: Deque::new(), dropped: 0 },
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

    /// Lasers emitting, one bit per channel.
    pub fn lasers_on(&self) -> u8 {
        self.lasers.iter().enumerate().fold(0, |m, (i, l)| if l.emitting { m | bit(i as u8) } else { m })
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
        self.events.queue.pop_front()
    }

    /// Events dropped because the queue was full (after the overflow fault).
    pub fn dropped_events(&self) -> u32 {
        self.events.dropped
    }

    /// A stepper axis' position in steps.
    pub fn axis_position(&self, axis: u8) -> Option<i64> {
        self.axes.get(usize::from(axis)).map(|a| a.motor.position)
    }

    /// A galvo pair's output position.
    pub fn galvo_position(&self, galvo: u8) -> Option<Xy> {
        self.galvos.get(usize::from(galvo)).map(|g| g.pos)
    }

    // ---------------------------------------------------------------- host contact & safety

    /// The host spoke at `now` (any command counts as a heartbeat). `watch` starts the
    /// heartbeat watchdog (the session is open).
    pub fn host_seen(&mut self, now: u64, watch: bool) {
        self.due_fresh = false;
        self.heartbeat.last = now;
        self.heartbeat.watching |= watch;
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
            self.events.dropped = self.events.dropped.saturating_add(1);
            if self.fault.is_none() {
                self.enter_safe_state(FaultCause::EventOverflow, now);
            }
            return;
        }
        let _ = self.events.queue.push_back(event);
    }

    /// For the safe state's own events: may use the reserved slots.
    fn emit_reserved(&mut self, event: Event) {
        if self.events.queue.push_back(event).is_err() {
            self.events.dropped = self.events.dropped.saturating_add(1);
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
        if self.fault.is_none() {
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

    fn stop_motors(&mut self, now: u64, hard: bool) {
        for i in 0..MAX_STEPPERS {
            let purpose = match self.axes.get_mut(i) {
                Some(a) if hard => a.motor.stop_now(),
                Some(a) => a.motor.decelerate(),
                None => None,
            };
            if let Some(p) = purpose {
                self.motor_finished(AxisRef::Stepper(i as u8), p, now, false);
            }
        }
        for i in 0..MAX_FILTER_WHEELS {
            let purpose = match self.wheels.get_mut(i) {
                Some(w) if hard => w.motor.stop_now(),
                Some(w) => w.motor.decelerate(),
                None => None,
            };
            if let Some(p) = purpose {
                self.motor_finished(AxisRef::FilterWheel(i as u8), p, now, false);
            }
        }
    }

    fn park(&mut self, galvo: u8, now: u64) {
        let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
        g.line = None;
        if let Some(c) = g.config {
            g.pos = c.park;
            // Parking is the safe state's last resort; a failing output cannot be helped here.
            let _ = self.board.set_galvo(galvo, c.park, now);
        }
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
            ConfigItem::Galvo(c) => {
                let g = self.galvos.get_mut(usize::from(c.galvo)).ok_or(Error::Unsupported)?;
                // The first configuration has no position to jump from.
                let jumps = g.config.is_some() && g.pos != c.park;
                g.config = Some(c);
                g.line = None;
                g.pos = c.park;
                if jumps {
                    // Going to the new park position is a jump like any other: blanked.
                    self.blank_until = self.blank_until.max(now.saturating_add(u64::from(c.settle_ticks)));
                    self.blanking = true;
                    self.update_laser_outputs(now);
                }
                if self.board.set_galvo(c.galvo, c.park, now).is_err() {
                    self.enter_safe_state(FaultCause::GalvoOutput { galvo: c.galvo }, now);
                }
            }
            ConfigItem::Laser(c) => {
                self.laser_off(c.channel, now);
                let l = self.lasers.get_mut(usize::from(c.channel)).ok_or(Error::Unsupported)?;
                l.config = Some(c);
                self.board.set_laser(c.channel, level(c.enable, false), now);
            }
            ConfigItem::Stepper(c) => {
                let a = self.axes.get_mut(usize::from(c.axis)).ok_or(Error::Unsupported)?;
                if a.motor.is_moving() {
                    return Err(Error::Busy { axis: AxisRef::Stepper(c.axis) });
                }
                a.config = Some(c);
                a.homed = c.homing.mode == HomingMode::None;
                a.motor.configure(&mut self.board, c.invert_dir, c.enable, now);
            }
            ConfigItem::FilterWheel(c) => {
                let w = self.wheels.get_mut(usize::from(c.wheel)).ok_or(Error::Unsupported)?;
                if w.motor.is_moving() {
                    return Err(Error::Busy { axis: AxisRef::FilterWheel(c.wheel) });
                }
                w.config = Some(c);
                w.homed = false;
                w.slot = None;
                w.motor.configure(&mut self.board, c.invert_dir, c.enable, now);
            }
            ConfigItem::VoiceCoil(c) => {
                let k = self.coils.get_mut(usize::from(c.channel)).ok_or(Error::Unsupported)?;
                if !k.synth.is_silent() || !k.pending.is_empty() {
                    // A restart would click: fade the channel first (an empty partial list).
                    return Err(Error::InvalidState(self.state()));
                }
                *k = Coil {
                    config: Some(c),
                    synth: Synth::new(c.sample_rate_hz),
                    t0: now,
                    next_sample: 0,
                    pending: Deque::new(),
                };
            }
            ConfigItem::Camera(c) => {
                let k = self.cameras.get_mut(usize::from(c.camera)).ok_or(Error::Unsupported)?;
                k.config = Some(c);
                k.pulse_end = None;
                self.board.set_trigger(c.camera, level(c.polarity, false), now);
            }
            ConfigItem::Safety(s) => {
                self.heartbeat.timeout = u64::from(s.heartbeat_timeout_ticks);
            }
        }
        Ok(())
    }

    // ---------------------------------------------------------------- commands

    fn check_not_faulted(&self) -> Result<(), Error> {
        self.fault.map_or(Ok(()), |c| Err(Error::Faulted(c)))
    }

    /// Allows the lasers in `mask` to be turned on.
    pub fn arm(&mut self, mask: u8, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        for ch in 0..8u8 {
            if mask & bit(ch) != 0 {
                self.laser_config(ch)?;
            }
        }
        self.armed = mask;
        // Channels no longer armed go dark.
        for ch in 0..MAX_LASERS {
            if mask & bit(ch as u8) == 0 {
                self.laser_off(ch as u8, now);
            }
        }
        self.emit_state(now);
        Ok(())
    }

    /// Turns every laser off and disallows them. Always allowed.
    pub fn disarm(&mut self, now: u64) {
        self.due_fresh = false;
        self.armed = 0;
        for ch in 0..MAX_LASERS {
            self.laser_off(ch as u8, now);
        }
        self.emit_state(now);
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

    /// Starts homing an axis.
    pub fn home(&mut self, axis: AxisRef, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        if let Some(sequence) = self.running() {
            return Err(Error::InvalidState(DeviceState::Running { sequence }));
        }
        match axis {
            AxisRef::Stepper(i) => {
                let c = self.stepper_config(i)?;
                let a = self.axes.get_mut(usize::from(i)).ok_or(Error::Unsupported)?;
                if a.motor.is_moving() {
                    return Err(Error::Busy { axis });
                }
                let h = c.homing;
                let forward = match h.mode {
                    HomingMode::None => {
                        a.motor.position = i64::from(h.position);
                        a.homed = true;
                        self.emit(Event::Homed { axis, position: h.position, tick: now }, now);
                        return Ok(());
                    }
                    HomingMode::ToMinLimit => false,
                    HomingMode::ToMaxLimit | HomingMode::ToIndex => true,
                };
                a.homed = false;
                let span = seek_span(&c);
                let r = a.motor.start(
                    &mut self.board,
                    span,
                    forward,
                    h.speed,
                    c.accel,
                    self.tick_hz,
                    now,
                    Purpose::HomeSeek,
                );
                r.map_err(|_| Error::OutOfRange { kind: Peripheral::Stepper, index: i })
            }
            AxisRef::FilterWheel(i) => {
                let c = self.wheel_config(i)?;
                let w = self.wheels.get_mut(usize::from(i)).ok_or(Error::Unsupported)?;
                if w.motor.is_moving() {
                    return Err(Error::Busy { axis });
                }
                w.homed = false;
                w.slot = None;
                // One and a half turns always pass the index mark.
                let span = c.steps_per_rev.saturating_add(c.steps_per_rev / 2);
                let r = w.motor.start(
                    &mut self.board,
                    span,
                    true,
                    c.max_speed,
                    c.accel,
                    self.tick_hz,
                    now,
                    Purpose::WheelSeek,
                );
                r.map_err(|_| Error::OutOfRange { kind: Peripheral::FilterWheel, index: i })
            }
        }
    }

    /// Loads a chunk of a sequence; answers the buffer after it.
    pub fn load(&mut self, chunk: &Chunk) -> Result<BufferStatus, Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        self.seq.check_chunk(chunk)?;
        for item in &chunk.items {
            self.check_action(&item.action)?;
            if let Action::Laser { channel, on: true } = item.action {
                if self.armed & bit(channel) == 0 {
                    return Err(Error::NotArmed { channel });
                }
            }
        }
        self.seq.append(chunk);
        Ok(self.seq.status())
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

    fn laser_config(&self, ch: u8) -> Result<LaserConfig, Error> {
        configured(
            Peripheral::Laser,
            ch,
            self.caps.lasers,
            self.lasers.get(usize::from(ch)).and_then(|l| l.config),
        )
    }

    fn stepper_config(&self, i: u8) -> Result<StepperConfig, Error> {
        configured(
            Peripheral::Stepper,
            i,
            self.caps.steppers,
            self.axes.get(usize::from(i)).and_then(|a| a.config),
        )
    }

    fn wheel_config(&self, i: u8) -> Result<FilterWheelConfig, Error> {
        let c = self.wheels.get(usize::from(i)).and_then(|w| w.config);
        configured(Peripheral::FilterWheel, i, self.caps.filter_wheels, c)
    }

    fn galvo_config(&self, i: u8) -> Result<GalvoConfig, Error> {
        configured(
            Peripheral::Galvo,
            i,
            self.caps.galvos,
            self.galvos.get(usize::from(i)).and_then(|g| g.config),
        )
    }

    fn camera_config(&self, i: u8) -> Result<CameraConfig, Error> {
        configured(
            Peripheral::Camera,
            i,
            self.caps.cameras,
            self.cameras.get(usize::from(i)).and_then(|c| c.config),
        )
    }

    fn coil_config(&self, i: u8) -> Result<VoiceCoilConfig, Error> {
        let c = self.coils.get(usize::from(i)).and_then(|c| c.config);
        configured(Peripheral::VoiceCoil, i, self.caps.voice_coils, c)
    }

    /// Whether `action` is acceptable for the configuration (not the timing): the peripheral
    /// exists and is configured, and every value lies in its configured range.
    fn check_action(&self, action: &Action) -> Result<(), Error> {
        match *action {
            Action::GalvoPoint { galvo, to } => {
                let c = self.galvo_config(galvo)?;
                check_galvo_point(&c, to)
            }
            Action::GalvoLine { galvo, to, duration, steps } => {
                let c = self.galvo_config(galvo)?;
                check_galvo_point(&c, to)?;
                let ok = steps >= 1 && u32::from(steps) <= duration.max(1);
                ok.then_some(()).ok_or(Error::OutOfRange { kind: Peripheral::Galvo, index: galvo })
            }
            Action::Laser { channel, .. } => self.laser_config(channel).map(|_| ()),
            Action::StepperMove { axis, target, profile } => {
                let c = self.stepper_config(axis)?;
                let homed = self.axes.get(usize::from(axis)).is_some_and(|a| a.homed);
                if !homed {
                    return Err(Error::NotHomed { axis: AxisRef::Stepper(axis) });
                }
                let out = Error::OutOfRange { kind: Peripheral::Stepper, index: axis };
                if let Some(r) = c.limits {
                    if target < r.min || target > r.max {
                        return Err(out);
                    }
                }
                let (speed, accel) = move_profile(&c, profile);
                if speed > c.max_speed || accel > c.accel || u64::from(speed) * 2 > u64::from(self.tick_hz) {
                    return Err(out);
                }
                Ok(())
            }
            Action::FilterWheel { wheel, slot } => {
                let c = self.wheel_config(wheel)?;
                if !self.wheels.get(usize::from(wheel)).is_some_and(|w| w.homed) {
                    return Err(Error::NotHomed { axis: AxisRef::FilterWheel(wheel) });
                }
                if slot >= c.slots || u64::from(c.max_speed) * 2 > u64::from(self.tick_hz) {
                    return Err(Error::OutOfRange { kind: Peripheral::FilterWheel, index: wheel });
                }
                Ok(())
            }
            Action::VoiceCoil { channel, ref partials, .. } => {
                let c = self.coil_config(channel)?;
                let out = Error::OutOfRange { kind: Peripheral::VoiceCoil, index: channel };
                if partials.len() > usize::from(self.caps.partials_per_coil) {
                    return Err(out);
                }
                let sum: u32 = partials.iter().map(|p| u32::from(p.amplitude)).sum();
                if sum > u32::from(c.max_amplitude) {
                    return Err(out);
                }
                // Frequencies: above zero, below Nyquist, no duplicates (the synthesiser's rules).
                let synth = self.coils.get(usize::from(channel)).map(|k| &k.synth);
                synth.map_or(Err(out), |s| s.check(partials).map_err(|_| out))
            }
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

    fn busy_axis(&self, action: &Action) -> Option<AxisRef> {
        match *action {
            Action::StepperMove { axis, .. } => self
                .axes
                .get(usize::from(axis))
                .is_some_and(|a| a.motor.is_moving())
                .then_some(AxisRef::Stepper(axis)),
            Action::FilterWheel { wheel, .. } => self
                .wheels
                .get(usize::from(wheel))
                .is_some_and(|w| w.motor.is_moving())
                .then_some(AxisRef::FilterWheel(wheel)),
            _ => None,
        }
    }

    // ---------------------------------------------------------------- execution

    fn execute(&mut self, action: &Action, t: u64, origin: Origin) {
        match *action {
            Action::GalvoPoint { galvo, to } => {
                let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
                let Some(c) = g.config else { return };
                g.line = None;
                if g.pos != to {
                    // Blank every laser while the mirrors jump and settle.
                    self.blank_until = self.blank_until.max(t.saturating_add(u64::from(c.settle_ticks)));
                    self.blanking = true;
                    self.update_laser_outputs(t);
                }
                self.galvo_write(galvo, to, t);
            }
            Action::GalvoLine { galvo, to, duration, steps } => {
                let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
                g.line = Some(Line { from: g.pos, to, start: t, duration, steps, done: 0 });
            }
            Action::Laser { channel, on } => {
                if !on {
                    self.laser_off(channel, t);
                } else if self.armed & bit(channel) == 0 {
                    // Disarmed since the chunk was loaded: the host's disarm wins.
                    warn!("laser {} not armed; item skipped", channel);
                } else {
                    self.laser_on(channel, t);
                }
            }
            Action::StepperMove { axis, target, profile } => {
                let Ok(c) = self.stepper_config(axis) else { return };
                let Some(a) = self.axes.get_mut(usize::from(axis)) else { return };
                let id = AxisRef::Stepper(axis);
                if !a.homed {
                    // Reconfigured between loading and executing.
                    self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
                    return;
                }
                if a.motor.is_moving() {
                    self.enter_safe_state(FaultCause::AxisBusy { axis: id }, t);
                    return;
                }
                let distance = i64::from(target) - a.motor.position;
                let steps = u32::try_from(distance.unsigned_abs()).unwrap_or(u32::MAX);
                if steps == 0 {
                    self.emit(Event::MoveDone { axis: id, position: target, tick: t }, t);
                    return;
                }
                let (speed, accel) = move_profile(&c, profile);
                let r = a.motor.start(
                    &mut self.board,
                    steps,
                    distance > 0,
                    speed,
                    accel,
                    self.tick_hz,
                    t,
                    Purpose::Move,
                );
                if r.is_err() {
                    // `check_action` refused every profile the planner cannot run; a move too
                    // long for its tick arithmetic is the one left.
                    self.enter_safe_state(FaultCause::Limit { axis: id }, t);
                }
            }
            Action::FilterWheel { wheel, slot } => self.wheel_to(wheel, slot, t),
            Action::VoiceCoil { channel, ramp, ref partials } => {
                let setting = CoilSetting::Set { partials: partials.clone(), ramp };
                self.coil_schedule(channel, t, setting);
            }
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

    fn galvo_write(&mut self, galvo: u8, to: Xy, t: u64) {
        if let Some(g) = self.galvos.get_mut(usize::from(galvo)) {
            g.pos = to;
        }
        if self.board.set_galvo(galvo, to, t).is_err() {
            self.enter_safe_state(FaultCause::GalvoOutput { galvo }, t);
        }
    }

    fn laser_on(&mut self, channel: u8, t: u64) {
        let Some(l) = self.lasers.get_mut(usize::from(channel)) else { return };
        let Some(c) = l.config else { return };
        if l.on {
            return;
        }
        if let Input::Wired(p) = c.interlock {
            if !level(p, true).eq(&self.board.interlock_level(channel)) {
                self.enter_safe_state(FaultCause::Interlock { channel }, t);
                return;
            }
        }
        l.on = true;
        l.on_since = t;
        l.ready = false;
        self.update_laser_outputs(t);
    }

    fn laser_off(&mut self, channel: u8, t: u64) {
        let Some(l) = self.lasers.get_mut(usize::from(channel)) else { return };
        l.on = false;
        l.ready = false;
        self.update_laser_outputs(t);
    }

    /// Drives every laser output to what it should be at `t`: on, armed and not blanked.
    fn update_laser_outputs(&mut self, t: u64) {
        let blanked = t < self.blank_until;
        for (ch, l) in self.lasers.iter_mut().enumerate() {
            let Some(c) = l.config else { continue };
            let emit = l.on && !blanked && self.armed & bit(ch as u8) != 0;
            if emit != l.emitting {
                l.emitting = emit;
                self.board.set_laser(ch as u8, level(c.enable, emit), t);
            }
        }
    }

    fn trigger(&mut self, camera: u8, exposure: u32, t: u64, origin: Origin) {
        let Some(k) = self.cameras.get_mut(usize::from(camera)) else { return };
        let Some(c) = k.config else { return };
        let too_soon = k.pulse_end.is_some()
            || k.last_edge.is_some_and(|e| t.saturating_sub(e) < u64::from(c.min_interval_ticks));
        if too_soon {
            self.enter_safe_state(FaultCause::TriggerTooSoon { camera }, t);
            return;
        }
        let width = if exposure == 0 { c.pulse_ticks } else { exposure };
        k.pulse_end = Some(t.saturating_add(u64::from(width)));
        k.last_edge = Some(t);
        k.exposure_ended = false;
        self.board.set_trigger(camera, level(c.polarity, true), t);
        let (sequence, item, frame) = match origin {
            Origin::Sequence(i) => {
                let f = self.seq.frames.get_mut(usize::from(camera));
                let frame = f.map_or(0, |f| {
                    let n = *f;
                    *f = n.saturating_add(1);
                    n
                });
                (self.seq.id, i, frame)
            }
            Origin::Immediate => (IMMEDIATE_SEQUENCE, 0, 0),
        };
        let snapshot = self.snapshot();
        self.emit(
            Event::Trigger(TriggerEvent { sequence, item, frame, camera, tick: t, width, snapshot }),
            t,
        );
    }

    fn snapshot(&self) -> Snapshot {
        let mut s =
            Snapshot { galvos: Vec::new(), axes: Vec::new(), filters: Vec::new(), lasers: self.lasers_on() };
        for g in self.galvos.iter().take(usize::from(self.caps.galvos)) {
            let _ = s.galvos.push(g.pos);
        }
        for a in self.axes.iter().take(usize::from(self.caps.steppers)) {
            let _ = s.axes.push(a.motor.position.clamp(i32::MIN.into(), i32::MAX.into()) as i32);
        }
        for w in self.wheels.iter().take(usize::from(self.caps.filter_wheels)) {
            let _ = s.filters.push(w.slot);
        }
        s
    }

    fn wheel_to(&mut self, wheel: u8, slot: u8, t: u64) {
        let Ok(c) = self.wheel_config(wheel) else { return };
        let Some(w) = self.wheels.get_mut(usize::from(wheel)) else { return };
        let id = AxisRef::FilterWheel(wheel);
        if !w.homed {
            // `check_action` cannot know: homing may come between loading and executing.
            self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
            return;
        }
        if w.motor.is_moving() {
            self.enter_safe_state(FaultCause::AxisBusy { axis: id }, t);
            return;
        }
        let (delta, forward) = wheel_path(&c, w.motor.position, slot);
        if delta == 0 {
            w.slot = Some(slot);
            self.emit(Event::MoveDone { axis: id, position: i32::from(slot), tick: t }, t);
            return;
        }
        w.slot = None;
        let r = w.motor.start(
            &mut self.board,
            delta,
            forward,
            c.max_speed,
            c.accel,
            self.tick_hz,
            t,
            Purpose::WheelTo(slot),
        );
        if r.is_err() {
            self.enter_safe_state(FaultCause::Driver { axis: id }, t);
        }
    }

    // ---------------------------------------------------------------- voice coils

    fn coil_schedule(&mut self, channel: u8, t: u64, setting: CoilSetting) {
        let Some(k) = self.coils.get_mut(usize::from(channel)) else { return };
        let Some(c) = k.config else { return };
        let sample =
            sample_at_or_after(t.saturating_sub(k.t0), c.sample_rate_hz, self.tick_hz).max(k.next_sample);
        let ramp_samples = |ticks: u32| {
            let s = u64::from(ticks) * u64::from(c.sample_rate_hz) / u64::from(self.tick_hz.max(1));
            u32::try_from(s).unwrap_or(u32::MAX)
        };
        let setting = match setting {
            CoilSetting::Set { partials, ramp } => CoilSetting::Set { partials, ramp: ramp_samples(ramp) },
            CoilSetting::Fade { ramp } => CoilSetting::Fade { ramp: ramp_samples(ramp) },
        };
        if let Err((_, setting)) = k.pending.push_back((sample, setting)) {
            // More changes inside one block than a channel holds: apply the oldest now (a few
            // samples early) rather than lose one.
            if let Some((_, oldest)) = k.pending.pop_front() {
                apply_coil(&mut k.synth, oldest);
            }
            let _ = k.pending.push_back((sample, setting));
        }
    }

    fn coil_fade(&mut self, channel: u8, t: u64) {
        let ramp = ms_to_ticks(FADE_MS, self.tick_hz);
        self.coil_schedule(channel, t, CoilSetting::Fade { ramp: u32::try_from(ramp).unwrap_or(u32::MAX) });
    }

    /// Tick at which the block starting at `next_sample` may be computed: when its window ends.
    fn coil_due(&self, k: &Coil) -> Option<u64> {
        let c = k.config?;
        let end = k.next_sample + VOICE_COIL_BLOCK as u64;
        Some(k.t0.saturating_add(tick_of_sample(end, c.sample_rate_hz, self.tick_hz)))
    }

    fn coil_block(&mut self, channel: u8, t: u64) {
        let Some(k) = self.coils.get_mut(usize::from(channel)) else { return };
        let first = k.next_sample;
        let mut buf = [0i16; VOICE_COIL_BLOCK];
        let mut at = 0usize;
        while at < VOICE_COIL_BLOCK {
            // Settings due inside the block split it at their sample.
            let split = match k.pending.front() {
                Some(&(s, _)) if s <= first + at as u64 => {
                    if let Some((_, setting)) = k.pending.pop_front() {
                        apply_coil(&mut k.synth, setting);
                    }
                    continue;
                }
                Some(&(s, _)) => ((s - first) as usize).min(VOICE_COIL_BLOCK),
                None => VOICE_COIL_BLOCK,
            };
            if let Some(part) = buf.get_mut(at..split) {
                k.synth.fill(part);
            }
            at = split;
        }
        k.next_sample = first + VOICE_COIL_BLOCK as u64;
        self.board.write_samples(channel, first, &buf, t);
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

    fn laser_deadline(&self, l: &Laser) -> Option<u64> {
        // `on` first: most lasers are off, and the check is cheaper than the config's.
        if !l.on {
            return None;
        }
        let c = l.config.as_ref()?;
        let off = l.on_since.saturating_add(u64::from(c.max_on_ticks));
        if l.ready {
            Some(off)
        } else {
            Some(off.min(l.on_since.saturating_add(u64::from(c.warmup_ticks))))
        }
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

    /// Returns whether an open interlock tripped the safe state.
    fn check_interlocks(&mut self, now: u64) -> bool {
        let mut tripped = false;
        for ch in 0..MAX_LASERS {
            let Some(l) = self.lasers.get(ch) else { continue };
            let Some(c) = l.config.as_ref().filter(|_| l.on) else { continue };
            if let Input::Wired(p) = c.interlock {
                if self.board.interlock_level(ch as u8) != level(p, true) {
                    self.enter_safe_state(FaultCause::Interlock { channel: ch as u8 }, now);
                    tripped = true;
                }
            }
        }
        tripped
    }

    /// Returns whether the board had any capture to take.
    fn take_captures(&mut self, until: u64) -> bool {
        let mut any = false;
        while let Some(cap) = self.board.take_capture(until) {
            any = true;
            let Some(k) = self.cameras.get_mut(usize::from(cap.camera)) else { continue };
            let Some(c) = k.config else { continue };
            let Input::Wired(p) = c.exposure_input else { continue };
            let active = cap.level == level(p, true);
            if active == k.exposure_active {
                continue;
            }
            k.exposure_active = active;
            if !active {
                k.exposure_ended = true;
            }
            self.emit(Event::Exposure { camera: cap.camera, active, tick: cap.tick }, cap.tick);
            self.check_wait(cap.tick);
        }
        any
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

    fn run_lines(&mut self, t: u64) {
        for i in 0..MAX_GALVOS {
            let Some(line) = self.galvos.get(i).and_then(|g| g.line) else { continue };
            let n = line.done.saturating_add(1);
            if line.tick_of(n) != t {
                continue;
            }
            if let Some(g) = self.galvos.get_mut(i) {
                g.line = (n < line.steps).then_some(Line { done: n, ..line });
            }
            self.galvo_write(i as u8, line.point(n), t);
        }
    }

    fn run_pulse_ends(&mut self, t: u64) {
        for i in 0..MAX_CAMERAS {
            let Some(k) = self.cameras.get_mut(i) else { continue };
            if k.pulse_end == Some(t) {
                k.pulse_end = None;
                if let Some(c) = k.config {
                    self.board.set_trigger(i as u8, level(c.polarity, false), t);
                }
            }
        }
    }

    fn run_laser_timers(&mut self, t: u64) {
        for ch in 0..MAX_LASERS {
            let Some(l) = self.lasers.get(ch).filter(|l| l.on).copied() else { continue };
            let Some(c) = l.config else { continue };
            if t >= l.on_since.saturating_add(u64::from(c.max_on_ticks)) {
                self.enter_safe_state(FaultCause::LaserOnTime { channel: ch as u8 }, t);
            } else if !l.ready && t >= l.on_since.saturating_add(u64::from(c.warmup_ticks)) {
                if let Some(l) = self.lasers.get_mut(ch) {
                    l.ready = true;
                }
                self.emit(Event::LaserReady { channel: ch as u8, tick: t }, t);
                self.check_wait(t);
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

    fn after_step(&mut self, id: AxisRef, stepped: Stepped, t: u64) {
        // Switches are read after every step: the motor is what changes them.
        if let Some(p) = self.motor_purpose(id, &stepped) {
            if self.check_switches(id, p, t) {
                return;
            }
        }
        if let Stepped::Finished { purpose, complete } = stepped {
            self.motor_finished(id, purpose, t, complete);
        }
    }

    fn motor_purpose(&self, id: AxisRef, stepped: &Stepped) -> Option<Purpose> {
        if let Stepped::Finished { purpose, .. } = stepped {
            return Some(*purpose);
        }
        match id {
            AxisRef::Stepper(i) => {
                self.axes.get(usize::from(i)).and_then(|a| a.motor.motion.as_ref()).map(|m| m.purpose)
            }
            AxisRef::FilterWheel(i) => {
                self.wheels.get(usize::from(i)).and_then(|w| w.motor.motion.as_ref()).map(|m| m.purpose)
            }
        }
    }

    /// Reacts to the switches after a step. Returns whether the move was ended by them.
    fn check_switches(&mut self, id: AxisRef, purpose: Purpose, t: u64) -> bool {
        match id {
            AxisRef::Stepper(i) => {
                // The common case, every step of a plain move: no switch wired ahead, nothing
                // to read. Decided on the borrowed config, before copying it.
                let plain = self.axes.get(usize::from(i)).and_then(|a| {
                    let c = a.config.as_ref()?;
                    let ahead = if a.motor.direction()? < 0 { c.limit_min } else { c.limit_max };
                    Some(purpose != Purpose::HomeSeek && matches!(ahead, Input::Unused))
                });
                if plain == Some(true) {
                    return false;
                }
                let Ok(c) = self.stepper_config(i) else { return false };
                let active = |rig: &mut Self, input: Input, sw: Switch| match input {
                    Input::Wired(p) => rig.board.switch_level(id, sw) == level(p, true),
                    Input::Unused => false,
                };
                let seeking = purpose == Purpose::HomeSeek;
                let target = match c.homing.mode {
                    HomingMode::ToMinLimit => Some((c.limit_min, Switch::Min)),
                    HomingMode::ToMaxLimit => Some((c.limit_max, Switch::Max)),
                    HomingMode::ToIndex => Some((c.index, Switch::Index)),
                    HomingMode::None => None,
                };
                if seeking {
                    if let Some((input, sw)) = target {
                        if active(self, input, sw) {
                            let a = self.axes.get_mut(usize::from(i));
                            let Some(a) = a else { return true };
                            a.motor.stop_now();
                            let position = a.motor.position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                            self.emit(Event::Switch { axis: id, switch: sw, position, tick: t }, t);
                            self.home_backoff(i, &c, sw, t);
                            return true;
                        }
                    }
                }
                // Only the limit ahead counts: an axis may rest on a switch and leave it. While
                // homing, the switch being sought (and backed off) is expected; the other one
                // is a fault like any limit.
                let dir = self.axes.get(usize::from(i)).and_then(|a| a.motor.direction());
                let homing = matches!(purpose, Purpose::HomeSeek | Purpose::HomeBackoff);
                for (input, sw, ahead) in
                    [(c.limit_min, Switch::Min, dir == Some(-1)), (c.limit_max, Switch::Max, dir == Some(1))]
                {
                    let expected = homing && target.is_some_and(|(_, s)| s == sw);
                    if ahead && !expected && active(self, input, sw) {
                        let position = self.axes.get(usize::from(i)).map_or(0, |a| a.motor.position);
                        let position = position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                        self.emit(Event::Switch { axis: id, switch: sw, position, tick: t }, t);
                        if let Some(a) = self.axes.get_mut(usize::from(i)) {
                            a.motor.stop_now();
                        }
                        self.enter_safe_state(FaultCause::Limit { axis: id }, t);
                        return true;
                    }
                }
                false
            }
            AxisRef::FilterWheel(i) => {
                if purpose != Purpose::WheelSeek {
                    return false;
                }
                let Ok(c) = self.wheel_config(i) else { return false };
                let Input::Wired(p) = c.index else { return false };
                if self.board.switch_level(id, Switch::Index) != level(p, true) {
                    return false;
                }
                let at = self.wheels.get(usize::from(i)).map_or(0, |w| w.motor.position);
                let position = at.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                self.emit(Event::Switch { axis: id, switch: Switch::Index, position, tick: t }, t);
                let Some(w) = self.wheels.get_mut(usize::from(i)) else { return true };
                w.motor.stop_now();
                // Slot 0's centre lies `index_offset` steps past the mark.
                let spr = i64::from(c.steps_per_rev.max(1));
                w.motor.position = (-i64::from(c.index_offset)).rem_euclid(spr);
                let (delta, forward) = wheel_path(&c, w.motor.position, 0);
                if delta == 0 {
                    self.wheel_homed(i, t);
                } else {
                    let r = w.motor.start(
                        &mut self.board,
                        delta,
                        forward,
                        c.max_speed,
                        c.accel,
                        self.tick_hz,
                        t,
                        Purpose::WheelHome,
                    );
                    if r.is_err() {
                        self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
                    }
                }
                true
            }
        }
    }

    fn home_backoff(&mut self, i: u8, c: &StepperConfig, sw: Switch, t: u64) {
        let h = c.homing;
        let Some(a) = self.axes.get_mut(usize::from(i)) else { return };
        if h.backoff == 0 {
            return self.stepper_homed(i, t);
        }
        // Back away from the switch: forward off the min limit, backward off the others.
        let forward = sw == Switch::Min;
        let r = a.motor.start(
            &mut self.board,
            h.backoff,
            forward,
            h.speed,
            c.accel,
            self.tick_hz,
            t,
            Purpose::HomeBackoff,
        );
        if r.is_err() {
            self.enter_safe_state(FaultCause::HomingFailed { axis: AxisRef::Stepper(i) }, t);
        }
    }

    fn stepper_homed(&mut self, i: u8, t: u64) {
        let Ok(c) = self.stepper_config(i) else { return };
        let Some(a) = self.axes.get_mut(usize::from(i)) else { return };
        a.motor.position = i64::from(c.homing.position);
        a.homed = true;
        let axis = AxisRef::Stepper(i);
        self.emit(Event::Homed { axis, position: c.homing.position, tick: t }, t);
        self.check_wait(t);
    }

    fn wheel_homed(&mut self, i: u8, t: u64) {
        let Some(w) = self.wheels.get_mut(usize::from(i)) else { return };
        w.homed = true;
        w.slot = Some(0);
        self.emit(Event::Homed { axis: AxisRef::FilterWheel(i), position: 0, tick: t }, t);
        self.check_wait(t);
    }

    /// A move ended: `complete` when it reached its target, not when a stop cut it short.
    fn motor_finished(&mut self, id: AxisRef, purpose: Purpose, t: u64, complete: bool) {
        match (id, purpose) {
            (AxisRef::Stepper(i), Purpose::Move) => {
                let position = self.axes.get(usize::from(i)).map_or(0, |a| a.motor.position);
                let position = position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                self.emit(Event::MoveDone { axis: id, position, tick: t }, t);
            }
            // Homing interrupted by the safe state leaves the axis unhomed.
            (AxisRef::Stepper(i), Purpose::HomeBackoff) if complete => self.stepper_homed(i, t),
            (_, Purpose::HomeSeek | Purpose::WheelSeek) if self.fault.is_none() => {
                self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
            }
            (AxisRef::FilterWheel(i), Purpose::WheelTo(slot)) => {
                let Ok(c) = self.wheel_config(i) else { return };
                let Some(w) = self.wheels.get_mut(usize::from(i)) else { return };
                let spr = i64::from(c.steps_per_rev.max(1));
                w.motor.position = w.motor.position.rem_euclid(spr);
                // A wheel stopped short (safe state) rests between slots.
                let arrived = w.motor.position == slot_position(&c, slot);
                w.slot = arrived.then_some(slot);
                let position = if arrived { i32::from(slot) } else { -1 };
                self.emit(Event::MoveDone { axis: id, position, tick: t }, t);
            }
            (AxisRef::FilterWheel(i), Purpose::WheelHome) if complete => self.wheel_homed(i, t),
            _ => {}
        }
        self.check_wait(t);
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

fn apply_coil(synth: &mut Synth, setting: CoilSetting) {
    match setting {
        // Checked when the item was loaded; a refusal here would be a bug, and silence is
        // the safe answer to it.
        CoilSetting::Set { partials, ramp } => {
            if synth.set(&partials, ramp).is_err() {
                synth.fade_out(ramp);
            }
        }
        CoilSetting::Fade { ramp } => synth.fade_out(ramp),
    }
}

fn check_galvo_point(c: &GalvoConfig, to: Xy) -> Result<(), Error> {
    let ok = (c.x.min_code..=c.x.max_code).contains(&to.x) && (c.y.min_code..=c.y.max_code).contains(&to.y);
    ok.then_some(()).ok_or(Error::OutOfRange { kind: Peripheral::Galvo, index: c.galvo })
}

/// Speed and acceleration of a move: the profile's, or the axis' where the profile says 0.
fn move_profile(c: &StepperConfig, p: lightrig_protocol::sequence::Profile) -> (u32, u32) {
    let speed = if p.max_speed == 0 { c.max_speed } else { p.max_speed };
    let accel = if p.accel == 0 { c.accel } else { p.accel };
    (speed, accel)
}

/// How far a homing seek may travel before giving up: the soft-limit span and half again for a
/// linear axis; for an endless axis, 2^24 steps.
fn seek_span(c: &StepperConfig) -> u32 {
    match c.limits {
        Some(r) => {
            let span = (i64::from(r.max) - i64::from(r.min)).unsigned_abs();
            u32::try_from(span.saturating_add(span / 2)).unwrap_or(u32::MAX).max(1)
        }
        None => 1 << 24,
    }
}

/// Motor position (steps from slot 0's centre) of a filter slot's centre.
fn slot_position(c: &FilterWheelConfig, slot: u8) -> i64 {
    i64::from(slot) * i64::from(c.steps_per_rev) / i64::from(c.slots.max(1))
}

/// The shorter way from `position` to `slot`'s centre: (steps, forward). Ties go forward.
fn wheel_path(c: &FilterWheelConfig, position: i64, slot: u8) -> (u32, bool) {
    let spr = i64::from(c.steps_per_rev.max(1));
    let ahead = (slot_position(c, slot) - position).rem_euclid(spr);
    let (steps, forward) = if ahead * 2 <= spr { (ahead, true) } else { (spr - ahead, false) };
    (u32::try_from(steps).unwrap_or(u32::MAX), forward)
}

/// Ticks from sample 0 to sample `n`: `floor(n · tick_hz / rate)`.
fn tick_of_sample(n: u64, rate: u32, tick_hz: u32) -> u64 {
    let t = u128::from(n) * u128::from(tick_hz) / u128::from(rate.max(1));
    u64::try_from(t).unwrap_or(u64::MAX)
}

/// The first sample whose tick is at or after `ticks`.
fn sample_at_or_after(ticks: u64, rate: u32, tick_hz: u32) -> u64 {
    // Smallest n with floor(n·f/r) >= t  <=>  n·f >= t·r  <=>  n = ceil(t·r / f).
    let num = u128::from(ticks) * u128::from(rate);
    let f = u128::from(tick_hz.max(1));
    u64::try_from(num.div_ceil(f)).unwrap_or(u64::MAX)
}
