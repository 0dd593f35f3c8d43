//! Time: the embassy-time driver of the emulated board.
//!
//! The clock is SysTick, free-running on the 25 MHz processor clock with the full 24-bit
//! reload; its wraps are counted in the SysTick exception, so `cycles()` is a 64-bit count
//! that never loses a cycle. SysTick has no compare register (changing its reload would drop
//! the count in progress), so alarms use the CMSDK TIMER0 as a one-shot countdown on the same
//! 25 MHz clock. Under `qemu -icount shift=N` both count virtual time, which advances 2^N ns
//! per instruction: a cycle count is an instruction count.
//!
//! Device ticks are microseconds (`tick-hz-1_000_000`): `ticks = cycles / 25`.

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};
use core::task::Waker;

use cortex_m::peripheral::{syst::SystClkSource, SCB, SYST};
use critical_section::{CriticalSection, Mutex};
use embassy_time_driver::Driver as _;
use embassy_time_queue_utils::Queue;

use crate::irq;

/// The processor (and peripheral) clock of mps2-an386.
pub const CYCLES_HZ: u64 = 25_000_000;
/// Cycles per device tick.
pub const CYCLES_PER_TICK: u64 = CYCLES_HZ / embassy_time_driver::TICK_HZ;
const _: () = assert!(CYCLES_HZ.is_multiple_of(embassy_time_driver::TICK_HZ));

const SYST_RELOAD: u32 = 0x00FF_FFFF;

/// SysTick wraps (2^24 cycles each: 0.67 s; a u32 lasts 91 years).
static WRAPS: AtomicU32 = AtomicU32::new(0);

/// CMSDK APB TIMER0.
const TIMER0: usize = 0x4000_0000;
const TIMER_CTRL: usize = 0x00;
const TIMER_VALUE: usize = 0x04;
const TIMER_RELOAD: usize = 0x08;
const TIMER_INTCLEAR: usize = 0x0C;
const TIMER_EN: u32 = 1 << 0;
const TIMER_IRQ_EN: u32 = 1 << 3;
/// TIMER0's interrupt line.
pub const TIMER0_IRQ: u16 = 8;

fn timer_write(reg: usize, value: u32) {
    // SAFETY: TIMER0 registers of mps2-an386, only touched here, under a critical section.
    unsafe { core::ptr::write_volatile((TIMER0 + reg) as *mut u32, value) }
}

/// Starts SysTick and enables TIMER0's interrupt. Call once, before the executor runs.
pub fn init(syst: &mut SYST) {
    syst.set_clock_source(SystClkSource::Core);
    syst.set_reload(SYST_RELOAD);
    syst.clear_current();
    syst.enable_interrupt();
    syst.enable_counter();
    timer_write(TIMER_CTRL, 0);
    timer_write(TIMER_INTCLEAR, 1);
    irq::enable(TIMER0_IRQ);
}

/// Cycles since start (25 MHz), 64 bits.
pub fn cycles() -> u64 {
    critical_section::with(|_| {
        let mut value = SYST::get_current();
        let mut wraps = WRAPS.load(Ordering::Relaxed);
        // A wrap not yet counted by the exception: count it here, with a value read after it.
        if SCB::is_pendst_pending() {
            wraps += 1;
            value = SYST::get_current();
        }
        (u64::from(wraps) << 24) + u64::from(SYST_RELOAD - value)
    })
}

/// SysTick exception body: one more wrap.
pub fn on_systick() {
    WRAPS.fetch_add(1, Ordering::Relaxed);
}

struct Driver {
    queue: Mutex<RefCell<Queue>>,
}

embassy_time_driver::time_driver_impl!(static DRIVER: Driver = Driver { queue: Mutex::new(RefCell::new(Queue::new())) });

impl embassy_time_driver::Driver for Driver {
    fn now(&self) -> u64 {
        cycles() / CYCLES_PER_TICK
    }

    fn schedule_wake(&self, at: u64, waker: &Waker) {
        critical_section::with(|cs| {
            let Ok(mut queue) = self.queue.borrow(cs).try_borrow_mut() else { return };
            if queue.schedule_wake(at, waker) {
                rearm(cs, &mut queue);
            }
        });
    }
}

/// Wakes what is due and sets the alarm for the next expiry.
fn rearm(_cs: CriticalSection, queue: &mut Queue) {
    loop {
        let next = queue.next_expiration(DRIVER.now());
        if set_alarm(next) {
            break;
        }
    }
}

/// Programs TIMER0 to interrupt at tick `at`; `false` if `at` has passed already.
fn set_alarm(at: u64) -> bool {
    timer_write(TIMER_CTRL, 0);
    timer_write(TIMER_INTCLEAR, 1);
    if at == u64::MAX {
        return true;
    }
    let now = cycles();
    let due = at.saturating_mul(CYCLES_PER_TICK);
    if due <= now {
        return false;
    }
    // A countdown longer than 2^32 cycles (171 s) fires early; the queue then re-arms.
    let wait = u32::try_from(due - now).unwrap_or(u32::MAX);
    timer_write(TIMER_RELOAD, wait);
    timer_write(TIMER_VALUE, wait);
    timer_write(TIMER_CTRL, TIMER_EN | TIMER_IRQ_EN);
    true
}

/// TIMER0 interrupt body.
pub fn on_timer0() {
    critical_section::with(|cs| {
        timer_write(TIMER_CTRL, 0);
        timer_write(TIMER_INTCLEAR, 1);
        if let Ok(mut queue) = DRIVER.queue.borrow(cs).try_borrow_mut() {
            rearm(cs, &mut queue);
        }
    });
}
