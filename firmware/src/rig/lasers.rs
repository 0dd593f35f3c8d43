//! Lasers: arming, turning on and off (checking the interlock), the enable outputs under
//! blanking, warm-up, the on-time limit and the interlock watch.

use lightrig_protocol::config::{Input, LaserConfig};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{Event, FaultCause};
use lightrig_protocol::{Error, MAX_LASERS};

use super::{bit, configured, level, Rig};
use crate::hal::Board;

#[derive(Clone, Copy)]
pub(super) struct Laser {
    pub(super) config: Option<LaserConfig>,
    /// Asked on (by an item or `Immediate`).
    pub(super) on: bool,
    /// Output level is "emit".
    pub(super) emitting: bool,
    pub(super) on_since: u64,
    /// Warm-up finished since the last turn-on.
    pub(super) ready: bool,
}

impl<B: Board> Rig<B> {
    /// Lasers emitting, one bit per channel.
    pub fn lasers_on(&self) -> u8 {
        self.lasers.iter().enumerate().fold(0, |m, (i, l)| if l.emitting { m | bit(i as u8) } else { m })
    }

    /// Applies a laser's configuration: the channel goes off, its enable to the inactive level.
    pub(super) fn configure_laser(&mut self, c: LaserConfig, now: u64) -> Result<(), Error> {
        self.laser_off(c.channel, now);
        let l = self.lasers.get_mut(usize::from(c.channel)).ok_or(Error::Unsupported)?;
        l.config = Some(c);
        self.board.set_laser(c.channel, level(c.enable, false), now);
        Ok(())
    }

    /// Allows the lasers in `mask` to be turned on.
    pub fn arm(&mut self, mask: u8, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        for ch in 0..8u8 {
            if mask & bit(ch) != 0 {
                self.laser_config(ch)?;
            }
        }
        self.armed = mask;
        // Channels no longer armed go dark.
        for ch in 0..MAX_LASERS {
            if mask & bit(ch as u8) == 0 {
                self.laser_off(ch as u8, now);
            }
        }
        self.emit_state(now);
        Ok(())
    }

    /// Turns every laser off and disallows them. Always allowed.
    pub fn disarm(&mut self, now: u64) {
        self.due_fresh = false;
        self.armed = 0;
        for ch in 0..MAX_LASERS {
            self.laser_off(ch as u8, now);
        }
        self.emit_state(now);
    }

    pub(super) fn laser_config(&self, ch: u8) -> Result<LaserConfig, Error> {
        configured(
            Peripheral::Laser,
            ch,
            self.caps.lasers,
            self.lasers.get(usize::from(ch)).and_then(|l| l.config),
        )
    }

    /// A `Laser` action: off at any time, on only while the channel is armed.
    pub(super) fn switch_laser(&mut self, channel: u8, on: bool, t: u64) {
        if !on {
            self.laser_off(channel, t);
        } else if self.armed & bit(channel) == 0 {
            // Disarmed since the chunk was loaded: the host's disarm wins.
            warn!("laser {} not armed; item skipped", channel);
        } else {
            self.laser_on(channel, t);
        }
    }

    fn laser_on(&mut self, channel: u8, t: u64) {
        let Some(l) = self.lasers.get_mut(usize::from(channel)) else { return };
        let Some(c) = l.config else { return };
        if l.on {
            return;
        }
        if let Input::Wired(p) = c.interlock {
            if !level(p, true).eq(&self.board.interlock_level(channel)) {
                self.enter_safe_state(FaultCause::Interlock { channel }, t);
                return;
            }
        }
        l.on = true;
        l.on_since = t;
        l.ready = false;
        self.update_laser_outputs(t);
    }

    pub(super) fn laser_off(&mut self, channel: u8, t: u64) {
        let Some(l) = self.lasers.get_mut(usize::from(channel)) else { return };
        l.on = false;
        l.ready = false;
        self.update_laser_outputs(t);
    }

    /// Drives every laser output to what it should be at `t`: on, armed and not blanked.
    pub(super) fn update_laser_outputs(&mut self, t: u64) {
        let blanked = t < self.blank_until;
        for (ch, l) in self.lasers.iter_mut().enumerate() {
            let Some(c) = l.config else { continue };
            let emit = l.on && !blanked && self.armed & bit(ch as u8) != 0;
            if emit != l.emitting {
                l.emitting = emit;
                self.board.set_laser(ch as u8, level(c.enable, emit), t);
            }
        }
    }

    pub(super) fn laser_deadline(&self, l: &Laser) -> Option<u64> {
        // `on` first: most lasers are off, and the check is cheaper than the config's.
        if !l.on {
            return None;
        }
        let c = l.config.as_ref()?;
        let off = l.on_since.saturating_add(u64::from(c.max_on_ticks));
        if l.ready {
            Some(off)
        } else {
            Some(off.min(l.on_since.saturating_add(u64::from(c.warmup_ticks))))
        }
    }

    /// Returns whether an open interlock tripped the safe state.
    pub(super) fn check_interlocks(&mut self, now: u64) -> bool {
        let mut tripped = false;
        for ch in 0..MAX_LASERS {
            let Some(l) = self.lasers.get(ch) else { continue };
            let Some(c) = l.config.as_ref().filter(|_| l.on) else { continue };
            if let Input::Wired(p) = c.interlock {
                if self.board.interlock_level(ch as u8) != level(p, true) {
                    self.enter_safe_state(FaultCause::Interlock { channel: ch as u8 }, now);
                    tripped = true;
                }
            }
        }
        tripped
    }

    pub(super) fn run_laser_timers(&mut self, t: u64) {
        for ch in 0..MAX_LASERS {
            let Some(l) = self.lasers.get(ch).filter(|l| l.on).copied() else { continue };
            let Some(c) = l.config else { continue };
            if t >= l.on_since.saturating_add(u64::from(c.max_on_ticks)) {
                self.enter_safe_state(FaultCause::LaserOnTime { channel: ch as u8 }, t);
            } else if !l.ready && t >= l.on_since.saturating_add(u64::from(c.warmup_ticks)) {
                if let Some(l) = self.lasers.get_mut(ch) {
                    l.ready = true;
                }
                self.emit(Event::LaserReady { channel: ch as u8, tick: t }, t);
                self.check_wait(t);
            }
        }
    }
}
