//! One step/dir motor (a stepper axis or a filter wheel's motor) executing trapezoidal moves at
//! exact step ticks. What a move is *for* (a jog, homing, a filter change) is the rig's
//! business: the motor only reports when it finishes.

use lightrig_protocol::config::Polarity;
use lightrig_protocol::sequence::AxisRef;

use crate::hal::Motors;
use crate::motion::{PlanError, StepTimes, Trapezoid};

/// Why the motor is moving; decides what happens when the move ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Purpose {
    /// A commanded move; ends with `MoveDone`.
    Move,
    /// Seeking the homing switch; ending without finding it is a homing failure.
    HomeSeek,
    /// Backing off the homing switch; ends with `Homed`.
    HomeBackoff,
    /// Filter wheel turning to a slot.
    WheelTo(u8),
    /// Filter wheel seeking its index mark.
    WheelSeek,
    /// Filter wheel going from the index mark to slot 0 after homing.
    WheelHome,
}

/// A move in progress.
pub(crate) struct Motion {
    plan: Trapezoid,
    times: StepTimes,
    /// Tick of the move's start (step ticks count from here).
    start: u64,
    /// +1 or -1 per step.
    dir: i64,
    /// Absolute tick of the next step.
    next: Option<u64>,
    /// Steps made.
    done: u32,
    pub purpose: Purpose,
    /// Cut short by a decelerating stop: the move ends before its target.
    cut: bool,
}

/// What a due step produced.
pub(crate) enum Stepped {
    /// More steps follow.
    Moving,
    /// That was the last step of a move made for this purpose; `complete` unless the move was
    /// cut short by a decelerating stop.
    Finished { purpose: Purpose, complete: bool },
}

/// A motor's state: position in steps and the move in progress.
pub(crate) struct Motor {
    pub id: AxisRef,
    pub position: i64,
    pub motion: Option<Motion>,
    invert_dir: bool,
}

impl Motor {
    pub const fn new(id: AxisRef) -> Self {
        Self { id, position: 0, motion: None, invert_dir: false }
    }

    /// Applies a (re)configuration: the driver is energised at once, the position is kept.
    pub fn configure<B: Motors>(&mut self, board: &mut B, invert_dir: bool, enable: Polarity, at: u64) {
        self.invert_dir = invert_dir;
        self.motion = None;
        board.set_enable(self.id, enable == Polarity::ActiveHigh, at);
    }

    pub fn is_moving(&self) -> bool {
        self.motion.is_some()
    }

    /// Starts a move of `steps` (> 0) in direction `forward` at tick `at`. The direction output
    /// changes at `at`; the first step follows at least two ticks later (the planner refuses
    /// speeds above half the tick rate), which covers the drivers' direction setup time.
    #[allow(clippy::too_many_arguments)] // a move is all of these; a struct would only rename them
    pub fn start<B: Motors>(
        &mut self,
        board: &mut B,
        steps: u32,
        forward: bool,
        max_speed: u32,
        accel: u32,
        tick_hz: u32,
        at: u64,
        purpose: Purpose,
    ) -> Result<(), PlanError> {
        let plan = Trapezoid::new(steps, max_speed, accel, tick_hz)?;
        let mut times = plan.stepper();
        board.set_dir(self.id, forward != self.invert_dir, at);
        let next = times.next_tick().map(|dt| at.saturating_add(dt));
        self.motion = Some(Motion {
            plan,
            times,
            start: at,
            dir: if forward { 1 } else { -1 },
            next,
            done: 0,
            purpose,
            cut: false,
        });
        Ok(())
    }

    /// +1 or -1: the way the move in progress goes (logical steps).
    pub fn direction(&self) -> Option<i64> {
        self.motion.as_ref().map(|m| m.dir)
    }

    /// Tick of the next step.
    pub fn next_due(&self) -> Option<u64> {
        self.motion.as_ref().and_then(|m| m.next)
    }

    /// Makes the step due at `t` (the caller checked `next_due() == Some(t)`).
    pub fn step<B: Motors>(&mut self, board: &mut B, t: u64) -> Stepped {
        let Some(m) = self.motion.as_mut() else { return Stepped::Moving };
        board.step(self.id, t);
        self.position = self.position.saturating_add(m.dir);
        m.done = m.done.saturating_add(1);
        m.next = m.times.next_tick().map(|dt| m.start.saturating_add(dt));
        if m.next.is_some() {
            return Stepped::Moving;
        }
        let (purpose, complete) = (m.purpose, !m.cut);
        self.motion = None;
        Stepped::Finished { purpose, complete }
    }

    /// Stops at once (e-stop, limit switch, homing switch found); returns what the move was for.
    pub fn stop_now(&mut self) -> Option<Purpose> {
        self.motion.take().map(|m| m.purpose)
    }

    /// Decelerates to a stop as soon as the acceleration allows, keeping the steps already
    /// made exactly where they were. Returns the purpose if the motor is already at rest.
    pub fn decelerate(&mut self) -> Option<Purpose> {
        let m = self.motion.as_mut()?;
        if m.done == 0 {
            return self.stop_now();
        }
        let Some(plan) = m.plan.stopping_after(m.done) else { return self.stop_now() };
        m.times = plan.stepper_from(m.done);
        m.cut = plan.steps() < m.plan.steps();
        m.plan = plan;
        m.next = m.times.next_tick().map(|dt| m.start.saturating_add(dt));
        if m.next.is_none() {
            return self.stop_now();
        }
        None
    }
}
