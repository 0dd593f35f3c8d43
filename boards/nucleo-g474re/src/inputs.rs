//! Input edges the rig must see promptly: camera exposure edges and interlock changes.
//!
//! Exposure edges are time-stamped by TIM2's input capture on channel 3 (PB10, AF1): TIM2 is
//! embassy-time's clock, so the latched CCR3 is the edge's tick's low 16 bits, exact whatever
//! the interrupt latency. The same pin's EXTI line (it works in alternate-function mode) wakes
//! the handler below, which extends the capture to the 64-bit tick (`Counter::captured_tick`,
//! exact while it runs within 65 ms of the edge) and reads the level after the edge. The time
//! driver owns TIM2's interrupt (and clears every flag in it), so no capture flag is used.
//! Interlock changes only wake the run loop.
//!
//! The HAL's `exti` feature is off: these handlers own the EXTI vectors.

use core::cell::RefCell;

use critical_section::Mutex;
use embassy_stm32::gpio::{AfType, Flex, Pull};
use embassy_stm32::interrupt;
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{CcmrInputCcs, FilterValue};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use heapless::Deque;
use lightrig_firmware::hal::Capture;

use crate::board::TIM2_COUNTER;

/// Wakes the run loop: an exposure edge or an interlock change.
pub static WAKE: Signal<CriticalSectionRawMutex, ()> = Signal::new();

/// Captured exposure edges, oldest first.
static CAPTURES: Mutex<RefCell<Deque<Capture, 32>>> = Mutex::new(RefCell::new(Deque::new()));
/// An edge was dropped because the queue was full (the run loop stalled for 16 exposures).
static OVERFLOW: Mutex<RefCell<bool>> = Mutex::new(RefCell::new(false));

/// EXTI line of camera 0's exposure input (PB10).
pub const EXPOSURE0_LINE: usize = 10;
/// EXTI lines of the interlock inputs (PC8, PA9, PC2, PC3) and their ports (A = 0).
pub const INTERLOCK_LINES: [(usize, u8); 4] = [(8, 2), (9, 0), (2, 2), (3, 2)];

/// TIM2 channel 3 (CCER and CCR index 2; CCMR2 field 0) and PB10's alternate function for it.
const CAPTURE_CHANNEL: usize = 2;
const CAPTURE_CCMR: usize = 1;
const CAPTURE_FIELD: usize = 0;
const AF_TIM2: u8 = 1;

/// Puts the exposure input (PB10) on TIM2_CH3 and sets the channel to capture both edges,
/// unfiltered (a filter would delay the capture by its sampling time).
pub fn exposure_pin(mut pin: Flex<'static>) -> Flex<'static> {
    let t = pac::TIM2;
    t.ccer().modify(|w| w.set_cce(CAPTURE_CHANNEL, false)); // CC3S is writable only while off
    t.ccmr_input(CAPTURE_CCMR).modify(|w| {
        // The PAC names CCS = 0b01 `TI4` for channels 2/4; for channel 3 it is IC3 on TI3.
        w.set_ccs(CAPTURE_FIELD, CcmrInputCcs::TI4);
        w.set_icf(CAPTURE_FIELD, FilterValue::NO_FILTER);
        w.set_icpsc(CAPTURE_FIELD, 0);
    });
    t.ccer().modify(|w| {
        w.set_ccp(CAPTURE_CHANNEL, true);
        w.set_ccnp(CAPTURE_CHANNEL, true); // CCxP = CCxNP = 1: both edges
        w.set_cce(CAPTURE_CHANNEL, true);
    });
    pin.set_as_af_unchecked(AF_TIM2, AfType::input(Pull::None));
    pin
}

/// Routes the lines to their ports and enables both edges on each. The pins must already be
/// inputs (or, for the exposure input, on its timer).
pub fn init() {
    pac::RCC.apb2enr().modify(|w| w.set_syscfgen(true));
    // (line, port index: A = 0)
    for (line, port) in core::iter::once((EXPOSURE0_LINE, 1u8)).chain(INTERLOCK_LINES) {
        pac::SYSCFG.exticr(line / 4).modify(|w| w.set_exti(line % 4, port));
        pac::EXTI.rtsr(0).modify(|w| w.set_line(line, true));
        pac::EXTI.ftsr(0).modify(|w| w.set_line(line, true));
        pac::EXTI.pr(0).write(|w| w.set_line(line, true));
        pac::EXTI.imr(0).modify(|w| w.set_line(line, true));
    }
    // SAFETY: the handlers below only touch critical-section-protected state.
    unsafe {
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::EXTI2);
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::EXTI3);
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
    let pending = pac::EXTI.pr(0).read();
    if pending.line(EXPOSURE0_LINE) {
        // Pending first, then the capture: an edge after this read pends again and comes back
        // with its own capture (at worst a repeat of this one, which the rig ignores: same
        // level).
        pac::EXTI.pr(0).write(|w| w.set_line(EXPOSURE0_LINE, true));
        let captured = pac::TIM2.ccr(CAPTURE_CHANNEL).read() & 0xFFFF;
        // After the capture read, so `now` is at or after the edge.
        let now = embassy_time::Instant::now().as_ticks();
        let tick = TIM2_COUNTER.captured_tick(captured, now, u32::from(now as u16));
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

/// An interlock changed: clear its pending bits and wake the loop, which reads the levels.
fn interlock_edge() {
    let pending = pac::EXTI.pr(0).read();
    for (line, _) in INTERLOCK_LINES {
        if pending.line(line) {
            pac::EXTI.pr(0).write(|w| w.set_line(line, true));
            WAKE.signal(());
        }
    }
}

#[interrupt]
fn EXTI9_5() {
    interlock_edge();
}

#[interrupt]
fn EXTI2() {
    interlock_edge();
}

#[interrupt]
fn EXTI3() {
    interlock_edge();
}
