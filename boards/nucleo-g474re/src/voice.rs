//! Voice-coil streams: coil 0 on DAC1 channel 1 (PA4), coil 1 on DAC2 channel 1 (PA6). Each
//! channel has a circular DMA over its own ring of samples (DMA1 channels 1 and 2); both are
//! paced by TIM6's update event, so samples leave at the exact sample rate whatever the CPU
//! does, and the two DMAs advance in lockstep.
//!
//! Each ring holds four 64-sample blocks. A stream starts (sample 0) one block of silence ahead
//! of its DMA's read position: block `k`, handed over about one block after its window, is read
//! one block later still, i.e. two blocks (`VOICE_COIL_LATENCY_BLOCKS`) after its nominal time.
//! TIM6 and the tick counter share the 168 MHz clock, so a stream never drifts.

use core::ptr::{addr_of, addr_of_mut};

use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::Mms;
use lightrig_firmware::boards::NUCLEO_G474RE_VOICE_COIL_HZ;
use lightrig_firmware::rig::VOICE_COIL_BLOCK;

/// The one sample rate this board plays (168 MHz / 3500). The rig file's voice coils must say
/// `sample_rate_hz = 48000`.
pub const SAMPLE_RATE_HZ: u32 = NUCLEO_G474RE_VOICE_COIL_HZ;
const TIMER_HZ: u32 = 168_000_000;
const RING: usize = 4 * VOICE_COIL_BLOCK;
/// Coil channels on this board.
pub const COILS: usize = 2;
/// Mid-scale: the coil at rest (12-bit left-aligned).
const MID: u16 = 0x8000;
/// A stream with no block for this long is stopped (and the coil parked at mid-scale) rather
/// than left looping the ring.
const STALL_TICKS: u64 = 4_000;

/// The DMAs' sources, one ring per coil. Written only through raw pointers while the DMAs
/// read them.
static mut SAMPLES: [[u16; RING]; COILS] = [[MID; RING]; COILS];

/// Coil `coil`'s ring as its DMA sees it (`coil < COILS`).
pub fn ring(coil: usize) -> &'static [u16] {
    // SAFETY: the DMA only reads; the CPU writes individual elements with volatile writes and
    // never through this slice.
    unsafe { &(*addr_of!(SAMPLES))[coil % COILS] }
}

fn put(coil: usize, index: usize, value: u16) {
    // SAFETY: both indices are reduced into bounds; volatile so the write is not elided or
    // merged.
    unsafe {
        addr_of_mut!(SAMPLES).cast::<u16>().add((coil % COILS) * RING + index % RING).write_volatile(value)
    }
}

/// One coil's stream state; its DMA transfer runs in a `voice_coil_dma` task.
struct VoiceStream {
    coil: usize,
    running: bool,
    /// Ring index of sample 0.
    base: usize,
    /// The sample the next block must start with to continue the stream.
    next: u64,
    last_block: u64,
}

impl VoiceStream {
    const fn new(coil: usize) -> Self {
        Self { coil, running: false, base: 0, next: 0, last_block: 0 }
    }

    /// The ring slot this coil's DMA fetches next.
    fn read_position(&self) -> usize {
        let remaining = pac::DMA1.ch(self.coil).ndtr().read().ndt() as usize;
        (RING - remaining.min(RING)) % RING
    }

    /// Parks the coil at mid-scale; the DMA goes on reading the (now silent) ring.
    fn park(&mut self) {
        self.running = false;
        for i in 0..RING {
            put(self.coil, i, MID);
        }
        // The DAC's holding register already has the next (stale) sample: park it too.
        match self.coil {
            0 => pac::DAC1.dhr12l(0).write(|w| w.set_dhr(MID >> 4)),
            _ => pac::DAC2.dhr12l(0).write(|w| w.set_dhr(MID >> 4)),
        }
    }

    fn write(&mut self, first: u64, samples: &[i16], now: u64) {
        if !self.running || first != self.next {
            self.park();
            // The next ring slot the DMA fetches, plus one block of silence.
            self.base =
                (self.read_position() + VOICE_COIL_BLOCK + RING - (first % RING as u64) as usize) % RING;
        }
        for (i, &s) in samples.iter().enumerate() {
            let n = first.wrapping_add(i as u64);
            // i16 → offset binary, left-aligned for the 12-bit DAC.
            put(self.coil, self.base + (n % RING as u64) as usize, (s as u16) ^ 0x8000);
        }
        self.next = first.wrapping_add(samples.len() as u64);
        self.last_block = now;
        self.running = true;
    }
}

/// Both coils and the timer that paces them. TIM6 runs while any stream runs; it is stopped
/// only when both are parked, so the two DMAs never lose their lockstep.
pub struct VoiceOutputs {
    streams: [VoiceStream; COILS],
}

impl VoiceOutputs {
    /// Sets TIM6 to trigger the DACs at the sample rate (stopped until a stream starts).
    pub fn new() -> Self {
        pac::RCC.apb1enr1().modify(|w| w.set_tim6en(true));
        let t = pac::TIM6;
        t.cr1().modify(|w| w.set_cen(false));
        t.psc().write_value(0);
        t.arr().write(|w| w.set_arr((TIMER_HZ / SAMPLE_RATE_HZ - 1) as u16));
        t.cr2().modify(|w| w.set_mms(Mms::UPDATE));
        Self { streams: [VoiceStream::new(0), VoiceStream::new(1)] }
    }

    fn timer_running() -> bool {
        pac::TIM6.cr1().read().cen()
    }

    /// Samples `first..first + samples.len()` of `coil`; a block that does not continue the
    /// stream restarts it. Unknown coils are ignored (the configuration refuses them).
    pub fn write(&mut self, coil: u8, first: u64, samples: &[i16], now: u64) {
        let Some(s) = self.streams.get_mut(usize::from(coil)) else { return };
        s.write(first, samples, now);
        if !Self::timer_running() {
            pac::TIM6.cnt().write(|w| w.set_cnt(0));
            pac::TIM6.cr1().modify(|w| w.set_cen(true));
        }
    }

    /// Parks a stream whose blocks stopped coming; stops the timer once both are parked.
    pub fn service(&mut self, now: u64) {
        for s in &mut self.streams {
            if s.running && now.saturating_sub(s.last_block) > STALL_TICKS {
                defmt::warn!("voice coil {}: no block since {}, stream parked", s.coil, s.last_block);
                s.park();
            }
        }
        if Self::timer_running() && self.streams.iter().all(|s| !s.running) {
            pac::TIM6.cr1().modify(|w| w.set_cen(false));
        }
    }
}
