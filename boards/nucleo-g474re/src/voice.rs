//! Voice-coil stream on DAC1 channel 1 (PA4): a circular DMA over a ring of samples, paced by
//! TIM6's update event, so samples leave at the exact sample rate whatever the CPU does.
//!
//! The ring holds four 64-sample blocks. A stream starts (sample 0) one block of silence ahead
//! of the DMA's read position: block `k`, handed over about one block after its window, is read
//! one block later still, i.e. two blocks (`VOICE_COIL_LATENCY_BLOCKS`) after its nominal time.
//! TIM6 and the tick counter share the 168 MHz clock, so the stream never drifts.

use core::ptr::{addr_of, addr_of_mut};

use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::Mms;
use lightrig_firmware::rig::VOICE_COIL_BLOCK;

/// The one sample rate this board plays (168 MHz / 3500). The rig file's voice coil must say
/// `sample_rate_hz = 48000`.
pub const SAMPLE_RATE_HZ: u32 = 48_000;
const TIMER_HZ: u32 = 168_000_000;
const RING: usize = 4 * VOICE_COIL_BLOCK;
/// Mid-scale: the coil at rest (12-bit left-aligned).
const MID: u16 = 0x8000;
/// A stream with no block for this long is stopped (and the coil parked at mid-scale) rather
/// than left looping the ring.
const STALL_TICKS: u64 = 4_000;

/// The DMA's source. Written only through raw pointers while the DMA reads it.
static mut SAMPLES: [u16; RING] = [MID; RING];

/// The ring as the DMA sees it.
pub fn ring() -> &'static [u16] {
    // SAFETY: the DMA only reads; the CPU writes individual elements with volatile writes and
    // never through this slice.
    unsafe { &*addr_of!(SAMPLES) }
}

fn put(index: usize, value: u16) {
    // SAFETY: `index % RING` is in bounds; volatile so the write is not elided or merged.
    unsafe { addr_of_mut!(SAMPLES).cast::<u16>().add(index % RING).write_volatile(value) }
}

/// The stream's state; the DMA transfer itself runs in the `voice_coil` task.
pub struct VoiceStream {
    running: bool,
    /// Ring index of sample 0.
    base: usize,
    /// The sample the next block must start with to continue the stream.
    next: u64,
    last_block: u64,
}

impl VoiceStream {
    /// Sets TIM6 to trigger the DAC at the sample rate (stopped until a stream starts).
    pub fn new() -> Self {
        pac::RCC.apb1enr1().modify(|w| w.set_tim6en(true));
        let t = pac::TIM6;
        t.cr1().modify(|w| w.set_cen(false));
        t.psc().write_value(0);
        t.arr().write(|w| w.set_arr((TIMER_HZ / SAMPLE_RATE_HZ - 1) as u16));
        t.cr2().modify(|w| w.set_mms(Mms::UPDATE));
        Self { running: false, base: 0, next: 0, last_block: 0 }
    }

    fn stop(&mut self) {
        pac::TIM6.cr1().modify(|w| w.set_cen(false));
        self.running = false;
        for i in 0..RING {
            put(i, MID);
        }
        // The DAC's holding register already has the next (stale) sample: park it too.
        pac::DAC1.dhr12l(0).write(|w| w.set_dhr(MID >> 4));
    }

    /// Samples `first..first + samples.len()`; a block that does not continue the stream
    /// restarts it.
    pub fn write(&mut self, first: u64, samples: &[i16], now: u64) {
        if !self.running || first != self.next {
            self.stop();
            // The next ring slot the DMA fetches, plus one block of silence.
            let remaining = pac::DMA1.ch(0).ndtr().read().ndt() as usize;
            let read = (RING - remaining.min(RING)) % RING;
            self.base = (read + VOICE_COIL_BLOCK + RING - (first % RING as u64) as usize) % RING;
        }
        for (i, &s) in samples.iter().enumerate() {
            let n = first.wrapping_add(i as u64);
            // i16 → offset binary, left-aligned for the 12-bit DAC.
            put(self.base + (n % RING as u64) as usize, (s as u16) ^ 0x8000);
        }
        self.next = first.wrapping_add(samples.len() as u64);
        self.last_block = now;
        if !self.running {
            pac::TIM6.cnt().write(|w| w.set_cnt(0));
            pac::TIM6.cr1().modify(|w| w.set_cen(true));
            self.running = true;
        }
    }

    /// Stops a stream whose blocks stopped coming.
    pub fn service(&mut self, now: u64) {
        if self.running && now.saturating_sub(self.last_block) > STALL_TICKS {
            defmt::warn!("voice coil: no block since {}, stream parked", self.last_block);
            self.stop();
        }
    }
}
