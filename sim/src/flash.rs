//! The virtual board's flash: embassy-boot's three partitions in memory, a factory image in
//! the active one, and the board's update key.
//!
//! The virtual board trusts a development key whose secret is public ([`VIRTUAL_SECRET`],
//! `lightrig flash sign --virtual`): anyone can sign an image for the virtual rig, as a lab
//! signs its own board's images with the key `lightrig flash keygen` made for it.

use ed25519_dalek::SigningKey;
use lightrig_firmware::boot::BootSlots;
use lightrig_firmware::hal::FirmwareSlots;
use lightrig_firmware::sim::{SimFlash, SimSlots};
use lightrig_host::flash::Image;
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::ImageInfo;
use lightrig_protocol::SCHEMA_HASH;

/// Bytes of the active slot: the largest virtual image (the update slot is a page larger).
pub const ACTIVE_LEN: usize = 64 * 1024;

/// The virtual board's development signing key: public on purpose (never use it for a real
/// board).
pub const VIRTUAL_SECRET: [u8; 32] = *b"lightrig virtual board, dev key.";

/// The key that signs images for the virtual board.
pub fn virtual_key() -> SigningKey {
    SigningKey::from_bytes(&VIRTUAL_SECRET)
}

/// Stand-in code for a virtual firmware image of `version` (what a build would produce).
pub fn virtual_code(version: Version, len: usize) -> Vec<u8> {
    let seed = u32::from(version.major) << 16 ^ u32::from(version.minor) << 8 ^ u32::from(version.patch);
    (0..len as u32).map(|k| (k.wrapping_mul(2_654_435_761) ^ seed).to_le_bytes()[1]).collect()
}

/// A signed virtual image of `version`.
pub fn virtual_image(version: Version) -> Image {
    Image::sign(&virtual_code(version, 12_000), BoardId::Virtual, version, SCHEMA_HASH, &virtual_key())
}

/// Flash as a probe leaves it: `version`'s image in the active slot, the others erased.
pub fn factory(version: Version) -> SimSlots {
    let active = SimFlash::new(ACTIVE_LEN);
    let dfu = active.on_same_chip(ACTIVE_LEN + 2048);
    let state = active.on_same_chip(2048);
    active.program(0, &virtual_image(version).signed);
    SimSlots(BootSlots::new(active, dfu, state, lightrig_firmware::boards::DEVELOPMENT_PUBLIC_KEY))
}

/// What the active slot holds.
pub fn running(slots: &mut SimSlots) -> Option<ImageInfo> {
    let len = slots.0.active_len();
    ImageInfo::find(len, |at, buf| slots.0.read_active(at, buf).is_ok())
}
