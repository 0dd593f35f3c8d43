//! The emulated board's bootloader. QEMU loads this ELF and starts it at every power-on and
//! reset; it runs embassy-boot's boot step on the flash file the semihosting command line names
//! (`flash=PATH`: a marked image swapped in, an unconfirmed one swapped back; power-fail safe,
//! `cut=N` ends QEMU at the Nth flash operation), copies the active partition to the code RAM
//! at `APP_BASE` and jumps to it. Without `flash=` it jumps to whatever is at `APP_BASE` (a
//! firmware QEMU loaded there with `-device loader`).

#![no_std]
#![no_main]

use core::cell::RefCell;

use cortex_m_rt::{entry, exception};
use cortex_m_semihosting::{debug, nr, syscall1};
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::ReadNorFlash;
use lightrig_firmware::boards::qemu_flash::{ACTIVE, APP_BASE};

#[path = "../../qemu-mps2-an386/src/flash.rs"]
mod flash;

/// `flash=PATH` and `cut=N` from the semihosting command line.
fn args(line: &[u8]) -> (Option<&[u8]>, Option<u32>) {
    let (mut path, mut cut) = (None, None);
    for word in line.split(|&b| b == b' ') {
        if let Some(p) = word.strip_prefix(b"flash=") {
            path = Some(p);
        } else if let Some(n) = word.strip_prefix(b"cut=") {
            cut = core::str::from_utf8(n).ok().and_then(|t| t.parse().ok());
        }
    }
    (path, cut)
}

#[entry]
fn main() -> ! {
    let mut buf = [0u8; 256];
    let mut block = [buf.as_mut_ptr() as usize, buf.len() - 1];
    // SAFETY: SYS_GET_CMDLINE writes at most `block[1]` bytes into `buf` and the length back.
    let ok = unsafe { syscall1(nr::GET_CMDLINE, block.as_mut_ptr() as usize) } == 0;
    let line = if ok { buf.get(..block[1]).unwrap_or(&[]) } else { &[] };
    let (path, cut) = args(line);
    if let Some(path) = path {
        let Some(mut file) = flash::FileFlash::open(path) else { fail() };
        file.cut = cut;
        let shared: Mutex<NoopRawMutex, RefCell<flash::FileFlash>> = Mutex::new(RefCell::new(file));
        // SAFETY: `shared` lives until the jump, which never returns; the slots borrow it only
        // until then.
        let shared: &'static Mutex<NoopRawMutex, RefCell<flash::FileFlash>> =
            unsafe { &*core::ptr::addr_of!(shared) };
        let mut slots = flash::slots(shared);
        if slots.boot().is_err() {
            fail();
        }
        // The active partition into the code RAM: the firmware, linked at APP_BASE.
        // SAFETY: SSRAM1 from APP_BASE on is RAM no one else uses; this code runs below it.
        let code = unsafe { core::slice::from_raw_parts_mut(APP_BASE as *mut u8, ACTIVE.1 as usize) };
        if slots.active.read(0, code).is_err() {
            fail();
        }
    }
    // SAFETY: APP_BASE holds a vector table (initial stack pointer, reset vector) of a firmware
    // linked there; nothing of the bootloader is used after the jump.
    unsafe {
        (*cortex_m::peripheral::SCB::PTR).vtor.write(APP_BASE);
        cortex_m::asm::bootload(APP_BASE as *const u32)
    }
}

/// The flash file is missing or unreadable: nothing sensible to start.
fn fail() -> ! {
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}

#[exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    fail()
}

#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    fail()
}
