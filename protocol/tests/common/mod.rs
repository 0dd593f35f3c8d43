//! Shared by the protocol's integration tests.

use lightrig_protocol::session::*;
use lightrig_protocol::{MAX_PACKET, PROTOCOL_VERSION, SCHEMA_HASH};

/// A virtual-rig device as it answers `Hello`.
pub fn device_info() -> DeviceInfo {
    DeviceInfo {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
        firmware: Version { major: 0, minor: 1, patch: 0 },
        board: BoardId::Virtual,
        serial: 0x1234_5678_9abc_def0,
        tick_hz: 1_000_000,
        reset_cause: ResetCause::PowerOn,
        boot_id: 0x5eed_0001,
        capabilities: Capabilities {
            galvos: 1,
            lasers: 3,
            steppers: 2,
            filter_wheels: 1,
            voice_coils: 2,
            partials_per_coil: 8,
            cameras: 1,
            sequence_buffer: 256,
            event_queue: 64,
            link_window: 8,
            max_packet: MAX_PACKET as u16,
        },
    }
}
