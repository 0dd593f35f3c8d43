//! Interrupt numbers without a PAC: mps2-an386 has 32 external lines; the handlers are
//! dispatched by number from `DefaultHandler` (main.rs).

use cortex_m::interrupt::InterruptNumber;
use cortex_m::peripheral::NVIC;

#[derive(Clone, Copy)]
struct Irq(u16);

// SAFETY: every number used is one of the board's 32 external interrupt lines.
unsafe impl InterruptNumber for Irq {
    fn number(self) -> u16 {
        self.0
    }
}

/// Unmasks interrupt line `n`.
pub fn enable(n: u16) {
    // SAFETY: the handlers behind these lines only touch state under critical sections.
    unsafe { NVIC::unmask(Irq(n)) }
}

/// Makes interrupt line `n` pending, so its handler runs as soon as it may.
pub fn pend(n: u16) {
    NVIC::pend(Irq(n));
}
