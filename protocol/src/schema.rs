//! The schema hash: a 64-bit fingerprint of every type on the wire, computed at compile time.
//!
//! It covers the structure of [`HostMsg`], [`DeviceMsg`] and the link [`Header`] (every field
//! and variant name, order and type, via `postcard-schema`), plus the protocol constants that
//! bound their sizes and values. Renaming a field, reordering variants, changing a type or a capacity all
//! change it; comments and code outside the types do not. Host and device exchange it in the
//! handshake and refuse to talk on a mismatch.

use postcard_schema::key::Key;

use crate::link::Header;
use crate::message::{DeviceMsg, HostMsg};

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;

const fn fnv1a(mut state: u64, bytes: &[u8]) -> u64 {
    let mut i = 0;
    while i < bytes.len() {
        state ^= bytes[i] as u64;
        state = state.wrapping_mul(FNV_PRIME);
        i += 1;
    }
    state
}

const fn fold_key(state: u64, key: Key) -> u64 {
    fnv1a(state, &key.to_bytes())
}

const fn fold_u32(state: u64, value: u32) -> u64 {
    fnv1a(state, &value.to_le_bytes())
}

/// Sizes and validation limits that change what a peer accepts even when the type structure
/// does not.
const LIMITS: [usize; 24] = [
    crate::MAX_PACKET,
    crate::MAX_GALVOS,
    crate::MAX_LASERS,
    crate::MAX_STEPPERS,
    crate::MAX_FILTER_WHEELS,
    crate::MAX_FILTER_SLOTS as usize,
    crate::MAX_VOICE_COILS,
    crate::MAX_PARTIALS,
    crate::MAX_CAMERAS,
    crate::MAX_CHUNK_ITEMS,
    crate::LOG_TEXT_LEN,
    crate::link::SEQ_WINDOW_MAX as usize,
    crate::PROTOCOL_VERSION as usize,
    crate::config::MAX_STEP_RATE as usize,
    crate::config::SAMPLE_RATE_RANGE.0 as usize,
    crate::config::SAMPLE_RATE_RANGE.1 as usize,
    crate::config::WAVELENGTH_RANGE.0 as usize,
    crate::config::WAVELENGTH_RANGE.1 as usize,
    crate::config::HEARTBEAT_RANGE_MS.0 as usize,
    crate::config::HEARTBEAT_RANGE_MS.1 as usize,
    crate::config::DacKind::McuDac.max_code() as usize,
    crate::config::DacKind::Dac8563.max_code() as usize,
    crate::update::UPDATE_CHUNK,
    crate::update::TRAILER_LEN,
];

const fn compute() -> u64 {
    let mut h = FNV_OFFSET;
    h = fold_key(h, Key::for_path::<Header>("lightrig/link"));
    h = fold_key(h, Key::for_path::<HostMsg>("lightrig/host"));
    h = fold_key(h, Key::for_path::<DeviceMsg>("lightrig/device"));
    // Bodies of link control frames: Sync, SyncAck, Confirm and Nak.
    h = fold_key(h, Key::for_path::<u32>("lightrig/link/sync-nonce"));
    h = fold_key(h, Key::for_path::<crate::link::SyncAckBody>("lightrig/link/sync-ack"));
    h = fold_key(h, Key::for_path::<u32>("lightrig/link/confirm"));
    h = fold_key(h, Key::for_path::<crate::frame::FrameError>("lightrig/link/nak"));
    let mut i = 0;
    while i < LIMITS.len() {
        h = fold_u32(h, LIMITS[i] as u32);
        i += 1;
    }
    h
}

/// The schema hash of this build's protocol.
pub const SCHEMA_HASH: u64 = compute();
