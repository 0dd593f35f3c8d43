//! Sequences: the host plans, the device executes a clock-scheduled queue of items.
//!
//! A sequence is a stream of [`Item`]s, each an [`Action`] due `delta` ticks after the previous
//! item's due time (the first one: after the sequence's start tick). Times are integers all the
//! way, so a million items later the schedule is exact.
//!
//! The host streams items in [`Chunk`]s under credit flow control: it may have at most
//! [`BufferStatus::free`] items outstanding, and the device reports its buffer after every chunk
//! and as it drains. Running out of buffered items before a chunk marked `last` is an underrun:
//! the device stops in the safe state and reports `Underrun`, never stalls silently.

use heapless::Vec;
use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::config::Xy;
use crate::{MAX_CHUNK_ITEMS, MAX_PARTIALS};

/// One sine partial of a voice-coil signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Partial {
    /// Frequency in millihertz.
    pub freq_mhz: u32,
    /// Amplitude as a fraction of full scale (`u16::MAX` = full scale).
    pub amplitude: u16,
    /// Phase at the moment the setting takes effect, in 1/65536 of a turn.
    pub phase: u16,
}

/// Speed profile of a stepper or filter-wheel move; zero fields use the configured values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Profile {
    /// Top speed, steps per second (0 = configured `max_speed`).
    pub max_speed: u32,
    /// Acceleration, steps per second squared (0 = configured `accel`).
    pub accel: u32,
}

/// Something the device can move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum AxisRef {
    /// A stepper axis by index.
    Stepper(u8),
    /// A filter wheel by index.
    FilterWheel(u8),
}

/// A condition a [`Action::Wait`] waits for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum WaitFor {
    /// The axis has finished its move.
    MoveDone(AxisRef),
    /// The laser channel has finished warming up.
    LaserReady(u8),
    /// The camera's exposure-active input went inactive.
    ExposureEnd(u8),
}

/// What an item does when it is due.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Action {
    /// Jump a galvo pair to a point. If the point differs from where the mirrors are, the
    /// device blanks every laser from this tick until the pair's `settle_ticks` have passed
    /// (the spot never streaks), then lets the lasers that are on emit again.
    GalvoPoint {
        /// Galvo pair.
        galvo: u8,
        /// Target, DAC codes.
        to: Xy,
    },
    /// Sweep a galvo pair in a straight line from where it is to `to`, in `steps` equal
    /// updates spread evenly over `duration` ticks: update `i` (1..=steps) at
    /// `due + i·duration/steps` (floor) to `from + (to − from)·i/steps` (rounded towards
    /// `from`). Lasers stay on: this is a sweep, not a jump. `1 <= steps <= max(duration, 1)`.
    GalvoLine {
        /// Galvo pair.
        galvo: u8,
        /// End point, DAC codes.
        to: Xy,
        /// Ticks from the start to the end point.
        duration: u32,
        /// Number of updates, at least 1.
        steps: u16,
    },
    /// Open or close a laser shutter / enable. Turning on needs the channel armed.
    Laser {
        /// Channel.
        channel: u8,
        /// Light on.
        on: bool,
    },
    /// Move a stepper axis to an absolute position.
    StepperMove {
        /// Axis.
        axis: u8,
        /// Target position, steps.
        target: i32,
        /// Speed profile.
        profile: Profile,
    },
    /// Turn a filter wheel to a slot (the shorter way round).
    FilterWheel {
        /// Wheel.
        wheel: u8,
        /// Slot, `0..slots`.
        slot: u8,
    },
    /// Change a voice-coil channel's partials, ramping amplitudes over `ramp` ticks so the
    /// change never clicks. An empty list fades the channel to silence.
    VoiceCoil {
        /// Channel.
        channel: u8,
        /// Ramp time in ticks.
        ramp: u32,
        /// New partials.
        #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
        partials: Vec<Partial, MAX_PARTIALS>,
    },
    /// Fire a camera trigger and report a `Trigger` event with a snapshot of the rig.
    Trigger {
        /// Camera output.
        camera: u8,
        /// Pulse width in ticks (exposure in trigger-width mode); 0 = configured pulse.
        exposure: u32,
    },
    /// Hold the schedule until a condition holds; the next item's `delta` counts from the
    /// moment it does. Not holding within `timeout` ticks is a fault.
    Wait {
        /// The condition.
        until: WaitFor,
        /// Longest wait, ticks.
        timeout: u32,
    },
    /// Report a `Marker` event; used to delimit views, passes and calibration blocks.
    Marker {
        /// Host-chosen identifier.
        id: u32,
    },
}

/// One scheduled action.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Item {
    /// Ticks after the previous item's due time (or the sequence start).
    pub delta: u32,
    /// What to do.
    pub action: Action,
}

/// A run of consecutive items of one sequence (`Command::SequenceLoad`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Chunk {
    /// Sequence id, chosen by the host; chunk 0 opens a new sequence.
    pub sequence: u32,
    /// Chunk number, from 0, consecutive.
    pub chunk: u32,
    /// No chunk follows: draining the buffer after this one completes the sequence.
    pub last: bool,
    /// The items, in order.
    #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
    pub items: Vec<Item, MAX_CHUNK_ITEMS>,
}

/// The device's sequence buffer: the host's credit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct BufferStatus {
    /// Sequence the figures belong to.
    pub sequence: u32,
    /// Total item slots.
    pub capacity: u16,
    /// Free item slots: how many more items the host may send now.
    pub free: u16,
    /// The chunk number the device expects next.
    pub next_chunk: u32,
    /// Items executed so far in this sequence.
    pub executed: u32,
}

/// When a loaded sequence starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum StartAt {
    /// As soon as the command is processed.
    Now,
    /// At this device tick (from `GetClock` and the host's clock regression).
    Tick(u64),
}
