//! The NUCLEO-G474RE's bootloader: at every reset, embassy-boot finishes or starts a swap
//! (an update marked by the firmware, or the old image back when the new one was not confirmed;
//! power-fail safe: cut at any write, the next reset goes on where it stopped), then jumps to
//! the active partition. Images are verified by the firmware before it marks them (ed25519,
//! its public key built in), so the bootloader needs no key. It drives no pin: every laser and
//! driver output stays high-impedance, as at reset, until the firmware configures it.
//! Layout: boards/nucleo-g474re/layout.rs; guide: docs/flashing.md.

#![no_std]
#![no_main]

use core::cell::RefCell;

use cortex_m_rt::{entry, exception};
use embassy_boot_stm32::{BootLoader, BootLoaderConfig};
use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_stm32::flash::{Blocking, Flash};
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;

include!("../../nucleo-g474re/layout.rs");

/// Swap buffer: a page is copied in pieces of this size (a multiple of the 8-byte flash write).
const BUFFER: usize = 2048;

#[entry]
fn main() -> ! {
    // Default clocks (HSI16): the swap is bound by flash erase and write times, not the CPU.
    let p = embassy_stm32::init(Default::default());
    let flash: Mutex<NoopRawMutex, RefCell<Flash<'_, Blocking>>> =
        Mutex::new(RefCell::new(Flash::new_blocking(p.FLASH)));
    let config = BootLoaderConfig {
        active: BlockingPartition::new(&flash, ACTIVE.0, ACTIVE.1),
        dfu: BlockingPartition::new(&flash, DFU.0, DFU.1),
        state: BlockingPartition::new(&flash, STATE.0, STATE.1),
    };
    // A failed swap step (a flash error) is retried at the next reset; meanwhile the active
    // partition, whole or half-swapped, is started: embassy-boot never leaves it without a
    // way back.
    let loader = match BootLoader::try_prepare::<_, _, _, BUFFER>(config) {
        Ok(l) => l,
        Err(_) => cortex_m::peripheral::SCB::sys_reset(),
    };
    // SAFETY: the active partition holds a firmware linked at this address (its vector table
    // first); nothing of the bootloader is used after the jump.
    unsafe { loader.load(FLASH_BASE + ACTIVE.0) }
}

#[exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}

#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}
