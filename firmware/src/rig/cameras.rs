//! Cameras: trigger pulses (with the rig's snapshot in each `Trigger` event) and the exposure
//! input's captured edges.

use heapless::Vec;
use lightrig_protocol::config::{CameraConfig, Input};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{Event, FaultCause, Snapshot, TriggerEvent};
use lightrig_protocol::{Error, MAX_CAMERAS};

use super::{configured, level, Origin, Rig, IMMEDIATE_SEQUENCE};
use crate::hal::Board;

pub(super) struct Camera {
    pub(super) config: Option<CameraConfig>,
    /// Tick at which the trigger pulse in progress ends.
    pub(super) pulse_end: Option<u64>,
    pub(super) last_edge: Option<u64>,
    pub(super) exposure_active: bool,
    /// The exposure input went inactive since the last trigger.
    pub(super) exposure_ended: bool,
}

impl<B: Board> Rig<B> {
    /// Applies a camera's configuration: the trigger output goes inactive.
    pub(super) fn configure_camera(&mut self, c: CameraConfig, now: u64) -> Result<(), Error> {
        let k = self.cameras.get_mut(usize::from(c.camera)).ok_or(Error::Unsupported)?;
        k.config = Some(c);
        k.pulse_end = None;
        self.board.set_trigger(c.camera, level(c.polarity, false), now);
        Ok(())
    }

    pub(super) fn camera_config(&self, i: u8) -> Result<CameraConfig, Error> {
        configured(
            Peripheral::Camera,
            i,
            self.caps.cameras,
            self.cameras.get(usize::from(i)).and_then(|c| c.config),
        )
    }

    pub(super) fn trigger(&mut self, camera: u8, exposure: u32, t: u64, origin: Origin) {
        let Some(k) = self.cameras.get_mut(usize::from(camera)) else { return };
        let Some(c) = k.config else { return };
        let too_soon = k.pulse_end.is_some()
            || k.last_edge.is_some_and(|e| t.saturating_sub(e) < u64::from(c.min_interval_ticks));
        if too_soon {
            self.enter_safe_state(FaultCause::TriggerTooSoon { camera }, t);
            return;
        }
        let width = if exposure == 0 { c.pulse_ticks } else { exposure };
        k.pulse_end = Some(t.saturating_add(u64::from(width)));
        k.last_edge = Some(t);
        k.exposure_ended = false;
        self.board.set_trigger(camera, level(c.polarity, true), t);
        let (sequence, item, frame) = match origin {
            Origin::Sequence(i) => {
                let f = self.seq.frames.get_mut(usize::from(camera));
                let frame = f.map_or(0, |f| {
                    let n = *f;
                    *f = n.saturating_add(1);
                    n
                });
                (self.seq.id, i, frame)
            }
            Origin::Immediate => (IMMEDIATE_SEQUENCE, 0, 0),
        };
        let snapshot = self.snapshot();
        self.emit(
            Event::Trigger(TriggerEvent { sequence, item, frame, camera, tick: t, width, snapshot }),
            t,
        );
    }

    fn snapshot(&self) -> Snapshot {
        let mut s =
            Snapshot { galvos: Vec::new(), axes: Vec::new(), filters: Vec::new(), lasers: self.lasers_on() };
        for g in self.galvos.iter().take(usize::from(self.caps.galvos)) {
            let _ = s.galvos.push(g.pos);
        }
        for a in self.axes.iter().take(usize::from(self.caps.steppers)) {
            let _ = s.axes.push(a.motor.position.clamp(i32::MIN.into(), i32::MAX.into()) as i32);
        }
        for w in self.wheels.iter().take(usize::from(self.caps.filter_wheels)) {
            let _ = s.filters.push(w.slot);
        }
        s
    }

    /// Returns whether the board had any capture to take.
    pub(super) fn take_captures(&mut self, until: u64) -> bool {
        let mut any = false;
        while let Some(cap) = self.board.take_capture(until) {
            any = true;
            let Some(k) = self.cameras.get_mut(usize::from(cap.camera)) else { continue };
            let Some(c) = k.config else { continue };
            let Input::Wired(p) = c.exposure_input else { continue };
            let active = cap.level == level(p, true);
            if active == k.exposure_active {
                continue;
            }
            k.exposure_active = active;
            if !active {
                k.exposure_ended = true;
            }
            self.emit(Event::Exposure { camera: cap.camera, active, tick: cap.tick }, cap.tick);
            self.check_wait(cap.tick);
        }
        any
    }

    pub(super) fn run_pulse_ends(&mut self, t: u64) {
        for i in 0..MAX_CAMERAS {
            let Some(k) = self.cameras.get_mut(i) else { continue };
            if k.pulse_end == Some(t) {
                k.pulse_end = None;
                if let Some(c) = k.config {
                    self.board.set_trigger(i as u8, level(c.polarity, false), t);
                }
            }
        }
    }
}
