//! Simulated peripherals for the host (feature `std`): a [`SimBoard`] that implements every
//! [`crate::hal`] trait, records each output change with its tick, and models just enough
//! physics to close the loops: motor positions from the step and direction outputs, limit and
//! index switches at physical positions, interlocks, and cameras whose exposure input follows
//! their trigger.
//!
//! Steps can be counted without being recorded ([`SimBoard::record_steps`]), so a move of
//! millions of steps does not fill memory.

use std::cell::Cell;
use std::collections::VecDeque;
use std::rc::Rc;
use std::vec::Vec;

use lightrig_protocol::config::Xy;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::session::{BoardId, Capabilities, DeviceInfo, ResetCause, Version};
use lightrig_protocol::{
    MAX_CAMERAS, MAX_FILTER_WHEELS, MAX_LASERS, MAX_PACKET, MAX_STEPPERS, MAX_VOICE_COILS, PROTOCOL_VERSION,
    SCHEMA_HASH,
};

use crate::controller::Clock;
use crate::hal::{Cameras, Capture, FirmwareSlots, Galvos, HwError, Lasers, Motors, SlotError, VoiceCoils};

/// What the virtual rig's controller says of itself: a [`SimBoard`] behind a
/// [`crate::Controller`] at 1 MHz (host µs = device ticks). Its `boot_id` is 0: whoever starts
/// a virtual device gives it a fresh one, as a real device's differs at every start.
pub fn virtual_device_info() -> DeviceInfo {
    DeviceInfo {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
        firmware: Version { major: 0, minor: 1, patch: 0 },
        board: BoardId::Virtual,
        serial: 0,
        tick_hz: 1_000_000,
        reset_cause: ResetCause::PowerOn,
        boot_id: 0,
        capabilities: Capabilities {
            galvos: 1,
            lasers: 4,
            steppers: 2,
            filter_wheels: 1,
            voice_coils: 2,
            partials_per_coil: 8,
            cameras: MAX_CAMERAS as u8,
            sequence_buffer: 256,
            event_queue: 64,
            link_window: 8,
            max_packet: MAX_PACKET as u16,
        },
    }
}

/// Simulated device time, shared by clones (1 tick = 1/`tick_hz` s).
#[derive(Debug, Clone, Default)]
pub struct SimClock(Rc<Cell<u64>>);

impl SimClock {
    /// Moves time forward.
    pub fn advance(&self, ticks: u64) {
        self.0.set(self.0.get().saturating_add(ticks));
    }

    /// Sets the time (never backwards).
    pub fn set(&self, tick: u64) {
        self.0.set(self.0.get().max(tick));
    }
}

impl Clock for SimClock {
    fn now(&self) -> u64 {
        self.0.get()
    }
}

/// One output change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    /// Galvo pair driven to a position.
    Galvo { pair: u8, to: Xy },
    /// Laser enable output level.
    Laser { channel: u8, level: bool },
    /// One step pulse.
    Step { motor: AxisRef },
    /// Direction output level.
    Dir { motor: AxisRef, level: bool },
    /// Driver-enable output level.
    Enable { motor: AxisRef, level: bool },
    /// Camera trigger output level.
    Trigger { camera: u8, level: bool },
    /// A block of voice-coil samples handed over (the samples are in [`SimBoard::samples`]).
    Samples { channel: u8, first: u64, len: u16 },
}

/// An output change and the tick it belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Change {
    /// Tick.
    pub tick: u64,
    /// What changed.
    pub output: Output,
}

/// A simulated step/dir motor with its switches, in physical steps (direction level high =
/// positive).
#[derive(Debug, Clone, Default)]
pub struct SimMotor {
    /// Physical position, steps.
    pub position: i64,
    /// Steps made (either way).
    pub steps: u64,
    /// Present direction output level.
    pub dir: bool,
    /// Driver enabled (electrical level as last written).
    pub enable: Option<bool>,
    /// Min limit switch is active (high) at and below this position.
    pub limit_min_at: Option<i64>,
    /// Max limit switch is active (high) at and above this position.
    pub limit_max_at: Option<i64>,
    /// Index sensor active (high) where `position.rem_euclid(period) == at`: `(at, period)`.
    pub index_at: Option<(i64, i64)>,
    /// Tick of the last step.
    pub last_step: Option<u64>,
    /// Switches wired active-low (closing to ground against a pull-up), indexed
    /// `[Min, Max, Index]`: their level is low while active.
    pub active_low: [bool; 3],
}

/// A simulated camera's exposure-active output: it goes active `delay` ticks after a trigger's
/// leading edge and stays active `length` ticks.
#[derive(Debug, Clone, Copy, Default)]
pub struct SimExposure {
    /// Ticks from trigger to exposure start.
    pub delay: u64,
    /// Exposure length, ticks.
    pub length: u64,
    /// The camera's trigger input is active low (its leading edge is a falling one).
    pub trigger_active_low: bool,
    /// The exposure-active output is active low.
    pub output_active_low: bool,
}

/// The simulated board.
#[derive(Debug)]
pub struct SimBoard {
    /// Every output change, in call order (ticks non-decreasing).
    pub record: Vec<Change>,
    /// Record `Step` changes (counted in [`SimMotor`] either way).
    pub record_steps: bool,
    /// Galvo positions.
    pub galvos: [Option<Xy>; 2],
    /// Laser output levels.
    pub lasers: [bool; MAX_LASERS],
    /// Interlock input levels (high = closed, by default).
    pub interlocks: [bool; MAX_LASERS],
    /// Stepper axes.
    pub steppers: [SimMotor; MAX_STEPPERS],
    /// Filter-wheel motors.
    pub wheels: [SimMotor; MAX_FILTER_WHEELS],
    /// Trigger output levels.
    pub triggers: [bool; MAX_CAMERAS],
    /// Camera exposure models (`None`: the camera's strobe output is not connected).
    pub exposure: [Option<SimExposure>; MAX_CAMERAS],
    /// Exposure edges waiting to be taken, in tick order.
    pub captures: VecDeque<Capture>,
    /// Voice-coil samples received, per channel, from sample 0.
    pub samples: [Vec<i16>; MAX_VOICE_COILS],
    /// Make galvo writes fail (a broken converter).
    pub galvo_fails: bool,
    /// Flash slots with a bootloader (`None`: not updated over the link).
    pub slots: Option<SimSlots>,
    /// The voice-coil sample rates it plays (a board's DAC timer may play only one).
    pub sample_rates: (u32, u32),
}

/// The simulated board's flash: 2 KiB pages and 8-byte writes, as on the STM32G4.
pub type SimFlash = crate::memflash::MemFlash<2048, 8>;

/// The simulated board's flash slots: embassy-boot over [`SimFlash`] partitions, which survive
/// the board's resets.
pub struct SimSlots(pub crate::boot::BootSlots<SimFlash, SimFlash, SimFlash>);

impl std::fmt::Debug for SimSlots {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SimSlots")
    }
}

impl FirmwareSlots for SimBoard {
    fn active_len(&self) -> u32 {
        self.slots.as_ref().map_or(0, |s| s.0.active_len())
    }
    fn fallback_offset(&self) -> u32 {
        self.slots.as_ref().map_or(0, |s| s.0.fallback_offset())
    }
    fn read_active(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.read_active(offset, buf)
    }
    fn read_update(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.read_update(offset, buf)
    }
    fn erase_update(&mut self) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.erase_update()
    }
    fn write_update(&mut self, offset: u32, data: &[u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.write_update(offset, data)
    }
    fn verify_and_mark(&mut self, len: u32, signature: &[u8; 64]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.verify_and_mark(len, signature)
    }
    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        self.slots.as_mut().map_or(Ok(false), |s| s.0.unconfirmed())
    }
    fn confirm(&mut self) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.0.confirm()
    }
}

impl Default for SimBoard {
    fn default() -> Self {
        Self {
            record: Vec::new(),
            record_steps: true,
            galvos: [None; 2],
            lasers: [false; MAX_LASERS],
            interlocks: [true; MAX_LASERS],
            steppers: Default::default(),
            wheels: Default::default(),
            triggers: [false; MAX_CAMERAS],
            exposure: [None; MAX_CAMERAS],
            captures: VecDeque::new(),
            samples: Default::default(),
            galvo_fails: false,
            slots: None,
            sample_rates: lightrig_protocol::config::SAMPLE_RATE_RANGE,
        }
    }
}

impl SimBoard {
    /// The simulated motor behind `motor`.
    pub fn motor(&self, motor: AxisRef) -> Option<&SimMotor> {
        match motor {
            AxisRef::Stepper(i) => self.steppers.get(usize::from(i)),
            AxisRef::FilterWheel(i) => self.wheels.get(usize::from(i)),
        }
    }

    /// The simulated motor behind `motor`, mutably (to place its switches).
    pub fn motor_mut(&mut self, motor: AxisRef) -> Option<&mut SimMotor> {
        match motor {
            AxisRef::Stepper(i) => self.steppers.get_mut(usize::from(i)),
            AxisRef::FilterWheel(i) => self.wheels.get_mut(usize::from(i)),
        }
    }

    /// Tick of the next exposure edge not yet taken (for a run loop that must wake for it).
    pub fn next_capture(&self) -> Option<u64> {
        self.captures.front().map(|c| c.tick)
    }

    /// The changes recorded for one kind of output, as `(tick, output)`.
    pub fn changes(&self, mut keep: impl FnMut(&Output) -> bool) -> Vec<Change> {
        self.record.iter().filter(|c| keep(&c.output)).copied().collect()
    }

    fn push(&mut self, tick: u64, output: Output) {
        self.record.push(Change { tick, output });
    }

    fn add_capture(&mut self, c: Capture) {
        let at = self.captures.iter().position(|x| x.tick > c.tick).unwrap_or(self.captures.len());
        self.captures.insert(at, c);
    }
}

impl Galvos for SimBoard {
    fn set_galvo(&mut self, pair: u8, to: Xy, at: u64) -> Result<(), HwError> {
        if self.galvo_fails {
            return Err(HwError);
        }
        if let Some(g) = self.galvos.get_mut(usize::from(pair)) {
            *g = Some(to);
        }
        self.push(at, Output::Galvo { pair, to });
        Ok(())
    }
}

impl Lasers for SimBoard {
    fn set_laser(&mut self, channel: u8, level: bool, at: u64) {
        if let Some(l) = self.lasers.get_mut(usize::from(channel)) {
            *l = level;
        }
        self.push(at, Output::Laser { channel, level });
    }

    fn interlock_level(&mut self, channel: u8) -> bool {
        self.interlocks.get(usize::from(channel)).copied().unwrap_or(false)
    }
}

impl Motors for SimBoard {
    fn step(&mut self, motor: AxisRef, at: u64) {
        if let Some(m) = self.motor_mut(motor) {
            m.position += if m.dir { 1 } else { -1 };
            m.steps += 1;
            m.last_step = Some(at);
        }
        if self.record_steps {
            self.push(at, Output::Step { motor });
        }
    }

    fn set_dir(&mut self, motor: AxisRef, level: bool, at: u64) {
        if let Some(m) = self.motor_mut(motor) {
            m.dir = level;
        }
        self.push(at, Output::Dir { motor, level });
    }

    fn set_enable(&mut self, motor: AxisRef, level: bool, at: u64) {
        if let Some(m) = self.motor_mut(motor) {
            m.enable = Some(level);
        }
        self.push(at, Output::Enable { motor, level });
    }

    fn switch_level(&mut self, motor: AxisRef, switch: Switch) -> bool {
        let Some(m) = self.motor(motor) else { return false };
        let (active, low) = match switch {
            Switch::Min => (m.limit_min_at.is_some_and(|p| m.position <= p), m.active_low[0]),
            Switch::Max => (m.limit_max_at.is_some_and(|p| m.position >= p), m.active_low[1]),
            Switch::Index => (
                m.index_at.is_some_and(|(at, period)| m.position.rem_euclid(period.max(1)) == at),
                m.active_low[2],
            ),
        };
        active != low
    }
}

impl Cameras for SimBoard {
    fn set_trigger(&mut self, camera: u8, level: bool, at: u64) {
        let before = match self.triggers.get_mut(usize::from(camera)) {
            Some(t) => Some(std::mem::replace(t, level)),
            None => None,
        };
        if let (Some(before), Some(Some(e))) = (before, self.exposure.get(usize::from(camera)).copied()) {
            // The camera starts an exposure on its trigger input's leading edge.
            let asserted = |l: bool| l != e.trigger_active_low;
            if asserted(level) && !asserted(before) {
                let start = at + e.delay;
                let active = !e.output_active_low;
                self.add_capture(Capture { camera, level: active, tick: start });
                self.add_capture(Capture { camera, level: !active, tick: start + e.length });
            }
        }
        self.push(at, Output::Trigger { camera, level });
    }

    fn take_capture(&mut self, until: u64) -> Option<Capture> {
        if self.captures.front().is_some_and(|c| c.tick <= until) {
            return self.captures.pop_front();
        }
        None
    }
}

impl VoiceCoils for SimBoard {
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64) {
        if let Some(s) = self.samples.get_mut(usize::from(channel)) {
            // Blocks arrive in order; a gap would be a controller bug, made visible as zeros.
            s.resize(first_sample as usize, 0);
            s.extend_from_slice(samples);
        }
        let len = samples.len() as u16;
        self.push(at, Output::Samples { channel, first: first_sample, len });
    }

    fn sample_rates(&self) -> (u32, u32) {
        self.sample_rates
    }
}

impl crate::rig::Rig<SimBoard> {
    /// Runs the rig to `until`, waking at every tick it has work and at every exposure edge
    /// the simulated cameras produce: what a board's run loop does, without the waiting.
    pub fn run_until(&mut self, until: u64) {
        loop {
            let next = [self.next_due(), self.board().next_capture()].into_iter().flatten().min();
            match next {
                Some(t) if t <= until => self.poll(t),
                _ => break,
            }
        }
        self.poll(until);
    }

    /// Takes every event the rig holds.
    pub fn drain_events(&mut self) -> Vec<lightrig_protocol::Event> {
        core::iter::from_fn(|| self.pop_event()).collect()
    }
}
