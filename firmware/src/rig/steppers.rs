//! Stepper axes and filter wheels: moves, homing (seek, switch, back-off; a wheel's index
//! mark), the limit and index switches read after every step, and what ends a move. Each
//! drives a [`Motor`].

use lightrig_protocol::config::{FilterWheelConfig, HomingMode, Input, StepperConfig};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{DeviceState, Event, FaultCause, Switch};
use lightrig_protocol::sequence::{Action, AxisRef, Profile};
use lightrig_protocol::{Error, MAX_FILTER_WHEELS, MAX_STEPPERS};

use super::motor::{Motor, Purpose, Stepped};
use super::{configured, level, Rig};
use crate::hal::Board;

pub(super) struct Axis {
    pub(super) config: Option<StepperConfig>,
    pub(super) motor: Motor,
    pub(super) homed: bool,
}

pub(super) struct Wheel {
    pub(super) config: Option<FilterWheelConfig>,
    /// Position in motor steps, 0 = centre of slot 0, kept in `0..steps_per_rev`.
    pub(super) motor: Motor,
    pub(super) homed: bool,
    /// The slot the wheel rests at (`None` while moving or not homed).
    pub(super) slot: Option<u8>,
}

impl<B: Board> Rig<B> {
    /// A stepper axis' position in steps.
    pub fn axis_position(&self, axis: u8) -> Option<i64> {
        self.axes.get(usize::from(axis)).map(|a| a.motor.position)
    }

    pub(super) fn stop_motors(&mut self, now: u64, hard: bool) {
        for i in 0..MAX_STEPPERS {
            let purpose = match self.axes.get_mut(i) {
                Some(a) if hard => a.motor.stop_now(),
                Some(a) => a.motor.decelerate(),
                None => None,
            };
            if let Some(p) = purpose {
                self.motor_finished(AxisRef::Stepper(i as u8), p, now, false);
            }
        }
        for i in 0..MAX_FILTER_WHEELS {
            let purpose = match self.wheels.get_mut(i) {
                Some(w) if hard => w.motor.stop_now(),
                Some(w) => w.motor.decelerate(),
                None => None,
            };
            if let Some(p) = purpose {
                self.motor_finished(AxisRef::FilterWheel(i as u8), p, now, false);
            }
        }
    }

    /// Applies a stepper axis' configuration (refused while it moves); the position is kept.
    pub(super) fn configure_stepper(&mut self, c: StepperConfig, now: u64) -> Result<(), Error> {
        let a = self.axes.get_mut(usize::from(c.axis)).ok_or(Error::Unsupported)?;
        if a.motor.is_moving() {
            return Err(Error::Busy { axis: AxisRef::Stepper(c.axis) });
        }
        a.config = Some(c);
        a.homed = c.homing.mode == HomingMode::None;
        a.motor.configure(&mut self.board, c.invert_dir, c.enable, now);
        Ok(())
    }

    /// Applies a filter wheel's configuration (refused while it moves); it must home again.
    pub(super) fn configure_wheel(&mut self, c: FilterWheelConfig, now: u64) -> Result<(), Error> {
        let w = self.wheels.get_mut(usize::from(c.wheel)).ok_or(Error::Unsupported)?;
        if w.motor.is_moving() {
            return Err(Error::Busy { axis: AxisRef::FilterWheel(c.wheel) });
        }
        w.config = Some(c);
        w.homed = false;
        w.slot = None;
        w.motor.configure(&mut self.board, c.invert_dir, c.enable, now);
        Ok(())
    }

    /// Starts homing an axis.
    pub fn home(&mut self, axis: AxisRef, now: u64) -> Result<(), Error> {
        self.due_fresh = false;
        self.check_not_faulted()?;
        if let Some(sequence) = self.running() {
            return Err(Error::InvalidState(DeviceState::Running { sequence }));
        }
        match axis {
            AxisRef::Stepper(i) => {
                let c = self.stepper_config(i)?;
                let a = self.axes.get_mut(usize::from(i)).ok_or(Error::Unsupported)?;
                if a.motor.is_moving() {
                    return Err(Error::Busy { axis });
                }
                let h = c.homing;
                let forward = match h.mode {
                    HomingMode::None => {
                        a.motor.position = i64::from(h.position);
                        a.homed = true;
                        self.emit(Event::Homed { axis, position: h.position, tick: now }, now);
                        return Ok(());
                    }
                    HomingMode::ToMinLimit => false,
                    HomingMode::ToMaxLimit | HomingMode::ToIndex => true,
                };
                a.homed = false;
                let span = seek_span(&c);
                let r = a.motor.start(
                    &mut self.board,
                    span,
                    forward,
                    h.speed,
                    c.accel,
                    self.tick_hz,
                    now,
                    Purpose::HomeSeek,
                );
                r.map_err(|_| Error::OutOfRange { kind: Peripheral::Stepper, index: i })
            }
            AxisRef::FilterWheel(i) => {
                let c = self.wheel_config(i)?;
                let w = self.wheels.get_mut(usize::from(i)).ok_or(Error::Unsupported)?;
                if w.motor.is_moving() {
                    return Err(Error::Busy { axis });
                }
                w.homed = false;
                w.slot = None;
                // One and a half turns always pass the index mark.
                let span = c.steps_per_rev.saturating_add(c.steps_per_rev / 2);
                let r = w.motor.start(
                    &mut self.board,
                    span,
                    true,
                    c.max_speed,
                    c.accel,
                    self.tick_hz,
                    now,
                    Purpose::WheelSeek,
                );
                r.map_err(|_| Error::OutOfRange { kind: Peripheral::FilterWheel, index: i })
            }
        }
    }

    pub(super) fn stepper_config(&self, i: u8) -> Result<StepperConfig, Error> {
        configured(
            Peripheral::Stepper,
            i,
            self.caps.steppers,
            self.axes.get(usize::from(i)).and_then(|a| a.config),
        )
    }

    pub(super) fn wheel_config(&self, i: u8) -> Result<FilterWheelConfig, Error> {
        let c = self.wheels.get(usize::from(i)).and_then(|w| w.config);
        configured(Peripheral::FilterWheel, i, self.caps.filter_wheels, c)
    }

    /// `check_action` for a `StepperMove`: homed, the target within the soft limits, the profile
    /// within the axis' and the planner's.
    pub(super) fn check_stepper_move(&self, axis: u8, target: i32, profile: Profile) -> Result<(), Error> {
        let c = self.stepper_config(axis)?;
        let homed = self.axes.get(usize::from(axis)).is_some_and(|a| a.homed);
        if !homed {
            return Err(Error::NotHomed { axis: AxisRef::Stepper(axis) });
        }
        let out = Error::OutOfRange { kind: Peripheral::Stepper, index: axis };
        if let Some(r) = c.limits {
            if target < r.min || target > r.max {
                return Err(out);
            }
        }
        let (speed, accel) = move_profile(&c, profile);
        if speed > c.max_speed || accel > c.accel || u64::from(speed) * 2 > u64::from(self.tick_hz) {
            return Err(out);
        }
        Ok(())
    }

    /// `check_action` for a `FilterWheel`: homed, the slot exists, the speed within the planner's.
    pub(super) fn check_wheel_to(&self, wheel: u8, slot: u8) -> Result<(), Error> {
        let c = self.wheel_config(wheel)?;
        if !self.wheels.get(usize::from(wheel)).is_some_and(|w| w.homed) {
            return Err(Error::NotHomed { axis: AxisRef::FilterWheel(wheel) });
        }
        if slot >= c.slots || u64::from(c.max_speed) * 2 > u64::from(self.tick_hz) {
            return Err(Error::OutOfRange { kind: Peripheral::FilterWheel, index: wheel });
        }
        Ok(())
    }

    pub(super) fn busy_axis(&self, action: &Action) -> Option<AxisRef> {
        match *action {
            Action::StepperMove { axis, .. } => self
                .axes
                .get(usize::from(axis))
                .is_some_and(|a| a.motor.is_moving())
                .then_some(AxisRef::Stepper(axis)),
            Action::FilterWheel { wheel, .. } => self
                .wheels
                .get(usize::from(wheel))
                .is_some_and(|w| w.motor.is_moving())
                .then_some(AxisRef::FilterWheel(wheel)),
            _ => None,
        }
    }

    /// Executes a `StepperMove`.
    pub(super) fn stepper_move(&mut self, axis: u8, target: i32, profile: Profile, t: u64) {
        let Ok(c) = self.stepper_config(axis) else { return };
        let Some(a) = self.axes.get_mut(usize::from(axis)) else { return };
        let id = AxisRef::Stepper(axis);
        if !a.homed {
            // Reconfigured between loading and executing.
            self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
            return;
        }
        if a.motor.is_moving() {
            self.enter_safe_state(FaultCause::AxisBusy { axis: id }, t);
            return;
        }
        let distance = i64::from(target) - a.motor.position;
        let steps = u32::try_from(distance.unsigned_abs()).unwrap_or(u32::MAX);
        if steps == 0 {
            self.emit(Event::MoveDone { axis: id, position: target, tick: t }, t);
            return;
        }
        let (speed, accel) = move_profile(&c, profile);
        let r =
            a.motor.start(&mut self.board, steps, distance > 0, speed, accel, self.tick_hz, t, Purpose::Move);
        if r.is_err() {
            // `check_action` refused every profile the planner cannot run; a move too
            // long for its tick arithmetic is the one left.
            self.enter_safe_state(FaultCause::Limit { axis: id }, t);
        }
    }

    pub(super) fn wheel_to(&mut self, wheel: u8, slot: u8, t: u64) {
        let Ok(c) = self.wheel_config(wheel) else { return };
        let Some(w) = self.wheels.get_mut(usize::from(wheel)) else { return };
        let id = AxisRef::FilterWheel(wheel);
        if !w.homed {
            // `check_action` cannot know: homing may come between loading and executing.
            self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
            return;
        }
        if w.motor.is_moving() {
            self.enter_safe_state(FaultCause::AxisBusy { axis: id }, t);
            return;
        }
        let (delta, forward) = wheel_path(&c, w.motor.position, slot);
        if delta == 0 {
            w.slot = Some(slot);
            self.emit(Event::MoveDone { axis: id, position: i32::from(slot), tick: t }, t);
            return;
        }
        w.slot = None;
        let r = w.motor.start(
            &mut self.board,
            delta,
            forward,
            c.max_speed,
            c.accel,
            self.tick_hz,
            t,
            Purpose::WheelTo(slot),
        );
        if r.is_err() {
            self.enter_safe_state(FaultCause::Driver { axis: id }, t);
        }
    }

    pub(super) fn after_step(&mut self, id: AxisRef, stepped: Stepped, t: u64) {
        // Switches are read after every step: the motor is what changes them.
        if let Some(p) = self.motor_purpose(id, &stepped) {
            if self.check_switches(id, p, t) {
                return;
            }
        }
        if let Stepped::Finished { purpose, complete } = stepped {
            self.motor_finished(id, purpose, t, complete);
        }
    }

    fn motor_purpose(&self, id: AxisRef, stepped: &Stepped) -> Option<Purpose> {
        if let Stepped::Finished { purpose, .. } = stepped {
            return Some(*purpose);
        }
        match id {
            AxisRef::Stepper(i) => {
                self.axes.get(usize::from(i)).and_then(|a| a.motor.motion.as_ref()).map(|m| m.purpose)
            }
            AxisRef::FilterWheel(i) => {
                self.wheels.get(usize::from(i)).and_then(|w| w.motor.motion.as_ref()).map(|m| m.purpose)
            }
        }
    }

    /// Reacts to the switches after a step. Returns whether the move was ended by them.
    fn check_switches(&mut self, id: AxisRef, purpose: Purpose, t: u64) -> bool {
        match id {
            AxisRef::Stepper(i) => {
                // The common case, every step of a plain move: no switch wired ahead, nothing
                // to read. Decided on the borrowed config, before copying it.
                let plain = self.axes.get(usize::from(i)).and_then(|a| {
                    let c = a.config.as_ref()?;
                    let ahead = if a.motor.direction()? < 0 { c.limit_min } else { c.limit_max };
                    Some(purpose != Purpose::HomeSeek && matches!(ahead, Input::Unused))
                });
                if plain == Some(true) {
                    return false;
                }
                let Ok(c) = self.stepper_config(i) else { return false };
                let active = |rig: &mut Self, input: Input, sw: Switch| match input {
                    Input::Wired(p) => rig.board.switch_level(id, sw) == level(p, true),
                    Input::Unused => false,
                };
                let seeking = purpose == Purpose::HomeSeek;
                let target = match c.homing.mode {
                    HomingMode::ToMinLimit => Some((c.limit_min, Switch::Min)),
                    HomingMode::ToMaxLimit => Some((c.limit_max, Switch::Max)),
                    HomingMode::ToIndex => Some((c.index, Switch::Index)),
                    HomingMode::None => None,
                };
                if seeking {
                    if let Some((input, sw)) = target {
                        if active(self, input, sw) {
                            let a = self.axes.get_mut(usize::from(i));
                            let Some(a) = a else { return true };
                            a.motor.stop_now();
                            let position = a.motor.position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                            self.emit(Event::Switch { axis: id, switch: sw, position, tick: t }, t);
                            self.home_backoff(i, &c, sw, t);
                            return true;
                        }
                    }
                }
                // Only the limit ahead counts: an axis may rest on a switch and leave it. While
                // homing, the switch being sought (and backed off) is expected; the other one
                // is a fault like any limit.
                let dir = self.axes.get(usize::from(i)).and_then(|a| a.motor.direction());
                let homing = matches!(purpose, Purpose::HomeSeek | Purpose::HomeBackoff);
                for (input, sw, ahead) in
                    [(c.limit_min, Switch::Min, dir == Some(-1)), (c.limit_max, Switch::Max, dir == Some(1))]
                {
                    let expected = homing && target.is_some_and(|(_, s)| s == sw);
                    if ahead && !expected && active(self, input, sw) {
                        let position = self.axes.get(usize::from(i)).map_or(0, |a| a.motor.position);
                        let position = position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                        self.emit(Event::Switch { axis: id, switch: sw, position, tick: t }, t);
                        if let Some(a) = self.axes.get_mut(usize::from(i)) {
                            a.motor.stop_now();
                        }
                        self.enter_safe_state(FaultCause::Limit { axis: id }, t);
                        return true;
                    }
                }
                false
            }
            AxisRef::FilterWheel(i) => {
                if purpose != Purpose::WheelSeek {
                    return false;
                }
                let Ok(c) = self.wheel_config(i) else { return false };
                let Input::Wired(p) = c.index else { return false };
                if self.board.switch_level(id, Switch::Index) != level(p, true) {
                    return false;
                }
                let at = self.wheels.get(usize::from(i)).map_or(0, |w| w.motor.position);
                let position = at.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                self.emit(Event::Switch { axis: id, switch: Switch::Index, position, tick: t }, t);
                let Some(w) = self.wheels.get_mut(usize::from(i)) else { return true };
                w.motor.stop_now();
                // Slot 0's centre lies `index_offset` steps past the mark.
                let spr = i64::from(c.steps_per_rev.max(1));
                w.motor.position = (-i64::from(c.index_offset)).rem_euclid(spr);
                let (delta, forward) = wheel_path(&c, w.motor.position, 0);
                if delta == 0 {
                    self.wheel_homed(i, t);
                } else {
                    let r = w.motor.start(
                        &mut self.board,
                        delta,
                        forward,
                        c.max_speed,
                        c.accel,
                        self.tick_hz,
                        t,
                        Purpose::WheelHome,
                    );
                    if r.is_err() {
                        self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
                    }
                }
                true
            }
        }
    }

    fn home_backoff(&mut self, i: u8, c: &StepperConfig, sw: Switch, t: u64) {
        let h = c.homing;
        let Some(a) = self.axes.get_mut(usize::from(i)) else { return };
        if h.backoff == 0 {
            return self.stepper_homed(i, t);
        }
        // Back away from the switch: forward off the min limit, backward off the others.
        let forward = sw == Switch::Min;
        let r = a.motor.start(
            &mut self.board,
            h.backoff,
            forward,
            h.speed,
            c.accel,
            self.tick_hz,
            t,
            Purpose::HomeBackoff,
        );
        if r.is_err() {
            self.enter_safe_state(FaultCause::HomingFailed { axis: AxisRef::Stepper(i) }, t);
        }
    }

    fn stepper_homed(&mut self, i: u8, t: u64) {
        let Ok(c) = self.stepper_config(i) else { return };
        let Some(a) = self.axes.get_mut(usize::from(i)) else { return };
        a.motor.position = i64::from(c.homing.position);
        a.homed = true;
        let axis = AxisRef::Stepper(i);
        self.emit(Event::Homed { axis, position: c.homing.position, tick: t }, t);
        self.check_wait(t);
    }

    fn wheel_homed(&mut self, i: u8, t: u64) {
        let Some(w) = self.wheels.get_mut(usize::from(i)) else { return };
        w.homed = true;
        w.slot = Some(0);
        self.emit(Event::Homed { axis: AxisRef::FilterWheel(i), position: 0, tick: t }, t);
        self.check_wait(t);
    }

    /// A move ended: `complete` when it reached its target, not when a stop cut it short.
    fn motor_finished(&mut self, id: AxisRef, purpose: Purpose, t: u64, complete: bool) {
        match (id, purpose) {
            (AxisRef::Stepper(i), Purpose::Move) => {
                let position = self.axes.get(usize::from(i)).map_or(0, |a| a.motor.position);
                let position = position.clamp(i32::MIN.into(), i32::MAX.into()) as i32;
                self.emit(Event::MoveDone { axis: id, position, tick: t }, t);
            }
            // Homing interrupted by the safe state leaves the axis unhomed.
            (AxisRef::Stepper(i), Purpose::HomeBackoff) if complete => self.stepper_homed(i, t),
            (_, Purpose::HomeSeek | Purpose::WheelSeek) if self.fault.is_none() => {
                self.enter_safe_state(FaultCause::HomingFailed { axis: id }, t);
            }
            (AxisRef::FilterWheel(i), Purpose::WheelTo(slot)) => {
                let Ok(c) = self.wheel_config(i) else { return };
                let Some(w) = self.wheels.get_mut(usize::from(i)) else { return };
                let spr = i64::from(c.steps_per_rev.max(1));
                w.motor.position = w.motor.position.rem_euclid(spr);
                // A wheel stopped short (safe state) rests between slots.
                let arrived = w.motor.position == slot_position(&c, slot);
                w.slot = arrived.then_some(slot);
                let position = if arrived { i32::from(slot) } else { -1 };
                self.emit(Event::MoveDone { axis: id, position, tick: t }, t);
            }
            (AxisRef::FilterWheel(i), Purpose::WheelHome) if complete => self.wheel_homed(i, t),
            _ => {}
        }
        self.check_wait(t);
    }
}

/// Speed and acceleration of a move: the profile's, or the axis' where the profile says 0.
fn move_profile(c: &StepperConfig, p: Profile) -> (u32, u32) {
    let speed = if p.max_speed == 0 { c.max_speed } else { p.max_speed };
    let accel = if p.accel == 0 { c.accel } else { p.accel };
    (speed, accel)
}

/// How far a homing seek may travel before giving up: the soft-limit span and half again for a
/// linear axis; for an endless axis, 2^24 steps.
fn seek_span(c: &StepperConfig) -> u32 {
    match c.limits {
        Some(r) => {
            let span = (i64::from(r.max) - i64::from(r.min)).unsigned_abs();
            u32::try_from(span.saturating_add(span / 2)).unwrap_or(u32::MAX).max(1)
        }
        None => 1 << 24,
    }
}

/// Motor position (steps from slot 0's centre) of a filter slot's centre.
fn slot_position(c: &FilterWheelConfig, slot: u8) -> i64 {
    i64::from(slot) * i64::from(c.steps_per_rev) / i64::from(c.slots.max(1))
}

/// The shorter way from `position` to `slot`'s centre: (steps, forward). Ties go forward.
fn wheel_path(c: &FilterWheelConfig, position: i64, slot: u8) -> (u32, bool) {
    let spr = i64::from(c.steps_per_rev.max(1));
    let ahead = (slot_position(c, slot) - position).rem_euclid(spr);
    let (steps, forward) = if ahead * 2 <= spr { (ahead, true) } else { (spr - ahead, false) };
    (u32::try_from(steps).unwrap_or(u32::MAX), forward)
}
