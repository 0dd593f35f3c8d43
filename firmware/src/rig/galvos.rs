//! Galvo pairs: configuration and park position, point jumps (blanking every laser while the
//! mirrors settle) and line sweeps at exact update ticks.

use lightrig_protocol::config::{GalvoConfig, Xy};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::FaultCause;
use lightrig_protocol::{Error, MAX_GALVOS};

use super::{configured, Rig};
use crate::hal::Board;

pub(super) struct Galvo {
    pub(super) config: Option<GalvoConfig>,
    pub(super) pos: Xy,
    pub(super) line: Option<Line>,
}

/// A galvo sweep in progress.
#[derive(Clone, Copy)]
pub(super) struct Line {
    from: Xy,
    to: Xy,
    start: u64,
    duration: u32,
    steps: u16,
    /// Updates made.
    pub(super) done: u16,
}

impl Line {
    pub(super) fn tick_of(&self, i: u16) -> u64 {
        self.start.saturating_add(u64::from(self.duration) * u64::from(i) / u64::from(self.steps.max(1)))
    }

    fn point(&self, i: u16) -> Xy {
        let lerp = |a: u16, b: u16| {
            let d = i64::from(b) - i64::from(a);
            let v = i64::from(a) + d * i64::from(i) / i64::from(self.steps.max(1));
            v.clamp(0, i64::from(u16::MAX)) as u16
        };
        Xy { x: lerp(self.from.x, self.to.x), y: lerp(self.from.y, self.to.y) }
    }
}

impl<B: Board> Rig<B> {
    /// A galvo pair's output position.
    pub fn galvo_position(&self, galvo: u8) -> Option<Xy> {
        self.galvos.get(usize::from(galvo)).map(|g| g.pos)
    }

    pub(super) fn park(&mut self, galvo: u8, now: u64) {
        let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
        g.line = None;
        if let Some(c) = g.config {
            g.pos = c.park;
            // Parking is the safe state's last resort; a failing output cannot be helped here.
            let _ = self.board.set_galvo(galvo, c.park, now);
        }
    }

    /// Applies a galvo pair's configuration: the mirrors go to its park position, blanked
    /// like any jump when they were somewhere else.
    pub(super) fn configure_galvo(&mut self, c: GalvoConfig, now: u64) -> Result<(), Error> {
        let g = self.galvos.get_mut(usize::from(c.galvo)).ok_or(Error::Unsupported)?;
        // The first configuration has no position to jump from.
        let jumps = g.config.is_some() && g.pos != c.park;
        g.config = Some(c);
        g.line = None;
        g.pos = c.park;
        if jumps {
            // Going to the new park position is a jump like any other: blanked.
            self.blank_until = self.blank_until.max(now.saturating_add(u64::from(c.settle_ticks)));
            self.blanking = true;
            self.update_laser_outputs(now);
        }
        if self.board.set_galvo(c.galvo, c.park, now).is_err() {
            self.enter_safe_state(FaultCause::GalvoOutput { galvo: c.galvo }, now);
        }
        Ok(())
    }

    pub(super) fn galvo_config(&self, i: u8) -> Result<GalvoConfig, Error> {
        configured(
            Peripheral::Galvo,
            i,
            self.caps.galvos,
            self.galvos.get(usize::from(i)).and_then(|g| g.config),
        )
    }

    /// `check_action` for a `GalvoLine`: the end point in range, at least one update, and no
    /// more updates than ticks.
    pub(super) fn check_galvo_line(&self, galvo: u8, to: Xy, duration: u32, steps: u16) -> Result<(), Error> {
        let c = self.galvo_config(galvo)?;
        check_galvo_point(&c, to)?;
        let ok = steps >= 1 && u32::from(steps) <= duration.max(1);
        ok.then_some(()).ok_or(Error::OutOfRange { kind: Peripheral::Galvo, index: galvo })
    }

    /// Executes a `GalvoPoint`.
    pub(super) fn galvo_point(&mut self, galvo: u8, to: Xy, t: u64) {
        let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
        let Some(c) = g.config else { return };
        g.line = None;
        if g.pos != to {
            // Blank every laser while the mirrors jump and settle.
            self.blank_until = self.blank_until.max(t.saturating_add(u64::from(c.settle_ticks)));
            self.blanking = true;
            self.update_laser_outputs(t);
        }
        self.galvo_write(galvo, to, t);
    }

    /// Executes a `GalvoLine`: the updates come from the schedule (`run_lines`).
    pub(super) fn galvo_line(&mut self, galvo: u8, to: Xy, duration: u32, steps: u16, t: u64) {
        let Some(g) = self.galvos.get_mut(usize::from(galvo)) else { return };
        g.line = Some(Line { from: g.pos, to, start: t, duration, steps, done: 0 });
    }

    fn galvo_write(&mut self, galvo: u8, to: Xy, t: u64) {
        if let Some(g) = self.galvos.get_mut(usize::from(galvo)) {
            g.pos = to;
        }
        if self.board.set_galvo(galvo, to, t).is_err() {
            self.enter_safe_state(FaultCause::GalvoOutput { galvo }, t);
        }
    }

    pub(super) fn run_lines(&mut self, t: u64) {
        for i in 0..MAX_GALVOS {
            let Some(line) = self.galvos.get(i).and_then(|g| g.line) else { continue };
            let n = line.done.saturating_add(1);
            if line.tick_of(n) != t {
                continue;
            }
            if let Some(g) = self.galvos.get_mut(i) {
                g.line = (n < line.steps).then_some(Line { done: n, ..line });
            }
            self.galvo_write(i as u8, line.point(n), t);
        }
    }
}

pub(super) fn check_galvo_point(c: &GalvoConfig, to: Xy) -> Result<(), Error> {
    let ok = (c.x.min_code..=c.x.max_code).contains(&to.x) && (c.y.min_code..=c.y.max_code).contains(&to.y);
    ok.then_some(()).ok_or(Error::OutOfRange { kind: Peripheral::Galvo, index: c.galvo })
}
