//! The simulated peripherals, compiled in: a handle to one global [`RecordingBoard`], so the
//! run loop's debug port and the panic handler reach the same pins as the controller.

use core::cell::RefCell;

use critical_section::Mutex;
use lightrig_firmware::hal::{Cameras, Capture, Galvos, HwError, Lasers, Motors, VoiceCoils};
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

/// The board the controller drives.
pub struct QemuBoard;

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

/// No bootloader on the emulated board yet: not updated over the link.
impl lightrig_firmware::hal::FirmwareSlots for QemuBoard {}

impl VoiceCoils for QemuBoard {
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64) {
        with_pins(|p| p.write_samples(channel, first_sample, samples, at));
    }
}
