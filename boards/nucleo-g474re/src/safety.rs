//! Laser safety that must not depend on the firmware working: the pin state at reset, the
//! panic handler, and the reset cause (a reset after a panic reports `ResetCause::Panic`).
//!
//! Safe outputs (laser enables, camera triggers, stepper enables) are left high-impedance, the
//! state they have at reset: the board's pull resistors, matched to the wired lasers, hold them
//! inactive (docs/boards/nucleo-g474re.md). The rig drives a pin only once it knows its polarity.

use core::mem::MaybeUninit;
use core::panic::PanicInfo;
use core::sync::atomic::{compiler_fence, Ordering};

use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals::Moder;
use lightrig_protocol::session::ResetCause;

/// Port index (A = 0) and pin of every output that must go inactive on a panic.
pub const SAFE_OUTPUTS: [(usize, usize); 11] = [
    (1, 5),  // PB5  laser 0 enable
    (2, 7),  // PC7  laser 1 enable
    (2, 4),  // PC4  laser 2 enable
    (2, 5),  // PC5  laser 3 enable
    (0, 10), // PA10 camera 0 trigger (TIM2_CH4)
    (0, 1),  // PA1  stepper 0 enable
    (1, 11), // PB11 stepper 1 enable
    (1, 15), // PB15 filter wheel 0 enable
    (2, 6),  // PC6  stepper 0 step (TIM3_CH1)
    (1, 9),  // PB9  stepper 1 step (TIM17_CH1)
    (1, 14), // PB14 filter wheel 0 step (TIM15_CH1)
];

fn port(index: usize) -> pac::gpio::Gpio {
    match index {
        0 => pac::GPIOA,
        1 => pac::GPIOB,
        _ => pac::GPIOC,
    }
}

/// Puts every safe output into high impedance by direct register writes: usable before the
/// HAL is initialised and from the panic handler, whatever state the HAL is in.
pub fn release_outputs() {
    pac::RCC.ahb2enr().modify(|w| {
        w.set_gpioaen(true);
        w.set_gpioben(true);
        w.set_gpiocen(true);
    });
    for (p, pin) in SAFE_OUTPUTS {
        port(p).moder().modify(|w| w.set_moder(pin, Moder::INPUT));
    }
}

const PANIC_MAGIC: u32 = 0x5041_4e43; // "PANC"

/// Survives a software reset (not a power cycle): `.uninit` is never initialised by the
/// runtime.
#[link_section = ".uninit.lightrig_panic"]
static mut PANIC_MARK: MaybeUninit<u32> = MaybeUninit::uninit();

/// Why the MCU started, from RCC_CSR and the panic mark; clears both for the next start.
pub fn reset_cause() -> ResetCause {
    let csr = pac::RCC.csr().read();
    // SAFETY: single-threaded boot code; a volatile access to a plain u32 (any bit pattern
    // is a valid u32, so the uninitialised value after power-on is fine).
    let mark = unsafe {
        let p = core::ptr::addr_of_mut!(PANIC_MARK).cast::<u32>();
        let m = p.read_volatile();
        p.write_volatile(0);
        m
    };
    pac::RCC.csr().modify(|w| w.set_rmvf(true));
    if csr.iwdgrstf() || csr.wwdgrstf() {
        ResetCause::Watchdog
    } else if csr.sftrstf() && mark == PANIC_MAGIC {
        ResetCause::Panic
    } else if csr.sftrstf() {
        ResetCause::Software
    } else if csr.borrstf() {
        ResetCause::PowerOn
    } else if csr.pinrstf() {
        ResetCause::External
    } else {
        ResetCause::Unknown
    }
}

#[panic_handler]
fn panic(info: &PanicInfo) -> ! {
    cortex_m::interrupt::disable();
    // Lasers first: nothing below may run before this.
    release_outputs();
    compiler_fence(Ordering::SeqCst);
    defmt::error!("panic: {}", defmt::Display2Format(info));
    // SAFETY: interrupts are off; a volatile write of a plain u32.
    unsafe { core::ptr::addr_of_mut!(PANIC_MARK).cast::<u32>().write_volatile(PANIC_MAGIC) };
    // With a debugger attached (C_DEBUGEN), stop here so probe-rs shows the panic; otherwise
    // reset, and the host sees `ResetCause::Panic` and a new boot id.
    // SAFETY: read-only access to the core debug register DHCSR.
    let debugging = unsafe { (*cortex_m::peripheral::DCB::PTR).dhcsr.read() } & 1 != 0;
    if debugging {
        loop {
            cortex_m::asm::bkpt();
        }
    }
    cortex_m::peripheral::SCB::sys_reset()
}
