//! `decode_raw`: arbitrary bytes on the wire.
//!
//! Input layout: `ctl ‖ stream`. `ctl` seeds the split points (and the links' epoch and
//! start state); `stream` is what arrives on the wire.
//!
//! Properties (any failure is a bug):
//! 1. `FrameDecoder` never panics, and the sequence of frame results does not depend on how
//!    the stream is cut: all at once (`feed`), in random pieces (`feed`), byte by byte
//!    (`push` + `packet`) all give the same results.
//! 2. The results equal those of a straightforward reference model (split at zeros; too long,
//!    bad COBS, packet over `MAX_PACKET`, too short, bad CRC, in that order).
//! 3. Every accepted packet has a valid CRC and re-seals (`frame::seal`) into a frame that
//!    decodes back to the same packet.
//! 4. A `Link<DeviceMsg, HostMsg, 8>` responder and a `Link<HostMsg, DeviceMsg, 8>` initiator
//!    (fresh, or connected by the three-way handshake with messages in flight) fed the stream
//!    never panic; the frame-level rejections they count equal the decoder's; everything they
//!    transmit is a well-formed frame (control bodies exactly one canonical value of their
//!    type); `poll_transmit` always runs dry.
//! 5. A link fed the stream whole and one fed it in pieces (same time, no transmission in
//!    between) end in the same state: same deliveries, counters and transmitted bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lightrig_protocol::frame::{seal, FrameDecoder, FrameError, CRC32, CRC_LEN};
use lightrig_protocol::link::{
    self, Delivery, FrameKind, Header, Link, LinkConfig, LinkState, LinkStats, Role, SyncAckBody,
};
use lightrig_protocol::message::Message;
use lightrig_protocol::{Command, DeviceMsg, Event, HostMsg, MAX_ENCODED, MAX_FRAME, MAX_PACKET};

type Results = Vec<Result<Vec<u8>, FrameError>>;

const RTO: u64 = 50;
/// The host session nonce of the links (seeds carry it in their Sync/SyncAck frames).
const NONCE: u32 = 7;
/// The responders' boot nonce (seeds carry it in their SyncAck/Confirm frames).
const BOOT: u32 = 0xB007;
const W: usize = 8;

/// Tiny deterministic PRNG for the split points.
struct XorShift(u64);

impl XorShift {
    fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }
}

/// Cuts `stream` into pieces (some empty), the sizes drawn from a PRNG seeded by `ctl`.
fn pieces(ctl: u8, stream: &[u8]) -> Vec<&[u8]> {
    let mut rng = XorShift(0x9E37_79B9_7F4A_7C15 ^ (u64::from(ctl) << 32 | stream.len() as u64));
    // The low two bits choose how coarse the cuts are: 1, 8, 64 or 600 bytes at most.
    let max = [1usize, 8, 64, 600][usize::from(ctl & 3)];
    let mut out = Vec::new();
    let mut rest = stream;
    while !rest.is_empty() {
        let n = (rng.next() as usize % (max + 1)).min(rest.len());
        let (a, b) = rest.split_at(n);
        out.push(a);
        rest = b;
    }
    out
}

fn feed_whole(stream: &[u8]) -> Results {
    let mut dec = FrameDecoder::new();
    let mut out = Vec::new();
    dec.feed(stream, |r| out.push(r.map(<[u8]>::to_vec)));
    out
}

fn feed_pieces(parts: &[&[u8]]) -> Results {
    let mut dec = FrameDecoder::new();
    let mut out = Vec::new();
    for part in parts {
        dec.feed(part, |r| out.push(r.map(<[u8]>::to_vec)));
    }
    out
}

fn push_bytes(stream: &[u8]) -> Results {
    let mut dec = FrameDecoder::new();
    let mut out = Vec::new();
    for &b in stream {
        match dec.push(b) {
            Some(Ok(len)) => {
                let p = dec.packet(len);
                assert_eq!(p.len(), len, "packet(len) must be len bytes long");
                out.push(Ok(p.to_vec()));
            }
            Some(Err(e)) => out.push(Err(e)),
            None => {}
        }
    }
    out
}

/// The reference model of the framing layer.
fn reference(stream: &[u8]) -> Results {
    let mut out = Vec::new();
    let mut segments: Vec<&[u8]> = stream.split(|&b| b == 0).collect();
    segments.pop(); // bytes after the last delimiter: an unfinished frame
    for seg in segments {
        if seg.is_empty() {
            continue; // idle delimiter
        }
        if seg.len() > MAX_ENCODED {
            out.push(Err(FrameError::TooLong));
            continue;
        }
        let mut buf = seg.to_vec();
        let Ok(n) = cobs::decode_in_place(&mut buf) else {
            out.push(Err(FrameError::BadCobs));
            continue;
        };
        if n > MAX_PACKET {
            out.push(Err(FrameError::TooLong));
            continue;
        }
        if n < link::HEADER_MIN + CRC_LEN {
            out.push(Err(FrameError::TooShort));
            continue;
        }
        let (packet, crc) = buf[..n].split_at(n - CRC_LEN);
        if CRC32.checksum(packet).to_le_bytes() != crc {
            out.push(Err(FrameError::BadCrc));
            continue;
        }
        out.push(Ok(packet.to_vec()));
    }
    out
}

fn check_packet(packet: &[u8]) {
    assert!(packet.len() >= link::HEADER_MIN, "accepted packet shorter than a header");
    assert!(packet.len() + CRC_LEN <= MAX_PACKET, "accepted a packet over MAX_PACKET");
    {
        let mut buf = [0u8; MAX_PACKET];
        buf[..packet.len()].copy_from_slice(packet);
        let mut frame = [0u8; MAX_FRAME];
        let n = seal(&mut buf, packet.len(), &mut frame);
        assert!(n <= MAX_FRAME);
        assert_eq!(frame[n - 1], 0, "sealed frame must end with its delimiter");
        assert!(!frame[..n - 1].contains(&0), "sealed frame must contain no other zero");
        assert_eq!(feed_whole(&frame[..n]), vec![Ok(packet.to_vec())], "re-sealed packet must decode back");
    }
}

/// Checks one frame a link transmitted: one intact packet, a header, a body fitting the kind.
fn check_transmitted<T: Message>(frame: &[u8]) {
    assert!(frame.len() <= MAX_FRAME, "transmitted frame too long");
    let results = feed_whole(frame);
    assert_eq!(results.len(), 1, "a transmitted frame must be exactly one frame");
    assert_eq!(frame.last(), Some(&0));
    let packet = results.into_iter().next().unwrap().expect("a transmitted frame must be intact");
    assert!(packet.len() + CRC_LEN <= MAX_PACKET, "transmitted packet over MAX_PACKET");
    let (header, body) =
        postcard::take_from_bytes::<Header>(&packet).expect("transmitted header must decode");
    match header.kind {
        FrameKind::Data | FrameKind::Datagram => {
            link::decode::<T>(body).expect("transmitted message must decode");
        }
        FrameKind::Nak => {
            let (_, rest) =
                postcard::take_from_bytes::<FrameError>(body).expect("Nak body must be a FrameError");
            assert!(rest.is_empty(), "Nak body has trailing bytes");
        }
        FrameKind::Sync | FrameKind::Confirm => exact::<u32>(body),
        FrameKind::SyncAck => exact::<SyncAckBody>(body),
        FrameKind::Ack | FrameKind::Resync => {
            assert!(body.is_empty(), "Ack/Resync frame with a body");
        }
    }
}

/// A control body must be exactly one canonical `B`.
fn exact<B: serde::Serialize + for<'de> serde::Deserialize<'de>>(body: &[u8]) {
    let (b, rest) = postcard::take_from_bytes::<B>(body).expect("control body must decode");
    assert!(rest.is_empty(), "control body has trailing bytes");
    assert_eq!(
        postcard::experimental::serialized_size(&b).ok(),
        Some(body.len()),
        "control body not canonical"
    );
}

fn drain<T: Message, R: Message>(link: &mut Link<T, R, W>, now: u64) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let mut all = Vec::new();
    for _ in 0..64 {
        match link.poll_transmit(now, &mut out) {
            Some(n) => {
                check_transmitted::<T>(&out[..n]);
                all.extend_from_slice(&out[..n]);
            }
            None => return all,
        }
    }
    panic!("poll_transmit did not run dry after 64 frames");
}

fn host_msg(id: u16) -> HostMsg {
    HostMsg { id, command: Command::GetStatus }
}

fn device_msg(index: u32) -> DeviceMsg {
    DeviceMsg::Event { index, event: Event::Marker { sequence: 1, item: index, id: 7, tick: 1000 } }
}

/// Starts syncing in epoch `epoch` (`connect` moves one epoch forward per call).
fn connect_to(host: &mut Link<HostMsg, DeviceMsg, W>, epoch: u8) {
    host.connect(0);
    while host.epoch() != epoch {
        host.connect(0);
    }
}

/// An initiator/responder pair connected in epoch `epoch` (Sync, SyncAck, Confirm), each with
/// three messages sent and unacknowledged (so acks, Naks and duplicates in the stream have
/// something to act on).
fn established(epoch: u8) -> (Link<HostMsg, DeviceMsg, W>, Link<DeviceMsg, HostMsg, W>) {
    let mut host = Link::new(Role::Initiator, LinkConfig { rto: RTO, rx_reserve: 0, nonce: NONCE });
    let mut dev = Link::new(Role::Responder, LinkConfig { rto: RTO, rx_reserve: 1, nonce: BOOT });
    connect_to(&mut host, epoch);
    let sync = drain(&mut host, 0);
    dev.receive_all(&sync, 0, |_| {});
    assert_eq!(dev.state(), LinkState::Syncing);
    let ack = drain(&mut dev, 0);
    host.receive_all(&ack, 0, |_| {});
    let confirm = drain(&mut host, 0);
    dev.receive_all(&confirm, 0, |_| {});
    assert_eq!((host.state(), dev.state()), (LinkState::Up, LinkState::Up));
    for i in 0..3 {
        host.send(host_msg(i)).unwrap();
        dev.send(device_msg(u32::from(i))).unwrap();
    }
    drain(&mut host, 0); // sent, and lost: the stream decides what is acknowledged
    drain(&mut dev, 0);
    (host, dev)
}

/// Frame-level rejections (the ones only the decoder produces).
fn frame_rejects(s: &LinkStats) -> [u32; 4] {
    [s.bad_cobs, s.bad_crc, s.too_long, s.too_short]
}

fn expected_rejects(results: &Results) -> [u32; 4] {
    let mut r = [0u32; 4];
    for e in results.iter().filter_map(|r| r.as_ref().err()) {
        match e {
            FrameError::BadCobs => r[0] += 1,
            FrameError::BadCrc => r[1] += 1,
            FrameError::TooLong => r[2] += 1,
            FrameError::TooShort => r[3] += 1,
            other => panic!("the frame decoder produced {other:?}"),
        }
    }
    r
}

fn add(a: [u32; 4], b: [u32; 4]) -> [u32; 4] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]]
}

/// Feeds `parts` to `link`, polling after each piece; checks counters against the decoder.
fn run_link<T: Message, R: Message>(mut link: Link<T, R, W>, parts: &[&[u8]], results: &Results, ctl: u8) {
    let before = *link.stats();
    let mut now = 1;
    let mut delivered = 0u32;
    for part in parts {
        link.receive_all(part, now, |d| {
            if !matches!(d, Delivery::Connected { .. }) {
                delivered += 1;
            }
        });
        drain(&mut link, now);
        now += u64::from(ctl >> 4) * 7 + part.len() as u64;
        assert!(link.unacked() <= W && link.free() == W - link.unacked());
    }
    let after = *link.stats();
    assert_eq!(frame_rejects(&after), add(frame_rejects(&before), expected_rejects(results)));
    let accepted = results.iter().filter(|r| r.is_ok()).count() as u32;
    assert!(after.frames_received - before.frames_received <= accepted);
    assert!(delivered <= accepted, "more deliveries than intact frames");
}

/// Feeds the whole stream to one link and the pieces to an identical one: same outcome.
fn same_whole_and_pieces<T: Message + PartialEq, R: Message + PartialEq>(
    make: impl Fn() -> Link<T, R, W>,
    stream: &[u8],
    parts: &[&[u8]],
) {
    let (mut a, mut b) = (make(), make());
    let (mut da, mut db) = (Vec::new(), Vec::new());
    a.receive_all(stream, 5, |d| da.push(d));
    for part in parts {
        // One delivery at a time, as a firmware would.
        let mut rest: &[u8] = part;
        while !rest.is_empty() {
            let (used, d) = b.receive(rest, 5);
            assert!(used >= 1 && used <= rest.len(), "receive consumed {used} of {} bytes", rest.len());
            assert!(d.is_some() || used == rest.len(), "receive stopped early without a delivery");
            db.extend(d);
            rest = &rest[used..];
        }
    }
    assert_eq!(da, db, "deliveries depend on how the stream was cut");
    assert_eq!(a.stats(), b.stats(), "counters depend on how the stream was cut");
    assert_eq!((a.state(), a.epoch(), a.unacked()), (b.state(), b.epoch(), b.unacked()));
    assert_eq!(drain(&mut a, 5), drain(&mut b, 5), "transmissions depend on how the stream was cut");
}

fuzz_target!(|data: &[u8]| {
    let Some((&ctl, stream)) = data.split_first() else { return };
    let parts = pieces(ctl, stream);

    // 1, 2: the framing layer.
    let whole = feed_whole(stream);
    assert_eq!(feed_pieces(&parts), whole, "frame results depend on the split points");
    assert_eq!(push_bytes(stream), whole, "push/packet differs from feed");
    assert_eq!(reference(stream), whole, "frame decoder differs from the reference model");
    // 3: every accepted packet.
    for packet in whole.iter().filter_map(|r| r.as_ref().ok()) {
        check_packet(packet);
    }

    // 4: the links, fresh or established, epoch from ctl.
    let epoch = ctl.rotate_right(2);
    if ctl & 4 == 0 {
        let config = LinkConfig { rto: RTO, rx_reserve: usize::from(ctl >> 7), nonce: BOOT };
        let mut host =
            Link::<HostMsg, DeviceMsg, W>::new(Role::Initiator, LinkConfig { nonce: NONCE, ..config });
        connect_to(&mut host, epoch);
        run_link(host, &parts, &whole, ctl);
        run_link(Link::<DeviceMsg, HostMsg, W>::new(Role::Responder, config), &parts, &whole, ctl);
    } else {
        let (host, dev) = established(epoch);
        run_link(host, &parts, &whole, ctl);
        run_link(dev, &parts, &whole, ctl);
    }

    // 5: whole versus pieces, on established links (the richer state).
    same_whole_and_pieces(|| established(epoch).0, stream, &parts);
    same_whole_and_pieces(|| established(epoch).1, stream, &parts);
});
