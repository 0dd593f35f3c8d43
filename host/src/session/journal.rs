//! The journal's line format: `CRC<TAB>JSON<LF>`, one record per line.
//!
//! `CRC` is exactly 8 lowercase hexadecimal digits: the CRC-32/ISO-HDLC (the zlib / PNG /
//! Ethernet CRC-32) of the JSON bytes, i.e. of every byte after the tab and before the line
//! feed. serde_json never writes a raw tab or line feed inside its output (they are escaped in
//! strings), so a line's payload is unambiguous. A line is committed once its line feed is on
//! disk: a last line without one is a torn write.

use std::fs::File;
use std::io::{BufRead, BufReader, Read};

/// CRC-32/ISO-HDLC: polynomial 0x04C11DB7 reflected, init and final XOR 0xFFFFFFFF.
const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// CRC-32/ISO-HDLC of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

/// A running CRC-32/ISO-HDLC.
pub struct Crc32(crc::Digest<'static, u32>);

impl Crc32 {
    /// A fresh checksum.
    pub fn new() -> Self {
        Crc32(CRC32.digest())
    }
    /// Adds bytes.
    pub fn update(&mut self, bytes: &[u8]) {
        self.0.update(bytes);
    }
    /// The checksum.
    pub fn finish(self) -> u32 {
        self.0.finalize()
    }
}

impl Default for Crc32 {
    fn default() -> Self {
        Self::new()
    }
}

/// The line for a JSON payload, line feed included.
pub fn encode_line(payload: &[u8]) -> Vec<u8> {
    let mut line = Vec::with_capacity(payload.len() + 10);
    line.extend_from_slice(format!("{:08x}\t", crc32(payload)).as_bytes());
    line.extend_from_slice(payload);
    line.push(b'\n');
    line
}

/// Why a line is not a committed record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Damage {
    /// The last line has no line feed: the write was cut short.
    Torn,
    /// The line does not start with 8 lowercase hex digits and a tab.
    BadPrefix,
    /// The CRC does not match the payload.
    CrcMismatch,
}

impl Damage {
    /// In words.
    pub fn describe(self) -> &'static str {
        match self {
            Damage::Torn => "the last line has no line feed (a torn write)",
            Damage::BadPrefix => "a line does not start with an 8-digit lowercase hex CRC and a tab",
            Damage::CrcMismatch => "a line's CRC does not match its JSON",
        }
    }
}

/// Checks one line (line feed included if present); the payload if it is committed and intact.
pub fn decode_line(line: &[u8]) -> Result<&[u8], Damage> {
    let Some(body) = line.strip_suffix(b"\n") else { return Err(Damage::Torn) };
    if body.len() < 9 || body[8] != b'\t' {
        return Err(Damage::BadPrefix);
    }
    let mut crc = 0u32;
    for &c in &body[..8] {
        let d = match c {
            b'0'..=b'9' => c - b'0',
            b'a'..=b'f' => c - b'a' + 10,
            _ => return Err(Damage::BadPrefix),
        };
        crc = crc << 4 | u32::from(d);
    }
    let payload = &body[9..];
    if crc32(payload) != crc {
        return Err(Damage::CrcMismatch);
    }
    Ok(payload)
}

/// Where a scan stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScanEnd {
    /// Bytes of committed, intact records from the start.
    pub good_len: u64,
    /// Total file length.
    pub file_len: u64,
    /// The damage at `good_len`, if the file goes on past it.
    pub damage: Option<Damage>,
    /// Intact-looking lines after the damage (a hint: damage before intact lines is not a torn
    /// tail but corruption inside the file).
    pub intact_after: usize,
}

/// Reads the journal line by line, handing each intact payload (with its 1-based line number) to
/// `each`, up to the first damaged line. An error from `each` stops the scan.
pub fn scan<E>(
    file: &File,
    mut each: impl FnMut(usize, &[u8]) -> Result<(), E>,
    io_err: impl Fn(std::io::Error) -> E,
) -> Result<ScanEnd, E> {
    let file_len = file.metadata().map_err(&io_err)?.len();
    let mut reader = BufReader::with_capacity(1 << 16, file.take(file_len));
    let mut line = Vec::new();
    let mut good_len = 0u64;
    let mut number = 0usize;
    loop {
        line.clear();
        let n = reader.read_until(b'\n', &mut line).map_err(&io_err)?;
        if n == 0 {
            return Ok(ScanEnd { good_len, file_len, damage: None, intact_after: 0 });
        }
        number += 1;
        match decode_line(&line) {
            Ok(payload) => {
                each(number, payload)?;
                good_len += n as u64;
            }
            Err(damage) => {
                let mut intact_after = 0;
                loop {
                    line.clear();
                    if reader.read_until(b'\n', &mut line).map_err(&io_err)? == 0 {
                        break;
                    }
                    intact_after += usize::from(decode_line(&line).is_ok());
                }
                return Ok(ScanEnd { good_len, file_len, damage: Some(damage), intact_after });
            }
        }
    }
}
