//! Hardware-timed edges on a free-running timer counter, in integer ticks: the arithmetic a
//! board needs to latch an output edge at an exact tick (output compare) and to time-stamp an
//! input edge (input capture), apart from the registers.
//!
//! The counter advances once per tick and holds only the low `bits` bits of the tick (plus,
//! for a timer that is not the clock's own, a constant offset: every function takes the
//! counter's value read at a known tick `now`). The controller's ticks are 64-bit; a compare
//! value or a capture is a counter value, so it names one tick per counter period.
//!
//! Output edges reach the board early enough to arm only if the run loop polls the rig ahead
//! of the clock: [`wake_tick`] and [`lookahead_tick`] are that schedule. An output the board
//! cannot latch in hardware waits for its tick instead ([`must_wait`]).
//!
//! Pulses of a fixed width (step pulses) come from a one-pulse-mode timer started at the
//! pulse's tick: [`one_pulse`] gives its compare and reload values.

/// A free-running up-counter of `bits` bits (1..=32), one count per tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Counter {
    bits: u32,
}

/// What to do with an output edge due at a tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EdgePlan {
    /// Load this value into the compare register: the pin changes exactly at the edge's tick.
    Compare(u32),
    /// Too close to arm safely, or past: drive the pin now. `late` is how many ticks after
    /// the edge's tick that is (0 while the tick is still ahead).
    DriveNow {
        /// Ticks the edge is already past.
        late: u64,
    },
    /// More than one counter period ahead: a compare now would fire a period (or more) early.
    /// Plan again closer to the tick.
    TooFar,
}

impl Counter {
    /// A `bits`-bit counter; `bits` is clamped to 1..=32.
    pub const fn new(bits: u32) -> Self {
        let bits = if bits < 1 {
            1
        } else if bits > 32 {
            32
        } else {
            bits
        };
        Self { bits }
    }

    /// Counter width in bits.
    pub const fn bits(self) -> u32 {
        self.bits
    }

    /// Ticks per counter period: 2^bits.
    pub const fn period(self) -> u64 {
        1 << self.bits
    }

    const fn mask(self) -> u64 {
        self.period() - 1
    }

    /// The counter's value at tick `at`, given that it read `counter` at tick `now` (`at` may
    /// be before or after `now`).
    pub const fn value_at(self, at: u64, now: u64, counter: u32) -> u32 {
        ((counter as u64).wrapping_add(at.wrapping_sub(now)) & self.mask()) as u32
    }

    /// The 64-bit tick of a captured counter value, read back at tick `now` when the counter
    /// read `counter`: the latest tick at or before `now` at which the counter held `captured`.
    /// Exact while the capture is read less than one counter period after its edge.
    pub const fn captured_tick(self, captured: u32, now: u64, counter: u32) -> u64 {
        let elapsed = (counter as u64).wrapping_sub(captured as u64) & self.mask();
        now.saturating_sub(elapsed)
    }

    /// How to produce an output edge due at tick `at`, at tick `now` when the counter reads
    /// `counter`. An edge is armed only if it is at least `min_lead` ticks ahead, so the
    /// counter cannot pass the compare value while the registers are being written (a missed
    /// match would wait a whole period).
    pub const fn plan_edge(self, at: u64, now: u64, counter: u32, min_lead: u64) -> EdgePlan {
        if at.saturating_sub(now) < min_lead {
            EdgePlan::DriveNow { late: now.saturating_sub(at) }
        } else if at - now >= self.period() {
            EdgePlan::TooFar
        } else {
            EdgePlan::Compare(self.value_at(at, now, counter))
        }
    }
}

/// When the run loop must wake: at the link's deadline, or `lead` ticks before the rig's next
/// due tick, so the outputs of that tick can be armed (or waited for) before it.
pub const fn wake_tick(link_deadline: Option<u64>, rig_due: Option<u64>, lead: u64) -> Option<u64> {
    match (link_deadline, rig_due) {
        (Some(l), Some(r)) => {
            let r = r.saturating_sub(lead);
            Some(if l < r { l } else { r })
        }
        (Some(l), None) => Some(l),
        (None, Some(r)) => Some(r.saturating_sub(lead)),
        (None, None) => None,
    }
}

/// The tick to poll the rig at ahead of the clock, if its next due tick `rig_due` is in the
/// future but no more than `lead` ticks after `now`. Work already due is the ordinary poll's.
pub const fn lookahead_tick(rig_due: Option<u64>, now: u64, lead: u64) -> Option<u64> {
    match rig_due {
        Some(t) if t > now && t - now <= lead => Some(t),
        _ => None,
    }
}

/// Whether an output due at `at` must still wait at `now`: its tick is ahead, by no more than
/// `max_wait` (anything further is a scheduling error; the output goes out now rather than
/// stall the loop).
pub const fn must_wait(at: u64, now: u64, max_wait: u64) -> bool {
    at > now && at - now <= max_wait
}

/// Compare and reload values of a timer in one-pulse mode with PWM mode 2 (output inactive
/// while the counter is below the compare value): started from 0, its output goes active
/// `ccr` counts later, stays active through `arr`, and the update at the end stops the timer
/// and brings the output back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OnePulse {
    /// Compare value: the delay from the start to the pulse, in counts.
    pub ccr: u16,
    /// Reload value: the pulse's last count.
    pub arr: u16,
}

/// A pulse `width` counts wide, `delay` counts after the start (at least 1: the counter starts
/// at 0, where the output must still be inactive). `None` if it does not fit 16 bits or is
/// empty.
pub const fn one_pulse(delay: u32, width: u32) -> Option<OnePulse> {
    if delay == 0 || width == 0 {
        return None;
    }
    let arr = delay as u64 + width as u64 - 1;
    if arr > u16::MAX as u64 {
        return None;
    }
    Some(OnePulse { ccr: delay as u16, arr: arr as u16 })
}

/// Timer counts covering at least `ns` nanoseconds at `timer_hz` (rounded up: a pulse is never
/// shorter than asked).
pub const fn counts_for_ns(ns: u32, timer_hz: u32) -> u32 {
    let counts = (ns as u64 * timer_hz as u64).div_ceil(1_000_000_000);
    if counts > u32::MAX as u64 {
        u32::MAX
    } else {
        counts as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T16: Counter = Counter::new(16);
    const T32: Counter = Counter::new(32);

    #[test]
    fn counter_width_is_clamped() {
        assert_eq!(Counter::new(0).bits(), 1);
        assert_eq!(Counter::new(16).period(), 65_536);
        assert_eq!(Counter::new(40).bits(), 32);
        assert_eq!(Counter::new(32).period(), 1 << 32);
    }

    #[test]
    fn compare_value_is_the_ticks_low_bits_on_the_clocks_own_counter() {
        // The counter is the tick's low 16 bits: the compare value is `at`'s.
        let now = 1_000_000;
        assert_eq!(T16.plan_edge(1_000_050, now, now as u16 as u32, 2), EdgePlan::Compare(0x4272));
        assert_eq!(1_000_050 & 0xFFFF, 0x4272);
    }

    #[test]
    fn compare_value_wraps_at_2_pow_16() {
        // Counter at 0xFFF0; the edge 0x15 ticks later is at counter value 0x0005.
        let now = 0x3_FFF0;
        assert_eq!(T16.plan_edge(0x4_0005, now, 0xFFF0, 2), EdgePlan::Compare(0x0005));
        // Exactly at the wrap.
        assert_eq!(T16.plan_edge(0x4_0000, now, 0xFFF0, 2), EdgePlan::Compare(0x0000));
        // The last value before it.
        assert_eq!(T16.plan_edge(0x3_FFFF, now, 0xFFF0, 2), EdgePlan::Compare(0xFFFF));
    }

    #[test]
    fn compare_value_across_the_2_pow_32_tick_boundary() {
        let now = 0xFFFF_FFF0;
        assert_eq!(T16.plan_edge(0x1_0000_0010, now, 0xFFF0, 2), EdgePlan::Compare(0x0010));
        assert_eq!(T32.plan_edge(0x1_0000_0010, now, 0xFFFF_FFF0, 2), EdgePlan::Compare(0x10));
        assert_eq!(T32.plan_edge(0x1_0000_0000, now, 0xFFFF_FFF0, 2), EdgePlan::Compare(0));
    }

    #[test]
    fn compare_value_with_a_counter_offset() {
        // A timer 0x1234 counts ahead of the tick's low bits: the compare keeps that offset.
        let now = 1_000;
        let counter = (1_000 + 0x1234) & 0xFFFF;
        assert_eq!(T16.plan_edge(1_100, now, counter, 2), EdgePlan::Compare(counter + 100));
        // ... and wraps with it.
        assert_eq!(T16.plan_edge(1_010, now, 0xFFFA, 2), EdgePlan::Compare(0x0004));
        assert_eq!(T16.value_at(990, now, 5), 0xFFFB, "a tick before `now`");
    }

    #[test]
    fn too_close_or_past_is_driven_now() {
        let now = 5_000;
        let c = now as u16 as u32;
        // `min_lead` 2: one tick ahead is too close, two is armable.
        assert_eq!(T16.plan_edge(now + 1, now, c, 2), EdgePlan::DriveNow { late: 0 });
        assert_eq!(T16.plan_edge(now + 2, now, c, 2), EdgePlan::Compare((now + 2) as u32));
        assert_eq!(T16.plan_edge(now, now, c, 2), EdgePlan::DriveNow { late: 0 });
        assert_eq!(T16.plan_edge(now - 1, now, c, 2), EdgePlan::DriveNow { late: 1 });
        assert_eq!(T16.plan_edge(now - 1_500, now, c, 2), EdgePlan::DriveNow { late: 1_500 });
        // No underflow near tick 0.
        assert_eq!(T16.plan_edge(0, 0, 0, 2), EdgePlan::DriveNow { late: 0 });
        assert_eq!(T16.plan_edge(u64::MAX, u64::MAX - 1, 0xFFFE, 2), EdgePlan::DriveNow { late: 0 });
    }

    #[test]
    fn more_than_a_period_ahead_is_too_far() {
        let now = 70_000;
        let c = now as u16 as u32;
        assert_eq!(
            T16.plan_edge(now + 65_535, now, c, 2),
            EdgePlan::Compare(((now + 65_535) & 0xFFFF) as u32)
        );
        assert_eq!(T16.plan_edge(now + 65_536, now, c, 2), EdgePlan::TooFar);
        let c = now as u32;
        assert_eq!(T32.plan_edge(now + (1 << 32) - 1, now, c, 2), EdgePlan::Compare((now - 1) as u32));
        assert_eq!(T32.plan_edge(now + (1 << 32), now, c, 2), EdgePlan::TooFar);
    }

    #[test]
    fn capture_extends_to_64_bits() {
        // Read 7 ticks after the edge.
        assert_eq!(T16.captured_tick(0x1230, 0x5_1237, 0x1237), 0x5_1230);
        // Read in the same tick.
        assert_eq!(T16.captured_tick(0x1237, 0x5_1237, 0x1237), 0x5_1237);
    }

    #[test]
    fn capture_across_the_counters_wrap() {
        // Edge at counter 0xFFFE, read after the 16-bit counter wrapped to 0x0003.
        assert_eq!(T16.captured_tick(0xFFFE, 0x6_0003, 0x0003), 0x5_FFFE);
    }

    #[test]
    fn capture_across_the_2_pow_32_tick_boundary() {
        // 16-bit counter: edge 3 ticks before tick 2^32, read 4 ticks after it.
        assert_eq!(T16.captured_tick(0xFFFD, 0x1_0000_0004, 0x0004), 0xFFFF_FFFD);
        // 32-bit counter, same edge.
        assert_eq!(T32.captured_tick(0xFFFF_FFFD, 0x1_0000_0004, 4), 0xFFFF_FFFD);
        // An edge on the boundary tick itself.
        assert_eq!(T32.captured_tick(0, 0x1_0000_0004, 4), 0x1_0000_0000);
    }

    #[test]
    fn capture_read_late() {
        // Read 65 535 ticks after the edge (the last exact read of a 16-bit counter).
        let edge = 0x7_8000u64;
        let now = edge + 65_535;
        assert_eq!(T16.captured_tick(0x8000, now, now as u16 as u32), edge);
        // One tick later the counter has come round: the capture reads as a period later.
        let now = edge + 65_536;
        assert_eq!(T16.captured_tick(0x8000, now, now as u16 as u32), edge + 65_536);
        // A 32-bit counter read a whole 2^31 ticks late is still exact.
        let edge = 0x2_FFFF_FF00u64;
        let now = edge + (1 << 31);
        assert_eq!(T32.captured_tick(0xFFFF_FF00, now, now as u32), edge);
    }

    #[test]
    fn capture_with_a_counter_offset_and_near_tick_zero() {
        // Counter runs 0x100 ahead of the tick's low bits.
        assert_eq!(T16.captured_tick(0x0150, 0x60, 0x0160), 0x50);
        // A capture that would lie before tick 0 (a stale register) saturates at 0.
        assert_eq!(T16.captured_tick(0x0200, 0x10, 0x0010), 0);
    }

    #[test]
    fn wake_tick_is_lead_before_the_rigs_work() {
        assert_eq!(wake_tick(None, None, 50), None);
        assert_eq!(wake_tick(Some(10_000), None, 50), Some(10_000), "the link is not led");
        assert_eq!(wake_tick(None, Some(10_000), 50), Some(9_950));
        assert_eq!(wake_tick(Some(9_960), Some(10_000), 50), Some(9_950));
        assert_eq!(wake_tick(Some(9_940), Some(10_000), 50), Some(9_940));
        assert_eq!(wake_tick(None, Some(20), 50), Some(0));
    }

    #[test]
    fn lookahead_polls_only_the_near_future() {
        assert_eq!(lookahead_tick(None, 1_000, 50), None);
        assert_eq!(lookahead_tick(Some(1_000), 1_000, 50), None, "due now: the ordinary poll's");
        assert_eq!(lookahead_tick(Some(999), 1_000, 50), None);
        assert_eq!(lookahead_tick(Some(1_001), 1_000, 50), Some(1_001));
        assert_eq!(lookahead_tick(Some(1_050), 1_000, 50), Some(1_050));
        assert_eq!(lookahead_tick(Some(1_051), 1_000, 50), None);
    }

    #[test]
    fn outputs_wait_for_their_tick_within_bounds() {
        assert!(must_wait(1_010, 1_000, 100));
        assert!(must_wait(1_100, 1_000, 100));
        assert!(!must_wait(1_101, 1_000, 100), "beyond the bound: out now");
        assert!(!must_wait(1_000, 1_000, 100));
        assert!(!must_wait(900, 1_000, 100));
    }

    #[test]
    fn one_pulse_values_exact() {
        // 2 µs at 168 MHz: 336 counts, one count after the start.
        assert_eq!(counts_for_ns(2_000, 168_000_000), 336);
        assert_eq!(one_pulse(1, 336), Some(OnePulse { ccr: 1, arr: 336 }));
        // Active from CNT = ccr through CNT = arr: arr - ccr + 1 counts.
        let p = one_pulse(5, 100).unwrap();
        assert_eq!(u32::from(p.arr - p.ccr) + 1, 100);
        // Rounded up, never shorter: 1.9 µs at 168 MHz is 319.2 counts.
        assert_eq!(counts_for_ns(1_900, 168_000_000), 320);
        assert_eq!(counts_for_ns(0, 168_000_000), 0);
        assert_eq!(counts_for_ns(u32::MAX, u32::MAX), u32::MAX, "saturates");
    }

    #[test]
    fn one_pulse_limits() {
        assert_eq!(one_pulse(0, 10), None, "the output must be inactive at count 0");
        assert_eq!(one_pulse(1, 0), None);
        assert_eq!(one_pulse(1, 65_535), Some(OnePulse { ccr: 1, arr: 65_535 }));
        assert_eq!(one_pulse(2, 65_535), None);
        assert_eq!(one_pulse(u32::MAX, u32::MAX), None);
    }
}
