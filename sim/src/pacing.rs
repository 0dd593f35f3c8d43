//! Real-time pacing of simulated time.
//!
//! The virtual rig's clock is a [`SimClock`](lightrig_firmware::sim::SimClock) that only moves
//! when told. By default it jumps straight to whatever is due next, so an acquisition takes as
//! long as the rendering, not as long as its exposures. Paced, it moves with the wall clock
//! instead, but still only *to* each deadline, never past it unpolled: when this process wakes
//! late, the device does that deadline's work stamped with the deadline's tick (as a board whose
//! timer fired on time would), and catches up with the wall clock at once. So a loaded machine
//! delays the simulation a little but never makes its schedule late, and pin records and event
//! ticks stay exact.

use std::time::{Duration, Instant};

/// A wall clock in device ticks (1 tick = 1 µs, the virtual device's rate), anchored at a
/// simulated tick.
#[derive(Debug, Clone, Copy)]
pub struct RealTime {
    anchor: Instant,
    anchor_tick: u64,
}

impl RealTime {
    /// Wall clock and simulated time agree now, at `tick`.
    pub fn starting_at(tick: u64) -> Self {
        Self { anchor: Instant::now(), anchor_tick: tick }
    }

    /// The tick the wall clock has reached.
    pub fn now(&self) -> u64 {
        self.anchor_tick.saturating_add(self.anchor.elapsed().as_micros() as u64)
    }

    /// How long until the wall clock reaches `tick` (zero if it has).
    pub fn until(&self, tick: u64) -> Duration {
        Duration::from_micros(tick.saturating_sub(self.now()))
    }

    /// Blocks until the wall clock reaches `tick`.
    pub fn wait_until(&self, tick: u64) {
        let d = self.until(tick);
        if !d.is_zero() {
            std::thread::sleep(d);
        }
    }
}
