//! The simulated peripherals, compiled in: a handle to one global [`RecordingBoard`], so the
//! run loop's debug port and the panic handler reach the same pins as the controller.

use core::cell::RefCell;

use critical_section::Mutex;
use lightrig_firmware::hal::{
    Cameras, Capture, FirmwareSlots, Galvos, HwError, Lasers, Motors, SlotError, VoiceCoils,
};
use lightrig_firmware::record::RecordingBoard;
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::AxisRef;

/// Output changes the ring keeps (16 bytes each: 256 KiB of the 4 MiB RAM).
pub const RECORDS: usize = 16_384;

static PINS: Mutex<RefCell<RecordingBoard<RECORDS>>> = Mutex::new(RefCell::new(RecordingBoard::new()));

/// Runs `f` on the pins; `None` only if they are in use further up the stack (a panic
/// inside a board call).
pub fn with_pins<R>(f: impl FnOnce(&mut RecordingBoard<RECORDS>) -> R) -> Option<R> {
    critical_section::with(|cs| PINS.borrow(cs).try_borrow_mut().ok().map(|mut p| f(&mut p)))
}

/// The board the controller drives: the recorded pins, and the update slots in the flash file
/// when the command line names one.
pub struct QemuBoard {
    pub slots: Option<crate::flash::Slots>,
}

impl Galvos for QemuBoard {
    fn set_galvo(&mut self, pair: u8, to: Xy, at: u64) -> Result<(), HwError> {
        with_pins(|p| p.set_galvo(pair, to, at)).unwrap_or(Err(HwError))
    }
}

impl Lasers for QemuBoard {
    fn set_laser(&mut self, channel: u8, level: bool, at: u64) {
        with_pins(|p| p.set_laser(channel, level, at));
    }

    fn interlock_level(&mut self, channel: u8) -> bool {
        // Unreadable counts as open: the safe reading.
        with_pins(|p| p.interlock_level(channel)).unwrap_or(false)
    }
}

impl Motors for QemuBoard {
    fn step(&mut self, motor: AxisRef, at: u64) {
        with_pins(|p| p.step(motor, at));
    }

    fn set_dir(&mut self, motor: AxisRef, level: bool, at: u64) {
        with_pins(|p| p.set_dir(motor, level, at));
    }

    fn set_enable(&mut self, motor: AxisRef, level: bool, at: u64) {
        with_pins(|p| p.set_enable(motor, level, at));
    }

    fn switch_level(&mut self, motor: AxisRef, switch: Switch) -> bool {
        with_pins(|p| p.switch_level(motor, switch)).unwrap_or(false)
    }
}

impl Cameras for QemuBoard {
    fn set_trigger(&mut self, camera: u8, level: bool, at: u64) {
        with_pins(|p| p.set_trigger(camera, level, at));
    }

    fn take_capture(&mut self, until: u64) -> Option<Capture> {
        with_pins(|p| p.take_capture(until)).flatten()
    }
}

/// The slots in the flash file (`flash.rs`); without one, not updated over the link.
impl FirmwareSlots for QemuBoard {
    fn active_len(&self) -> u32 {
        self.slots.as_ref().map_or(0, |s| s.active_len())
    }

    fn fallback_offset(&self) -> u32 {
        self.slots.as_ref().map_or(0, |s| s.fallback_offset())
    }

    fn read_active(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.read_active(offset, buf)
    }

    fn read_update(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.read_update(offset, buf)
    }

    fn erase_update(&mut self) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.erase_update()
    }

    fn write_update(&mut self, offset: u32, data: &[u8]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.write_update(offset, data)
    }

    fn verify_and_mark(&mut self, len: u32, signature: &[u8; 64]) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.verify_and_mark(len, signature)
    }

    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        self.slots.as_mut().map_or(Ok(false), |s| s.unconfirmed())
    }

    fn confirm(&mut self) -> Result<(), SlotError> {
        self.slots.as_mut().ok_or(SlotError::Unsupported)?.confirm()
    }
}

impl VoiceCoils for QemuBoard {
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64) {
        with_pins(|p| p.write_samples(channel, first_sample, samples, at));
    }
}
