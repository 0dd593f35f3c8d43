//! Input edges the rig must see promptly: camera exposure edges, time-stamped in the EXTI
//! interrupt (tick = embassy-time's counter, read within the interrupt latency, well under one
//! 1 µs tick at 168 MHz), and interlock changes, which only wake the run loop.
//!
//! The HAL's `exti` feature is off: these handlers own the EXTI vectors.

use core::cell::RefCell;

use critical_section::Mutex;
use embassy_stm32::interrupt;
use embassy_stm32::pac;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use heapless::Deque;
use lightrig_firmware::hal::Capture;

/// Wakes the run loop: an exposure edge or an interlock change.
pub static WAKE: Signal<CriticalSectionRawMutex, ()> = Signal::new();

/// Captured exposure edges, oldest first.
static CAPTURES: Mutex<RefCell<Deque<Capture, 32>>> = Mutex::new(RefCell::new(Deque::new()));
/// An edge was dropped because the queue was full (the run loop stalled for 16 exposures).
static OVERFLOW: Mutex<RefCell<bool>> = Mutex::new(RefCell::new(false));

/// EXTI line of camera 0's exposure input (PB10).
pub const EXPOSURE0_LINE: usize = 10;
/// EXTI lines of the interlock inputs (PC8, PA9).
pub const INTERLOCK_LINES: [usize; 2] = [8, 9];

/// Routes the lines to their ports and enables both edges on each. The pins must already be
/// inputs.
pub fn init() {
    pac::RCC.apb2enr().modify(|w| w.set_syscfgen(true));
    // (line, port index: A = 0)
    for (line, port) in [(EXPOSURE0_LINE, 1u8), (INTERLOCK_LINES[0], 2), (INTERLOCK_LINES[1], 0)] {
        pac::SYSCFG.exticr(line / 4).modify(|w| w.set_exti(line % 4, port));
        pac::EXTI.rtsr(0).modify(|w| w.set_line(line, true));
        pac::EXTI.ftsr(0).modify(|w| w.set_line(line, true));
        pac::EXTI.pr(0).write(|w| w.set_line(line, true));
        pac::EXTI.imr(0).modify(|w| w.set_line(line, true));
    }
    // SAFETY: the handlers below only touch critical-section-protected state.
    unsafe {
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::EXTI9_5);
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::EXTI15_10);
    }
}

/// The oldest capture at or before `until`.
pub fn take(until: u64) -> Option<Capture> {
    critical_section::with(|cs| {
        let mut q = CAPTURES.borrow_ref_mut(cs);
        match q.front() {
            Some(c) if c.tick <= until => q.pop_front(),
            _ => None,
        }
    })
}

/// Whether edges were lost since the last call.
pub fn take_overflow() -> bool {
    critical_section::with(|cs| core::mem::replace(&mut *OVERFLOW.borrow_ref_mut(cs), false))
}

#[interrupt]
fn EXTI15_10() {
    let tick = embassy_time::Instant::now().as_ticks();
    let pending = pac::EXTI.pr(0).read();
    if pending.line(EXPOSURE0_LINE) {
        pac::EXTI.pr(0).write(|w| w.set_line(EXPOSURE0_LINE, true));
        // The level after the edge; an edge pair shorter than the latency reads the same level
        // twice, which the rig tolerates (it acts on levels).
        let level = pac::GPIOB.idr().read().idr(10) == pac::gpio::vals::Idr::HIGH;
        critical_section::with(|cs| {
            if CAPTURES.borrow_ref_mut(cs).push_back(Capture { camera: 0, level, tick }).is_err() {
                *OVERFLOW.borrow_ref_mut(cs) = true;
            }
        });
        WAKE.signal(());
    }
}

#[interrupt]
fn EXTI9_5() {
    let pending = pac::EXTI.pr(0).read();
    for line in INTERLOCK_LINES {
        if pending.line(line) {
            pac::EXTI.pr(0).write(|w| w.set_line(line, true));
            WAKE.signal(());
        }
    }
}
