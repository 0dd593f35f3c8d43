//! Firmware update over the link: what an image says about itself, the commands that carry it
//! to the device, and the device's answer.
//!
//! An image is the firmware's code, padded with `0xFF` to a multiple of [`TRAILER_LEN`], then
//! a trailer ([`ImageInfo::trailer`]: [`TRAILER_MAGIC`] and the image's board, version, schema
//! hash and code length). The signature (ed25519 over the SHA-512 of code, padding and
//! trailer, as `embassy-boot` verifies it) covers the trailer, so the claims about board and
//! version are signed too. The host announces the trailer with [`UpdateCommand::Begin`] (the
//! device refuses an image for another board before a byte is written), writes the signed
//! bytes in order with [`UpdateCommand::Write`], and ends with [`UpdateCommand::Finish`]: the
//! device checks that the trailer it stored is the one announced, verifies the signature and
//! marks the image for the bootloader, which swaps it in at the next reset. The new firmware
//! must be confirmed ([`UpdateCommand::Confirm`]) before the next reset, else the bootloader
//! swaps the old one back.
//!
//! A host of any protocol version must be able to update a device: the update path's encoding
//! is frozen (`docs/protocol.md`, "Firmware update"), and a device accepts it after a `Hello`
//! whose version or schema hash it refused.

use heapless::Vec as HVec;
use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::session::{BoardId, Version};

/// Bytes of an image per [`UpdateCommand::Write`]; every chunk but the last is this long.
pub const UPDATE_CHUNK: usize = 256;

/// Length of the trailer, and the alignment of the code before it.
pub const TRAILER_LEN: usize = 64;

/// How a trailer begins.
pub const TRAILER_MAGIC: [u8; 8] = *b"LRIGIMG1";

/// What an image says about itself (its trailer).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct ImageInfo {
    /// The board the image was built for.
    pub board: BoardId,
    /// Its firmware version.
    pub version: Version,
    /// Its [`crate::SCHEMA_HASH`].
    pub schema_hash: u64,
    /// Bytes of code before the padding and the trailer.
    pub code_len: u32,
}

impl ImageInfo {
    /// Where the trailer starts: the code's length rounded up to [`TRAILER_LEN`].
    pub const fn trailer_at(&self) -> u32 {
        self.code_len.div_ceil(TRAILER_LEN as u32).saturating_mul(TRAILER_LEN as u32)
    }

    /// Bytes the signature covers and the host writes: code, padding, trailer.
    pub const fn signed_len(&self) -> u32 {
        self.trailer_at().saturating_add(TRAILER_LEN as u32)
    }

    /// The trailer: [`TRAILER_MAGIC`], then the info in postcard, zero-padded.
    pub fn trailer(&self) -> [u8; TRAILER_LEN] {
        let mut out = [0u8; TRAILER_LEN];
        out[..8].copy_from_slice(&TRAILER_MAGIC);
        // At most 1 + 3·3 + 10 + 5 bytes: always fits.
        let _ = postcard::to_slice(self, &mut out[8..]);
        out
    }

    /// The info in a trailer; `None` if `bytes` is no trailer.
    pub fn from_trailer(bytes: &[u8]) -> Option<ImageInfo> {
        if bytes.len() < TRAILER_LEN || bytes[..8] != TRAILER_MAGIC {
            return None;
        }
        postcard::from_bytes(&bytes[8..TRAILER_LEN]).ok()
    }

    /// The first trailer in a slot of `len` bytes, scanning [`TRAILER_LEN`]-aligned offsets
    /// from the start: the image the slot holds (bytes after its trailer may be an older,
    /// longer image's). `read(offset, buf)` reads the slot; a failed read ends the scan.
    pub fn find(len: u32, mut read: impl FnMut(u32, &mut [u8]) -> bool) -> Option<ImageInfo> {
        let mut buf = [0u8; TRAILER_LEN];
        let mut at = 0u32;
        while at.saturating_add(TRAILER_LEN as u32) <= len {
            if !read(at, &mut buf[..8]) {
                return None;
            }
            if buf[..8] == TRAILER_MAGIC {
                if !read(at, &mut buf) {
                    return None;
                }
                if let Some(info) = ImageInfo::from_trailer(&buf) {
                    if info.trailer_at() == at {
                        return Some(info);
                    }
                }
            }
            at += TRAILER_LEN as u32;
        }
        None
    }
}

/// An ed25519 signature, in two halves (serde's arrays stop at 32).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Signature {
    /// Bytes 0..32.
    pub r: [u8; 32],
    /// Bytes 32..64.
    pub s: [u8; 32],
}

impl Signature {
    /// From the 64 bytes of a signature.
    pub fn from_bytes(b: &[u8; 64]) -> Signature {
        let mut r = [0; 32];
        let mut s = [0; 32];
        r.copy_from_slice(&b[..32]);
        s.copy_from_slice(&b[32..]);
        Signature { r, s }
    }

    /// The 64 bytes.
    pub fn to_bytes(&self) -> [u8; 64] {
        let mut out = [0; 64];
        out[..32].copy_from_slice(&self.r);
        out[32..].copy_from_slice(&self.s);
        out
    }
}

/// The update commands (`Command::Update`). Each is answered with `Reply::Update`.
// A chunk is carried inline, as the other commands' payloads are (no allocation).
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum UpdateCommand {
    /// Where the update stands, and the versions in the slots.
    Status,
    /// Start receiving this image (or go on with it: the same image already begun keeps what
    /// was received, so a transfer cut by an unplug resumes). Refused while a sequence runs;
    /// lasers are disarmed, and nothing that moves or lights is accepted until the device
    /// resets or the update is cancelled.
    Begin(ImageInfo),
    /// Signed bytes at `offset`, which must be where the device stands (`received`); a chunk
    /// the device already has (a retransmission after a lost answer) is acknowledged as is.
    Write {
        /// Offset in the image.
        offset: u32,
        /// The bytes: [`UPDATE_CHUNK`] of them, fewer only at the image's end.
        #[cfg_attr(feature = "arbitrary", arbitrary(with = crate::arb::vec))]
        data: HVec<u8, UPDATE_CHUNK>,
    },
    /// Every byte sent: verify the trailer and the signature, mark the image to be swapped in
    /// at the next reset.
    Finish(Signature),
    /// Give up the update begun (the device accepts everything again).
    Cancel,
    /// The new firmware works: keep it (else the bootloader swaps the old one back at the next
    /// reset).
    Confirm,
}

/// Where an update stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum UpdatePhase {
    /// No update under way; the running firmware is confirmed.
    Idle,
    /// Receiving an image.
    Receiving {
        /// The image.
        image: ImageInfo,
        /// Bytes received, from the image's start.
        received: u32,
    },
    /// Verified and marked: swapped in at the next reset.
    Ready {
        /// The image.
        image: ImageInfo,
    },
    /// The running firmware was just swapped in and is not confirmed: the bootloader swaps
    /// the old one back at the next reset unless the host sends `Confirm`.
    Unconfirmed,
}

/// The answer to every update command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct UpdateStatus {
    /// Where the update stands.
    pub phase: UpdatePhase,
    /// The running image's trailer, if it has one (a board flashed without the bootloader
    /// has none).
    pub running: Option<ImageInfo>,
    /// The image the bootloader would swap back to (the one before the last update), if any.
    pub fallback: Option<ImageInfo>,
    /// The largest image the update slot takes, bytes (0: this board cannot be updated over
    /// the link).
    pub slot: u32,
}

/// Why an update command was refused (`Error::Update`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum UpdateError {
    /// This board has no update slot (flash it through its debug probe).
    Unsupported,
    /// The image was built for another board.
    WrongBoard {
        /// The image's board.
        image: BoardId,
        /// This device's.
        device: BoardId,
    },
    /// The image does not fit the slot.
    TooLarge {
        /// Signed bytes of the image.
        image: u32,
        /// The slot's size.
        slot: u32,
    },
    /// `Write`, `Finish` or `Cancel` without a `Begin` of this image.
    NotBegun,
    /// A `Write` at another offset than the device's, or longer than the image.
    OutOfOrder {
        /// Where the device stands.
        expected: u32,
    },
    /// `Finish` before every byte arrived.
    Incomplete {
        /// Bytes received.
        received: u32,
    },
    /// The stored trailer is not the one announced with `Begin`.
    TrailerMismatch,
    /// The signature does not match the image and the device's public key.
    BadSignature,
    /// The running firmware is not confirmed yet: `Confirm` it before the next update.
    Unconfirmed,
    /// `Confirm` with nothing to confirm.
    NothingToConfirm,
    /// An update is under way: nothing that moves or lights until it is finished or
    /// cancelled.
    InProgress,
    /// The flash refused a read, write or erase.
    Flash,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(code_len: u32) -> ImageInfo {
        ImageInfo {
            board: BoardId::NucleoG474re,
            version: Version { major: 1, minor: 2, patch: 3 },
            schema_hash: 0x0123_4567_89ab_cdef,
            code_len,
        }
    }

    #[test]
    fn the_trailer_follows_the_code_at_a_64_byte_boundary_and_reads_back() {
        assert_eq!((info(0).trailer_at(), info(1).trailer_at(), info(64).trailer_at()), (0, 64, 64));
        assert_eq!(info(65).signed_len(), 192);
        let t = info(1000).trailer();
        assert_eq!(&t[..8], b"LRIGIMG1");
        assert_eq!(ImageInfo::from_trailer(&t), Some(info(1000)));
        let mut bad = t;
        bad[0] ^= 1;
        assert_eq!(ImageInfo::from_trailer(&bad), None);
        assert_eq!(ImageInfo::from_trailer(&t[..63]), None);
    }

    #[test]
    fn find_takes_the_first_trailer_where_its_own_code_length_puts_it() {
        // A slot: a 100-byte image (trailer at 128), then the rest of an older, longer image
        // (its trailer at 512).
        let mut slot = [0xFFu8; 1024];
        slot[128..192].copy_from_slice(&info(100).trailer());
        slot[512..576].copy_from_slice(&info(500).trailer());
        let read = |at: u32, buf: &mut [u8]| {
            let at = at as usize;
            buf.copy_from_slice(&slot[at..at + buf.len()]);
            true
        };
        assert_eq!(ImageInfo::find(1024, read), Some(info(100)));
        // Magic where the code length does not put the trailer: not a trailer (code that
        // happens to hold the magic).
        let mut odd = [0xFFu8; 256];
        odd[64..128].copy_from_slice(&info(300).trailer());
        let read = |at: u32, buf: &mut [u8]| {
            let at = at as usize;
            buf.copy_from_slice(&odd[at..at + buf.len()]);
            true
        };
        assert_eq!(ImageInfo::find(256, read), None);
        assert_eq!(ImageInfo::find(1024, |_, _| false), None);
    }

    #[test]
    fn a_signature_round_trips_through_its_halves() {
        let b: [u8; 64] = core::array::from_fn(|i| i as u8);
        assert_eq!(Signature::from_bytes(&b).to_bytes(), b);
    }
}
