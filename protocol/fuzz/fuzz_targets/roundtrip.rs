//! `roundtrip`: message encoding in both directions.
//!
//! (a) Structured: a `HostMsg` and a `DeviceMsg` built by `arbitrary` from the input. Each
//!     serializes (its `serialized_size` is what `to_slice` writes), `Link::send` accepts it
//!     exactly when it fits (`serialized_size <= link::MAX_MESSAGE`, else `TooLarge`), and one
//!     that fits, written with `link::write` under a fuzzer-chosen `Data` header, goes through
//!     `FrameDecoder` and `link::decode` back to the same header and the same message.
//! (b) Raw: the input decoded as a message body (`link::decode::<HostMsg>` and `<DeviceMsg>`).
//!     When it decodes, the message re-encodes (canonically, so no longer than the input),
//!     decodes back equal, and re-encodes byte-identically. When it does not, the error is
//!     `UnknownType` exactly when the message carries a whole tag this build does not know,
//!     `BadPayload` otherwise (a body too short for its tag included).
//!     The same for the link `Header` (prefix decoding; canonical encoding within
//!     `HEADER_MIN..=HEADER_MAX` bytes).
//! (c) Control frames: a `Sync` or `Confirm` with a `u32` body and a `SyncAck` with a
//!     `SyncAckBody`, from the input, written with `link::write`, come back through
//!     `FrameDecoder` as the same header and exactly the body's canonical encoding.
#![no_main]

use arbitrary::{Arbitrary, Unstructured};
use libfuzzer_sys::fuzz_target;
use lightrig_protocol::frame::{FrameDecoder, FrameError};
use lightrig_protocol::link::{self, FrameKind, Header, Link, LinkConfig, Role, SendError, SyncAckBody};
use lightrig_protocol::message::Message;
use lightrig_protocol::{DeviceMsg, HostMsg, MAX_FRAME, MAX_PACKET};

/// Big enough for any message: 32 items of at most ~110 bytes, 80-byte strings.
const BUF: usize = 16 * 1024;

fn encode<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    let mut buf = vec![0u8; BUF];
    let n = postcard::to_slice(msg, &mut buf).expect("every message serializes into 16 KiB").len();
    buf.truncate(n);
    buf
}

/// (a) for one message type.
fn structured<T: Message + PartialEq, R: Message>(msg: T, header: Header) {
    let size = postcard::experimental::serialized_size(&msg).expect("serialized_size failed");
    let bytes = encode(&msg);
    assert_eq!(bytes.len(), size, "serialized_size differs from the encoding's length");
    assert!(T::known_tag(&bytes), "an encoded message must carry a known tag");

    let mut link = Link::<T, R, 8>::new(Role::Responder, LinkConfig { rto: 10, rx_reserve: 0, nonce: 0 });
    match link.send(msg.clone()) {
        Ok(()) => assert!(size <= link::MAX_MESSAGE, "send accepted a {size}-byte message"),
        Err(SendError::TooLarge(m)) => {
            assert!(size > link::MAX_MESSAGE, "send refused a {size}-byte message as too large");
            assert_eq!(m, msg, "TooLarge must hand the message back");
        }
        Err(SendError::WindowFull(_)) => panic!("window full on an empty link"),
    }
    if size > link::MAX_MESSAGE {
        return;
    }

    let mut frame = [0u8; MAX_FRAME];
    let n = link::write(&header, Some(&msg), &mut frame);
    let frame = &frame[..n];
    assert_eq!(frame.last(), Some(&0), "frame must end with its delimiter");
    assert!(!frame[..n - 1].contains(&0), "frame must contain no other zero");

    let mut dec = FrameDecoder::new();
    let mut results = Vec::new();
    dec.feed(frame, |r| results.push(r.map(<[u8]>::to_vec)));
    assert_eq!(results.len(), 1, "one frame in, one result out");
    let packet = results.pop().unwrap().expect("a written frame must be intact");
    assert!(packet.len() <= MAX_PACKET - lightrig_protocol::frame::CRC_LEN, "packet over MAX_PACKET");
    let (h, body) = postcard::take_from_bytes::<Header>(&packet).expect("header must decode");
    assert_eq!(h, header, "header did not round-trip");
    assert_eq!(body, &bytes[..], "body is not the message's encoding");
    assert!(packet.len() - body.len() <= link::HEADER_MAX, "header longer than HEADER_MAX");
    assert_eq!(link::decode::<T>(body), Ok(msg), "message did not round-trip");
}

/// (b) for one message type.
fn raw<T: Message + PartialEq>(data: &[u8]) {
    match link::decode::<T>(data) {
        Ok(msg) => {
            assert!(T::known_tag(data), "decoded a message whose tag is unknown");
            let first = encode(&msg);
            assert!(first.len() <= data.len(), "re-encoding is longer than the input");
            let again = link::decode::<T>(&first).expect("re-encoded message does not decode");
            assert_eq!(again, msg, "re-encoded message decodes to something else");
            assert_eq!(encode(&again), first, "re-encoding is not deterministic");
            // The message is exactly the input when the input was canonical.
            if first.len() == data.len() {
                assert_eq!(first, data, "same length, different bytes");
            }
        }
        Err(FrameError::UnknownType) => assert!(T::unknown_tag(data), "UnknownType without an unknown tag"),
        Err(FrameError::BadPayload) => assert!(!T::unknown_tag(data), "BadPayload for an unknown tag"),
        Err(other) => panic!("decode returned {other:?}"),
    }
}

fn raw_header(data: &[u8]) {
    if let Ok((h, rest)) = postcard::take_from_bytes::<Header>(data) {
        // postcard accepts over-long varints (`80 80 80 00` is kind 0), so a received header may
        // be longer than HEADER_MAX; its canonical encoding is not.
        let used = data.len() - rest.len();
        assert!(used >= link::HEADER_MIN, "header of {used} bytes");
        let first = encode(&h);
        assert!((link::HEADER_MIN..=link::HEADER_MAX).contains(&first.len()), "header encodes to {first:?}");
        assert!(first.len() <= used);
        assert_eq!(postcard::from_bytes::<Header>(&first), Ok(h));
    }
}

/// Writes `header` and `body` as a frame and reads it back: the same header, then exactly `body`.
fn control<B: serde::Serialize + for<'de> serde::Deserialize<'de> + PartialEq + core::fmt::Debug>(
    header: Header,
    body: B,
) {
    let mut frame = [0u8; MAX_FRAME];
    let n = link::write(&header, Some(&body), &mut frame);
    let mut dec = FrameDecoder::new();
    let mut results = Vec::new();
    dec.feed(&frame[..n], |r| results.push(r.map(<[u8]>::to_vec)));
    assert_eq!(results.len(), 1, "one control frame in, one result out");
    let packet = results.pop().unwrap().expect("a written control frame must be intact");
    let (h, rest) = postcard::take_from_bytes::<Header>(&packet).expect("header must decode");
    assert_eq!(h, header, "control header did not round-trip");
    let (b, tail) = postcard::take_from_bytes::<B>(rest).expect("control body must decode");
    assert!(tail.is_empty(), "control frame has bytes after its body");
    assert_eq!(b, body, "control body did not round-trip");
    assert_eq!(encode(&b), rest, "control body is not canonical");
}

fuzz_target!(|data: &[u8]| {
    raw::<HostMsg>(data);
    raw::<DeviceMsg>(data);
    raw_header(data);

    let mut u = Unstructured::new(data);
    let header = |u: &mut Unstructured| -> arbitrary::Result<Header> {
        Ok(Header { kind: FrameKind::Data, epoch: u.arbitrary()?, seq: u.arbitrary()?, ack: u.arbitrary()? })
    };
    if let (Ok(msg), Ok(h)) = (HostMsg::arbitrary(&mut u), header(&mut u)) {
        structured::<HostMsg, DeviceMsg>(msg, h);
    }
    if let (Ok(msg), Ok(h)) = (DeviceMsg::arbitrary(&mut u), header(&mut u)) {
        structured::<DeviceMsg, HostMsg>(msg, h);
    }

    if let (Ok(sel), Ok(epoch), Ok(body)) =
        (u8::arbitrary(&mut u), u8::arbitrary(&mut u), SyncAckBody::arbitrary(&mut u))
    {
        let h = |kind| Header { kind, epoch, seq: 0, ack: 0 };
        match sel % 3 {
            0 => control(h(FrameKind::Sync), body.nonce),
            1 => control(h(FrameKind::Confirm), body.boot_nonce),
            _ => control(h(FrameKind::SyncAck), body),
        }
    }
});
