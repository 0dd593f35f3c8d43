//! The simulated peripherals' state at every tick, for the virtual camera.
//!
//! A trigger's snapshot holds the rig at the trigger's tick. A real camera integrates over its
//! whole exposure, though, and a plan that moves an axis, a galvo or a shutter while the
//! exposure is open gets a smeared or half-lit frame. The [`Timeline`] keeps every output
//! change of the simulated board (galvo writes, laser enables, each step of an axis or a filter
//! wheel with its direction) with its tick, so the camera can rebuild the rig's state at any
//! tick of an exposure ([`Timeline::between`]), and the voice-coil samples with the tick each
//! plays at ([`Timeline::coil_samples`]). It knows how far simulated time has got
//! ([`Timeline::horizon`]): a frame is rendered once its exposure has ended, as a real camera
//! delivers it.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use lightrig_firmware::rig::{VOICE_COIL_BLOCK, VOICE_COIL_LATENCY_BLOCKS};
use lightrig_firmware::sim::{Change, Output, SimBoard};
use lightrig_protocol::sequence::AxisRef;

/// Ticks a voice-coil block is kept after it was handed over (1 s on the virtual device).
const BLOCK_MARGIN: u64 = 1_000_000;

/// One change of what the camera can see.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Motion {
    /// A galvo pair driven to `[x, y]` codes.
    Galvo {
        /// Pair index.
        pair: u8,
        /// Codes.
        to: [u16; 2],
    },
    /// A laser's enable output changed level: it toggles between emitting and dark.
    LaserToggled {
        /// Channel.
        channel: u8,
    },
    /// One step of a stepper axis, `+1` or `-1` physical step (direction output high or low).
    Step {
        /// Stepper axis index.
        axis: u8,
        /// `+1` or `-1`.
        physical: i8,
    },
    /// One step of a filter wheel's motor, `+1` or `-1` physical step.
    WheelStep {
        /// Filter wheel index.
        wheel: u8,
        /// `+1` or `-1`.
        physical: i8,
    },
}

/// A block of voice-coil samples as the board received it.
#[derive(Debug, Clone)]
struct Block {
    channel: u8,
    /// Tick the block was handed over: the end of its samples' nominal window.
    written: u64,
    /// Index of its first sample on the channel.
    first: u64,
    samples: Vec<i16>,
}

#[derive(Debug, Default)]
struct Inner {
    changes: VecDeque<(u64, Motion)>,
    /// Direction (steppers, filter wheels) and laser output levels as of the last change
    /// taken in.
    dir: Vec<bool>,
    wheel_dir: Vec<bool>,
    laser: Vec<bool>,
    blocks: VecDeque<Block>,
    horizon: u64,
    /// Each reader's "I need nothing before this tick".
    marks: Vec<u64>,
}

/// The board's output changes in tick order, shared between the virtual transport that takes
/// them from the board and the camera that reads them.
#[derive(Debug, Clone, Default)]
pub struct Timeline(Arc<Mutex<Inner>>);

impl Timeline {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic elsewhere while holding the lock leaves plain data behind: still usable.
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Starts following `board` now: its present levels are the starting point, and every
    /// step is recorded from here on.
    pub(crate) fn attach(&self, board: &mut SimBoard) {
        let mut t = self.lock();
        t.dir = board.steppers.iter().map(|m| m.dir).collect();
        t.wheel_dir = board.wheels.iter().map(|m| m.dir).collect();
        t.laser = board.lasers.to_vec();
        board.record_steps = true;
        board.record.clear();
    }

    /// Takes the board's recorded changes (the board keeps none) up to `now`.
    pub(crate) fn take(&self, board: &mut SimBoard, now: u64) {
        let mut t = self.lock();
        let t = &mut *t;
        for Change { tick, output } in board.record.drain(..) {
            let motion = match output {
                Output::Galvo { pair, to } => Some(Motion::Galvo { pair, to: [to.x, to.y] }),
                Output::Laser { channel, level } => {
                    let slot = usize::from(channel);
                    if t.laser.len() <= slot {
                        t.laser.resize(slot + 1, false);
                    }
                    let toggled = t.laser[slot] != level;
                    t.laser[slot] = level;
                    toggled.then_some(Motion::LaserToggled { channel })
                }
                Output::Dir { motor: AxisRef::Stepper(a), level } => {
                    let slot = usize::from(a);
                    if t.dir.len() <= slot {
                        t.dir.resize(slot + 1, false);
                    }
                    t.dir[slot] = level;
                    None
                }
                Output::Step { motor: AxisRef::Stepper(a) } => {
                    let high = t.dir.get(usize::from(a)).copied().unwrap_or(false);
                    Some(Motion::Step { axis: a, physical: if high { 1 } else { -1 } })
                }
                Output::Dir { motor: AxisRef::FilterWheel(w), level } => {
                    let slot = usize::from(w);
                    if t.wheel_dir.len() <= slot {
                        t.wheel_dir.resize(slot + 1, false);
                    }
                    t.wheel_dir[slot] = level;
                    None
                }
                Output::Step { motor: AxisRef::FilterWheel(w) } => {
                    let high = t.wheel_dir.get(usize::from(w)).copied().unwrap_or(false);
                    Some(Motion::WheelStep { wheel: w, physical: if high { 1 } else { -1 } })
                }
                Output::Samples { channel, first, len } => {
                    let all = board.samples.get(usize::from(channel)).map_or(&[][..], |s| &s[..]);
                    let (a, b) = (first as usize, first as usize + usize::from(len));
                    if let Some(samples) = all.get(a..b) {
                        t.blocks.push_back(Block {
                            channel,
                            written: tick,
                            first,
                            samples: samples.to_vec(),
                        });
                    }
                    None
                }
                _ => None,
            };
            if let Some(m) = motion {
                t.changes.push_back((tick, m));
            }
        }
        t.horizon = t.horizon.max(now);
    }

    /// The tick simulated time has reached: every change up to it is in.
    pub fn horizon(&self) -> u64 {
        self.lock().horizon
    }

    /// The changes with `from < tick < to`, in order (a change at `from` is already in a
    /// snapshot taken at `from`).
    pub fn between(&self, from: u64, to: u64) -> Vec<(u64, Motion)> {
        let t = self.lock();
        let start = t.changes.partition_point(|&(tick, _)| tick <= from);
        t.changes.range(start..).take_while(|&&(tick, _)| tick < to).copied().collect()
    }

    /// A new reader (a camera): changes are kept until every reader has let go of them.
    pub fn reader(&self) -> usize {
        let mut t = self.lock();
        t.marks.push(0);
        t.marks.len() - 1
    }

    /// Reader `reader` will ask for nothing before `tick` again; changes no reader needs are
    /// dropped.
    pub fn forget_before(&self, reader: usize, tick: u64) {
        let mut t = self.lock();
        if let Some(m) = t.marks.get_mut(reader) {
            *m = (*m).max(tick);
        }
        let keep = t.marks.iter().copied().min().unwrap_or(tick);
        let n = t.changes.partition_point(|&(c, _)| c < keep);
        t.changes.drain(..n);
        // A block's samples play within a few blocks after it is written (a few ms at the
        // device's ≥ 48 kHz): a second of margin keeps every block an exposure may still ask for.
        let n = t.blocks.partition_point(|b| b.written.saturating_add(BLOCK_MARGIN) < keep);
        t.blocks.drain(..n);
    }

    /// The samples voice-coil `channel` (at `rate_hz`, on a device counting `tick_hz`) plays
    /// at ticks `from ≤ tick < to`. Sample `n` of a channel started at tick `t₀` has its
    /// nominal tick at `t₀ + ⌊n·tick_hz/rate⌋` and plays
    /// [`VOICE_COIL_LATENCY_BLOCKS`] blocks later; its block is handed over at the end of the
    /// block's nominal window, which gives `t₀` back exactly.
    pub fn coil_samples(&self, channel: u8, rate_hz: u32, tick_hz: u32, from: u64, to: u64) -> Vec<i16> {
        let tick_of = |n: u64| (u128::from(n) * u128::from(tick_hz) / u128::from(rate_hz.max(1))) as u64;
        let t = self.lock();
        let mut out = Vec::new();
        for b in t.blocks.iter().filter(|b| b.channel == channel) {
            let t0 = b.written.saturating_sub(tick_of(b.first + VOICE_COIL_BLOCK as u64));
            for (j, &s) in b.samples.iter().enumerate() {
                let n = b.first + j as u64;
                let plays = t0 + tick_of(n + VOICE_COIL_LATENCY_BLOCKS * VOICE_COIL_BLOCK as u64);
                if plays >= from && plays < to {
                    out.push(s);
                }
            }
        }
        out
    }

    /// Changes held.
    pub fn len(&self) -> usize {
        self.lock().changes.len()
    }

    /// No changes held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
