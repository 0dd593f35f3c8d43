//! A recording board for targets without the real peripherals (the emulated board): it
//! implements every [`crate::hal`] trait by recording what the pins would do, each change with
//! its tick, in a fixed ring buffer (no_std, no allocation), and answers the *debug port*
//! messages that read the record out.
//!
//! The debug port is a side channel of the board, not part of the lightrig protocol: its
//! packets are framed like the protocol's (`COBS(packet ‖ CRC-32) 0x00`,
//! [`lightrig_protocol::frame`]) and carry the small messages below, all little-endian.
//!
//! Every packet starts with the magic `4C 52 44` ("LRD"), which also makes it long enough
//! for the protocol's frame decoder (at least 4 bytes), then:
//!
//! | request | bytes | answer |
//! |---|---|---|
//! | read records | `01 ‖ from: u64 ‖ max: u8` | `81 ‖ first: u64 ‖ written: u64 ‖ n: u8 ‖ n × record` |
//! | set interlock | `02 ‖ channel: u8 ‖ level: u8` | `82` |
//! | board info | `03` | `83 ‖ written: u64 ‖ capacity: u32 ‖ now: u64 ‖ 4 × counter: u64` |
//!
//! Records are numbered from 0 at start; the ring keeps the last `capacity`. A read returns up
//! to `max` (at most [`RECORDS_PER_READ`]) records from number `max(from, written −
//! capacity)` on: `first` is the number of the first one returned, so `first > from` means
//! records were overwritten before they were read. A record is 16 bytes:
//! `tick: u64 ‖ kind: u8 ‖ unit: u8 ‖ level: u8 ‖ len: u8 ‖ a: u32`, see [`Record::encode`].

use lightrig_protocol::config::Xy;
use lightrig_protocol::event::Switch;
use lightrig_protocol::frame::{seal, CRC_LEN};
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::{MAX_FRAME, MAX_LASERS, MAX_PACKET};

use crate::hal::{Cameras, Capture, Galvos, HwError, Lasers, Motors, VoiceCoils};

/// Bytes of one encoded record.
pub const RECORD_LEN: usize = 16;
/// Most records in one answer to a read (they fill one packet).
pub const RECORDS_PER_READ: usize = (MAX_PACKET - CRC_LEN - MAGIC.len() - 18) / RECORD_LEN;
/// First bytes of every debug-port packet.
pub const MAGIC: [u8; 3] = *b"LRD";

/// One output change, as the pins would show it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    /// Galvo pair driven to a position.
    Galvo { pair: u8, to: Xy },
    /// Laser enable output level.
    Laser { channel: u8, level: bool },
    /// One step pulse.
    Step { motor: AxisRef },
    /// Direction output level.
    Dir { motor: AxisRef, level: bool },
    /// Driver-enable output level.
    Enable { motor: AxisRef, level: bool },
    /// Camera trigger output level.
    Trigger { camera: u8, level: bool },
    /// A block of voice-coil samples handed over; `first` is the block's first sample number
    /// modulo 2³² (the record holds 32 bits of it).
    Samples { channel: u8, first: u32, len: u8 },
}

/// An output change and the tick it belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Record {
    /// Tick.
    pub tick: u64,
    /// What changed.
    pub output: Output,
}

fn motor_code(m: AxisRef) -> u8 {
    match m {
        AxisRef::Stepper(i) => i & 0x7f,
        AxisRef::FilterWheel(i) => 0x80 | (i & 0x7f),
    }
}

fn motor_from(code: u8) -> AxisRef {
    if code & 0x80 == 0 {
        AxisRef::Stepper(code)
    } else {
        AxisRef::FilterWheel(code & 0x7f)
    }
}

impl Record {
    /// The 16-byte form: `tick: u64 LE ‖ kind ‖ unit ‖ level ‖ len ‖ a: u32 LE`. Kinds: 0 galvo
    /// (`unit` = pair, `a` = x | y << 16), 1 laser, 2 step, 3 dir, 4 enable, 5 trigger, 6
    /// samples (`unit` = channel, `len`, `a` = first sample). Motors are `unit` = axis index,
    /// bit 7 set for a filter wheel.
    pub fn encode(&self) -> [u8; RECORD_LEN] {
        let (kind, unit, level, len, a) = match self.output {
            Output::Galvo { pair, to } => (0, pair, 0, 0, u32::from(to.x) | (u32::from(to.y) << 16)),
            Output::Laser { channel, level } => (1, channel, u8::from(level), 0, 0),
            Output::Step { motor } => (2, motor_code(motor), 0, 0, 0),
            Output::Dir { motor, level } => (3, motor_code(motor), u8::from(level), 0, 0),
            Output::Enable { motor, level } => (4, motor_code(motor), u8::from(level), 0, 0),
            Output::Trigger { camera, level } => (5, camera, u8::from(level), 0, 0),
            Output::Samples { channel, first, len } => (6, channel, 0, len, first),
        };
        let mut out = [0u8; RECORD_LEN];
        out[..8].copy_from_slice(&self.tick.to_le_bytes());
        out[8] = kind;
        out[9] = unit;
        out[10] = level;
        out[11] = len;
        out[12..].copy_from_slice(&a.to_le_bytes());
        out
    }

    /// Reads the 16-byte form; `None` for an unknown kind or a short slice.
    pub fn decode(b: &[u8]) -> Option<Self> {
        let tick = u64::from_le_bytes(b.get(..8)?.try_into().ok()?);
        let (kind, unit, level, len) = (*b.get(8)?, *b.get(9)?, *b.get(10)? != 0, *b.get(11)?);
        let a = u32::from_le_bytes(b.get(12..16)?.try_into().ok()?);
        let output = match kind {
            0 => Output::Galvo { pair: unit, to: Xy { x: a as u16, y: (a >> 16) as u16 } },
            1 => Output::Laser { channel: unit, level },
            2 => Output::Step { motor: motor_from(unit) },
            3 => Output::Dir { motor: motor_from(unit), level },
            4 => Output::Enable { motor: motor_from(unit), level },
            5 => Output::Trigger { camera: unit, level },
            6 => Output::Samples { channel: unit, first: a, len },
            _ => return None,
        };
        Some(Record { tick, output })
    }
}

/// The last `N` records, numbered from 0.
#[derive(Debug, Clone)]
pub struct Recorder<const N: usize> {
    ring: [Record; N],
    written: u64,
}

impl<const N: usize> Default for Recorder<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Recorder<N> {
    /// An empty recorder.
    pub const fn new() -> Self {
        // All zero bytes, so a static recorder lands in .bss, not in .data.
        let blank = Record { tick: 0, output: Output::Galvo { pair: 0, to: Xy { x: 0, y: 0 } } };
        Self { ring: [blank; N], written: 0 }
    }

    /// Appends a record, overwriting the oldest once `N` are held.
    pub fn push(&mut self, tick: u64, output: Output) {
        if N == 0 {
            return;
        }
        let slot = (self.written % N as u64) as usize;
        if let Some(r) = self.ring.get_mut(slot) {
            *r = Record { tick, output };
        }
        self.written += 1;
    }

    /// Records written since start (the number the next one gets).
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Number of the oldest record still held.
    pub fn oldest(&self) -> u64 {
        self.written.saturating_sub(N as u64)
    }

    /// Record number `n`, if still held.
    pub fn get(&self, n: u64) -> Option<&Record> {
        if n < self.oldest() || n >= self.written {
            return None;
        }
        self.ring.get((n % N as u64) as usize)
    }
}

/// A board whose pins are a [`Recorder`] of `N` changes. Inputs: interlocks (closed unless the
/// debug port opens them); switches and exposure strobes are not connected (inactive, no
/// captures).
#[derive(Debug, Clone)]
pub struct RecordingBoard<const N: usize> {
    /// What the outputs did.
    pub record: Recorder<N>,
    /// Interlock inputs opened (low) through the debug port; closed (high) by default. Kept
    /// as "open" so that the power-on state is all zero bytes.
    pub interlock_open: [bool; MAX_LASERS],
    /// Laser enable output levels.
    pub lasers: [bool; MAX_LASERS],
}

impl<const N: usize> Default for RecordingBoard<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> RecordingBoard<N> {
    /// Interlocks closed, every output low, nothing recorded.
    pub const fn new() -> Self {
        Self { record: Recorder::new(), interlock_open: [false; MAX_LASERS], lasers: [false; MAX_LASERS] }
    }

    /// Forces every laser enable low at `at` (the panic handler's duty; lasers are wired
    /// active-high on this board), recording each one that was high.
    pub fn lasers_off(&mut self, at: u64) {
        for channel in 0..MAX_LASERS {
            if self.lasers[channel] {
                self.set_laser(channel as u8, false, at);
            }
        }
    }

    /// Answers one debug-port request packet (CRC already checked and removed) into `out`;
    /// returns the frame length, 0 if the request is malformed (it gets no answer). `now` and
    /// the board's four `counters` go into the info answer.
    pub fn answer(
        &mut self,
        request: &[u8],
        now: u64,
        counters: [u64; 4],
        out: &mut [u8; MAX_FRAME],
    ) -> usize {
        let Some(request) = request.strip_prefix(&MAGIC[..]) else { return 0 };
        let mut packet = [0u8; MAX_PACKET];
        packet[..3].copy_from_slice(&MAGIC);
        let buf = &mut packet[3..];
        let len = 3 + match *request {
            [0x01, ref rest @ ..] if rest.len() == 9 => {
                let mut from = [0u8; 8];
                from.copy_from_slice(&rest[..8]);
                let from = u64::from_le_bytes(from).max(self.record.oldest());
                let max = usize::from(rest[8]).min(RECORDS_PER_READ);
                let written = self.record.written();
                let n = (written.saturating_sub(from) as usize).min(max);
                buf[0] = 0x81;
                buf[1..9].copy_from_slice(&from.to_le_bytes());
                buf[9..17].copy_from_slice(&written.to_le_bytes());
                buf[17] = n as u8;
                let mut at = 18;
                for k in 0..n as u64 {
                    if let Some(r) = self.record.get(from + k) {
                        buf[at..at + RECORD_LEN].copy_from_slice(&r.encode());
                    }
                    at += RECORD_LEN;
                }
                at
            }
            [0x02, channel, level] => {
                if let Some(open) = self.interlock_open.get_mut(usize::from(channel)) {
                    *open = level == 0;
                }
                buf[0] = 0x82;
                1
            }
            [0x03] => {
                buf[0] = 0x83;
                buf[1..9].copy_from_slice(&self.record.written().to_le_bytes());
                buf[9..13].copy_from_slice(&(N as u32).to_le_bytes());
                buf[13..21].copy_from_slice(&now.to_le_bytes());
                for (i, c) in counters.iter().enumerate() {
                    buf[21 + 8 * i..29 + 8 * i].copy_from_slice(&c.to_le_bytes());
                }
                53
            }
            _ => return 0,
        };
        seal(&mut packet, len, out)
    }
}

/// Debug-port requests, for the host side.
pub mod request {
    /// Read up to `max` records from number `from` on.
    pub fn read(from: u64, max: u8) -> [u8; 13] {
        let mut r = [0u8; 13];
        r[..3].copy_from_slice(&super::MAGIC);
        r[3] = 0x01;
        r[4..12].copy_from_slice(&from.to_le_bytes());
        r[12] = max;
        r
    }

    /// Set a laser's interlock input level (`true` = closed).
    pub fn set_interlock(channel: u8, level: bool) -> [u8; 6] {
        let [m0, m1, m2] = super::MAGIC;
        [m0, m1, m2, 0x02, channel, u8::from(level)]
    }

    /// Board information.
    pub fn info() -> [u8; 4] {
        let [m0, m1, m2] = super::MAGIC;
        [m0, m1, m2, 0x03]
    }
}

/// A debug-port answer, decoded (host side).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Answer<'a> {
    /// Records from number `first` on (`records`: `n` × 16 bytes), and how many were written.
    Records { first: u64, written: u64, records: &'a [u8] },
    /// An interlock was set.
    InterlockSet,
    /// Records written, ring capacity, the board's tick and its four counters.
    Info { written: u64, capacity: u32, now: u64, counters: [u64; 4] },
}

impl<'a> Answer<'a> {
    /// Decodes an answer packet (CRC removed); `None` if it is malformed.
    pub fn decode(p: &'a [u8]) -> Option<Self> {
        let p = p.strip_prefix(&MAGIC[..])?;
        let u64_at = |i: usize| p.get(i..i + 8).and_then(|b| b.try_into().ok()).map(u64::from_le_bytes);
        match *p.first()? {
            0x81 => {
                let n = usize::from(*p.get(17)?);
                let records = p.get(18..18 + n * RECORD_LEN)?;
                (p.len() == 18 + n * RECORD_LEN).then_some(Answer::Records {
                    first: u64_at(1)?,
                    written: u64_at(9)?,
                    records,
                })
            }
            0x82 if p.len() == 1 => Some(Answer::InterlockSet),
            0x83 if p.len() == 53 => Some(Answer::Info {
                written: u64_at(1)?,
                capacity: u32::from_le_bytes(p.get(9..13)?.try_into().ok()?),
                now: u64_at(13)?,
                counters: [u64_at(21)?, u64_at(29)?, u64_at(37)?, u64_at(45)?],
            }),
            _ => None,
        }
    }
}

impl<const N: usize> Galvos for RecordingBoard<N> {
    fn set_galvo(&mut self, pair: u8, to: Xy, at: u64) -> Result<(), HwError> {
        self.record.push(at, Output::Galvo { pair, to });
        Ok(())
    }
}

impl<const N: usize> Lasers for RecordingBoard<N> {
    fn set_laser(&mut self, channel: u8, level: bool, at: u64) {
        if let Some(l) = self.lasers.get_mut(usize::from(channel)) {
            *l = level;
        }
        self.record.push(at, Output::Laser { channel, level });
    }

    fn interlock_level(&mut self, channel: u8) -> bool {
        self.interlock_open.get(usize::from(channel)).is_some_and(|open| !open)
    }
}

impl<const N: usize> Motors for RecordingBoard<N> {
    fn step(&mut self, motor: AxisRef, at: u64) {
        self.record.push(at, Output::Step { motor });
    }

    fn set_dir(&mut self, motor: AxisRef, level: bool, at: u64) {
        self.record.push(at, Output::Dir { motor, level });
    }

    fn set_enable(&mut self, motor: AxisRef, level: bool, at: u64) {
        self.record.push(at, Output::Enable { motor, level });
    }

    fn switch_level(&mut self, _motor: AxisRef, _switch: Switch) -> bool {
        false
    }
}

impl<const N: usize> Cameras for RecordingBoard<N> {
    fn set_trigger(&mut self, camera: u8, level: bool, at: u64) {
        self.record.push(at, Output::Trigger { camera, level });
    }

    fn take_capture(&mut self, _until: u64) -> Option<Capture> {
        None
    }
}

/// Not updated over the link: it records outputs only.
impl<const N: usize> crate::hal::FirmwareSlots for RecordingBoard<N> {}

impl<const N: usize> VoiceCoils for RecordingBoard<N> {
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64) {
        let len = samples.len().min(usize::from(u8::MAX)) as u8;
        self.record.push(at, Output::Samples { channel, first: first_sample as u32, len });
    }
}

#[cfg(test)]
mod tests {
    use lightrig_protocol::frame::FrameDecoder;

    use super::*;

    fn unframe(frame: &[u8]) -> std::vec::Vec<u8> {
        let mut d = FrameDecoder::new();
        let mut got = None;
        d.feed(frame, |p| got = Some(p.map(|p| p.to_vec())));
        got.expect("one frame").expect("intact")
    }

    #[test]
    fn records_round_trip_through_their_16_bytes() {
        let outputs = [
            Output::Galvo { pair: 1, to: Xy { x: 0xBEEF, y: 0x1234 } },
            Output::Laser { channel: 7, level: true },
            Output::Step { motor: AxisRef::Stepper(3) },
            Output::Dir { motor: AxisRef::FilterWheel(1), level: true },
            Output::Enable { motor: AxisRef::Stepper(0), level: false },
            Output::Trigger { camera: 2, level: true },
            Output::Samples { channel: 3, first: 0xDEAD_BEEF, len: 64 },
        ];
        for (i, output) in outputs.into_iter().enumerate() {
            let r = Record { tick: 0x0102_0304_0506_0708 + i as u64, output };
            assert_eq!(Record::decode(&r.encode()), Some(r));
        }
        let laser = Record { tick: 0x0102_0304_0506_0708, output: Output::Laser { channel: 7, level: true } };
        assert_eq!(laser.encode(), [8, 7, 6, 5, 4, 3, 2, 1, 1, 7, 1, 0, 0, 0, 0, 0]);
        let mut bad = laser.encode();
        bad[8] = 7;
        assert_eq!(Record::decode(&bad), None);
        assert_eq!(Record::decode(&laser.encode()[..15]), None);
    }

    #[test]
    fn the_ring_keeps_the_last_n_and_reads_say_what_was_lost() {
        let mut board = RecordingBoard::<4>::new();
        for t in 0..6 {
            board.set_trigger(0, t % 2 == 0, t * 10);
        }
        assert_eq!((board.record.written(), board.record.oldest()), (6, 2));
        let mut out = [0u8; MAX_FRAME];
        let n = board.answer(&request::read(0, 3), 99, [0; 4], &mut out);
        let p = unframe(&out[..n]);
        let Some(Answer::Records { first, written, records }) = Answer::decode(&p) else { panic!("{p:?}") };
        assert_eq!((first, written, records.len()), (2, 6, 3 * RECORD_LEN));
        let ticks: std::vec::Vec<u64> =
            records.chunks(RECORD_LEN).map(|r| Record::decode(r).expect("record").tick).collect();
        assert_eq!(ticks, [20, 30, 40]);
        // Nothing new: an empty answer at the end.
        let n = board.answer(&request::read(6, 30), 99, [0; 4], &mut out);
        let p = unframe(&out[..n]);
        assert_eq!(Answer::decode(&p), Some(Answer::Records { first: 6, written: 6, records: &[] }));
    }

    #[test]
    fn interlock_and_info_requests_and_malformed_ones() {
        let mut board = RecordingBoard::<8>::new();
        let mut out = [0u8; MAX_FRAME];
        assert!(board.interlock_level(2));
        let n = board.answer(&request::set_interlock(2, false), 0, [0; 4], &mut out);
        assert_eq!(Answer::decode(&unframe(&out[..n])), Some(Answer::InterlockSet));
        assert!(!board.interlock_level(2));
        board.set_laser(1, true, 5);
        board.lasers_off(9);
        let n = board.answer(&request::info(), 77, [1, 2, 3, 4], &mut out);
        assert_eq!(
            Answer::decode(&unframe(&out[..n])),
            Some(Answer::Info { written: 2, capacity: 8, now: 77, counters: [1, 2, 3, 4] })
        );
        assert_eq!(
            board.record.get(1),
            Some(&Record { tick: 9, output: Output::Laser { channel: 1, level: false } })
        );
        for bad in [&[][..], b"LRD\x01\0\0", b"LRD\x03\0", b"LRD\x7f", b"XYZ\x03"] {
            assert_eq!(board.answer(bad, 0, [0; 4], &mut out), 0, "{bad:?}");
        }
        assert_eq!(RECORDS_PER_READ, 29);
    }
}
