//! Voice-coil synthesis: a [`Synth`] turns one channel's sine partials into 16-bit samples,
//! in integer arithmetic only (the Cortex-M4 path has no floating point).
//!
//! **Phase.** Each voice has a 32-bit phase φ (2^32 = one turn). With the sample rate `r` in Hz
//! and the frequency `f` in mHz, the exact increment per sample is `f·2^32 / D` with
//! `D = 1000·r`, split into `inc = ⌊f·2^32 / D⌋` and `rem = f·2^32 mod D`. Every sample φ grows
//! by `inc` and an error term `e` by `rem`; when `e` reaches `D` it gives `D` back and φ takes
//! one more step (Bresenham). That keeps `φ·D + e = φ₀·D + n·f·2^32` (mod `2^32·D`), so after
//! `n` samples `φₙ = φ₀ + ⌊n·f·2^32 / D⌋ mod 2^32` exactly: the frequency is right to the
//! millihertz however long it runs: no drift.
//!
//! **Sine.** A quarter wave `sin(π/2 · i/1024)`, `i = 0..=1024`, in Q30, computed at compile
//! time by a `const fn` and mirrored into a half wave (2049 entries, 8 KiB of flash). Bit 31 of
//! the phase negates, the next eleven bits pick the segment, and the low twenty interpolate
//! linearly with one 32×32→64 multiply; reading the mirrored half forwards is bit-identical to
//! reading the quarter backwards (see `sine`), so the wave is exactly symmetric. The error is
//! at most `(π/2048)²/8 ≈ 2.9·10⁻⁷` of full scale (-130 dB), far under the 16-bit output's
//! quantisation.
//!
//! **Amplitude.** A voice's amplitude `A` is kept in output LSBs × 2^14 (`u16::MAX` →
//! `32767·2^14`). A ramp from `A₀` to `A₁` over `R` samples is a Bresenham line too:
//! `A_k = A₀ ± ⌊k·|A₁ − A₀| / R⌋`, so every step is `⌊Δ/R⌋` or `⌈Δ/R⌉` and `A_R = A₁` exactly,
//! however long the ramp (a plain fixed-point increment stalls or overshoots on long ones).
//!
//! **Output.** `y = round(Σ A·s / 2^44)` with `s` the Q30 sine, saturated to ±32767, so one
//! voice at `u16::MAX` is exactly full scale. The `i64` sum cannot overflow: at most 16 voices
//! of at most `32767·2^14 · 2^30` each stay under 2^63.
//!
//! **Changing partials** ([`Synth::set`]). Voices are matched by frequency. A voice whose
//! frequency is in the new list keeps its phase (the new `phase` field is ignored: taking it
//! would be a jump) and ramps to the new amplitude; the others ramp to 0 and are freed; new
//! partials start at amplitude 0 with their `phase` and ramp up. All ramps start from the
//! amplitudes of the moment, so a `set` during a ramp never jumps, and all end `R` samples
//! later. That needs at most 16 voices (8 fading, 8 rising) when sets are at least a ramp
//! apart. A set arriving mid-ramp may need more: then the quietest fading voices each lend
//! their slot to one new partial, fading over the first `⌈R/2⌉` samples instead of `R`, and the
//! new partial rises over the remaining `⌊R/2⌋` (with the phase it would have had from the
//! start). Still linear ramps, at most twice as steep, ending on time; never an error.

use heapless::Vec;
use lightrig_protocol::config::SAMPLE_RATE_RANGE;
use lightrig_protocol::sequence::Partial;
use lightrig_protocol::MAX_PARTIALS;

/// Voices per channel: the current partials plus as many fading out.
pub const VOICES: usize = 2 * MAX_PARTIALS;

/// The output's full scale: one partial at `u16::MAX` swings ±`FULL_SCALE`.
pub const FULL_SCALE: i16 = i16::MAX;

/// Why [`Synth::set`] refused a list of partials. The channel is left as it was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SynthError {
    /// More than `MAX_PARTIALS` partials.
    TooManyPartials,
    /// A partial at or above half the sample rate: it would alias to another frequency.
    AboveNyquist {
        /// The offending frequency, mHz.
        freq_mhz: u32,
    },
    /// A 0 Hz partial: a DC offset, which heats the coil instead of rippling the surface.
    ZeroFrequency,
    /// Two partials with the same frequency: they would be one sine, and which of them a
    /// running voice continues would be ambiguous.
    DuplicateFrequency {
        /// The repeated frequency, mHz.
        freq_mhz: u32,
    },
}

/// Quarter-wave segments; a power of two so the index is a bit field of the phase.
const SEGMENTS: usize = 1024;
const SEGMENT_BITS: u32 = SEGMENTS.trailing_zeros();
/// Phase bits below the segment index, used to interpolate.
const FRAC_BITS: u32 = 30 - SEGMENT_BITS;
const FRAC_MASK: u32 = (1 << FRAC_BITS) - 1;
/// The quarter wave mirrored into a half wave: `HALF[j] = sin(π/2 · j/SEGMENTS)` for
/// `j = 0..=2·SEGMENTS`, the second quarter an exact copy of the first read backwards (8 KiB).
/// Reading it forwards gives exactly the mirrored quarter-wave interpolation (see [`sine`])
/// without computing the mirror per sample.
static HALF: [i32; 2 * SEGMENTS + 1] = half_table();

/// Amplitude fraction bits below one output LSB.
const AMP_FRAC_BITS: u32 = 14;
/// Bits to drop from `amplitude (Q14 LSB) × sine (Q30)` to get output LSBs.
const OUT_SHIFT: u32 = AMP_FRAC_BITS + 30;
/// Samples rendered per block: voice by voice, so each voice's state stays in registers.
const BLOCK: usize = 32;

/// `sin x` for `0 ≤ x ≤ π/2` by its Taylor series, accurate to f64 rounding there (the last
/// term kept is below 10⁻²⁴). `f64::sin` is not a `const fn`.
const fn sin_const(x: f64) -> f64 {
    let x2 = x * x;
    let mut term = x;
    let mut sum = x;
    let mut k = 1;
    while k < 14 {
        term = -term * x2 / ((2 * k * (2 * k + 1)) as f64);
        sum += term;
        k += 1;
    }
    sum
}

const fn half_table() -> [i32; 2 * SEGMENTS + 1] {
    let mut table = [0; 2 * SEGMENTS + 1];
    let mut i = 0;
    while i <= SEGMENTS {
        let x = core::f64::consts::FRAC_PI_2 * i as f64 / SEGMENTS as f64;
        // Values are in [0, 1]: adding ½ and truncating rounds to nearest.
        table[i] = (sin_const(x) * (1u32 << 30) as f64 + 0.5) as i32;
        // sin(π − x) = sin x, exactly.
        table[2 * SEGMENTS - i] = table[i];
        i += 1;
    }
    table
}

/// `sin(2π · phase / 2^32)` in Q30.
///
/// Bits 20..=30 pick the half-wave segment `j`, the low twenty interpolate, bit 31 negates.
/// In the second quarter this equals reading the quarter wave backwards at the mirrored
/// position: for `x = j'·2^20 + f` past the crest with `d = Q[1024−j'] − Q[1023−j']`, the
/// mirror gives `Q[1023−j'] + ⌊d·(2^20 − f)/2^20⌋ = Q[1024−j'] − ⌈d·f/2^20⌉`, which is the
/// forward `HALF[j] + ⌊−d·f/2^20⌋`. So the wave is exactly symmetric about the crest.
#[inline(always)]
fn sine(phase: u32) -> i32 {
    // j ≤ 2·SEGMENTS − 1 by the mask, so both reads are in bounds without a check.
    let j = ((phase >> FRAC_BITS) as usize) & (2 * SEGMENTS - 1);
    let a = HALF[j];
    let b = HALF[j + 1];
    // |b − a| < 2^21, so the product fits easily; the sum stays within [0, 2^30].
    let v = a + ((i64::from(b - a) * i64::from(phase & FRAC_MASK)) >> FRAC_BITS) as i32;
    // Bit 31: the negative half wave.
    let negate = 0i32.wrapping_sub((phase >> 31) as i32);
    (v ^ negate) - negate
}

/// A phase accumulator with the exact Bresenham fraction (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Osc {
    phase: u32,
    inc: u32,
    rem: u32,
    err: u32,
}

impl Osc {
    /// `freq_mhz` must be below `den / 2` (checked by [`Synth::set`]), so `inc < 2^31`.
    fn new(freq_mhz: u32, phase: u16, den: u32) -> Self {
        let num = u64::from(freq_mhz) << 32;
        let den = u64::from(den);
        Self { phase: u32::from(phase) << 16, inc: (num / den) as u32, rem: (num % den) as u32, err: 0 }
    }

    #[inline(always)]
    fn step(&mut self, den: u32) {
        self.phase = self.phase.wrapping_add(self.inc);
        // err, rem < den < 2^28: no overflow.
        self.err += self.rem;
        if self.err >= den {
            self.err -= den;
            self.phase = self.phase.wrapping_add(1);
        }
    }

    /// The state `n` samples later, in O(1): the same as `n` calls to `step`.
    fn advanced(mut self, n: u32, den: u32) -> Self {
        // err + n·rem < 2^28 + 2^32·2^28: fits u64.
        let total = u64::from(self.err) + u64::from(n) * u64::from(self.rem);
        let den = u64::from(den);
        // Truncating the carry count to u32 is the phase's wrap-around.
        let carries = (total / den) as u32;
        self.phase = self.phase.wrapping_add(self.inc.wrapping_mul(n)).wrapping_add(carries);
        self.err = (total % den) as u32;
        self
    }
}

/// A linear amplitude ramp, exact at every sample (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Ramp {
    /// The amplitude now, output LSBs × 2^14.
    amp: i32,
    target: i32,
    /// Whole amplitude step per sample, signed.
    step: i32,
    /// +1 or −1: the direction of the carried fraction.
    dir: i32,
    /// Fractional step: `rem / len` per sample, carried in `err`.
    rem: u32,
    err: u32,
    len: u32,
    /// Samples until the ramp is on target; 0 = not ramping.
    left: u32,
}

impl Ramp {
    /// From `from` to `to` in `len` samples; no ramp at all when there is nothing to change.
    fn new(from: i32, to: i32, len: u32) -> Self {
        if len == 0 || from == to {
            return Self { amp: to, target: to, step: 0, dir: 1, rem: 0, err: 0, len: 0, left: 0 };
        }
        let delta = to.abs_diff(from); // < 2^29
        let dir = if to >= from { 1 } else { -1 };
        let step = (delta / len) as i32 * dir;
        Self { amp: from, target: to, step, dir, rem: delta % len, err: 0, len, left: len }
    }

    /// One sample along the ramp (the caller checks `left != 0`).
    #[inline(always)]
    fn advance(&mut self) {
        self.left -= 1;
        self.amp += self.step;
        // err + rem ≥ len, written so that it cannot overflow for len near u32::MAX.
        if self.err >= self.len - self.rem {
            self.err -= self.len - self.rem;
            self.amp += self.dir;
        } else {
            self.err += self.rem;
        }
    }
}

/// A partial waiting for a fading voice's slot (see "Changing partials" in the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Pending {
    freq_mhz: u32,
    /// Already advanced to the moment it takes over.
    osc: Osc,
    ramp: Ramp,
}

/// One sine: a partial of the latest list, or one fading out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Voice {
    freq_mhz: u32,
    osc: Osc,
    ramp: Ramp,
    /// In the latest list. Otherwise the voice is fading out and is freed at 0.
    listed: bool,
    /// Takes over this slot when the fade ends.
    next: Option<Pending>,
}

impl Voice {
    /// Listed, or fading but not yet at 0. A fading voice only reaches 0 at the end of its
    /// ramp (the ramp is monotonic), where a pending partial has already taken the slot over.
    fn alive(&self) -> bool {
        self.listed || self.ramp.amp != 0
    }

    /// Adds this voice's next `acc.len()` samples to `acc`. The loops work on local copies of
    /// the state so that it stays in registers; a ramp's end splits the block.
    #[inline(always)]
    fn render(&mut self, mut acc: &mut [i64], den: u32) {
        while self.ramp.left != 0 {
            // Ramping: up to the ramp's end, at most the block.
            let n = acc.len().min(self.ramp.left as usize);
            let Some((now, rest)) = acc.split_at_mut_checked(n) else { return };
            let (mut osc, mut ramp) = (self.osc, self.ramp);
            for a in now.iter_mut() {
                *a += i64::from(ramp.amp) * i64::from(sine(osc.phase));
                osc.step(den);
                ramp.advance();
            }
            (self.osc, self.ramp) = (osc, ramp);
            acc = rest;
            if ramp.left == 0 {
                // Only a fading voice carries a pending partial, so the slot is silent now.
                if let Some(next) = self.next.take() {
                    *self = Voice {
                        freq_mhz: next.freq_mhz,
                        osc: next.osc,
                        ramp: next.ramp,
                        listed: true,
                        next: None,
                    };
                }
            }
            if acc.is_empty() {
                return;
            }
        }
        if self.ramp.amp == 0 {
            // Listed but silent: only the phase moves on.
            self.osc = self.osc.advanced(acc.len() as u32, den);
            return;
        }
        let (mut osc, amp) = (self.osc, i64::from(self.ramp.amp));
        for a in acc.iter_mut() {
            *a += amp * i64::from(sine(osc.phase));
            osc.step(den);
        }
        self.osc = osc;
    }
}

/// `amplitude` (fraction of full scale) in output LSBs × 2^14, rounded.
fn level(amplitude: u16) -> i32 {
    let full = u64::from(FULL_SCALE as u16) << AMP_FRAC_BITS;
    let max = u64::from(u16::MAX);
    ((u64::from(amplitude) * full + max / 2) / max) as i32
}

/// One voice-coil channel's synthesiser: up to [`VOICES`] sine voices, summed to 16 bits.
#[derive(Debug, Clone)]
pub struct Synth {
    rate_hz: u32,
    /// `1000 · rate`: the phase fraction's denominator.
    den: u32,
    voices: Vec<Voice, VOICES>,
}

impl Synth {
    /// A silent channel at `sample_rate_hz`. The configuration accepts only
    /// [`SAMPLE_RATE_RANGE`]; a rate outside it is clamped into it, which keeps the phase
    /// arithmetic in range.
    pub fn new(sample_rate_hz: u32) -> Self {
        let rate_hz = sample_rate_hz.clamp(SAMPLE_RATE_RANGE.0, SAMPLE_RATE_RANGE.1);
        Self { rate_hz, den: 1000 * rate_hz, voices: Vec::new() }
    }

    /// The sample rate in use, Hz.
    pub fn sample_rate_hz(&self) -> u32 {
        self.rate_hz
    }

    /// Changes the partials, ramping every amplitude linearly over `ramp_samples` (0 = at
    /// once) from where it is now; see "Changing partials" in the module docs. An empty list
    /// fades to silence. The first sample after the call is where each new partial has its
    /// `phase`. On error nothing changes.
    pub fn set(&mut self, partials: &[Partial], ramp_samples: u32) -> Result<(), SynthError> {
        self.check(partials)?;
        self.apply(partials, ramp_samples);
        Ok(())
    }

    /// Fades every voice to 0 over `ramp_samples`: the safe state, reached without a click.
    pub fn fade_out(&mut self, ramp_samples: u32) {
        self.apply(&[], ramp_samples);
    }

    /// Every amplitude is 0 and nothing is ramping: the output is 0 until the next `set`.
    pub fn is_silent(&self) -> bool {
        self.voices.iter().all(|v| v.ramp.amp == 0 && v.ramp.left == 0)
    }

    /// Voices being synthesised: the current partials plus those still fading out.
    pub fn active_voices(&self) -> usize {
        self.voices.len()
    }

    /// Writes the next `out.len()` samples.
    pub fn fill(&mut self, out: &mut [i16]) {
        for chunk in out.chunks_mut(BLOCK) {
            let mut acc = [0i64; BLOCK];
            // Chunks are at most BLOCK long, so this is never the empty fallback.
            let acc = acc.get_mut(..chunk.len()).unwrap_or_default();
            for voice in self.voices.iter_mut() {
                voice.render(acc, self.den);
            }
            for (o, &a) in chunk.iter_mut().zip(acc.iter()) {
                let y = (a + (1 << (OUT_SHIFT - 1))) >> OUT_SHIFT;
                *o = y.clamp(-i64::from(FULL_SCALE), i64::from(FULL_SCALE)) as i16;
            }
            if !self.voices.iter().all(Voice::alive) {
                self.voices.retain(Voice::alive);
            }
        }
    }

    /// The next sample; the same as `fill` with a one-sample buffer.
    pub fn next_sample(&mut self) -> i16 {
        let mut out = [0];
        self.fill(&mut out);
        let [y] = out;
        y
    }

    /// Whether `set(partials, _)` would be accepted (the controller checks items on load).
    pub fn check(&self, partials: &[Partial]) -> Result<(), SynthError> {
        if partials.len() > MAX_PARTIALS {
            return Err(SynthError::TooManyPartials);
        }
        for (i, p) in partials.iter().enumerate() {
            if p.freq_mhz == 0 {
                return Err(SynthError::ZeroFrequency);
            }
            if u64::from(p.freq_mhz) * 2 >= u64::from(self.den) {
                return Err(SynthError::AboveNyquist { freq_mhz: p.freq_mhz });
            }
            if partials.iter().skip(i + 1).any(|q| q.freq_mhz == p.freq_mhz) {
                return Err(SynthError::DuplicateFrequency { freq_mhz: p.freq_mhz });
            }
        }
        Ok(())
    }

    /// `set` on a checked list.
    fn apply(&mut self, partials: &[Partial], ramp: u32) {
        // Re-target what is sounding. Pending partials have never sounded: dropping them is
        // silent, and a listed one comes back as a new partial below.
        for v in self.voices.iter_mut() {
            v.next = None;
            let new = partials.iter().find(|p| p.freq_mhz == v.freq_mhz);
            v.listed = new.is_some();
            v.ramp = Ramp::new(v.ramp.amp, new.map_or(0, |p| level(p.amplitude)), ramp);
        }
        // Unlisted voices at 0 go now (with ramp 0, every unlisted one).
        self.voices.retain(Voice::alive);

        let den = self.den;
        for p in partials {
            if self.voices.iter().any(|v| v.freq_mhz == p.freq_mhz) {
                continue;
            }
            let fresh = Voice {
                freq_mhz: p.freq_mhz,
                osc: Osc::new(p.freq_mhz, p.phase, den),
                ramp: Ramp::new(0, level(p.amplitude), ramp),
                listed: true,
                next: None,
            };
            let Err(fresh) = self.voices.push(fresh) else { continue };
            // All slots busy: borrow the quietest fading voice's. There always is one free to
            // lend: a full array holds k matched + j new + u unlisted = 16 voices, and the
            // m − k − j ≤ 8 − k − j partials left to place are fewer than u.
            let host =
                self.voices.iter_mut().filter(|v| !v.listed && v.next.is_none()).min_by_key(|v| v.ramp.amp);
            if let Some(host) = host {
                // ramp ≥ 1 here (ramp 0 freed every unlisted voice), so the fade is ≥ 1 sample.
                let fade = ramp - ramp / 2;
                host.ramp = Ramp::new(host.ramp.amp, 0, fade);
                host.next = Some(Pending {
                    freq_mhz: fresh.freq_mhz,
                    osc: fresh.osc.advanced(fade, den),
                    ramp: Ramp::new(0, fresh.ramp.target, ramp / 2),
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use rustfft::num_complex::Complex;
    use rustfft::FftPlanner;
    use std::vec::Vec;
    use std::{println, vec};

    const FS: i32 = (FULL_SCALE as i32) << AMP_FRAC_BITS;

    fn partial(freq_mhz: u32, amplitude: u16, phase: u16) -> Partial {
        Partial { freq_mhz, amplitude, phase }
    }

    /// `(freq_mhz, osc, amp)` of every voice.
    type State = Vec<(u32, Osc, i32)>;

    /// The voices, by frequency.
    fn voices(s: &Synth) -> State {
        let mut v: Vec<_> = s.voices.iter().map(|v| (v.freq_mhz, v.osc, v.ramp.amp)).collect();
        v.sort_by_key(|v| v.0);
        v
    }

    fn amp_of(s: &Synth, freq_mhz: u32) -> Option<i32> {
        s.voices.iter().find(|v| v.freq_mhz == freq_mhz).map(|v| v.ramp.amp)
    }

    /// The phase `n` samples after a partial took effect, from the closed form.
    fn closed_form(phase: u16, freq_mhz: u32, rate: u32, n: u64) -> u32 {
        let turns = ((u128::from(n) * u128::from(freq_mhz)) << 32) / (1000 * u128::from(rate));
        ((u128::from(phase) << 16) + turns) as u32
    }

    /// The quarter-wave form `sine` replaced: the mirror computed per sample.
    fn sine_by_quarter_wave(phase: u32) -> i32 {
        let q = |i: usize| if i <= SEGMENTS { HALF[i] } else { HALF[2 * SEGMENTS - i] };
        let m = 0u32.wrapping_sub((phase >> 30) & 1);
        let pos = ((phase & 0x3FFF_FFFF) ^ m).wrapping_add(m & 0x4000_0001);
        let i = (pos >> FRAC_BITS) as usize;
        let (a, b) = (q(i), q(i + 1));
        let v = a + ((i64::from(b - a) * i64::from(pos & FRAC_MASK)) >> FRAC_BITS) as i32;
        if phase >> 31 == 1 {
            -v
        } else {
            v
        }
    }

    #[test]
    fn half_wave_equals_mirrored_quarter_wave() {
        // Every segment of every quadrant, at its ends and inside; then random phases.
        for k in 0..4096u32 {
            for f in [0, 1, 2, 0x7_FFFF, 0x8_0000, 0xF_FFFE, 0xF_FFFF, 0x1_2345, 0xE_DCBA] {
                let p = k << FRAC_BITS | f;
                assert_eq!(sine(p), sine_by_quarter_wave(p), "phase {p:#x}");
            }
        }
        let mut x = 0x2545_F491u32;
        for _ in 0..1 << 22 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            assert_eq!(sine(x), sine_by_quarter_wave(x), "phase {x:#x}");
        }
        assert_eq!(HALF[SEGMENTS], 1 << 30);
        assert_eq!((HALF[0], HALF[2 * SEGMENTS]), (0, 0));
    }

    #[test]
    fn sine_table_error() {
        let mut worst = 0.0f64;
        let mut check = |p: u32| {
            let exact = (p as f64 * core::f64::consts::TAU / 4_294_967_296.0).sin();
            worst = worst.max((f64::from(sine(p)) / f64::from(1 << 30) - exact).abs());
        };
        (0..1u64 << 22).for_each(|k| check((k << 10) as u32 | 0x1FF));
        let mut x = 0x9E37_79B9u32;
        for _ in 0..1 << 20 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            check(x);
        }
        [0, 1 << 30, 1 << 31, 3 << 30, u32::MAX].into_iter().for_each(&mut check);
        println!("sine table + interpolation: max error {worst:.3e} of full scale");
        assert!(worst < 3.5e-7, "{worst:e}");
        assert_eq!(sine(1 << 30), 1 << 30);
        assert_eq!(sine(3 << 30), -(1 << 30));
    }

    #[test]
    fn full_scale_and_starting_phase() {
        let mut s = Synth::new(48_000);
        // A quarter turn: the first sample is the crest, exactly full scale.
        s.set(&[partial(1_000_000, u16::MAX, 0x4000)], 0).unwrap();
        assert_eq!(s.next_sample(), FULL_SCALE);
        s.set(&[partial(2_000_000, u16::MAX, 0xC000)], 0).unwrap();
        assert_eq!(s.next_sample(), -FULL_SCALE);
        assert_eq!(level(u16::MAX), FS);
        assert_eq!(level(0), 0);
    }

    /// SFDR of one partial, coherently sampled: `seconds` at `rate` hold a whole number of
    /// periods (the phase comes back exactly, see the module docs), so the rectangular-window
    /// FFT has `1/seconds` Hz bins and no leakage: the carrier is one bin, everything else is
    /// spurs. Returns (SFDR dBc, carrier amplitude in LSB).
    fn sfdr(rate: u32, freq_mhz: u32, seconds: u32, amplitude: u16) -> (f64, f64) {
        let n = (rate * seconds) as usize;
        let bin = (freq_mhz * seconds / 1000) as usize;
        assert_eq!(bin as u32 * 1000, freq_mhz * seconds, "not coherent");
        let mut s = Synth::new(rate);
        s.set(&[partial(freq_mhz, amplitude, 0x1234)], 0).unwrap();
        let mut out = vec![0i16; n];
        s.fill(&mut out);
        let mut buf: Vec<Complex<f64>> = out.iter().map(|&y| Complex::new(f64::from(y), 0.0)).collect();
        FftPlanner::new().plan_fft_forward(n).process(&mut buf);
        let carrier = buf[bin].norm_sqr();
        let spur = (0..=n / 2).filter(|&k| k != bin).map(|k| buf[k].norm_sqr()).fold(0.0, f64::max);
        (10.0 * (carrier / spur).log10(), 2.0 * carrier.sqrt() / n as f64)
    }

    #[test]
    fn sfdr_at_least_90_dbc() {
        let amplitude = (0.9 * 65535.0) as u16;
        let cases = [
            (48_000, 997_000, 1),
            (48_000, 1_000_000, 1),
            (48_000, 20_000, 1),
            (48_000, 20_011_000, 1),
            (48_000, 997_250, 4), // a millihertz-resolution frequency, 0.25 Hz bins
            (192_000, 997_000, 1),
            (192_000, 71_993_000, 1),
        ];
        for (rate, freq_mhz, seconds) in cases {
            let (dbc, amp) = sfdr(rate, freq_mhz, seconds, amplitude);
            let hz = f64::from(freq_mhz) / 1000.0;
            println!("SFDR {hz} Hz at {rate} Hz, 0.9 FS: {dbc:.1} dBc (carrier {amp:.2} LSB)");
            assert!(dbc >= 90.0, "{hz} Hz at {rate}: {dbc:.1} dBc");
            let expected = f64::from(level(amplitude)) / f64::from(1 << AMP_FRAC_BITS);
            assert!((amp - expected).abs() < 0.05, "{amp} vs {expected}");
        }
    }

    #[test]
    fn phase_is_exact_after_ten_million_samples() {
        let n = 10_000_000u64;
        let (rate, a, b) = (192_000, 12_345_678, 95_999_999); // b: 1 mHz under Nyquist
        let mut s = Synth::new(rate);
        s.set(&[partial(a, 1000, 0x0123), partial(b, 1000, 0xFEDC)], 0).unwrap();
        let mut buf = vec![0i16; 100_000];
        for _ in 0..n / 100_000 {
            s.fill(&mut buf);
        }
        let v = voices(&s);
        assert_eq!(v[0].1.phase, closed_form(0x0123, a, rate, n));
        assert_eq!(v[1].1.phase, closed_form(0xFEDC, b, rate, n));
        // The O(1) jump agrees, far beyond any session (2^32 samples = 6 hours at 192 kHz).
        let o = Osc::new(a, 7, s.den).advanced(u32::MAX, s.den);
        assert_eq!(o.phase, closed_form(7, a, rate, u64::from(u32::MAX)));
    }

    proptest! {
        #[test]
        fn phase_matches_closed_form(
            rate in 48_000u32..=192_000,
            f in 1u32..96_000_000,
            phase: u16,
            steps in 0u32..3_000,
            jump: u32,
        ) {
            let den = 1000 * rate;
            let f = f % (den / 2) + 1;
            let f = f.min(den / 2 - 1);
            let mut o = Osc::new(f, phase, den);
            for _ in 0..steps {
                o.step(den);
            }
            prop_assert_eq!(o, Osc::new(f, phase, den).advanced(steps, den));
            prop_assert_eq!(o.phase, closed_form(phase, f, rate, steps.into()));
            let far = o.advanced(jump, den);
            prop_assert_eq!(far.phase, closed_form(phase, f, rate, u64::from(steps) + u64::from(jump)));
        }
    }

    /// Runs `n` samples and returns each voice's amplitude (by frequency) before each.
    fn amp_track(s: &mut Synth, freq_mhz: u32, n: u32) -> Vec<i32> {
        (0..n)
            .map(|_| {
                let a = amp_of(s, freq_mhz).unwrap_or(0);
                s.next_sample();
                a
            })
            .collect()
    }

    #[test]
    fn ramps_are_exact_lines() {
        let f = 440_000;
        for (from, to, r) in [
            (0u16, u16::MAX, 480u32),
            (u16::MAX, 1, 480),
            (1000, 1003, 48_000),
            (40_000, 30_000, 7),
            (5, 5, 100),
        ] {
            let mut s = Synth::new(48_000);
            s.set(&[partial(f, from, 0)], 0).unwrap();
            s.set(&[partial(f, to, 0)], r).unwrap();
            let (a0, a1) = (level(from), level(to));
            let track = amp_track(&mut s, f, r);
            let delta = a0.abs_diff(a1);
            for (k, &a) in track.iter().enumerate() {
                // On the exact line A₀ ± ⌊k·Δ/R⌋.
                let along = (u64::from(delta) * k as u64 / u64::from(r)) as i32;
                assert_eq!(a, if a1 >= a0 { a0 + along } else { a0 - along }, "sample {k}");
            }
            for w in track.windows(2) {
                let d = w[0].abs_diff(w[1]);
                assert!(d == delta / r || d == delta.div_ceil(r));
            }
            assert_eq!(amp_of(&s, f), Some(a1), "lands on target after exactly R samples");
            assert!(s.is_silent() == (to == 0));
        }
    }

    /// The largest sample-to-sample change a sum of these sines can make on its own, plus the
    /// amplitude steps and rounding.
    fn slope_bound(rate: u32, parts: &[(u32, i32)], amp_steps: f64) -> f64 {
        let lsb = f64::from(1 << AMP_FRAC_BITS);
        let sines: f64 = parts
            .iter()
            .map(|&(f, a)| {
                f64::from(a) / lsb * core::f64::consts::TAU * f64::from(f) / 1000.0 / f64::from(rate)
            })
            .sum();
        sines + amp_steps / lsb + 1.01
    }

    fn max_jump(out: &[i16]) -> i32 {
        out.windows(2).map(|w| (i32::from(w[1]) - i32::from(w[0])).abs()).max().unwrap_or(0)
    }

    #[test]
    fn amplitude_change_does_not_click() {
        let (rate, f, r) = (48_000, 1_000_000, 480);
        let mut s = Synth::new(rate);
        s.set(&[partial(f, 13_000, 0x2000)], 0).unwrap();
        let mut out = vec![0i16; 2_000];
        s.fill(&mut out[..500]);
        s.set(&[partial(f, 60_000, 0x9999)], r).unwrap();
        s.fill(&mut out[500..]);
        let step = f64::from((level(60_000) - level(13_000)) / r as i32 + 1);
        let bound = slope_bound(rate, &[(f, level(60_000))], step);
        println!("amplitude ramp: max jump {} LSB, bound {bound:.1}", max_jump(&out));
        assert!(f64::from(max_jump(&out)) <= bound);
        // The phase went on: the new `phase` field of a running frequency is ignored.
        assert_eq!(voices(&s)[0].1.phase, closed_form(0x2000, f, rate, 2_000));
    }

    #[test]
    fn new_frequency_crossfades() {
        let (rate, f1, f2, r) = (48_000, 200_000, 300_000, 1_000);
        let mut s = Synth::new(rate);
        s.set(&[partial(f1, 50_000, 0)], 0).unwrap();
        let mut out = vec![0i16; 3 * r as usize];
        s.fill(&mut out[..r as usize]);
        s.set(&[partial(f2, 50_000, 0x4000)], r).unwrap();
        assert_eq!(voices(&s)[1].1.phase, 0x4000 << 16, "new partial starts at its phase");
        for k in r..2 * r {
            assert_eq!(s.active_voices(), 2);
            let (a1, a2) = (amp_of(&s, f1).unwrap(), amp_of(&s, f2).unwrap());
            // Equal amplitudes: the two lines are mirror images, the sum stays put.
            assert_eq!(a1 + a2, level(50_000));
            out[k as usize] = s.next_sample();
        }
        assert_eq!(s.active_voices(), 1);
        assert_eq!(amp_of(&s, f2), Some(level(50_000)));
        let mut s2 = s.clone();
        s2.fill(&mut out[2 * r as usize..]);
        let step = f64::from(level(50_000) / r as i32 + 1);
        let bound = slope_bound(rate, &[(f1, level(50_000)), (f2, level(50_000))], 2.0 * step);
        assert!(f64::from(max_jump(&out)) <= bound);
    }

    #[test]
    fn empty_list_fades_to_silence_in_exactly_r_samples() {
        let r = 4_800;
        let mut s = Synth::new(48_000);
        let parts = [partial(20_000, 20_000, 0), partial(30_000, 12_000, 16_384), partial(7_000_000, 999, 5)];
        s.set(&parts, 0).unwrap();
        s.fill(&mut [0; 1_000]);
        s.set(&[], r).unwrap();
        for k in 0..r {
            assert!(!s.is_silent(), "silent after {k} of {r}");
            s.next_sample();
        }
        assert!(s.is_silent());
        assert_eq!(s.active_voices(), 0);
        let mut out = [1i16; 100];
        s.fill(&mut out);
        assert_eq!(out, [0; 100]);

        // fade_out is the same, and a silent channel stays silent.
        s.set(&parts, 10).unwrap();
        s.fill(&mut [0; 10]);
        s.fade_out(3);
        s.fill(&mut [0; 3]);
        assert!(s.is_silent() && s.active_voices() == 0);
        s.fade_out(100);
        assert!(s.is_silent());
    }

    #[test]
    fn set_mid_ramp_starts_where_the_amplitude_is() {
        let f = 50_000;
        let mut s = Synth::new(48_000);
        s.set(&[partial(f, 60_000, 0)], 1_000).unwrap();
        s.fill(&mut [0; 400]);
        let mid = amp_of(&s, f).unwrap();
        assert_eq!(mid, level(60_000) * 2 / 5);
        s.set(&[partial(f, 0, 0)], 100).unwrap();
        assert_eq!(amp_of(&s, f), Some(mid));
        let track = amp_track(&mut s, f, 100);
        assert_eq!(track[0], mid);
        assert!(track.windows(2).all(|w| w[0] > w[1] && w[0] - w[1] <= mid / 100 + 1));
        // A listed partial at 0 keeps its voice (and phase) but is silent.
        assert!(s.is_silent());
        assert_eq!(s.active_voices(), 1);
        s.fill(&mut [0; 12_345]);
        s.set(&[partial(f, 100, 0x7777)], 0).unwrap();
        assert_eq!(voices(&s)[0].1.phase, closed_form(0, f, 48_000, 400 + 100 + 12_345));
    }

    #[test]
    fn ramp_zero_jumps() {
        let mut s = Synth::new(48_000);
        s.set(&[partial(1_000_000, 30_000, 0)], 0).unwrap();
        assert_eq!(amp_of(&s, 1_000_000), Some(level(30_000)));
        s.set(&[partial(2_000_000, 30_000, 0)], 0).unwrap();
        assert_eq!(s.active_voices(), 1);
        assert_eq!(amp_of(&s, 2_000_000), Some(level(30_000)));
        s.fade_out(0);
        assert!(s.is_silent() && s.active_voices() == 0);
    }

    #[test]
    fn overlapping_sets_borrow_fading_slots() {
        let (rate, r) = (48_000, 1_000u32);
        let list = |base: u32| -> Vec<Partial> {
            (0..8).map(|i| partial(base + 1_000 * i, 4_000 + 500 * i as u16, 100 * i as u16)).collect()
        };
        let (a, b, c) = (list(100_000), list(200_000), list(300_000));
        let mut s = Synth::new(rate);
        s.set(&a, 0).unwrap();
        s.fill(&mut [0; 100]);
        s.set(&b, r).unwrap();
        s.fill(&mut [0; 300]);
        assert_eq!(s.active_voices(), 16);
        // All 16 slots sound: c's partials go to the 8 quietest fading voices (a's, lowest).
        let before = voices(&s);
        s.set(&c, r).unwrap();
        let after = voices(&s);
        assert_eq!(before, after, "no voice jumps or vanishes at the set");
        let mut out = vec![0i16; r as usize + 10];
        let mut prev = voices(&s);
        for (k, y) in out.iter_mut().enumerate() {
            *y = s.next_sample();
            let now = voices(&s);
            for &(f, _, a1) in &now {
                let a0 = prev.iter().find(|v| v.0 == f).map_or(0, |v| v.2);
                assert!(a0.abs_diff(a1) <= (FS as u32).div_ceil(r / 2), "sample {k}, {f} mHz");
            }
            for &(f, _, a0) in &prev {
                if !now.iter().any(|v| v.0 == f) {
                    assert!(a0 <= FS / (r / 2) as i32 + 1, "{f} mHz left at {a0}");
                }
            }
            assert!(s.active_voices() <= VOICES);
            prev = now;
        }
        // On time and on target, with the phases they would have had from the set.
        assert_eq!(s.active_voices(), 8);
        for p in &c {
            let v = s.voices.iter().find(|v| v.freq_mhz == p.freq_mhz).unwrap();
            assert_eq!(v.ramp.amp, level(p.amplitude));
            assert_eq!(v.osc.phase, closed_form(p.phase, p.freq_mhz, rate, out.len() as u64));
        }
        let sines: Vec<_> =
            [&a, &b, &c].iter().flat_map(|l| l.iter().map(|p| (p.freq_mhz, level(p.amplitude)))).collect();
        assert!(
            f64::from(max_jump(&out)) <= slope_bound(rate, &sines, 24.0 * f64::from(FS) / f64::from(r / 2))
        );
    }

    #[test]
    fn refuses_invalid_lists_and_changes_nothing() {
        let mut s = Synth::new(48_000);
        s.set(&[partial(1_000, 100, 0)], 0).unwrap();
        let before = voices(&s);
        let nine: Vec<_> = (1..=9).map(|i| partial(i * 1000, 1, 0)).collect();
        assert_eq!(s.set(&nine, 10), Err(SynthError::TooManyPartials));
        assert_eq!(s.set(&nine[..8], 10), Ok(()));
        s.set(&[partial(1_000, 100, 0)], 0).unwrap();
        assert_eq!(
            s.set(&[partial(24_000_000, 1, 0)], 0),
            Err(SynthError::AboveNyquist { freq_mhz: 24_000_000 })
        );
        assert_eq!(
            s.set(&[partial(u32::MAX, 1, 0)], 0),
            Err(SynthError::AboveNyquist { freq_mhz: u32::MAX })
        );
        assert_eq!(s.set(&[partial(0, 1, 0)], 0), Err(SynthError::ZeroFrequency));
        assert_eq!(
            s.set(&[partial(5, 1, 0), partial(6, 1, 0), partial(5, 2, 0)], 0),
            Err(SynthError::DuplicateFrequency { freq_mhz: 5 })
        );
        assert_eq!(voices(&s), before);
        assert_eq!(s.set(&[partial(23_999_999, 1, 0)], 0), Ok(()));
        let mut fast = Synth::new(192_000);
        assert_eq!(fast.set(&[partial(95_999_999, 1, 0)], 0), Ok(()));
        assert!(fast.set(&[partial(96_000_000, 1, 0)], 0).is_err());
        // Rates outside the configurable range are clamped, never divide by zero.
        assert_eq!(Synth::new(0).sample_rate_hz(), 48_000);
        assert_eq!(Synth::new(u32::MAX).sample_rate_hz(), 192_000);
    }

    #[test]
    fn saturates_instead_of_wrapping() {
        let mut s = Synth::new(48_000);
        let eight: Vec<_> = (1..=8).map(|i| partial(i * 1_000, u16::MAX, 0x4000)).collect();
        s.set(&eight, 0).unwrap();
        assert_eq!(s.next_sample(), FULL_SCALE);
        let mut out = [0i16; 48_000];
        s.fill(&mut out);
        assert!(out.iter().all(|y| (-FULL_SCALE..=FULL_SCALE).contains(y)));
    }

    #[test]
    fn channels_are_independent() {
        let pa = [partial(20_000, 20_000, 0), partial(30_000, 12_000, 16_384)];
        let pb = [partial(1_000_000, 30_000, 7)];
        let (mut a, mut b) = (Synth::new(48_000), Synth::new(96_000));
        let (mut lone_a, mut lone_b) = (a.clone(), b.clone());
        a.set(&pa, 100).unwrap();
        lone_a.set(&pa, 100).unwrap();
        b.set(&pb, 50).unwrap();
        lone_b.set(&pb, 50).unwrap();
        let (mut ya, mut yb) = ([0i16; 256], [0i16; 256]);
        for _ in 0..10 {
            a.fill(&mut ya);
            b.fill(&mut yb);
            b.fade_out(10);
            lone_b.fade_out(10);
        }
        let (mut za, mut zb) = ([0i16; 256], [0i16; 256]);
        for _ in 0..10 {
            lone_a.fill(&mut za);
        }
        for _ in 0..10 {
            lone_b.fill(&mut zb);
        }
        assert_eq!(ya, za);
        assert_eq!(yb, zb);
        assert!(b.is_silent() && !a.is_silent());
    }

    /// Frequencies for the random sequences: few enough that lists share some, enough that
    /// overlapping sets run out of slots and borrow fading ones.
    const FREQS: [u32; 24] = [
        20_000, 33_333, 55_555, 71_000, 100_001, 250_000, 440_000, 997_000, 1_000_000, 1_234_567, 2_500_000,
        3_000_000, 4_999_999, 7_000_000, 8_888_888, 10_000_000, 12_345_678, 15_000_000, 17_500_001,
        19_999_999, 21_000_000, 22_222_222, 23_500_000, 23_999_999,
    ];

    fn op() -> impl Strategy<Value = (Vec<(usize, u16, u16)>, u32, u32)> {
        let partial = (0..FREQS.len(), any::<u16>(), any::<u16>());
        // Full lists often: they are the ones that run out of slots.
        let list = prop_oneof![
            proptest::collection::vec(partial.clone(), 0..=MAX_PARTIALS),
            proptest::collection::vec(partial, MAX_PARTIALS),
        ];
        let ramp = prop_oneof![0u32..4, 4u32..600, 600u32..3_000];
        (list, ramp, 0u32..1_500)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        /// Random sequences of sets: never a panic or an error for a valid list, never more
        /// than VOICES voices, amplitudes only move along ramps (never more than a ramp step per
        /// sample, twice the usual for borrowed slots), phases only advance, and so the output
        /// never jumps more than the sines and ramp steps allow. Any block size gives the same
        /// samples.
        #[test]
        fn random_sets_never_click(ops in proptest::collection::vec(op(), 1..8), chunk in 1usize..100) {
            let rate = 48_000;
            let mut s = Synth::new(rate);
            let mut twin = s.clone();
            let den = s.den;
            let lsb = f64::from(1 << AMP_FRAC_BITS);
            // Runs of (sample, state it came from, Σ|ΔA| to the next state), split at jumps.
            let mut segments: Vec<Vec<(i16, State, f64)>> = vec![Vec::new()];
            for (list, ramp, run) in ops {
                let mut parts: Vec<Partial> = Vec::new();
                for (i, amplitude, phase) in list {
                    if !parts.iter().any(|p| p.freq_mhz == FREQS[i]) {
                        parts.push(partial(FREQS[i], amplitude / 8, phase));
                    }
                }
                let before = voices(&s);
                prop_assert_eq!(s.set(&parts, ramp), Ok(()));
                twin.set(&parts, ramp).unwrap();
                let after = voices(&s);
                if ramp > 0 {
                    // The set itself changes nothing audible.
                    for &(f, o, a) in &before {
                        match after.iter().find(|v| v.0 == f) {
                            Some(&(_, o2, a2)) => prop_assert!(o2 == o && a2 == a),
                            None => prop_assert_eq!(a, 0),
                        }
                    }
                    for &(f, _, a) in &after {
                        prop_assert!(before.iter().any(|v| v.0 == f) || a == 0);
                    }
                } else {
                    segments.push(Vec::new());
                }
                let limit = if ramp >= 2 { (FS as u32).div_ceil(ramp / 2) } else { FS as u32 };
                let mut prev = after;
                let mut ys = Vec::new();
                for _ in 0..run {
                    let y = s.next_sample();
                    ys.push(y);
                    let now = voices(&s);
                    prop_assert!(s.active_voices() <= VOICES);
                    let mut steps = 0.0;
                    for &(f, o1, a1) in &now {
                        let (o0, a0) = match prev.iter().find(|v| v.0 == f) {
                            Some(&(_, o0, a0)) => (Some(o0), a0),
                            None => (None, 0),
                        };
                        if let Some(mut o0) = o0 {
                            o0.step(den);
                            prop_assert_eq!(o0, o1, "phase of {} mHz", f);
                        }
                        prop_assert!(a0.abs_diff(a1) <= limit);
                        steps += f64::from(a0.abs_diff(a1));
                    }
                    for &(f, _, a0) in &prev {
                        if !now.iter().any(|v| v.0 == f) {
                            prop_assert!(a0.unsigned_abs() <= limit);
                            steps += f64::from(a0);
                        }
                    }
                    if let Some(seg) = segments.last_mut() {
                        seg.push((y, prev, steps));
                    }
                    prev = now;
                }
                let mut tw = vec![0i16; run as usize];
                for c in tw.chunks_mut(chunk) {
                    twin.fill(c);
                }
                prop_assert_eq!(tw, ys);
                if run >= ramp {
                    // On target: exactly the listed partials at their amplitudes.
                    prop_assert_eq!(s.active_voices(), parts.len());
                    for p in &parts {
                        prop_assert_eq!(amp_of(&s, p.freq_mhz), Some(level(p.amplitude)));
                    }
                }
            }
            // Output slope: y[n+1] − y[n] = Σ (A' − A)·s' + A·(s' − s), so it is at most
            // Σ |ΔA| + Σ A·ω (ω = 2π f/rate bounds the sine's step) + 1 for rounding.
            for w in segments.iter().flat_map(|seg| seg.windows(2)) {
                let (y0, ref state0, steps) = w[0];
                let y1 = w[1].0;
                let sines: f64 = state0
                    .iter()
                    .map(|&(f, _, a)| f64::from(a) / lsb * core::f64::consts::TAU * f64::from(f) / 1000.0 / f64::from(rate))
                    .sum();
                let bound = sines * (1.0 + 1e-6) + steps / lsb + 1.01;
                prop_assert!(f64::from((i32::from(y1) - i32::from(y0)).abs()) <= bound);
            }
        }
    }
}
