//! Codec throughput: encode+frame and deframe+decode of two representative messages.
//!
//!     cargo bench -p lightrig-protocol --bench codec
//!
//! - `trigger`: a `DeviceMsg::Event` carrying `Event::Trigger` with a snapshot of 2 galvos,
//!   3 axes and 1 filter wheel: the message the device sends per camera frame.
//! - `chunk`: a `HostMsg` with `Command::SequenceLoad`, a chunk of typical items (galvo
//!   points, laser on/off, camera triggers), as many as one packet takes: `MAX_CHUNK_ITEMS`
//!   at most, encoded within `link::MAX_MESSAGE`.
//!
//! `encode` is `link::write` under a `Data` header (postcard, CRC-32, COBS, delimiter);
//! `decode` is `FrameDecoder::feed` (COBS, CRC check) then the header and `link::decode`.
//! Throughput is reported in wire bytes (decimal MB/s); one iteration is one message, so
//! messages/s is 1 / time. The frame sizes are printed first.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::{Snapshot, TriggerEvent};
use lightrig_protocol::frame::FrameDecoder;
use lightrig_protocol::link::{self, FrameKind, Header};
use lightrig_protocol::message::Message;
use lightrig_protocol::sequence::{Action, Chunk, Item};
use lightrig_protocol::{Command, DeviceMsg, Event, HostMsg, MAX_CHUNK_ITEMS, MAX_FRAME};

/// A trigger event as the device reports it mid-sequence (1 MHz ticks, ~20 minutes in).
fn trigger_event() -> DeviceMsg {
    let snapshot = Snapshot {
        galvos: heapless::Vec::from_slice(&[Xy { x: 31_874, y: 29_310 }, Xy { x: 40_102, y: 12_550 }])
            .unwrap(),
        axes: heapless::Vec::from_slice(&[152_400, -20_315, 3_600]).unwrap(),
        filters: heapless::Vec::from_slice(&[Some(3)]).unwrap(),
        lasers: 0b0000_0101,
    };
    let event = TriggerEvent {
        sequence: 42,
        item: 18_344,
        frame: 4_585,
        camera: 1,
        tick: 1_234_567_890,
        width: 2_000,
        snapshot,
    };
    DeviceMsg::Event { index: 91_733, event: Event::Trigger(event) }
}

/// A scan pattern: move the galvos, light up, trigger the camera, go dark; repeated.
fn typical_item(i: u32) -> Item {
    let action = match i % 4 {
        0 => Action::GalvoPoint {
            galvo: (i / 4 % 2) as u8,
            to: Xy { x: 20_000 + (i * 397 % 25_000) as u16, y: 18_000 + (i * 211 % 27_000) as u16 },
        },
        1 => Action::Laser { channel: 2, on: true },
        2 => Action::Trigger { camera: 0, exposure: 1_500 },
        _ => Action::Laser { channel: 2, on: false },
    };
    let delta = [250, 40, 10, 1_500][(i % 4) as usize];
    Item { delta, action }
}

/// A `SequenceLoad` chunk holding as many typical items as one packet takes.
fn full_chunk() -> HostMsg {
    let mut msg = HostMsg {
        id: 1_207,
        command: Command::SequenceLoad(Chunk {
            sequence: 42,
            chunk: 573,
            last: false,
            items: heapless::Vec::new(),
        }),
    };
    for i in 0..MAX_CHUNK_ITEMS as u32 {
        let Command::SequenceLoad(chunk) = &mut msg.command else { unreachable!() };
        chunk.items.push(typical_item(i)).unwrap();
        if postcard::experimental::serialized_size(&msg).unwrap() > link::MAX_MESSAGE {
            let Command::SequenceLoad(chunk) = &mut msg.command else { unreachable!() };
            chunk.items.pop();
            break;
        }
    }
    msg
}

/// A mid-stream Data header: two- and three-byte varints, as after a while on the link.
const HEADER: Header = Header { kind: FrameKind::Data, epoch: 3, seq: 20_000, ack: 300 };

fn frame_of<T: Message>(msg: &T) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let n = link::write(&HEADER, Some(msg), &mut out);
    out[..n].to_vec()
}

fn bench_message<T: Message + PartialEq>(c: &mut Criterion, name: &str, note: &str, msg: T) {
    let frame = frame_of(&msg);
    let body = postcard::experimental::serialized_size(&msg).unwrap();
    println!("{name}: {note}message {body} B, frame {} B on the wire", frame.len());

    // The decode path must give the message back, or the measurement is meaningless.
    let mut dec = FrameDecoder::new();
    let mut decoded = None;
    dec.feed(&frame, |r| {
        let (h, body) = postcard::take_from_bytes::<Header>(r.unwrap()).unwrap();
        assert_eq!(h, HEADER);
        decoded = Some(link::decode::<T>(body).unwrap());
    });
    assert!(decoded.as_ref() == Some(&msg));

    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::BytesDecimal(frame.len() as u64));
    group.bench_function("encode", |b| {
        let mut out = [0u8; MAX_FRAME];
        b.iter(|| link::write(black_box(&HEADER), Some(black_box(&msg)), &mut out))
    });
    group.bench_function("decode", |b| {
        let mut dec = FrameDecoder::new();
        b.iter(|| {
            let mut got = None;
            dec.feed(black_box(&frame), |r| {
                if let Ok(packet) = r {
                    if let Ok((header, body)) = postcard::take_from_bytes::<Header>(packet) {
                        got = Some((header, link::decode::<T>(body)));
                    }
                }
            });
            got
        })
    });
    group.finish();
}

fn codec(c: &mut Criterion) {
    bench_message(c, "trigger", "", trigger_event());
    let chunk = full_chunk();
    let Command::SequenceLoad(ref load) = chunk.command else { unreachable!() };
    let note = format!("{} items, ", load.items.len());
    bench_message(c, "chunk", &note, chunk);
}

criterion_group!(benches, codec);
criterion_main!(benches);
