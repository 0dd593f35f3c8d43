//! The NUCLEO-G474RE's peripherals behind the firmware's hardware traits.
//!
//! The run loop polls the rig up to `LOOKAHEAD_TICKS` ahead of the clock, so an output call
//! can come before its tick `at`. The camera trigger arms a timer compare for `at`
//! (`trigger.rs`); every other output waits for `at` in a busy loop (at most the look-ahead)
//! and then changes. A call that comes after `at` (the loop woke late) acts at once. See
//! docs/boards/nucleo-g474re.md, "Timing".

use embassy_stm32::gpio::{Flex, Input, Level, Output, Speed};
#[cfg(not(feature = "xy2-100"))]
use embassy_stm32::mode::Blocking;
#[cfg(not(feature = "xy2-100"))]
use embassy_stm32::spi::{self, Spi};
use embassy_time::Instant;
#[cfg(not(feature = "xy2-100"))]
use embedded_hal_bus::spi::{ExclusiveDevice, NoDelay};
use lightrig_firmware::galvo::GalvoOutput;
#[cfg(not(feature = "xy2-100"))]
use lightrig_firmware::galvo::SpiDacGalvo;
#[cfg(feature = "xy2-100")]
use lightrig_firmware::galvo::Xy2Gpio;
use lightrig_firmware::hal::{
    Cameras, Capture, FirmwareSlots, Galvos, HwError, Lasers, Motors, SlotError, VoiceCoils,
};
use lightrig_firmware::timer_schedule::{must_wait, Counter};
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::AxisRef;

use crate::inputs;
use crate::slots::Slots;
use crate::step::StepPulse;
use crate::trigger::Trigger;
use crate::voice::VoiceOutputs;

/// The galvo DAC's SPI device: SPI1 with the DAC8563's SYNC as chip select.
#[cfg(not(feature = "xy2-100"))]
pub type GalvoSpi = ExclusiveDevice<Spi<'static, Blocking, spi::mode::Master>, Output<'static>, NoDelay>;

/// The galvo pair's output: a DAC8563 on SPI1.
#[cfg(not(feature = "xy2-100"))]
pub type Galvo = SpiDacGalvo<GalvoSpi>;
/// The galvo pair's output: an XY2-100 link on GPIOC (feature `xy2-100`).
#[cfg(feature = "xy2-100")]
pub type Galvo = Xy2Gpio<crate::xy2::Xy2Port>;

/// How far ahead of the clock the run loop polls the rig: it covers the loop's wake-up (timer
/// interrupt, executor, the USB reads' futures, the ordinary poll) when no USB frame is being
/// handled, so a trigger edge is armed before its tick. The price: each due tick's outputs
/// other than the trigger busy-wait up to this long for their tick.
pub const LOOKAHEAD_TICKS: u64 = 50;

/// TIM2 as embassy-time's driver runs it: one count per tick, ARR = 0xFFFF, so its counter is
/// the tick's low 16 bits. The trigger's compare and the exposure capture use it directly.
pub const TIM2_COUNTER: Counter = Counter::new(16);

/// The tick now (embassy-time's counter).
pub fn now_ticks() -> u64 {
    Instant::now().as_ticks()
}

/// Busy-waits until tick `at` (at most `LOOKAHEAD_TICKS`; anything further would be a
/// scheduling error, and the output goes out now rather than stall the loop).
pub fn wait_until(at: u64) {
    while must_wait(at, now_ticks(), LOOKAHEAD_TICKS) {}
}

/// A safety output: high impedance (held inactive by its pull resistor) until the rig first
/// drives it, which it does only once the peripheral's polarity is configured.
pub struct SafeOutput {
    pin: Flex<'static>,
    driven: bool,
}

impl SafeOutput {
    pub fn new(pin: Flex<'static>) -> Self {
        Self { pin, driven: false }
    }

    fn set(&mut self, level: bool) {
        // Level first, then output mode: no glitch to the other level.
        self.pin.set_level(Level::from(level));
        if !self.driven {
            self.pin.set_as_output(Speed::High);
            self.driven = true;
        }
    }
}

/// One step/dir/enable driver and its switches.
pub struct Motor {
    pub step: StepPulse,
    pub dir: Output<'static>,
    pub enable: SafeOutput,
    pub limit_min: Option<Input<'static>>,
    pub limit_max: Option<Input<'static>>,
    pub index: Option<Input<'static>>,
}

impl Motor {
    fn pulse(&mut self) {
        self.step.fire();
    }

    fn switch(&self, switch: Switch) -> bool {
        let pin = match switch {
            Switch::Min => &self.limit_min,
            Switch::Max => &self.limit_max,
            Switch::Index => &self.index,
        };
        // An unwired switch reads low; the rig file must not configure it.
        pin.as_ref().is_some_and(|p| p.is_high())
    }
}

/// Everything the rig drives on this board.
pub struct Nucleo {
    pub galvo: Galvo,
    pub lasers: [SafeOutput; 4],
    pub interlocks: [Input<'static>; 4],
    pub trigger: Trigger,
    /// Camera 0 exposure input (PB10, TIM2_CH3): held so nothing else claims it; its edges are
    /// captured by TIM2 and collected in the EXTI handler.
    pub _exposure: Flex<'static>,
    pub steppers: [Motor; 2],
    pub wheel: Motor,
    pub voice: VoiceOutputs,
    pub slots: Slots,
}

impl Nucleo {
    fn motor(&mut self, motor: AxisRef) -> Option<&mut Motor> {
        match motor {
            AxisRef::Stepper(n) => self.steppers.get_mut(usize::from(n)),
            AxisRef::FilterWheel(0) => Some(&mut self.wheel),
            _ => None,
        }
    }

    /// Board housekeeping between polls.
    pub fn service(&mut self, now: u64) {
        self.voice.service(now);
        if inputs::take_overflow() {
            defmt::error!("exposure captures lost: run loop stalled");
        }
        let late = self.trigger.take_late_edges();
        if late > 0 {
            defmt::warn!("{} trigger edge(s) driven after their tick", late);
        }
    }
}

impl Galvos for Nucleo {
    fn set_galvo(&mut self, pair: u8, to: Xy, at: u64) -> Result<(), HwError> {
        if pair != 0 {
            return Err(HwError);
        }
        wait_until(at);
        self.galvo.set(to).map_err(|e| {
            defmt::error!("galvo output: {}", defmt::Debug2Format(&e));
            HwError
        })
    }
}

impl Lasers for Nucleo {
    fn set_laser(&mut self, channel: u8, level: bool, at: u64) {
        if let Some(l) = self.lasers.get_mut(usize::from(channel)) {
            wait_until(at);
            l.set(level);
        }
    }

    fn interlock_level(&mut self, channel: u8) -> bool {
        // An unknown channel reads open: lasers stay off.
        self.interlocks.get(usize::from(channel)).is_some_and(|p| p.is_high())
    }
}

impl Motors for Nucleo {
    fn step(&mut self, motor: AxisRef, at: u64) {
        if let Some(m) = self.motor(motor) {
            wait_until(at);
            m.pulse();
        }
    }

    fn set_dir(&mut self, motor: AxisRef, level: bool, at: u64) {
        if let Some(m) = self.motor(motor) {
            wait_until(at);
            m.dir.set_level(Level::from(level));
        }
    }

    fn set_enable(&mut self, motor: AxisRef, level: bool, at: u64) {
        if let Some(m) = self.motor(motor) {
            wait_until(at);
            m.enable.set(level);
        }
    }

    fn switch_level(&mut self, motor: AxisRef, switch: Switch) -> bool {
        self.motor(motor).is_some_and(|m| m.switch(switch))
    }
}

impl Cameras for Nucleo {
    fn set_trigger(&mut self, camera: u8, level: bool, at: u64) {
        if camera == 0 {
            self.trigger.set(level, at);
        }
    }

    fn take_capture(&mut self, until: u64) -> Option<Capture> {
        inputs::take(until)
    }
}

/// The embassy-boot slots (`slots.rs`).
impl FirmwareSlots for Nucleo {
    fn active_len(&self) -> u32 {
        self.slots.active_len()
    }

    fn fallback_offset(&self) -> u32 {
        self.slots.fallback_offset()
    }

    fn read_active(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.read_active(offset, buf)
    }

    fn read_update(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.read_update(offset, buf)
    }

    fn erase_update(&mut self) -> Result<(), SlotError> {
        self.slots.erase_update()
    }

    fn write_update(&mut self, offset: u32, data: &[u8]) -> Result<(), SlotError> {
        self.slots.write_update(offset, data)
    }

    fn verify_and_mark(&mut self, len: u32, signature: &[u8; 64]) -> Result<(), SlotError> {
        self.slots.verify_and_mark(len, signature)
    }

    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        self.slots.unconfirmed()
    }

    fn confirm(&mut self) -> Result<(), SlotError> {
        self.slots.confirm()
    }
}

impl VoiceCoils for Nucleo {
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64) {
        self.voice.write(channel, first_sample, samples, at);
    }

    /// TIM6 paces both DACs at one rate.
    fn sample_rates(&self) -> (u32, u32) {
        (crate::voice::SAMPLE_RATE_HZ, crate::voice::SAMPLE_RATE_HZ)
    }
}
