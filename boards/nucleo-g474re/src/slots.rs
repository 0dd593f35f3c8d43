//! The firmware's flash slots for updates over the link: embassy-boot's active, update and
//! state partitions (layout.rs) on the MCU's flash, through the firmware's `BootSlots`
//! (ed25519 with the key built in from `LIGHTRIG_UPDATE_KEY`). The bootloader
//! (boards/nucleo-g474re-bootloader) does the swap at the reset that follows.

use core::cell::RefCell;

use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_stm32::flash::{Blocking, Flash};
use embassy_stm32::pac;
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use lightrig_firmware::boot::BootSlots;
use lightrig_firmware::hal::{FirmwareSlots, SlotError};
use lightrig_protocol::update::ImageInfo;
use static_cell::StaticCell;

use crate::layout::{ACTIVE, DFU, STATE};
include!(concat!(env!("OUT_DIR"), "/update_key.rs"));

/// The MCU's flash, feeding the independent watchdog before each erase and write: erasing the
/// update slot (118 pages of ~20 ms) takes longer than the watchdog's 500 ms, and the loop is
/// blocked meanwhile. A flash operation that hangs still trips it (it is fed only between
/// operations).
pub struct FedFlash(Flash<'static, Blocking>);

fn feed_watchdog() {
    pac::IWDG.kr().write(|w| w.set_key(pac::iwdg::vals::Key::RESET));
}

impl ErrorType for FedFlash {
    type Error = embassy_stm32::flash::Error;
}

impl ReadNorFlash for FedFlash {
    const READ_SIZE: usize = <Flash<'static, Blocking> as ReadNorFlash>::READ_SIZE;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0.read(offset, bytes)
    }

    fn capacity(&self) -> usize {
        self.0.capacity()
    }
}

impl NorFlash for FedFlash {
    const WRITE_SIZE: usize = <Flash<'static, Blocking> as NorFlash>::WRITE_SIZE;
    const ERASE_SIZE: usize = <Flash<'static, Blocking> as NorFlash>::ERASE_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        // Page by page, fed in between.
        let mut at = from;
        while at < to {
            feed_watchdog();
            let end = (at + Self::ERASE_SIZE as u32).min(to);
            self.0.erase(at, end)?;
            at = end;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        feed_watchdog();
        self.0.write(offset, bytes)
    }
}

type Part = BlockingPartition<'static, NoopRawMutex, FedFlash>;

/// The board's slots, or none when the firmware was built without an update key.
pub struct Slots(Option<BootSlots<Part, Part, Part>>);

impl Slots {
    pub fn new(flash: Flash<'static, Blocking>) -> Self {
        static FLASH: StaticCell<Mutex<NoopRawMutex, RefCell<FedFlash>>> = StaticCell::new();
        let flash = FLASH.init(Mutex::new(RefCell::new(FedFlash(flash))));
        Slots(UPDATE_KEY.map(|key| {
            BootSlots::new(
                BlockingPartition::new(flash, ACTIVE.0, ACTIVE.1),
                BlockingPartition::new(flash, DFU.0, DFU.1),
                BlockingPartition::new(flash, STATE.0, STATE.1),
                key,
            )
        }))
    }

    /// The signed image the active partition holds (none: flashed through the probe as an
    /// ELF, or built without a key).
    pub fn running(&mut self) -> Option<ImageInfo> {
        let s = self.0.as_mut()?;
        let len = s.active_len();
        ImageInfo::find(len, |at, buf| s.read_active(at, buf).is_ok())
    }

    fn slots(&mut self) -> Result<&mut BootSlots<Part, Part, Part>, SlotError> {
        self.0.as_mut().ok_or(SlotError::Unsupported)
    }
}

impl FirmwareSlots for Slots {
    fn active_len(&self) -> u32 {
        self.0.as_ref().map_or(0, |s| s.active_len())
    }

    fn fallback_offset(&self) -> u32 {
        self.0.as_ref().map_or(0, |s| s.fallback_offset())
    }

    fn read_active(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots()?.read_active(offset, buf)
    }

    fn read_update(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.slots()?.read_update(offset, buf)
    }

    fn erase_update(&mut self) -> Result<(), SlotError> {
        self.slots()?.erase_update()
    }

    fn write_update(&mut self, offset: u32, data: &[u8]) -> Result<(), SlotError> {
        self.slots()?.write_update(offset, data)
    }

    fn verify_and_mark(&mut self, len: u32, signature: &[u8; 64]) -> Result<(), SlotError> {
        self.slots()?.verify_and_mark(len, signature)
    }

    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        match self.0.as_mut() {
            Some(s) => s.unconfirmed(),
            None => Ok(false),
        }
    }

    fn confirm(&mut self) -> Result<(), SlotError> {
        self.slots()?.confirm()
    }
}
