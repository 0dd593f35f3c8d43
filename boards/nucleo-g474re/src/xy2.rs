//! XY2-100 galvo link (feature `xy2-100`): CLOCK, SYNC, X, Y on PC10, PC11, PC12, PC9.
//!
//! DMA2 channel 1 writes precomputed BSRR words into GPIOC at 4 MHz, one per request from
//! TIM7's update (168 MHz / 42, the ticks' clock): two states per bit, 20 bits per 10 µs frame,
//! so 100 kHz frames whatever the CPU does. The ring holds two frames and loops; a new position
//! goes into the frame the DMA is not reading, then into the other at the next half boundary
//! (the DMA's half/complete interrupt, on only while a half is stale), so no frame on the link
//! mixes two positions (`Xy2Refresh`). The link stays idle (all lines low) until the first
//! position: the galvo holds its own rest position until the rig drives it.

use core::cell::RefCell;
use core::convert::Infallible;
use core::ptr::{addr_of, addr_of_mut};

use critical_section::{CriticalSection, Mutex};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::pac;
use embassy_stm32::pac::bdma::vals::{Dir, Pl, Size};
use embassy_stm32::peripherals::{DMA2_CH1, PC10, PC11, PC12, PC9, TIM7};
use embassy_stm32::{interrupt, Peri};
use lightrig_firmware::galvo::{GpioStream, Xy2PortPins, Xy2Refresh, XY2_100_RING, XY2_100_STATES};

/// The lines' pin numbers on GPIOC.
pub const PINS: Xy2PortPins = Xy2PortPins { clock: 10, sync: 11, x: 12, y: 9 };
/// TIM7 counts 168 MHz / 42 = 4 MHz: one DMA request per state.
const TIM7_ARR: u16 = 42 - 1;
/// DMAMUX request of TIM7's update (RM0440, DMAMUX: 9 = TIM7_UP).
const DMAREQ_TIM7_UP: u8 = 9;
/// DMAMUX channel of DMA2 channel 1 (DMA1's 8 channels come first).
const DMAMUX_CHANNEL: usize = 8;
/// DMA2 channel 1 (index 0).
const DMA_CHANNEL: usize = 0;
/// States the DMA must still have to go in its half before the CPU copies a frame (40 words,
/// well under 2 µs with interrupts off) into the other: 8 states = 2 µs.
const COPY_MARGIN: usize = 8;

/// The DMA's source. Written only through raw pointers, in critical sections.
static mut RING: [u32; XY2_100_RING] = [0; XY2_100_RING];
/// The newest frame and which halves hold it; shared with the DMA interrupt.
static STATE: Mutex<RefCell<Shared>> =
    Mutex::new(RefCell::new(Shared { latest: [0; XY2_100_STATES], refresh: Xy2Refresh::new(COPY_MARGIN) }));

struct Shared {
    latest: [u32; XY2_100_STATES],
    refresh: Xy2Refresh,
}

fn write_half(half: usize, words: &[u32; XY2_100_STATES]) {
    let base = half.min(1) * XY2_100_STATES;
    for (i, &w) in words.iter().enumerate() {
        // SAFETY: `base + i` < XY2_100_RING; volatile, since the DMA reads the ring.
        unsafe { addr_of_mut!(RING).cast::<u32>().add(base + i).write_volatile(w) }
    }
}

fn remaining() -> u16 {
    pac::DMA2.ch(DMA_CHANNEL).ndtr().read().ndt()
}

fn set_boundary_interrupts(on: bool) {
    pac::DMA2.ch(DMA_CHANNEL).cr().modify(|w| {
        w.set_htie(on);
        w.set_tcie(on);
    });
}

/// Copies the newest frame into a stale half if the DMA allows it now; keeps the boundary
/// interrupts on while a half is stale.
fn refresh(cs: CriticalSection) {
    let mut s = STATE.borrow_ref_mut(cs);
    if let Some(half) = s.refresh.refresh(remaining()) {
        write_half(half, &s.latest);
    }
    set_boundary_interrupts(s.refresh.pending());
}

/// The XY2-100 port: owns its pins, TIM7 and DMA2 channel 1.
pub struct Xy2Port {
    _lines: [Output<'static>; 4],
    _tim: Peri<'static, TIM7>,
    _dma: Peri<'static, DMA2_CH1>,
    running: bool,
}

impl Xy2Port {
    /// Lines low, TIM7 and the DMA set up but stopped.
    pub fn new(
        clock: Peri<'static, PC10>,
        sync: Peri<'static, PC11>,
        x: Peri<'static, PC12>,
        y: Peri<'static, PC9>,
        tim: Peri<'static, TIM7>,
        dma: Peri<'static, DMA2_CH1>,
    ) -> Self {
        let lines = [
            Output::new(clock, Level::Low, Speed::VeryHigh),
            Output::new(sync, Level::Low, Speed::VeryHigh),
            Output::new(x, Level::Low, Speed::VeryHigh),
            Output::new(y, Level::Low, Speed::VeryHigh),
        ];

        pac::RCC.apb1enr1().modify(|w| w.set_tim7en(true));
        let t = pac::TIM7;
        t.cr1().modify(|w| w.set_cen(false));
        t.psc().write_value(0); // as at reset, so no update event is needed to load it
        t.arr().write(|w| w.set_arr(TIM7_ARR));
        t.dier().modify(|w| w.set_ude(true));

        pac::DMAMUX1.ccr(DMAMUX_CHANNEL).write(|w| w.set_dmareq_id(DMAREQ_TIM7_UP));
        let ch = pac::DMA2.ch(DMA_CHANNEL);
        ch.cr().write(|w| w.set_en(false));
        ch.par().write_value(pac::GPIOC.bsrr().as_ptr() as u32);
        ch.mar().write_value(addr_of!(RING) as u32);
        ch.ndtr().write(|w| w.set_ndt(XY2_100_RING as u16));
        ch.cr().write(|w| {
            w.set_dir(Dir::FROM_MEMORY);
            w.set_psize(Size::BITS32);
            w.set_msize(Size::BITS32);
            w.set_minc(true);
            w.set_circ(true);
            w.set_pl(Pl::VERY_HIGH);
        });
        Self { _lines: lines, _tim: tim, _dma: dma, running: false }
    }
}

impl GpioStream for Xy2Port {
    type Error = Infallible;

    fn queue_frame(&mut self, states: &[u8; XY2_100_STATES]) -> Result<(), Infallible> {
        let words = PINS.bsrr_frame(states);
        critical_section::with(|cs| {
            STATE.borrow_ref_mut(cs).latest = words;
            if self.running {
                STATE.borrow_ref_mut(cs).refresh.new_frame();
                refresh(cs);
            } else {
                // First frame: both halves, then start the stream at word 0.
                write_half(0, &words);
                write_half(1, &words);
                pac::DMA2.ch(DMA_CHANNEL).cr().modify(|w| w.set_en(true));
                pac::TIM7.cr1().modify(|w| w.set_cen(true));
                self.running = true;
            }
        });
        Ok(())
    }
}

#[interrupt]
fn DMA2_CHANNEL1() {
    // Half boundary: the DMA has just entered one half, the other is free for 10 µs.
    pac::DMA2.ifcr().write(|w| {
        w.set_htif(DMA_CHANNEL, true);
        w.set_tcif(DMA_CHANNEL, true);
        w.set_gif(DMA_CHANNEL, true);
    });
    critical_section::with(refresh);
}
