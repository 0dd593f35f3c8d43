//! Events: what the device reports unasked. Each is numbered (`DeviceMsg::Event::index`) and
//! delivered over the acknowledged link, so none is lost; the number lets the host drop the
//! duplicates a reconnection can cause.

use heapless::{String, Vec};
use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::config::Xy;
use crate::sequence::{AxisRef, BufferStatus};
use crate::{LOG_TEXT_LEN, MAX_FILTER_WHEELS, MAX_GALVOS, MAX_STEPPERS};

/// The rig's state at the tick a camera trigger fired.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Snapshot {
    /// Each galvo pair's position, by index.
    #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
    pub galvos: Vec<Xy, MAX_GALVOS>,
    /// Each stepper axis' position in steps, by index.
    #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
    pub axes: Vec<i32, MAX_STEPPERS>,
    /// Each filter wheel's slot, by index (`None` while moving or not homed).
    #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
    pub filters: Vec<Option<u8>, MAX_FILTER_WHEELS>,
    /// Lasers emitting, one bit per channel.
    pub lasers: u8,
}

/// A camera trigger fired.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct TriggerEvent {
    /// Sequence the trigger item belongs to.
    pub sequence: u32,
    /// Index of the trigger item within the sequence, from 0.
    pub item: u32,
    /// Count of triggers on this camera since the sequence started, from 0: the frame number
    /// the camera should have produced.
    pub frame: u32,
    /// Camera output.
    pub camera: u8,
    /// Tick of the leading edge.
    pub tick: u64,
    /// Pulse width in ticks.
    pub width: u32,
    /// The rig at that tick.
    pub snapshot: Snapshot,
}

/// Which switch an axis hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Switch {
    /// Limit at the negative end.
    Min,
    /// Limit at the positive end.
    Max,
    /// Index / home sensor.
    Index,
}

/// Why the device entered the safe state. Latched until `ClearFault`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum FaultCause {
    /// No heartbeat from the host within the configured timeout.
    HeartbeatLost,
    /// The host sent `EmergencyStop`.
    EmergencyStop,
    /// A laser interlock input went inactive.
    Interlock {
        /// Laser channel.
        channel: u8,
    },
    /// A laser stayed on longer than its `max_on_ticks`.
    LaserOnTime {
        /// Laser channel.
        channel: u8,
    },
    /// An axis hit a limit switch outside homing, or was asked past a soft limit.
    Limit {
        /// The axis.
        axis: AxisRef,
    },
    /// Homing did not find its switch.
    HomingFailed {
        /// The axis.
        axis: AxisRef,
    },
    /// The sequence buffer ran dry before the last chunk.
    Underrun {
        /// Sequence id.
        sequence: u32,
    },
    /// A `Wait` item's condition did not hold within its timeout.
    WaitTimeout {
        /// Sequence id.
        sequence: u32,
        /// Item index.
        item: u32,
    },
    /// An item came due later than the device could execute it exactly.
    Late {
        /// Sequence id.
        sequence: u32,
        /// Item index.
        item: u32,
    },
    /// A motor could not run its move: the driver reported an error, or the move could not be
    /// planned (too long for the device's tick arithmetic).
    Driver {
        /// The axis.
        axis: AxisRef,
    },
    /// The event queue to the host overflowed: the host stopped acknowledging.
    EventOverflow,
    /// A sequence item asked an axis to move while it was still moving.
    AxisBusy {
        /// The axis.
        axis: AxisRef,
    },
    /// A trigger came sooner after the previous one than the camera's `min_interval_ticks`
    /// (or while the previous pulse was still high).
    TriggerTooSoon {
        /// Camera.
        camera: u8,
    },
    /// A galvo output reported an error (converter or bus).
    GalvoOutput {
        /// Galvo pair.
        galvo: u8,
    },
}

/// The controller's overall state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum DeviceState {
    /// Waiting for a matching `Hello` (at start, or after the host reconnected); a latched
    /// fault is reported instead.
    AwaitingHello,
    /// Ready for configuration, commands and sequences.
    Ready,
    /// Executing a sequence.
    Running {
        /// Sequence id.
        sequence: u32,
    },
    /// In the safe state with a latched fault.
    Faulted(FaultCause),
}

/// Severity of a log line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum LogLevel {
    /// Something failed.
    Error,
    /// Something is off.
    Warn,
    /// Normal operation.
    Info,
    /// Detail for developers.
    Debug,
}

/// Something the device reports unasked.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Event {
    /// A camera trigger fired.
    Trigger(TriggerEvent),
    /// The camera's exposure-active input changed.
    Exposure {
        /// Camera.
        camera: u8,
        /// The input is now active.
        active: bool,
        /// Tick of the edge.
        tick: u64,
    },
    /// An axis reached its target.
    MoveDone {
        /// The axis.
        axis: AxisRef,
        /// Position reached, steps (slot for a filter wheel).
        position: i32,
        /// Tick of the last step.
        tick: u64,
    },
    /// An axis finished homing.
    Homed {
        /// The axis.
        axis: AxisRef,
        /// Position assigned.
        position: i32,
        /// Tick.
        tick: u64,
    },
    /// An axis hit a switch.
    Switch {
        /// The axis.
        axis: AxisRef,
        /// Which switch.
        switch: Switch,
        /// Position when it triggered.
        position: i32,
        /// Tick.
        tick: u64,
    },
    /// A laser finished warming up.
    LaserReady {
        /// Channel.
        channel: u8,
        /// Tick.
        tick: u64,
    },
    /// A `Marker` item was reached.
    Marker {
        /// Sequence id.
        sequence: u32,
        /// Item index.
        item: u32,
        /// Marker id.
        id: u32,
        /// Tick.
        tick: u64,
    },
    /// The sequence buffer changed (flow-control credit).
    Buffer(BufferStatus),
    /// The buffer ran dry before the last chunk; the device is now in the safe state.
    Underrun {
        /// Sequence id.
        sequence: u32,
        /// Index of the first item that was not there in time.
        item: u32,
        /// Tick at which the device found the buffer empty: when the item before it ran.
        tick: u64,
    },
    /// A sequence executed its last item.
    SequenceDone {
        /// Sequence id.
        sequence: u32,
        /// Items executed.
        items: u32,
        /// Tick of the last item.
        tick: u64,
    },
    /// The device entered the safe state.
    Fault {
        /// Why.
        cause: FaultCause,
        /// Tick.
        tick: u64,
    },
    /// The device state changed (arming, fault cleared, sequence started).
    State {
        /// New state.
        state: DeviceState,
        /// Armed lasers, one bit per channel.
        armed: u8,
        /// Tick.
        tick: u64,
    },
    /// A log line.
    Log {
        /// Severity.
        level: LogLevel,
        /// Tick.
        tick: u64,
        /// Text, truncated to [`LOG_TEXT_LEN`] bytes.
        #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::string))]
        text: String<LOG_TEXT_LEN>,
    },
}
