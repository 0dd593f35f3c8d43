//! Voice coils: settings placed on their exact sample, blocks computed once their window has
//! passed and handed to the board's DMA, the fade to silence.

use heapless::{Deque, Vec};
use lightrig_protocol::config::{ConfigError, ConfigField, InvalidReason, VoiceCoilConfig};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::sequence::Partial;
use lightrig_protocol::{Error, MAX_PARTIALS};

use super::{configured, ms_to_ticks, Rig, FADE_MS};
use crate::hal::Board;
use crate::synth::Synth;

/// Samples per voice-coil DMA block.
pub const VOICE_COIL_BLOCK: usize = 64;
/// A voice-coil sample plays this many blocks after its nominal tick: the block is computed
/// once its window has passed (so every setting inside it lands on its exact sample), then
/// waits one block in the DMA double buffer. Constant, so the host plans around it.
pub const VOICE_COIL_LATENCY_BLOCKS: u64 = 2;
/// Settings a voice-coil channel holds for its current block.
const COIL_PENDING: usize = 8;

pub(super) struct Coil {
    pub(super) config: Option<VoiceCoilConfig>,
    pub(super) synth: Synth,
    /// Tick of sample 0.
    pub(super) t0: u64,
    /// First sample of the next block to compute.
    pub(super) next_sample: u64,
    /// Settings that take effect inside the block being collected, by sample.
    pub(super) pending: Deque<(u64, CoilSetting), COIL_PENDING>,
}

#[derive(Clone)]
pub(super) enum CoilSetting {
    Set { partials: Vec<Partial, MAX_PARTIALS>, ramp: u32 },
    Fade { ramp: u32 },
}

impl<B: Board> Rig<B> {
    /// Applies a voice-coil channel's configuration: a fresh synthesiser with sample 0 at `now`;
    /// refused while the channel sounds.
    pub(super) fn configure_coil(&mut self, c: VoiceCoilConfig, now: u64) -> Result<(), Error> {
        let (lo, hi) = self.board.sample_rates();
        if !(lo..=hi).contains(&c.sample_rate_hz) {
            // A board whose timer plays one rate (or a few) says so rather than play at another.
            return Err(Error::InvalidConfig(ConfigError {
                field: ConfigField::VoiceCoilSampleRate,
                index: c.channel,
                reason: InvalidReason::OutsideRange { min: lo.into(), max: hi.into() },
            }));
        }
        let k = self.coils.get_mut(usize::from(c.channel)).ok_or(Error::Unsupported)?;
        if !k.synth.is_silent() || !k.pending.is_empty() {
            // A restart would click: fade the channel first (an empty partial list).
            return Err(Error::InvalidState(self.state()));
        }
        *k = Coil {
            config: Some(c),
            synth: Synth::new(c.sample_rate_hz),
            t0: now,
            next_sample: 0,
            pending: Deque::new(),
        };
        Ok(())
    }

    fn coil_config(&self, i: u8) -> Result<VoiceCoilConfig, Error> {
        let c = self.coils.get(usize::from(i)).and_then(|c| c.config);
        configured(Peripheral::VoiceCoil, i, self.caps.voice_coils, c)
    }

    /// `check_action` for a `VoiceCoil`: the partials fit the channel and the synthesiser.
    pub(super) fn check_coil(&self, channel: u8, partials: &[Partial]) -> Result<(), Error> {
        let c = self.coil_config(channel)?;
        let out = Error::OutOfRange { kind: Peripheral::VoiceCoil, index: channel };
        if partials.len() > usize::from(self.caps.partials_per_coil) {
            return Err(out);
        }
        let sum: u32 = partials.iter().map(|p| u32::from(p.amplitude)).sum();
        if sum > u32::from(c.max_amplitude) {
            return Err(out);
        }
        // Frequencies: above zero, below Nyquist, no duplicates (the synthesiser's rules).
        let synth = self.coils.get(usize::from(channel)).map(|k| &k.synth);
        synth.map_or(Err(out), |s| s.check(partials).map_err(|_| out))
    }

    /// Executes a `VoiceCoil`: the setting takes effect on the sample at or after `t`.
    pub(super) fn coil_set(&mut self, channel: u8, partials: &Vec<Partial, MAX_PARTIALS>, ramp: u32, t: u64) {
        let setting = CoilSetting::Set { partials: partials.clone(), ramp };
        self.coil_schedule(channel, t, setting);
    }

    fn coil_schedule(&mut self, channel: u8, t: u64, setting: CoilSetting) {
        let Some(k) = self.coils.get_mut(usize::from(channel)) else { return };
        let Some(c) = k.config else { return };
        let sample =
            sample_at_or_after(t.saturating_sub(k.t0), c.sample_rate_hz, self.tick_hz).max(k.next_sample);
        let ramp_samples = |ticks: u32| {
            let s = u64::from(ticks) * u64::from(c.sample_rate_hz) / u64::from(self.tick_hz.max(1));
            u32::try_from(s).unwrap_or(u32::MAX)
        };
        let setting = match setting {
            CoilSetting::Set { partials, ramp } => CoilSetting::Set { partials, ramp: ramp_samples(ramp) },
            CoilSetting::Fade { ramp } => CoilSetting::Fade { ramp: ramp_samples(ramp) },
        };
        if let Err((_, setting)) = k.pending.push_back((sample, setting)) {
            // More changes inside one block than a channel holds: apply the oldest now (a few
            // samples early) rather than lose one.
            if let Some((_, oldest)) = k.pending.pop_front() {
                apply_coil(&mut k.synth, oldest);
            }
            let _ = k.pending.push_back((sample, setting));
        }
    }

    pub(super) fn coil_fade(&mut self, channel: u8, t: u64) {
        let ramp = ms_to_ticks(FADE_MS, self.tick_hz);
        self.coil_schedule(channel, t, CoilSetting::Fade { ramp: u32::try_from(ramp).unwrap_or(u32::MAX) });
    }

    /// Tick at which the block starting at `next_sample` may be computed: when its window ends.
    pub(super) fn coil_due(&self, k: &Coil) -> Option<u64> {
        let c = k.config?;
        let end = k.next_sample + VOICE_COIL_BLOCK as u64;
        Some(k.t0.saturating_add(tick_of_sample(end, c.sample_rate_hz, self.tick_hz)))
    }

    pub(super) fn coil_block(&mut self, channel: u8, t: u64) {
        let Some(k) = self.coils.get_mut(usize::from(channel)) else { return };
        let first = k.next_sample;
        let mut buf = [0i16; VOICE_COIL_BLOCK];
        let mut at = 0usize;
        while at < VOICE_COIL_BLOCK {
            // Settings due inside the block split it at their sample.
            let split = match k.pending.front() {
                Some(&(s, _)) if s <= first + at as u64 => {
                    if let Some((_, setting)) = k.pending.pop_front() {
                        apply_coil(&mut k.synth, setting);
                    }
                    continue;
                }
                Some(&(s, _)) => ((s - first) as usize).min(VOICE_COIL_BLOCK),
                None => VOICE_COIL_BLOCK,
            };
            if let Some(part) = buf.get_mut(at..split) {
                k.synth.fill(part);
            }
            at = split;
        }
        k.next_sample = first + VOICE_COIL_BLOCK as u64;
        self.board.write_samples(channel, first, &buf, t);
    }
}

fn apply_coil(synth: &mut Synth, setting: CoilSetting) {
    match setting {
        // Checked when the item was loaded; a refusal here would be a bug, and silence is
        // the safe answer to it.
        CoilSetting::Set { partials, ramp } => {
            if synth.set(&partials, ramp).is_err() {
                synth.fade_out(ramp);
            }
        }
        CoilSetting::Fade { ramp } => synth.fade_out(ramp),
    }
}

/// Ticks from sample 0 to sample `n`: `floor(n · tick_hz / rate)`.
fn tick_of_sample(n: u64, rate: u32, tick_hz: u32) -> u64 {
    let t = u128::from(n) * u128::from(tick_hz) / u128::from(rate.max(1));
    u64::try_from(t).unwrap_or(u64::MAX)
}

/// The first sample whose tick is at or after `ticks`.
fn sample_at_or_after(ticks: u64, rate: u32, tick_hz: u32) -> u64 {
    // Smallest n with floor(n·f/r) >= t  <=>  n·f >= t·r  <=>  n = ceil(t·r / f).
    let num = u128::from(ticks) * u128::from(rate);
    let f = u128::from(tick_hz.max(1));
    u64::try_from(num.div_ceil(f)).unwrap_or(u64::MAX)
}
