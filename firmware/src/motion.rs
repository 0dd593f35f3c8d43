//! Trapezoidal stepper motion with exact integer step ticks.
//!
//! A move of `N` steps starts and ends at rest, accelerates at `a` steps/s² up to at most `v`
//! steps/s, cruises, and decelerates at `a`. The peak speed is `v_p = min(v, √(a·N))`: a
//! *trapezoid* when `v² < a·N`, a *triangle* (no cruise) otherwise. With `x_a = v²/(2a)` the
//! ramp length in steps (`N/2` for a triangle), the ideal position reaches `x` at
//!
//! ```text
//! accel   x ≤ x_a:           t(x) = √(2x/a)
//! cruise  x_a < x ≤ N − x_a:  t(x) = (2a·x + v²) / (2a·v)
//! decel   x > N − x_a:       t(x) = t_end − √(2(N − x)/a)
//! t_end = (N·a + v²) / (a·v)  (trapezoid),   2·√(N/a)  (triangle)
//! ```
//!
//! Step `k` (1..=N) fires at tick `T(k)` after the move's start, `f` ticks per second:
//!
//! ```text
//! accel:  T(k) = isqrt(⌊2k·f²/a⌋)               = ⌊f·t(k)⌋
//! cruise: T(k) = ⌊f·(2a·k + v²) / (2a·v)⌋        = ⌊f·t(k)⌋
//! decel:  T(k) = E − isqrt(⌊2(N − k)·f²/a⌋)
//! E = ⌊f·t_end⌋ = ⌊f·(N·a + v²) / (a·v)⌋  (trapezoid),   isqrt(⌊4N·f²/a⌋)  (triangle)
//! ```
//!
//! `isqrt(⌊y⌋) = ⌊√y⌋`, so the ramps are exact floors too; in the deceleration phase `T` is a
//! difference of two floors, hence `|T(k) − f·t(k)| < 1`: within one tick everywhere, with no
//! drift however long the move. Phase boundaries are exact rational comparisons
//! (`2a·x ≤ v²`, `2a·(N − x) < v²`, `2x ≤ N`); the formulas agree on the real line at the
//! boundaries and at `a·N = v²`, where both shapes coincide. Step `N` always lands on `E`.
//!
//! Strictly increasing ticks need `f ≥ 2·v_p`: consecutive steps are then at least 2 ticks
//! apart in real time, and two values each within 1 tick of theirs cannot meet. The check is
//! on `max_speed` (at most `tick_hz / 2`, else [`PlanError::TooFast`]) so that whether a
//! speed is accepted does not depend on the move's length.
//!
//! [`StepTimes`] yields the same ticks incrementally with 64-bit arithmetic only:
//! `Y(m) = ⌊2m·f²/a⌋` steps by `⌊2f²/a⌋` with the remainder `2f² mod a` carried Bresenham
//! style; its root is guessed as the previous root plus the previous stride and corrected by
//! ±1 comparing squares, with Newton steps (a division each) only when the guess is off by
//! more than 2, which happens in a ramp's first steps, the ones furthest apart. The cruise
//! adds `⌊f/v⌋` and carries `2a·(f mod v)` modulo `2a·v`. `Y` must fit a `u64`, which limits
//! a ramp to `2³²` ticks: about 25 s at 170 MHz, 71 min at 1 MHz ([`PlanError::TooLong`]).

use core::fmt;
use core::num::{NonZeroU128, NonZeroU32, NonZeroU64};

/// The largest root of a `u64`: `isqrt(u64::MAX)`.
const MAX_ROOT: u64 = u32::MAX as u64;

/// Why a move cannot be planned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlanError {
    /// A move of zero steps: nothing to plan.
    ZeroSteps,
    /// `max_speed` is zero: the move would never end.
    ZeroSpeed,
    /// `accel` is zero: the move would never start.
    ZeroAccel,
    /// `max_speed` exceeds `tick_hz / 2`: consecutive steps could share a tick.
    TooFast {
        /// The refused speed, steps/s.
        max_speed: u32,
    },
    /// A ramp longer than `2³²` ticks (or an end tick beyond `u64`): the step generator's
    /// 64-bit state cannot hold it.
    TooLong,
}

impl fmt::Display for PlanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::ZeroSteps => f.write_str("a move needs at least one step"),
            Self::ZeroSpeed => f.write_str("max_speed must not be zero"),
            Self::ZeroAccel => f.write_str("accel must not be zero"),
            Self::TooFast { max_speed } => {
                write!(f, "max_speed {max_speed} steps/s exceeds half the tick rate")
            }
            Self::TooLong => f.write_str("the move's ramps are too long for 64-bit step timing"),
        }
    }
}

/// Floor square root, exact for every `u128`: the closed form's (and setup's) square root.
pub fn isqrt_u128(n: u128) -> u64 {
    if n == 0 {
        return 0;
    }
    let bits = 128 - n.leading_zeros();
    // n < 2^bits ≤ (2^⌈bits/2⌉)², so the start is above the root; Newton then decreases
    // monotonically to it and stops there.
    let mut x: u128 = 1 << bits.div_ceil(2);
    loop {
        let Some(d) = NonZeroU128::new(x) else { return 0 };
        let next = midpoint_u128(x, n / d);
        if next >= x {
            return u64::try_from(x).unwrap_or(u64::MAX);
        }
        x = next;
    }
}

/// `⌊(x + y) / 2⌋` without overflow.
const fn midpoint_u128(x: u128, y: u128) -> u128 {
    (x >> 1) + (y >> 1) + (x & y & 1)
}

/// `⌊(x + y) / 2⌋` without overflow.
const fn midpoint_u64(x: u64, y: u64) -> u64 {
    (x >> 1) + (y >> 1) + (x & y & 1)
}

/// `isqrt(y)` given a guess that is usually within ±2 of it: squares only, no division.
fn isqrt_near(y: u64, guess: u64) -> u64 {
    let x = guess.min(MAX_ROOT);
    let sq = x * x; // x ≤ 2³² − 1
    if sq <= y {
        let gap = y - sq;
        if gap <= 2 * x {
            return x; // y < (x + 1)²
        }
        // x < MAX_ROOT here: at MAX_ROOT the gap is at most 2·MAX_ROOT.
        if gap - (2 * x + 1) <= 2 * x + 2 {
            return x + 1; // (x + 1)² ≤ y < (x + 2)²
        }
    } else if sq - (2 * x - 1) <= y {
        return x - 1; // x ≥ 1 as sq > y ≥ 0; (x − 1)² ≤ y < x²
    }
    isqrt_newton(y, x)
}

/// `isqrt(y)` by Newton's method started near `start` (the slow path of [`isqrt_near`]).
fn isqrt_newton(y: u64, start: u64) -> u64 {
    if y == 0 {
        return 0;
    }
    // The root lies in [low, 2·low): never start further below it than that.
    let low = 1u64 << ((63 - y.leading_zeros()) / 2);
    let mut x = start.clamp(low, MAX_ROOT);
    if x * x <= y {
        // From below, one step lands on or above the root (AM–GM, also with floors).
        let Some(d) = NonZeroU64::new(x) else { return 0 };
        x = midpoint_u64(x, y / d);
    }
    // From above the sequence decreases strictly until it reaches the root.
    loop {
        if x.checked_mul(x).is_some_and(|sq| sq <= y) {
            return x;
        }
        let Some(d) = NonZeroU64::new(x) else { return 0 };
        x = midpoint_u64(x, y / d);
    }
}

/// A `u128` known to fit: clamped rather than panicking.
fn narrow(x: u128) -> u64 {
    u64::try_from(x).unwrap_or(u64::MAX)
}

/// The incremental state of a ramp at distance `m` from rest (`m = k` accelerating,
/// `m = N − k` decelerating).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Ramp {
    /// `Y(m) = ⌊2m·f²/a⌋`.
    y: u64,
    /// `2m·f² mod a`.
    rem: u64,
    /// `isqrt(Y(m))`: ticks from rest.
    root: u64,
    /// `|root(m) − root(m ∓ 1)|` of the previous step: the next step's guess.
    stride: u64,
}

impl Ramp {
    const REST: Self = Self { y: 0, rem: 0, root: 0, stride: 0 };
}

/// A planned move: parameters, phase boundaries and the seeds of the incremental generator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Trapezoid {
    steps: u32,
    max_speed: NonZeroU32,
    accel: NonZeroU32,
    tick_hz: u32,
    /// Last step of the acceleration phase; 0 when the move starts in cruise.
    accel_end: u32,
    /// First step of the deceleration phase (step `N` is always in it).
    decel_start: u32,
    /// `E`, the tick of step `N`.
    end: u64,
    /// `⌊2f²/a⌋` and `2f² mod a`: a ramp step in `Y`.
    ramp_q: u64,
    ramp_r: u64,
    /// `⌊f/v⌋`: a cruise step in ticks, plus `2a·(f mod v)` carried modulo `2a·v`,
    /// stored as `2a·v − 2a·(f mod v)` so the carry test cannot overflow.
    cruise_q: u64,
    cruise_r: u64,
    cruise_gap: u64,
    /// `2a·v`.
    cruise_den: NonZeroU64,
    /// Cruise accumulator at step `accel_end`: `⌊f·(2a·k + v²) / (2a·v)⌋` and its remainder.
    cruise_seed: u64,
    cruise_seed_rem: u64,
    /// The ramp state at step `decel_start`.
    decel_seed: Ramp,
}

impl Trapezoid {
    /// Plans a move of `steps` steps at most `max_speed` steps/s, accelerating and
    /// decelerating at `accel` steps/s², timed in ticks of `tick_hz`.
    pub fn new(steps: u32, max_speed: u32, accel: u32, tick_hz: u32) -> Result<Self, PlanError> {
        if steps == 0 {
            return Err(PlanError::ZeroSteps);
        }
        let max_speed = NonZeroU32::new(max_speed).ok_or(PlanError::ZeroSpeed)?;
        let accel = NonZeroU32::new(accel).ok_or(PlanError::ZeroAccel)?;
        if 2 * u64::from(max_speed.get()) > u64::from(tick_hz) {
            return Err(PlanError::TooFast { max_speed: max_speed.get() });
        }
        // All products below stay under 2¹⁰⁰.
        let (n, v, f) = (u128::from(steps), u128::from(max_speed.get()), u128::from(tick_hz));
        let a = u128::from(accel.get());
        let a_nz = NonZeroU128::from(accel);
        let two_a = NonZeroU128::new(2 * a).ok_or(PlanError::ZeroAccel)?;
        let (accel_end, decel_start, end) = if v * v >= a * n {
            let half = steps / 2;
            (half, half + 1, u128::from(isqrt_u128(4 * n * f * f / a_nz)))
        } else {
            // x_a < N/2, so ⌊x_a⌋ fits and 1 ≤ ⌈x_a⌉ ≤ N.
            let accel_end = u32::try_from(v * v / two_a).map_err(|_| PlanError::TooLong)?;
            let ceil_xa = u32::try_from((v * v).div_ceil(2 * a)).map_err(|_| PlanError::TooLong)?;
            let decel_start = (steps - ceil_xa).checked_add(1).ok_or(PlanError::TooLong)?;
            let av = NonZeroU128::new(a * v).ok_or(PlanError::ZeroSpeed)?;
            (accel_end, decel_start, f * (n * a + v * v) / av)
        };
        let end = u64::try_from(end).map_err(|_| PlanError::TooLong)?;
        // Y is largest at the ends of the ramps: Y(accel_end) and Y(N − decel_start).
        let two_ff = 2 * f * f;
        let y_max = (u128::from(accel_end.max(steps - decel_start)) * two_ff) / a_nz;
        if y_max > u128::from(u64::MAX) {
            return Err(PlanError::TooLong);
        }
        // 2a·v < 2⁶⁴ because v ≤ f/2 < 2³¹.
        let cruise_den = u64::try_from(2 * a * v).map_err(|_| PlanError::TooLong)?;
        let cruise_den = NonZeroU64::new(cruise_den).ok_or(PlanError::ZeroSpeed)?;
        let cruise_r = narrow(2 * a * (f % v));
        let cruise_num = f * (2 * a * u128::from(accel_end) + v * v);
        let cruise_den_nz = NonZeroU128::from(cruise_den);
        let mut plan = Self {
            steps,
            max_speed,
            accel,
            tick_hz,
            accel_end,
            decel_start,
            end,
            // Only used when a ramp has a step at m ≥ 1, and then ⌊2f²/a⌋ = Y(1) ≤ y_max.
            ramp_q: narrow(two_ff / a_nz),
            ramp_r: narrow(two_ff % a_nz),
            cruise_q: narrow(f / v),
            cruise_r,
            cruise_gap: cruise_den.get() - cruise_r, // 2a·(f mod v) < 2a·v
            cruise_den,
            cruise_seed: narrow(cruise_num / cruise_den_nz),
            cruise_seed_rem: narrow(cruise_num % cruise_den_nz),
            decel_seed: Ramp::REST,
        };
        let m = steps - decel_start;
        plan.decel_seed = plan.ramp_state(m, m + 1);
        Ok(plan)
    }

    /// The move's length in steps.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// The speed limit, steps/s.
    pub fn max_speed(&self) -> u32 {
        self.max_speed.get()
    }

    /// The acceleration, steps/s².
    pub fn accel(&self) -> u32 {
        self.accel.get()
    }

    /// The tick rate the step ticks count in, Hz.
    pub fn tick_hz(&self) -> u32 {
        self.tick_hz
    }

    /// Whether the move never reaches `max_speed` (`v² ≥ a·N`).
    pub fn is_triangle(&self) -> bool {
        let v = u64::from(self.max_speed.get()); // < 2³¹
        v * v >= u64::from(self.accel.get()) * u64::from(self.steps)
    }

    /// The tick of the last step: the move's end, ticks after its start.
    pub fn duration(&self) -> u64 {
        self.end
    }

    /// The tick of step `k`, ticks after the move's start, from the closed form (128-bit
    /// arithmetic; use [`StepTimes`] in loops). 0 for `k = 0`, the end for `k ≥ N`.
    pub fn step_tick(&self, k: u32) -> u64 {
        if k == 0 {
            0
        } else if k >= self.steps {
            self.end
        } else if k <= self.accel_end {
            self.ramp_root(k)
        } else if k < self.decel_start {
            let (num, den) = self.cruise_fraction(k);
            narrow(num / den)
        } else {
            self.end.saturating_sub(self.ramp_root(self.steps - k))
        }
    }

    /// A generator of the step ticks from step 1.
    pub fn stepper(&self) -> StepTimes {
        self.stepper_from(0)
    }

    /// A generator that continues after step `k` (yields step `k + 1` first): what a move
    /// switched to mid-way, e.g. [`stopping_after`](Self::stopping_after), runs on.
    pub fn stepper_from(&self, k: u32) -> StepTimes {
        let done = k.min(self.steps);
        let mut gen = StepTimes { plan: *self, done, ramp: Ramp::REST, cruise: 0, cruise_rem: 0 };
        if done <= self.accel_end {
            gen.ramp = self.ramp_state(done, done.saturating_sub(1));
        } else if done < self.decel_start {
            let (num, den) = self.cruise_fraction(done);
            gen.cruise = narrow(num / den);
            gen.cruise_rem = narrow(num % den);
        } else {
            let m = self.steps - done;
            gen.ramp = self.ramp_state(m, m + 1);
        }
        gen
    }

    /// The move that stops as soon as possible after step `k`, keeping the ticks of steps
    /// `1..=k`: stopping while accelerating mirrors the ramp (a triangle of `2k` steps),
    /// while cruising decelerates after `k + ⌈x_a⌉` steps, while decelerating changes nothing.
    /// `None` for `k = 0`: the move has not started, so stopping means no step at all.
    pub fn stopping_after(&self, k: u32) -> Option<Trapezoid> {
        if k == 0 {
            return None;
        }
        if k >= self.decel_start {
            return Some(*self);
        }
        let steps = if k <= self.accel_end {
            2 * k // accel_end ≤ N/2
        } else {
            k + (self.steps - self.decel_start + 1) // ⌈x_a⌉; k < decel_start keeps it ≤ N
        };
        // Cannot fail: the plan only gets shorter with the same speed, accel and tick rate,
        // and the limits are monotone in the length. Keeping the move is the safe fallback.
        Some(Self::new(steps, self.max_speed.get(), self.accel.get(), self.tick_hz).unwrap_or(*self))
    }

    /// `isqrt(⌊2m·f²/a⌋)`: ticks from rest to ramp distance `m`.
    fn ramp_root(&self, m: u32) -> u64 {
        let f = u128::from(self.tick_hz);
        isqrt_u128(2 * u128::from(m) * f * f / NonZeroU128::from(self.accel))
    }

    /// The ramp state at distance `m` from rest, its stride taken from distance `neighbour`.
    fn ramp_state(&self, m: u32, neighbour: u32) -> Ramp {
        let f = u128::from(self.tick_hz);
        let a = NonZeroU128::from(self.accel);
        let num = 2 * u128::from(m) * f * f;
        let y = num / a;
        let root = isqrt_u128(y);
        Ramp { y: narrow(y), rem: narrow(num % a), root, stride: root.abs_diff(self.ramp_root(neighbour)) }
    }

    /// `f·(2a·k + v²)` over `2a·v`: the cruise tick of step `k` as a fraction.
    fn cruise_fraction(&self, k: u32) -> (u128, NonZeroU128) {
        let (a, v) = (u128::from(self.accel.get()), u128::from(self.max_speed.get()));
        (u128::from(self.tick_hz) * (2 * a * u128::from(k) + v * v), NonZeroU128::from(self.cruise_den))
    }
}

/// Yields the ticks of steps 1, 2, …, N (ticks after the move's start), each equal to
/// [`Trapezoid::step_tick`], computed incrementally with 64-bit arithmetic: a few additions
/// and one 64-bit multiply per step, a division only when the root guess is off by more
/// than 2 (early ramp steps).
#[derive(Debug, Clone)]
pub struct StepTimes {
    plan: Trapezoid,
    /// Steps yielded.
    done: u32,
    ramp: Ramp,
    /// Cruise accumulator `⌊f·(2a·k + v²) / (2a·v)⌋` and its remainder.
    cruise: u64,
    cruise_rem: u64,
}

impl StepTimes {
    /// The tick of the next step, `None` after step `N`.
    pub fn next_tick(&mut self) -> Option<u64> {
        let Trapezoid { steps, accel_end, decel_start, end, .. } = self.plan;
        if self.done >= steps {
            return None;
        }
        let k = self.done + 1;
        let tick = if k <= accel_end {
            self.accelerate()
        } else if k < decel_start {
            if k == accel_end + 1 {
                self.cruise = self.plan.cruise_seed;
                self.cruise_rem = self.plan.cruise_seed_rem;
            }
            self.cruise_step()
        } else if k == decel_start {
            self.ramp = self.plan.decel_seed;
            end.checked_sub(self.ramp.root)
        } else {
            self.decelerate().and_then(|root| end.checked_sub(root))
        };
        let tick = match tick {
            Some(tick) => {
                self.done = k;
                tick
            }
            // Unreachable within the plan's limits; recomputing keeps the ticks exact anyway.
            None => {
                *self = self.plan.stepper_from(k);
                self.plan.step_tick(k)
            }
        };
        Some(tick)
    }

    /// Steps yielded so far.
    pub fn done(&self) -> u32 {
        self.done
    }

    /// The plan being stepped.
    pub fn plan(&self) -> &Trapezoid {
        &self.plan
    }

    /// One acceleration step: `Y` up by `⌊2f²/a⌋` plus the carry, root near last + stride.
    fn accelerate(&mut self) -> Option<u64> {
        let a = u64::from(self.plan.accel.get());
        let prev = self.ramp;
        let mut y = prev.y.checked_add(self.plan.ramp_q)?;
        let mut rem = prev.rem + self.plan.ramp_r; // both < a ≤ 2³² − 1
        if rem >= a {
            rem -= a;
            y = y.checked_add(1)?;
        }
        let root = isqrt_near(y, prev.root.saturating_add(prev.stride));
        self.ramp = Ramp { y, rem, root, stride: root.saturating_sub(prev.root) };
        Some(root)
    }

    /// One deceleration step: `Y` down by `⌊2f²/a⌋` plus the borrow, root near last − stride.
    fn decelerate(&mut self) -> Option<u64> {
        let a = u64::from(self.plan.accel.get());
        let prev = self.ramp;
        let mut y = prev.y.checked_sub(self.plan.ramp_q)?;
        let rem = if prev.rem >= self.plan.ramp_r {
            prev.rem - self.plan.ramp_r
        } else {
            y = y.checked_sub(1)?;
            prev.rem + a - self.plan.ramp_r // ramp_r < a
        };
        let root = isqrt_near(y, prev.root.saturating_sub(prev.stride));
        self.ramp = Ramp { y, rem, root, stride: prev.root.saturating_sub(root) };
        Some(root)
    }

    /// One cruise step: `⌊f/v⌋` ticks plus the carry of `2a·(f mod v)` modulo `2a·v`.
    fn cruise_step(&mut self) -> Option<u64> {
        let p = &self.plan;
        let mut tick = self.cruise.checked_add(p.cruise_q)?;
        if self.cruise_rem >= p.cruise_gap {
            self.cruise_rem -= p.cruise_gap;
            tick = tick.checked_add(1)?;
        } else {
            self.cruise_rem += p.cruise_r; // stays below 2a·v
        }
        self.cruise = tick;
        Some(tick)
    }
}

impl Iterator for StepTimes {
    type Item = u64;

    fn next(&mut self) -> Option<u64> {
        self.next_tick()
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = usize::try_from(self.plan.steps - self.done).unwrap_or(usize::MAX);
        (left, Some(left))
    }
}

impl ExactSizeIterator for StepTimes {}

impl core::iter::FusedIterator for StepTimes {}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use std::vec::Vec;

    /// The spec's phase of step `k`, from exact rational comparisons (independent of the
    /// plan's precomputed boundaries).
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Phase {
        Accel,
        Cruise,
        Decel,
    }

    fn phase(p: &Trapezoid, k: u32) -> Phase {
        let (n, v, a) = (u128::from(p.steps), u128::from(p.max_speed()), u128::from(p.accel()));
        let k = u128::from(k);
        if v * v >= a * n {
            if 2 * k <= n {
                Phase::Accel
            } else {
                Phase::Decel
            }
        } else if 2 * a * k <= v * v {
            Phase::Accel
        } else if 2 * a * (n - k) < v * v {
            Phase::Decel
        } else {
            Phase::Cruise
        }
    }

    /// `t` is the floor of `√(num/den)`: `den·t² ≤ num < den·(t + 1)²`.
    fn is_floor_sqrt(t: u64, num: u128, den: u128) -> bool {
        let (t, t1) = (u128::from(t), u128::from(t) + 1);
        den.checked_mul(t * t).is_some_and(|lo| lo <= num)
            && den.checked_mul(t1 * t1).is_none_or(|hi| num < hi)
    }

    /// `t` is the floor of `num/den`.
    fn is_floor_div(t: u64, num: u128, den: u128) -> bool {
        let t = u128::from(t);
        t * den <= num && num < (t + 1) * den
    }

    /// Checks step `k` against the integer definitions exactly (no isqrt involved).
    fn assert_exact(p: &Trapezoid, k: u32) {
        let (n, v, a, f) =
            (u128::from(p.steps), u128::from(p.max_speed()), u128::from(p.accel()), u128::from(p.tick_hz));
        let e = p.duration();
        if v * v >= a * n {
            assert!(is_floor_sqrt(e, 4 * n * f * f, a), "E of {p:?}");
        } else {
            assert!(is_floor_div(e, f * (n * a + v * v), a * v), "E of {p:?}");
        }
        let t = p.step_tick(k);
        let x = u128::from(k);
        let ok = match phase(p, k) {
            Phase::Accel => is_floor_sqrt(t, 2 * x * f * f, a),
            Phase::Cruise => is_floor_div(t, f * (2 * a * x + v * v), 2 * a * v),
            Phase::Decel => e >= t && is_floor_sqrt(e - t, 2 * (n - x) * f * f, a),
        };
        assert!(ok, "step {k} ({:?}) of {p:?}: tick {t}", phase(p, k));
    }

    /// The continuous profile's time of step `k`, in ticks, in f64.
    fn analytic_ticks(p: &Trapezoid, k: u32) -> f64 {
        let (n, v, a, f) = (p.steps as f64, p.max_speed() as f64, p.accel() as f64, p.tick_hz as f64);
        let x = k as f64;
        let t_end = if p.is_triangle() { 2.0 * (n / a).sqrt() } else { n / v + v / a };
        let t = match phase(p, k) {
            Phase::Accel => (2.0 * x / a).sqrt(),
            Phase::Cruise => x / v + v / (2.0 * a),
            Phase::Decel => t_end - (2.0 * (n - x) / a).sqrt(),
        };
        t * f
    }

    /// Steps worth checking in a long move: both ends, every phase boundary ± 3, and an even
    /// spread of `samples` in between.
    fn sample_steps(p: &Trapezoid, samples: u32) -> Vec<u32> {
        let n = p.steps;
        let mut ks: Vec<u32> = (1..=n.min(4)).chain(n.saturating_sub(3).max(1)..=n).collect();
        for b in [p.accel_end, p.decel_start] {
            ks.extend((b.saturating_sub(3)..=b.saturating_add(3)).filter(|&k| (1..=n).contains(&k)));
        }
        ks.extend((1..=samples).map(|i| (u64::from(n) * u64::from(i) / u64::from(samples)) as u32));
        ks.retain(|&k| k >= 1);
        ks.sort_unstable();
        ks.dedup();
        ks
    }

    fn all_or_sampled(p: &Trapezoid) -> Vec<u32> {
        if p.steps <= 5_000 {
            (1..=p.steps).collect()
        } else {
            sample_steps(p, 2_000)
        }
    }

    /// Checks the generator against the closed form for every step, and the order.
    fn assert_stepper_exact(p: &Trapezoid) {
        let mut gen = p.stepper();
        let mut prev = 0;
        for k in 1..=p.steps {
            assert_eq!(gen.next_tick(), Some(p.step_tick(k)), "step {k} of {p:?}");
            let t = p.step_tick(k);
            assert!(t > prev, "step {k} of {p:?}: {t} after {prev}");
            prev = t;
        }
        assert_eq!(gen.next_tick(), None);
        assert_eq!(gen.done(), p.steps);
        assert_eq!(prev, p.duration());
    }

    /// A u32 in `1..=max`, log-uniform-ish so small and huge values both turn up.
    fn log_u32(max: u32) -> impl Strategy<Value = u32> {
        (0u32..=32, any::<u32>()).prop_map(move |(bits, x)| {
            let x = if bits == 0 { 0 } else { u64::from(x >> (32 - bits)) };
            (1 + x % u64::from(max.max(1))) as u32
        })
    }

    /// Random plannable parameters: `(steps, max_speed, accel, tick_hz)`.
    fn plan_params(max_steps: u32) -> impl Strategy<Value = (u32, u32, u32, u32)> {
        let f = prop_oneof![Just(1_000_000u32), Just(170_000_000), log_u32(u32::MAX).prop_map(|f| f.max(2))];
        (log_u32(max_steps), f, 0u32..=31, any::<u32>(), log_u32(u32::MAX)).prop_map(|(n, f, bits, x, a)| {
            let x = if bits == 0 { 0 } else { x >> (32 - bits) };
            (n, 1 + x % (f / 2), a, f)
        })
    }

    #[test]
    fn isqrt_u128_is_exact() {
        for n in 0u128..100_000 {
            let r = u128::from(isqrt_u128(n));
            assert!(r * r <= n && n < (r + 1) * (r + 1), "{n}");
        }
        for r in [1u64, 2, 3, 0xFFFF, 0x1_0000, u32::MAX as u64, 1 << 32, 1 << 53, u64::MAX - 1, u64::MAX] {
            let sq = u128::from(r) * u128::from(r);
            assert_eq!(isqrt_u128(sq), r);
            assert_eq!(isqrt_u128(sq - 1), r - 1);
            assert_eq!(isqrt_u128(sq + 2 * u128::from(r)), r); // (r + 1)² − 1
        }
        assert_eq!(isqrt_u128(u128::MAX), u64::MAX);
    }

    proptest! {
        #[test]
        fn isqrt_near_is_exact_from_any_guess(y: u64, off in -1_000_000i64..1_000_000, far: bool) {
            let root = isqrt_u128(u128::from(y));
            let guess = if far { off.unsigned_abs() } else { root.saturating_add_signed(off) };
            prop_assert_eq!(isqrt_near(y, guess), root);
            prop_assert_eq!(isqrt_newton(y, guess), root);
            prop_assert_eq!(isqrt_near(u64::MAX - (y >> 40), guess), isqrt_u128(u128::from(u64::MAX - (y >> 40))));
        }
    }

    #[test]
    fn errors() {
        assert_eq!(Trapezoid::new(0, 1, 1, 2), Err(PlanError::ZeroSteps));
        assert_eq!(Trapezoid::new(1, 0, 1, 2), Err(PlanError::ZeroSpeed));
        assert_eq!(Trapezoid::new(1, 1, 0, 2), Err(PlanError::ZeroAccel));
        assert_eq!(Trapezoid::new(1, 1, 1, 1), Err(PlanError::TooFast { max_speed: 1 }));
        assert_eq!(Trapezoid::new(1, 1, 1, 0), Err(PlanError::TooFast { max_speed: 1 }));
        assert_eq!(
            Trapezoid::new(10, 500_001, 1000, 1_000_000),
            Err(PlanError::TooFast { max_speed: 500_001 })
        );
        assert!(Trapezoid::new(10, 500_000, 1000, 1_000_000).is_ok());
        assert!(Trapezoid::new(1, u32::MAX / 2, u32::MAX, u32::MAX).is_ok());
        // Ramp ticks beyond 2³²: 170 MHz, 100 000 steps/s reached at 1000 steps/s² takes 100 s.
        assert_eq!(Trapezoid::new(100_000_000, 100_000, 1000, 170_000_000), Err(PlanError::TooLong));
        // The same ramp at 1 MHz fits (about 10⁸ ticks).
        assert!(Trapezoid::new(100_000_000, 100_000, 1000, 1_000_000).is_ok());
        // A triangle's ramp of √(N/a) = 31.6 s: beyond 2³² ticks at 170 MHz, not at 100 MHz.
        assert_eq!(Trapezoid::new(625_000_000, u32::MAX / 2, 2_000_000, u32::MAX), Err(PlanError::TooLong));
        assert_eq!(Trapezoid::new(1_000_000, 100_000, 1000, 170_000_000), Err(PlanError::TooLong));
        assert!(Trapezoid::new(1_000_000, 100_000, 1000, 100_000_000).is_ok());
        assert_eq!(Trapezoid::new(u32::MAX, u32::MAX / 2, 1, u32::MAX), Err(PlanError::TooLong));
        // The longest move there is: x_a = ½, so no ramp step but the last; E just fits.
        let p = Trapezoid::new(u32::MAX, 1, 1, u32::MAX).unwrap();
        assert_eq!(p.duration(), u64::from(u32::MAX) << 32); // f·(N + 1)
        assert_eq!(p.stepper_from(u32::MAX - 1).next_tick(), Some(p.duration()));
        assert_eq!(p.stepper_from(u32::MAX - 2).next(), Some(p.step_tick(u32::MAX - 1)));
        assert!(!std::format!("{}", PlanError::TooFast { max_speed: 7 }).is_empty());
    }

    /// Ramps whose squared ticks come right up to `u64::MAX`: the generator's 64-bit state at
    /// its limit, every step checked.
    #[test]
    fn ramps_at_the_limit() {
        let f = u32::MAX;
        // Y(N/2) = N·f²/a = f² exactly: the largest ramp there is at this tick rate.
        let p = Trapezoid::new(1_000_000, f / 2, 1_000_000, f).unwrap();
        assert_eq!(p.step_tick(500_000), MAX_ROOT);
        assert_stepper_exact(&p);
        assert_eq!(Trapezoid::new(1_000_000, f / 2, 999_999, f), Err(PlanError::TooLong));
        // 22 s of ramp at 170 MHz, 3.8·10⁹ ticks, with few, long steps.
        let p = Trapezoid::new(2_000, 1_000, 4, 170_000_000).unwrap();
        assert!(p.is_triangle() && p.step_tick(1000) > 3_000_000_000);
        assert_stepper_exact(&p);
        // A trapezoid: 23.3 s of ramp (19 794.5 steps) at 170 MHz, 3.96·10⁹ ticks, then cruise.
        let p = Trapezoid::new(100_000, 1_700, 73, 170_000_000).unwrap();
        assert_eq!((p.accel_end, p.decel_start), (19_794, 80_206));
        assert!(p.step_tick(19_794) > 3_900_000_000);
        assert_stepper_exact(&p);
    }

    /// Test 1: every step within one tick of the continuous profile. The f64 reference is off
    /// by a few ulps of the end time; moves are kept below 2⁴⁰ ticks so that slack
    /// (`8·ε·f·t_end` ≤ 2·10⁻³ tick) stays far below the tick being tested.
    #[test]
    fn closed_form_within_one_tick_of_the_analytic_profile() {
        let mut checked = 0u64;
        for f in [1_000_000u32, 170_000_000] {
            for v in [1u32, 2, 3, 10, 999, 10_000, 123_457, f / 4, f / 2 - 1, f / 2] {
                for a in [1u32, 2, 7, 1000, 65_537, 1_000_000, 10_000_000] {
                    for n in [1u32, 2, 3, 4, 5, 10, 99, 1000, 12_345, 100_000, 1_000_000, 10_000_000] {
                        let Ok(p) = Trapezoid::new(n, v, a, f) else { continue };
                        let end = analytic_ticks(&p, n);
                        if end > (1u64 << 40) as f64 {
                            continue;
                        }
                        let slack = 1e-6 + 8.0 * f64::EPSILON * end;
                        for k in all_or_sampled(&p) {
                            let t = p.step_tick(k) as f64;
                            let ideal = analytic_ticks(&p, k);
                            assert!((t - ideal).abs() < 1.0 + slack, "step {k} of {p:?}: {t} vs {ideal}");
                            if phase(&p, k) != Phase::Decel {
                                assert!(t <= ideal + slack, "floor: step {k} of {p:?}: {t} vs {ideal}");
                            }
                            checked += 1;
                        }
                    }
                }
            }
        }
        assert!(checked > 500_000, "{checked}");
    }

    /// The closed form meets the integer definitions exactly, checked by multiplication only.
    #[test]
    fn closed_form_is_the_exact_floor_on_a_grid() {
        for f in [2u32, 1_000_000, 170_000_000, u32::MAX] {
            for v in [1u32, 3, 1000, 65_536, f / 2] {
                for a in [1u32, 5, 1 << 20, u32::MAX] {
                    for n in [1u32, 2, 3, 7, 1000, 10_000_000, u32::MAX] {
                        let Ok(p) = Trapezoid::new(n, v.max(1), a, f) else { continue };
                        for k in sample_steps(&p, 200) {
                            assert_exact(&p, k);
                        }
                    }
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn closed_form_is_the_exact_floor((n, v, a, f) in plan_params(u32::MAX), pick: u32) {
            let p = Trapezoid::new(n, v, a, f);
            prop_assume!(p.is_ok());
            let p = p.unwrap();
            assert_exact(&p, 1 + pick % n);
            assert_exact(&p, n);
        }

        /// Test 2: the generator yields exactly the closed form, every step.
        #[test]
        fn stepper_equals_closed_form((n, v, a, f) in plan_params(3_000)) {
            let p = Trapezoid::new(n, v, a, f);
            prop_assume!(p.is_ok());
            assert_stepper_exact(&p.unwrap());
        }

        /// Resuming anywhere in huge moves (seeds of every phase), then running on.
        #[test]
        fn stepper_from_equals_closed_form((n, v, a, f) in plan_params(u32::MAX), pick: u32) {
            let p = Trapezoid::new(n, v, a, f);
            prop_assume!(p.is_ok());
            let p = p.unwrap();
            for k0 in [pick % n, p.accel_end, p.decel_start - 1, n.saturating_sub(200)] {
                let mut gen = p.stepper_from(k0);
                prop_assert_eq!(gen.done(), k0);
                let mut prev = p.step_tick(k0);
                for k in (k0 + 1..=n).take(300) {
                    let t = gen.next_tick();
                    prop_assert_eq!(t, Some(p.step_tick(k)), "step {} from {} of {:?}", k, k0, p);
                    prop_assert!(p.step_tick(k) > prev);
                    prev = p.step_tick(k);
                }
            }
        }
    }

    /// Test 2, long: 10⁷ steps, no drift. The generator runs every step; the closed form is
    /// compared at every step too.
    #[test]
    fn ten_million_steps_exact_and_without_drift() {
        let p = Trapezoid::new(10_000_000, 200_000, 400_000, 1_000_000).unwrap();
        assert!(!p.is_triangle());
        let mut gen = p.stepper();
        let mut prev = 0;
        let mut k = 0;
        while let Some(t) = gen.next_tick() {
            k += 1;
            assert!(t > prev, "step {k}");
            assert_eq!(t, p.step_tick(k), "step {k}");
            prev = t;
        }
        assert_eq!(k, 10_000_000);
        assert_eq!(prev, p.duration());
        // t_end = N/v + v/a = 50 s + 0.5 s exactly.
        assert_eq!(p.duration(), 50_500_000);
        assert!((prev as f64 - analytic_ticks(&p, k)).abs() < 1.0);
    }

    /// Test 3: small moves and the shape boundaries.
    #[test]
    fn boundary_cases() {
        let f = 1_000_000;
        // N = 1: a triangle (v² ≥ a) and a "trapezoid" whose only step decelerates (v² < a).
        for (v, a) in [(100, 100), (10, 1000), (1, 1), (500_000, 1)] {
            let p = Trapezoid::new(1, v, a, f).unwrap();
            assert_eq!(p.step_tick(1), p.duration());
            assert!(p.duration() >= 2);
            assert_stepper_exact(&p);
            assert_exact(&p, 1);
        }
        // N = 2, triangle: step 1 accelerates, step 2 ends; t_end = 2√(2/a).
        let p = Trapezoid::new(2, 1000, 100, f).unwrap();
        assert!(p.is_triangle());
        assert_eq!(p.step_tick(1), 141_421); // 10⁶·√(2/100)
        assert_eq!(p.step_tick(2), 282_842);
        assert_stepper_exact(&p);
        // a·N = v² exactly: x_a = N/2, triangle and trapezoid coincide. The next length up is a
        // trapezoid with one cruise step; the shared steps agree.
        let tri = Trapezoid::new(100, 100, 100, f).unwrap();
        let trap = Trapezoid::new(101, 100, 100, f).unwrap();
        assert!(tri.is_triangle() && !trap.is_triangle());
        assert_eq!(tri.duration(), 2 * u64::from(f)); // 2√(N/a) = N/v + v/a = 2 s
        assert_eq!((trap.accel_end, trap.decel_start), (50, 52));
        for k in 1..=50 {
            assert_eq!(tri.step_tick(k), trap.step_tick(k), "step {k}");
        }
        // Step 50 = x_a: the accel and cruise formulas give the same value there.
        assert_eq!(trap.step_tick(50), 1_000_000);
        assert_eq!(trap.step_tick(51), 1_010_000);
        for p in [tri, trap] {
            assert_stepper_exact(&p);
            for k in 1..=p.steps {
                assert_exact(&p, k);
            }
        }
        // The trapezoid formulas at a·N = v² give the triangle's ticks.
        let two_ff = 2 * u128::from(f) * u128::from(f);
        for k in 51..=100u32 {
            let e = u128::from(f) * (100 * 100 + 100 * 100) / (100 * 100);
            let tail = isqrt_u128(u128::from(100 - k) * two_ff / 100);
            assert_eq!(u128::from(tri.step_tick(k)), e - u128::from(tail));
        }
        // x_a fractional (v²/(2a) = 12.5): accel ends at 12, decel takes the last 13 steps.
        let p = Trapezoid::new(40, 50, 100, f).unwrap();
        assert_eq!((p.accel_end, p.decel_start), (12, 28));
        assert_stepper_exact(&p);
        // x_a below one step: the move starts in cruise.
        let p = Trapezoid::new(40, 10, 1000, f).unwrap();
        assert_eq!((p.accel_end, p.decel_start), (0, 40));
        assert_eq!(p.step_tick(1), 105_000); // 1/v + v/(2a) = 0.1 s + 5 ms
        assert_stepper_exact(&p);
        // Fastest allowed: v = f/2 keeps steps at least one tick apart.
        let p = Trapezoid::new(10_000, 500_000, 10_000_000, f).unwrap();
        assert_stepper_exact(&p);
        // Out-of-range indices.
        assert_eq!(p.step_tick(0), 0);
        assert_eq!(p.step_tick(u32::MAX), p.duration());
        assert_eq!(p.stepper_from(u32::MAX).next_tick(), None);
    }

    /// Test 4: stopping keeps the past and decelerates to rest.
    fn check_stop(p: &Trapezoid, k: u32) -> Trapezoid {
        let stop = p.stopping_after(k).unwrap();
        for j in 1..=k {
            assert_eq!(stop.step_tick(j), p.step_tick(j), "step {j}, stop after {k} of {p:?}");
        }
        assert!(stop.duration() <= p.duration());
        assert!(stop.steps() >= k && stop.steps() <= p.steps);
        // Mid-move switch: the old generator's first k steps, then the new one's.
        let mut gen = p.stepper();
        let mut ticks: Vec<u64> = gen.by_ref().take(k as usize).collect();
        let mut gen = stop.stepper_from(gen.done());
        ticks.extend(gen.by_ref());
        let expected: Vec<u64> = (1..=stop.steps()).map(|j| stop.step_tick(j)).collect();
        assert_eq!(ticks, expected);
        // Slowing down after step k: intervals grow (each tick is within 1 of the ideal, so an
        // interval may be up to 2 ticks shorter than an earlier one).
        let intervals: Vec<u64> = ticks.windows(2).map(|w| w[1] - w[0]).skip(k as usize).collect();
        for w in intervals.windows(2) {
            assert!(w[1] + 2 >= w[0], "intervals {w:?}, stop after {k} of {p:?}");
        }
        if intervals.len() >= 2 {
            assert!(intervals.last() >= intervals.first(), "stop after {k} of {p:?}");
        }
        stop
    }

    #[test]
    fn stopping_after_in_each_phase() {
        // x_a = 12.5: accel 1..=12, cruise 13..=987, decel 988..=1000.
        let p = Trapezoid::new(1000, 50, 100, 1_000_000).unwrap();
        assert_eq!(p.stopping_after(0), None);
        // Accelerating: the mirrored triangle.
        for k in [1, 5, 12] {
            let stop = check_stop(&p, k);
            assert_eq!(stop.steps(), 2 * k);
            assert!(stop.is_triangle());
        }
        // Cruising: decelerate over ⌈x_a⌉ = 13 steps.
        for k in [13, 14, 500, 986, 987] {
            assert_eq!(check_stop(&p, k).steps(), k + 13);
        }
        // Decelerating or done: unchanged.
        for k in [988, 999, 1000, 5000] {
            assert_eq!(p.stopping_after(k), Some(p));
        }
        // A triangle stops with a shorter triangle; stopping a stopping plan changes nothing.
        let tri = Trapezoid::new(1001, 1000, 100, 1_000_000).unwrap();
        let stop = check_stop(&tri, 300);
        assert_eq!(stop.steps(), 600);
        assert_eq!(stop.stopping_after(300), Some(stop));
        // x_a integral: accel_end = ⌈x_a⌉ = 50; stopping at 50 gives 100 steps either way.
        let p = Trapezoid::new(1000, 100, 100, 1_000_000).unwrap();
        assert_eq!(check_stop(&p, 50).steps(), 100);
        assert_eq!(check_stop(&p, 51).steps(), 101);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn stopping_after_keeps_the_past((n, v, a, f) in plan_params(2_000), pick: u32) {
            let p = Trapezoid::new(n, v, a, f);
            prop_assume!(p.is_ok());
            let p = p.unwrap();
            let k = 1 + pick % n;
            let stop = check_stop(&p, k);
            let expected = match phase(&p, k) {
                Phase::Accel => 2 * k,
                Phase::Cruise => k + (u64::from(v) * u64::from(v)).div_ceil(2 * u64::from(a)) as u32,
                Phase::Decel => n,
            };
            prop_assert_eq!(stop.steps(), expected);
            assert_stepper_exact(&stop);
        }
    }
}
