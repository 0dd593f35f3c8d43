//! Handshake: what a device says about itself when the host says `Hello`.

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

/// A semantic version, as carried on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Version {
    /// Incompatible changes.
    pub major: u16,
    /// Compatible additions.
    pub minor: u16,
    /// Fixes.
    pub patch: u16,
}

/// Which board the firmware runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum BoardId {
    /// The firmware logic on the host with simulated peripherals (the virtual rig).
    Virtual,
    /// The QEMU `mps2-an386` (Cortex-M4) emulated board.
    QemuMps2An386,
    /// ST NUCLEO-G474RE, the reference board.
    NucleoG474re,
    /// A board this protocol version has no name for, with a vendor-chosen number.
    Other(u16),
}

/// Why the device last started; a reset after a panic or watchdog is worth a look.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum ResetCause {
    /// Power applied.
    PowerOn,
    /// Reset pin or debugger.
    External,
    /// The watchdog fired.
    Watchdog,
    /// The firmware panicked and reset itself (lasers were forced off first).
    Panic,
    /// Requested by software.
    Software,
    /// The hardware did not say.
    Unknown,
}

/// How many of each peripheral the device drives, and how deep its buffers are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Capabilities {
    /// Galvo pairs (each has an X and a Y axis).
    pub galvos: u8,
    /// Laser channels.
    pub lasers: u8,
    /// Stepper axes, filter wheels not included.
    pub steppers: u8,
    /// Filter wheels.
    pub filter_wheels: u8,
    /// Voice-coil synthesis channels.
    pub voice_coils: u8,
    /// Sine partials per voice-coil channel.
    pub partials_per_coil: u8,
    /// Camera trigger outputs.
    pub cameras: u8,
    /// Sequence items the device buffers ahead of execution (the flow-control credit).
    pub sequence_buffer: u16,
    /// Events the device holds while waiting for the host to acknowledge them.
    pub event_queue: u16,
    /// Link window: frames in flight per direction before an acknowledgement.
    pub link_window: u8,
    /// Largest packet the device accepts (see [`crate::MAX_PACKET`]).
    pub max_packet: u16,
}

/// The device's answer to `Hello`.
///
/// The first two fields are frozen across protocol versions so that a host of any version can
/// read them and explain a mismatch (see `docs/protocol.md`, "Handshake").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct DeviceInfo {
    /// The device's [`crate::PROTOCOL_VERSION`].
    pub protocol_version: u16,
    /// The device's [`crate::SCHEMA_HASH`].
    pub schema_hash: u64,
    /// Firmware version.
    pub firmware: Version,
    /// Board the firmware was built for.
    pub board: BoardId,
    /// Unique id of this board (e.g. the MCU's UID folded to 64 bits).
    pub serial: u64,
    /// Device tick rate in Hz: every time on the wire is in these ticks.
    pub tick_hz: u32,
    /// Why the device last started.
    pub reset_cause: ResetCause,
    /// Differs at every start (random or a persistent counter). With `DeviceMsg::Event::index`,
    /// which restarts at 0, it identifies an event uniquely across device restarts.
    pub boot_id: u32,
    /// What the device drives.
    pub capabilities: Capabilities,
}
