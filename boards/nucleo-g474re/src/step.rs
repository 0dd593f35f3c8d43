//! Step pulses from one-pulse-mode timers: stepper 0's STEP on TIM3_CH1 (PC6, AF2), stepper
//! 1's on TIM17_CH1 (PB9, AF1), the filter wheel's on TIM15_CH1 (PB14, AF1). The CPU starts the timer at the step's tick (the board
//! has already waited for it); the timer makes the 2 µs pulse and stops, so the loop no longer
//! spins for the pulse's width.

use embassy_stm32::gpio::{AfType, Flex, OutputType, Speed};
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{CcmrOutputCcs, Ocm};
use embassy_stm32::pac::timer::TimGp16;
use lightrig_firmware::timer_schedule::{counts_for_ns, one_pulse, OnePulse};

/// Timer clock (APB1 and APB2 timers at HCLK).
const TIMER_HZ: u32 = 168_000_000;
/// Step pulse width: covers common drivers' minimum high time (DRV8825 1.9 µs, A4988 1 µs).
const PULSE_NS: u32 = 2_000;
/// The pulse one count after the start, `PULSE_NS` wide (336 counts; checked in the firmware's
/// tests, so the fallback is never used).
const PULSE: OnePulse = match one_pulse(1, counts_for_ns(PULSE_NS, TIMER_HZ)) {
    Some(p) => p,
    None => OnePulse { ccr: 1, arr: 336 },
};
/// Polls of a running pulse before a new one starts anyway (a pulse lasts 336 counts; each
/// poll takes several cycles, so this is never reached while the timer runs).
const MAX_BUSY_POLLS: u32 = 1_000;

/// Which timer makes a STEP pin's pulses.
#[derive(Clone, Copy)]
pub enum StepTimer {
    /// TIM3 channel 1 (PC6, AF2).
    Tim3,
    /// TIM15 channel 1 (PB14, AF1); has a main output enable.
    Tim15,
    /// TIM17 channel 1 (PB9, AF1); has a main output enable.
    Tim17,
}

impl StepTimer {
    /// The registers they share (same offsets in TIM3, TIM15 and TIM17: CR1, CCMR1, CCER, CNT,
    /// PSC, ARR, CCR1), through the general-purpose view.
    fn regs(self) -> TimGp16 {
        match self {
            StepTimer::Tim3 => pac::TIM3,
            // SAFETY: TIM15's block has these registers at the general-purpose offsets; only
            // they are used through this view.
            StepTimer::Tim15 => unsafe { TimGp16::from_ptr(pac::TIM15.as_ptr()) },
            // SAFETY: as TIM15 (TIM17 is the one-channel member of the same family).
            StepTimer::Tim17 => unsafe { TimGp16::from_ptr(pac::TIM17.as_ptr()) },
        }
    }

    fn af(self) -> u8 {
        match self {
            StepTimer::Tim3 => 2,
            StepTimer::Tim15 | StepTimer::Tim17 => 1,
        }
    }
}

/// A STEP output driven by a one-pulse timer.
pub struct StepPulse {
    _pin: Flex<'static>,
    timer: StepTimer,
}

impl StepPulse {
    /// Sets the timer up (stopped, output low) and puts the pin on it.
    pub fn new(mut pin: Flex<'static>, timer: StepTimer) -> Self {
        match timer {
            StepTimer::Tim3 => pac::RCC.apb1enr1().modify(|w| w.set_tim3en(true)),
            StepTimer::Tim15 => pac::RCC.apb2enr().modify(|w| w.set_tim15en(true)),
            StepTimer::Tim17 => pac::RCC.apb2enr().modify(|w| w.set_tim17en(true)),
        }
        let t = timer.regs();
        t.cr1().modify(|w| {
            w.set_cen(false);
            w.set_opm(true);
        });
        t.psc().write_value(0); // as at reset, so no update event is needed to load it
        t.arr().write(|w| w.set_arr(PULSE.arr));
        t.ccr(0).write(|w| w.set_ccr(PULSE.ccr));
        t.cnt().write(|w| w.set_cnt(0));
        t.ccmr_output(0).modify(|w| {
            w.set_ccs(0, CcmrOutputCcs::OUTPUT);
            w.set_ocpe(0, false);
            w.set_ocm(0, Ocm::FORCE_INACTIVE); // low now ...
        });
        // ... then PWM mode 2: inactive while CNT < CCR1, so low while stopped at 0.
        t.ccmr_output(0).modify(|w| w.set_ocm(0, Ocm::PWM_MODE2));
        t.ccer().modify(|w| {
            w.set_ccp(0, false);
            w.set_cce(0, true);
        });
        match timer {
            StepTimer::Tim3 => {}
            StepTimer::Tim15 => pac::TIM15.bdtr().modify(|w| w.set_moe(true)),
            StepTimer::Tim17 => pac::TIM17.bdtr().modify(|w| w.set_moe(true)),
        }
        pin.set_as_af_unchecked(timer.af(), AfType::output(OutputType::PushPull, Speed::High));
        Self { _pin: pin, timer }
    }

    /// Starts one pulse now (after the one in progress, if any).
    pub fn fire(&mut self) {
        let t = self.timer.regs();
        let mut polls = 0;
        while t.cr1().read().cen() && polls < MAX_BUSY_POLLS {
            polls += 1;
        }
        t.cr1().modify(|w| w.set_cen(true));
    }
}
