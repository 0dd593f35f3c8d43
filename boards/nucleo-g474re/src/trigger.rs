//! Camera 0's trigger: output compare on TIM2 channel 4 (PA10, AF10).
//!
//! TIM2 is embassy-time's clock: its counter is the tick's low 16 bits (the time driver runs it
//! at 1 MHz with ARR = 0xFFFF and builds the 64-bit tick around it). A compare on that very
//! counter changes the pin when the clock reaches the edge's tick, in hardware: no offset to
//! keep between two timers, nothing depending on interrupt latency. The time driver uses
//! channels 1-2 and never touches channel 4's mode, CCR4 or CCER bits 12-15.
//!
//! The run loop polls the rig ahead of the clock (`LOOKAHEAD_TICKS`), so `set` usually gets
//! the edge before its tick and arms the compare. An edge whose tick is past, or less than
//! `MIN_LEAD` ticks ahead, is forced at once (late, if past; the rig faults `Late` beyond 1 ms).

use embassy_stm32::gpio::{AfType, Flex, OutputType, Speed};
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{CcmrOutputCcs, Ocm};
use lightrig_firmware::timer_schedule::EdgePlan;

use crate::board::{now_ticks, wait_until, TIM2_COUNTER};
/// An edge closer than this is not armed: the compare and mode writes must land before the
/// counter reaches the value (they take well under a tick, with interrupts off).
const MIN_LEAD: u64 = 2;
/// Channel 4 (CCER index 3; CCMR2 field 1).
const CCER_INDEX: usize = 3;
const CCMR: usize = 1;
const CCMR_FIELD: usize = 1;
/// PA10's alternate function for TIM2_CH4.
const AF_TIM2: u8 = 10;

/// Camera 0's trigger output.
pub struct Trigger {
    pin: Flex<'static>,
    /// Whether the pin drives yet: high-impedance (held inactive by its pull resistor) until
    /// the rig first sets it, which it does only once the camera's polarity is configured.
    driven: bool,
    /// Tick of the edge armed in CCR4 and not yet reached.
    pending: Option<u64>,
    /// Edges driven after their tick (the loop woke too late to arm them).
    late_edges: u32,
}

impl Trigger {
    /// Channel 4 as a compare output, frozen, its pin still high-impedance.
    pub fn new(pin: Flex<'static>) -> Self {
        let t = pac::TIM2;
        t.ccer().modify(|w| w.set_cce(CCER_INDEX, false));
        t.ccmr_output(CCMR).modify(|w| {
            w.set_ccs(CCMR_FIELD, CcmrOutputCcs::OUTPUT);
            // No preload: a CCR4 write takes effect at once, not at the next update.
            w.set_ocpe(CCMR_FIELD, false);
            w.set_ocm(CCMR_FIELD, Ocm::FORCE_INACTIVE);
        });
        t.ccer().modify(|w| {
            w.set_ccp(CCER_INDEX, false); // OC4 = OC4REF: active = high
            w.set_cce(CCER_INDEX, true);
        });
        Self { pin, driven: false, pending: None, late_edges: 0 }
    }

    fn set_mode(mode: Ocm) {
        pac::TIM2.ccmr_output(CCMR).modify(|w| w.set_ocm(CCMR_FIELD, mode));
    }

    fn force(level: bool) {
        Self::set_mode(if level { Ocm::FORCE_ACTIVE } else { Ocm::FORCE_INACTIVE });
    }

    /// The pin goes to `level` at tick `at`: by the compare if there is time to arm it, else
    /// now.
    pub fn set(&mut self, level: bool, at: u64) {
        if !self.driven {
            // Level first, then the pin onto the timer: no glitch to the other level.
            wait_until(at);
            Self::force(level);
            self.pin.set_as_af_unchecked(AF_TIM2, AfType::output(OutputType::PushPull, Speed::High));
            self.driven = true;
            return;
        }
        // One compare register: an armed edge must happen before the next is armed (edges come
        // in tick order, so it is never later than `at`).
        if let Some(p) = self.pending.take() {
            wait_until(p);
        }
        let plan = critical_section::with(|_| {
            let now = now_ticks();
            let plan = TIM2_COUNTER.plan_edge(at, now, u32::from(now as u16), MIN_LEAD);
            match plan {
                EdgePlan::Compare(value) => {
                    pac::TIM2.ccr(CCER_INDEX).write_value(value);
                    Self::set_mode(if level { Ocm::ACTIVE_ON_MATCH } else { Ocm::INACTIVE_ON_MATCH });
                    self.pending = Some(at);
                }
                EdgePlan::DriveNow { late } if late > 0 => {
                    Self::force(level);
                    self.late_edges = self.late_edges.wrapping_add(1);
                }
                EdgePlan::DriveNow { .. } => {} // a tick or two ahead: below
                EdgePlan::TooFar => Self::force(level),
            }
            plan
        });
        match plan {
            EdgePlan::DriveNow { late: 0 } => {
                wait_until(at);
                Self::force(level);
            }
            EdgePlan::TooFar => defmt::error!("trigger edge at {} more than a counter period ahead", at),
            _ => {}
        }
    }

    /// Edges driven late since the last call.
    pub fn take_late_edges(&mut self) -> u32 {
        core::mem::take(&mut self.late_edges)
    }
}
