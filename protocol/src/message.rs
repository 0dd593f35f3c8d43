//! The top-level messages: [`HostMsg`] from host to device, [`DeviceMsg`] back.
//!
//! The host sends requests, each with an id; the device answers each with exactly one
//! `Response` carrying the same id and a `Result<Reply, Error>`. Events flow independently.
//!
//! Variant order is wire format (postcard encodes the variant index). The handshake must stay
//! readable by a peer of any version, so these are frozen: the frame format and link header,
//! `HostMsg.id` first, `Command::Hello` as variant 0 with its two fields, `DeviceMsg::Response`
//! as variant 0 with `id` then `result`, `Ok` = 0, `Reply::Hello` as variant 0, and
//! `DeviceInfo` starting with `protocol_version` and `schema_hash`. A host that cannot decode
//! the answer still reads those two fields (`Delivery::Incompatible`) and can say what to
//! update.

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::config::ConfigItem;
use crate::error::Error;
use crate::event::{DeviceState, Event};
use crate::frame::FrameError;
use crate::link::LinkStats;
use crate::sequence::{Action, AxisRef, BufferStatus, Chunk, StartAt};
use crate::session::DeviceInfo;
use crate::update::{UpdateCommand, UpdateStatus};

/// A request from the host.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct HostMsg {
    /// Request id, echoed in the response; the host picks it (usually a counter).
    pub id: u16,
    /// What to do.
    pub command: Command,
}

/// What the host asks for.
// `SequenceLoad` dominates the size; without an allocator there is nothing to box it into,
// and the device decodes one command at a time.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Command {
    /// Open a session: the device answers `Reply::Hello` with its [`DeviceInfo`], and accepts
    /// other commands only once versions and schema hashes match.
    Hello {
        /// The host's [`crate::PROTOCOL_VERSION`].
        protocol_version: u16,
        /// The host's [`crate::SCHEMA_HASH`].
        schema_hash: u64,
    },
    /// Read the device tick counter (`Reply::Clock`), for host-side clock regression.
    GetClock,
    /// Read the device state and counters (`Reply::Status`).
    GetStatus,
    /// The host is alive. Lapsing heartbeats put the device in the safe state.
    Heartbeat,
    /// Configure one peripheral.
    Configure(ConfigItem),
    /// Allow these lasers (bit mask) to be turned on by sequence items.
    Arm {
        /// One bit per channel.
        lasers: u8,
    },
    /// Turn all lasers off at once and disallow them.
    Disarm,
    /// Safe state at once: lasers off, steppers stop without deceleration, galvos park.
    /// Latched as a fault.
    EmergencyStop,
    /// Clear a latched fault (lasers stay disarmed).
    ClearFault,
    /// Home an axis.
    Home(AxisRef),
    /// Execute one action now, outside any sequence (jog, park, test shot).
    Immediate(Action),
    /// Load a chunk of a sequence (`Reply::Buffer` tells the new credit).
    SequenceLoad(Chunk),
    /// Start a loaded sequence.
    SequenceStart {
        /// Sequence id.
        sequence: u32,
        /// When.
        at: StartAt,
    },
    /// Stop a sequence: lasers off, axes decelerate, galvos park.
    SequenceAbort {
        /// Sequence id.
        sequence: u32,
    },
    /// Firmware update (`Reply::Update`). Its encoding is frozen, like `Hello`'s, and the
    /// device accepts it after a `Hello` it refused for another version or schema, so a host of
    /// any version can update a device of any other (see [`crate::update`]).
    Update(UpdateCommand),
}

/// A successful answer.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Reply {
    /// Answer to `Hello`.
    Hello(DeviceInfo),
    /// Answer to `GetClock`: the tick at which the device processed the request.
    Clock {
        /// Device tick.
        tick: u64,
    },
    /// Answer to `GetStatus`.
    Status(Status),
    /// The command was carried out.
    Done,
    /// Answer to `SequenceLoad`: the buffer after the chunk was accepted.
    Buffer(BufferStatus),
    /// Answer to `Update`: where the update stands.
    Update(UpdateStatus),
}

/// The device's state and counters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Status {
    /// Overall state.
    pub state: DeviceState,
    /// Armed lasers, one bit per channel.
    pub armed: u8,
    /// Lasers emitting, one bit per channel.
    pub lasers_on: u8,
    /// Device tick when the status was taken.
    pub tick: u64,
    /// Sequence buffer, if a sequence is loaded.
    pub buffer: Option<BufferStatus>,
    /// Messages (responses and events) the device holds until the host acknowledges them.
    pub unacked: u16,
    /// The device's link counters (frames received, rejected by reason, retransmitted).
    pub link: LinkStats,
}

/// A message from the device.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum DeviceMsg {
    /// Answer to the request with the same id.
    Response {
        /// The request's id.
        id: u16,
        /// The outcome.
        result: Result<Reply, Error>,
    },
    /// Something happened.
    Event {
        /// Event number, from 0 at device start, +1 per event; survives reconnections.
        index: u32,
        /// What.
        event: Event,
    },
    /// A sequenced frame from the host arrived intact (CRC good) but its message could not
    /// be decoded. It was acknowledged, so the host must not retransmit it.
    Rejected {
        /// Link sequence number of the rejected frame.
        seq: u16,
        /// Why.
        reason: FrameError,
    },
}

/// A message type the link can carry.
pub trait Message: Serialize + for<'de> Deserialize<'de> + Schema + Clone + core::fmt::Debug {
    /// Whether the encoded message starts with a type tag this build knows. Used to tell an
    /// unknown message type (a newer peer) from a damaged payload.
    fn known_tag(bytes: &[u8]) -> bool;

    /// Whether the encoded message carries a whole type tag this build does not know (a newer
    /// peer's message type). A body too short to hold its tag is damaged, not unknown.
    fn unknown_tag(bytes: &[u8]) -> bool;

    /// If an undecodable message starts like the answer to `Hello`, the peer's protocol
    /// version and schema hash, read from the frozen prefix (see the module docs).
    fn handshake_prefix(_bytes: &[u8]) -> Option<(u16, u64)> {
        None
    }
}

/// The frozen start of `Response { id, result: Ok(Reply::Hello(DeviceInfo { protocol_version,
/// schema_hash, .. })) }`, readable whatever follows.
#[derive(Deserialize)]
struct HelloAnswerPrefix {
    variant: u32,
    _id: u16,
    ok: u32,
    reply: u32,
    protocol_version: u16,
    schema_hash: u64,
}

/// Reads one postcard varint from the front of `bytes`: (value, bytes used).
pub(crate) fn read_varint(bytes: &[u8]) -> Option<(u32, usize)> {
    let mut value: u32 = 0;
    for (i, &b) in bytes.iter().enumerate().take(5) {
        value |= u32::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Some((value, i + 1));
        }
    }
    None
}

/// Number of variants of an enum schema (0 for anything else).
pub(crate) const fn variant_count(ty: &postcard_schema::schema::NamedType) -> u32 {
    match ty.ty {
        postcard_schema::schema::DataModelType::Enum(v) => v.len() as u32,
        _ => 0,
    }
}

/// Number of [`Command`] variants.
pub const COMMAND_COUNT: u32 = variant_count(Command::SCHEMA);
/// Number of [`DeviceMsg`] variants.
pub const DEVICE_MSG_COUNT: u32 = variant_count(DeviceMsg::SCHEMA);

impl Message for HostMsg {
    fn known_tag(bytes: &[u8]) -> bool {
        // `id` (varint), then the command's variant index.
        match read_varint(bytes) {
            Some((_, n)) => matches!(read_varint(&bytes[n..]), Some((tag, _)) if tag < COMMAND_COUNT),
            None => false,
        }
    }

    fn unknown_tag(bytes: &[u8]) -> bool {
        match read_varint(bytes) {
            Some((_, n)) => matches!(read_varint(&bytes[n..]), Some((tag, _)) if tag >= COMMAND_COUNT),
            None => false,
        }
    }
}

impl Message for DeviceMsg {
    fn known_tag(bytes: &[u8]) -> bool {
        matches!(read_varint(bytes), Some((tag, _)) if tag < DEVICE_MSG_COUNT)
    }

    fn unknown_tag(bytes: &[u8]) -> bool {
        matches!(read_varint(bytes), Some((tag, _)) if tag >= DEVICE_MSG_COUNT)
    }

    fn handshake_prefix(bytes: &[u8]) -> Option<(u16, u64)> {
        let (p, _) = postcard::take_from_bytes::<HelloAnswerPrefix>(bytes).ok()?;
        (p.variant == 0 && p.ok == 0 && p.reply == 0).then_some((p.protocol_version, p.schema_hash))
    }
}
