//! The one error type every response carries.

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::config::ConfigError;
use crate::event::{DeviceState, FaultCause};
use crate::sequence::AxisRef;
use crate::update::UpdateError;

/// A kind of peripheral, for errors that name one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Peripheral {
    /// Galvo pair.
    Galvo,
    /// Laser channel.
    Laser,
    /// Stepper axis.
    Stepper,
    /// Filter wheel.
    FilterWheel,
    /// Voice-coil channel.
    VoiceCoil,
    /// Camera trigger.
    Camera,
}

/// Why a command was refused. Every `Response` carries `Result<Reply, Error>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Error {
    /// The host must send a matching `Hello` first.
    HandshakeRequired,
    /// The host speaks another protocol version.
    VersionMismatch {
        /// The device's version.
        device: u16,
        /// The version the host sent.
        host: u16,
    },
    /// The host's message types differ from the device's.
    SchemaMismatch {
        /// The device's schema hash.
        device: u64,
        /// The hash the host sent.
        host: u64,
    },
    /// A configuration field was refused.
    InvalidConfig(ConfigError),
    /// The command names a peripheral the device does not have.
    NoSuchPeripheral {
        /// Kind of peripheral.
        kind: Peripheral,
        /// Index named.
        index: u8,
        /// How many the device has.
        count: u8,
    },
    /// The command uses a peripheral that has not been configured.
    NotConfigured {
        /// Kind of peripheral.
        kind: Peripheral,
        /// Index.
        index: u8,
    },
    /// A value in a command or item lies outside what the configuration allows.
    OutOfRange {
        /// Kind of peripheral concerned.
        kind: Peripheral,
        /// Its index.
        index: u8,
    },
    /// The command is not allowed in the current state.
    InvalidState(DeviceState),
    /// A fault is latched; send `ClearFault` first.
    Faulted(FaultCause),
    /// A laser was asked on without being armed.
    NotArmed {
        /// Channel.
        channel: u8,
    },
    /// The chunk holds more items than the buffer has free (credit exceeded).
    BufferFull {
        /// Free slots.
        free: u16,
    },
    /// A chunk arrived out of order or for another sequence.
    ChunkOutOfOrder {
        /// The sequence the device is loading.
        sequence: u32,
        /// The chunk number it expects.
        expected: u32,
    },
    /// No sequence with that id is loaded.
    NoSuchSequence {
        /// The id named.
        sequence: u32,
    },
    /// The firmware does not implement this command on this board.
    Unsupported,
    /// The axis has a homing procedure and has not been homed since it was configured (or its
    /// homing was interrupted): send `Home`.
    NotHomed {
        /// The axis.
        axis: AxisRef,
    },
    /// The axis is still moving (or homing); wait for its `MoveDone` / `Homed`.
    Busy {
        /// The axis.
        axis: AxisRef,
    },
    /// `SequenceStart` named a tick that has already passed.
    StartInPast {
        /// The device tick when the command was processed.
        now: u64,
    },
    /// A firmware update command was refused, or a command was refused because an update is
    /// under way.
    Update(UpdateError),
}
