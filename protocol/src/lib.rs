//! The lightrig wire protocol: every message the host and the rig controller exchange, the
//! frame format that carries them, and the reliable link that delivers them exactly once.
//!
//! Layers, bottom up (see `docs/protocol.md` for the byte-level specification):
//!
//! 1. [`frame`]: a frame is `COBS(packet ‖ CRC-32) 0x00`. The [`frame::FrameDecoder`] turns any
//!    byte stream into checked packets, resynchronising on the next zero byte and counting every
//!    rejected frame by reason.
//! 2. [`link`]: a packet is a [`link::Header`] (kind, epoch, sequence number, cumulative ack)
//!    followed by a postcard-encoded message. [`link::Link`] adds sequence numbers,
//!    acknowledgements, retransmission with a window and duplicate suppression, in *both*
//!    directions: a trigger event from the device is acknowledged like a host command.
//! 3. [`message`]: [`HostMsg`] (a request with an id) and [`DeviceMsg`] (a response carrying
//!    `Result<Reply, Error>`, or an event), serialized with postcard.
//!
//! The crate is `no_std`, allocation-free and contains no `unsafe`. Decoding never panics: every
//! malformed input becomes a typed error.
#![no_std]
#![forbid(unsafe_code)]
#![deny(missing_docs)]

#[cfg(any(test, feature = "std", feature = "arbitrary"))]
extern crate std;

#[cfg(feature = "arbitrary")]
pub mod arb;
pub mod config;
pub mod error;
pub mod event;
pub mod frame;
pub mod link;
pub mod message;
pub mod schema;
pub mod sequence;
pub mod session;
pub mod update;

pub use config::{ConfigError, ConfigField, ConfigItem, InvalidReason};
pub use error::Error;
pub use event::Event;
pub use message::{Command, DeviceMsg, HostMsg, Reply};
pub use schema::SCHEMA_HASH;

/// Version of the wire protocol. Bumped by hand on any change a peer must know about; the
/// [`SCHEMA_HASH`] catches the changes a human forgets.
pub const PROTOCOL_VERSION: u16 = 1;

/// Largest packet (link header, message and CRC, before COBS) either side may send.
pub const MAX_PACKET: usize = 504;
/// Largest COBS-encoded frame, without its zero delimiter.
pub const MAX_ENCODED: usize = cobs::max_encoding_length(MAX_PACKET);
/// Largest frame on the wire, zero delimiter included.
pub const MAX_FRAME: usize = MAX_ENCODED + 1;

/// Most galvo pairs (X/Y) a device can report.
pub const MAX_GALVOS: usize = 2;
/// Most laser channels; laser sets are carried as a `u8` bit mask.
pub const MAX_LASERS: usize = 8;
/// Most stepper axes (turntable, gantry, ...), filter wheels not included.
pub const MAX_STEPPERS: usize = 4;
/// Most filter wheels.
pub const MAX_FILTER_WHEELS: usize = 2;
/// Most positions on one filter wheel.
pub const MAX_FILTER_SLOTS: u8 = 32;
/// Most voice-coil synthesis channels.
pub const MAX_VOICE_COILS: usize = 4;
/// Most sine partials per voice-coil channel.
pub const MAX_PARTIALS: usize = 8;
/// Most camera trigger outputs.
pub const MAX_CAMERAS: usize = 4;
/// Most sequence items in one chunk (the packet size limit may allow fewer).
pub const MAX_CHUNK_ITEMS: usize = 32;
/// Longest log line text, in bytes of UTF-8.
pub const LOG_TEXT_LEN: usize = 80;

// The protocol's arrays must fit the masks and indices that carry them.
const _: () = assert!(MAX_LASERS <= 8);
const _: () = assert!(MAX_FRAME <= 512);
