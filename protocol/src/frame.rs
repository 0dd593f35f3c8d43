//! Framing: `frame = COBS(packet ‖ CRC-32(packet) as u32 LE) ‖ 0x00`.
//!
//! The CRC is CRC-32/ISO-HDLC (the zlib/Ethernet CRC: polynomial 0x04C11DB7 reflected,
//! init 0xFFFFFFFF, final xor 0xFFFFFFFF; `crc32("123456789") = 0xCBF43926`).
//! COBS removes every zero byte from the frame so the zero byte can delimit frames: a receiver
//! that joins mid-stream, or loses bytes, resynchronises at the next zero.

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::{MAX_ENCODED, MAX_PACKET};

/// The frame CRC: CRC-32/ISO-HDLC.
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Bytes of CRC at the end of each packet.
pub const CRC_LEN: usize = 4;

/// Why a frame (or the message in it) was rejected. The link counts each reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum FrameError {
    /// The bytes between two delimiters are not valid COBS.
    BadCobs,
    /// The CRC does not match: the frame was damaged.
    BadCrc,
    /// More than [`crate::MAX_ENCODED`] bytes without a delimiter (skipped to the next one),
    /// or a packet longer than [`crate::MAX_PACKET`].
    TooLong,
    /// Too short to hold a header and a CRC.
    TooShort,
    /// Intact, but of a frame kind or message type this build does not know.
    UnknownType,
    /// Intact and of a known type, but the header or message does not decode.
    BadPayload,
}

/// Appends the CRC to `buf[..len]` and COBS-encodes it with its delimiter into `out`.
/// Returns the frame length, or 0 (nothing written) if `len + CRC_LEN` exceeds `MAX_PACKET`.
pub fn seal(buf: &mut [u8; MAX_PACKET], len: usize, out: &mut [u8; crate::MAX_FRAME]) -> usize {
    if len > MAX_PACKET - CRC_LEN {
        return 0;
    }
    let crc = CRC32.checksum(&buf[..len]);
    buf[len..len + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    // Cannot fail: `out` holds the largest encoding of a MAX_PACKET input plus the delimiter.
    let n = cobs::encode(&buf[..len + CRC_LEN], &mut out[..MAX_ENCODED]);
    out[n] = 0;
    n + 1
}

/// Splits a byte stream into checked packets.
///
/// Feed it whatever arrives, in any pieces. It never panics and never reads out of bounds;
/// bytes of an over-long frame are discarded until the next delimiter.
#[derive(Debug)]
pub struct FrameDecoder {
    buf: [u8; MAX_ENCODED],
    len: usize,
    overflow: bool,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self { buf: [0; MAX_ENCODED], len: 0, overflow: false }
    }

    /// Drops a partly received frame (e.g. after the transport reconnects).
    pub fn reset(&mut self) {
        self.len = 0;
        self.overflow = false;
    }

    /// Feeds one byte. When it closes a non-empty frame, returns the packet's length (the
    /// packet, CRC checked and removed, is then [`FrameDecoder::packet`]) or why the frame was
    /// rejected.
    pub fn push(&mut self, byte: u8) -> Option<Result<usize, FrameError>> {
        if byte != 0 {
            if self.len < self.buf.len() {
                self.buf[self.len] = byte;
                self.len += 1;
            } else {
                self.overflow = true;
            }
            return None;
        }
        let (len, overflow) = (self.len, self.overflow);
        self.reset();
        if overflow {
            Some(Err(FrameError::TooLong))
        } else if len > 0 {
            Some(check(&mut self.buf[..len]))
        } else {
            None // an idle delimiter between frames
        }
    }

    /// The packet of the frame [`FrameDecoder::push`] last accepted, `len` bytes long.
    pub fn packet(&self, len: usize) -> &[u8] {
        self.buf.get(..len).unwrap_or(&[])
    }

    /// Feeds bytes, calling `on_frame` with each accepted packet or rejection reason.
    pub fn feed(&mut self, data: &[u8], mut on_frame: impl FnMut(Result<&[u8], FrameError>)) {
        for &byte in data {
            match self.push(byte) {
                Some(Ok(len)) => on_frame(Ok(self.packet(len))),
                Some(Err(e)) => on_frame(Err(e)),
                None => {}
            }
        }
    }
}

/// COBS-decodes a frame in place and checks its CRC; returns the packet length.
fn check(frame: &mut [u8]) -> Result<usize, FrameError> {
    let n = cobs::decode_in_place(frame).map_err(|_| FrameError::BadCobs)?;
    if n > MAX_PACKET {
        return Err(FrameError::TooLong);
    }
    if n < crate::link::HEADER_MIN + CRC_LEN {
        return Err(FrameError::TooShort);
    }
    let (packet, crc) = frame[..n].split_at(n - CRC_LEN);
    let mut le = [0u8; CRC_LEN];
    le.copy_from_slice(crc);
    if CRC32.checksum(packet) != u32::from_le_bytes(le) {
        return Err(FrameError::BadCrc);
    }
    Ok(packet.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::vec::Vec;

    fn frames(data: &[u8]) -> Vec<Result<Vec<u8>, FrameError>> {
        let mut dec = FrameDecoder::new();
        let mut out = Vec::new();
        dec.feed(data, |r| out.push(r.map(|p| p.to_vec())));
        out
    }

    fn sealed(packet: &[u8]) -> Vec<u8> {
        let mut buf = [0u8; MAX_PACKET];
        buf[..packet.len()].copy_from_slice(packet);
        let mut out = [0u8; crate::MAX_FRAME];
        let n = seal(&mut buf, packet.len(), &mut out);
        out[..n].to_vec()
    }

    #[test]
    fn crc_is_the_standard_crc32() {
        assert_eq!(CRC32.checksum(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn seal_exact_bytes() {
        // packet 01 00 02 03: CRC-32 = 0x6EEA5C11? computed below and pinned.
        let f = sealed(&[0x01, 0x00, 0x02, 0x03]);
        let crc = CRC32.checksum(&[0x01, 0x00, 0x02, 0x03]).to_le_bytes();
        // COBS of 01 00 02 03 c0 c1 c2 c3 (no zero in crc here) is 02 01 07 02 03 c0 c1 c2 c3.
        assert!(!crc.contains(&0));
        let mut expected = std::vec![0x02, 0x01, 0x07, 0x02, 0x03];
        expected.extend_from_slice(&crc);
        expected.push(0);
        assert_eq!(f, expected);
        assert_eq!(frames(&f), std::vec![Ok(std::vec![0x01, 0x00, 0x02, 0x03])]);
    }

    #[test]
    fn rejects_by_reason_and_resynchronises() {
        let good = sealed(&[1, 2, 3, 4, 5]);
        let mut corrupt = good.clone();
        corrupt[2] ^= 0x40;
        let mut stream = Vec::new();
        stream.extend_from_slice(&[0, 0]); // idle delimiters: ignored
        stream.extend_from_slice(&corrupt);
        stream.extend_from_slice(&[0x05, 0x01, 0x00]); // code byte past the end: bad COBS
        stream.extend_from_slice(&[0x02, 0x01, 0x00]); // decodes to 1 byte: too short
        stream.extend(std::iter::repeat_n(0x55, crate::MAX_ENCODED + 10));
        stream.push(0); // over-long
        stream.extend_from_slice(&good);
        assert_eq!(
            frames(&stream),
            std::vec![
                Err(FrameError::BadCrc),
                Err(FrameError::BadCobs),
                Err(FrameError::TooShort),
                Err(FrameError::TooLong),
                Ok(std::vec![1, 2, 3, 4, 5]),
            ]
        );
    }

    #[test]
    fn byte_at_a_time_equals_all_at_once() {
        let mut stream = sealed(&[9; 300]);
        stream.extend(sealed(&[0; 17]));
        let mut dec = FrameDecoder::new();
        let mut got = Vec::new();
        for b in &stream {
            dec.feed(core::slice::from_ref(b), |r| got.push(r.map(|p| p.to_vec())));
        }
        assert_eq!(got, frames(&stream));
        assert_eq!(got, std::vec![Ok(std::vec![9; 300]), Ok(std::vec![0; 17])]);
    }

    #[test]
    fn seal_refuses_an_oversized_packet() {
        let mut buf = [0u8; MAX_PACKET];
        let mut out = [0u8; crate::MAX_FRAME];
        assert_eq!(seal(&mut buf, MAX_PACKET - CRC_LEN + 1, &mut out), 0);
    }

    #[test]
    fn largest_packet_fits_the_largest_frame() {
        let f = sealed(&[0xAB; MAX_PACKET - CRC_LEN]);
        assert!(f.len() <= crate::MAX_FRAME);
        assert_eq!(frames(&f), std::vec![Ok(std::vec![0xAB; MAX_PACKET - CRC_LEN])]);
    }
}
