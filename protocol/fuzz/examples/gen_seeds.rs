//! Writes the seed corpus `fuzz/seeds/<target>/` from real frames and messages.
//!
//!     cargo +nightly run --manifest-path fuzz/Cargo.toml --example gen_seeds   # from protocol/
//!
//! The seeds are deterministic; rerun after a wire-format change and commit the result.

use std::fs;
use std::path::{Path, PathBuf};

use lightrig_protocol::config::Xy;
use lightrig_protocol::event::{Snapshot, TriggerEvent};
use lightrig_protocol::frame::FrameError;
use lightrig_protocol::link::{self, FrameKind, Header, SyncAckBody};
use lightrig_protocol::sequence::{Action, Chunk, Item};
use lightrig_protocol::{
    Command, DeviceMsg, Event, HostMsg, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
};
use serde::Serialize;

fn hello() -> HostMsg {
    HostMsg {
        id: 0,
        command: Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH },
    }
}

fn chunk() -> HostMsg {
    let mut items = heapless::Vec::new();
    let actions = [
        Action::GalvoPoint { galvo: 0, to: Xy { x: 30_000, y: 31_000 } },
        Action::Laser { channel: 1, on: true },
        Action::Trigger { camera: 0, exposure: 500 },
        Action::Laser { channel: 1, on: false },
    ];
    for (i, a) in actions.into_iter().enumerate() {
        items.push(Item { delta: 100 * i as u32, action: a }).unwrap();
    }
    HostMsg { id: 1, command: Command::SequenceLoad(Chunk { sequence: 7, chunk: 0, last: true, items }) }
}

fn trigger() -> DeviceMsg {
    let snapshot = Snapshot {
        galvos: heapless::Vec::from_slice(&[Xy { x: 30_000, y: 31_000 }, Xy { x: 1, y: 2 }]).unwrap(),
        axes: heapless::Vec::from_slice(&[1200, -5, 90_000]).unwrap(),
        filters: heapless::Vec::from_slice(&[Some(3)]).unwrap(),
        lasers: 0b10,
    };
    let event =
        TriggerEvent { sequence: 7, item: 2, frame: 0, camera: 0, tick: 1_234_567, width: 500, snapshot };
    DeviceMsg::Event { index: 0, event: Event::Trigger(event) }
}

fn done(id: u16) -> DeviceMsg {
    DeviceMsg::Response { id, result: Ok(Reply::Done) }
}

fn postcard<T: Serialize>(v: &T) -> Vec<u8> {
    let mut buf = [0u8; 4096];
    postcard::to_slice(v, &mut buf).unwrap().to_vec()
}

fn frame<B: Serialize>(kind: FrameKind, epoch: u8, seq: u16, ack: u16, body: Option<&B>) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let n = link::write(&Header { kind, epoch, seq, ack }, body, &mut out);
    out[..n].to_vec()
}

/// The host session nonce the `decode_raw` links use.
const NONCE: u32 = 7;
/// The boot nonce of the `decode_raw` responders.
const BOOT: u32 = 0xB007;

/// A control frame as the `decode_raw` links would send it (bodies: `Sync` the session nonce,
/// `SyncAck` that and the boot nonce, `Confirm` the boot nonce).
fn ctrl(kind: FrameKind, epoch: u8, ack: u16) -> Vec<u8> {
    match kind {
        FrameKind::Sync => frame(kind, epoch, 0, ack, Some(&NONCE)),
        FrameKind::SyncAck => {
            frame(kind, epoch, 0, ack, Some(&SyncAckBody { nonce: NONCE, boot_nonce: BOOT }))
        }
        FrameKind::Confirm => frame(kind, epoch, 0, ack, Some(&BOOT)),
        _ => frame::<()>(kind, epoch, 0, ack, None),
    }
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    fs::write(dir.join(name), bytes).unwrap();
}

fn cat(parts: &[&[u8]]) -> Vec<u8> {
    parts.concat()
}

/// `decode_raw`: `ctl ‖ stream`. ctl 0x04 = established links in epoch 1; 0x00 = fresh, epoch 0.
fn decode_raw(dir: &Path) {
    let e = 1u8;
    write(
        dir,
        "sync_handshake",
        &cat(&[
            &[0x00],
            &ctrl(FrameKind::Sync, 0, 0),
            &ctrl(FrameKind::SyncAck, 0, 0),
            &ctrl(FrameKind::Confirm, 0, 0),
        ]),
    );
    // Established links in epoch 1: a new Sync, then the Resync a restarted device would send.
    write(
        dir,
        "resync",
        &cat(&[
            &[0x04],
            &ctrl(FrameKind::Sync, 2, 0),
            &ctrl(FrameKind::Resync, e, 0),
            &ctrl(FrameKind::Confirm, 2, 0),
        ]),
    );
    write(dir, "data_host", &cat(&[&[0x04], &frame(FrameKind::Data, e, 0, 1, Some(&hello()))]));
    write(dir, "data_trigger", &cat(&[&[0x05], &frame(FrameKind::Data, e, 0, 2, Some(&trigger()))]));
    write(
        dir,
        "ack_nak_datagram",
        &cat(&[
            &[0x06],
            &ctrl(FrameKind::Ack, e, 2),
            &frame(FrameKind::Nak, e, 0, 1, Some(&FrameError::BadCrc)),
            &frame(FrameKind::Datagram, e, 0, 0, Some(&done(3))),
        ]),
    );
    let mut damaged = frame(FrameKind::Data, e, 1, 3, Some(&done(9)));
    damaged[3] ^= 0x10;
    write(dir, "damaged_and_junk", &cat(&[&[0x13], &damaged, &[0x05, 0x01, 0x00, 0x02, 0x01, 0x00]]));
}

/// `roundtrip`: message encodings (raw half) that also drive the `arbitrary` half.
fn roundtrip(dir: &Path) {
    write(dir, "host_hello", &postcard(&hello()));
    write(dir, "host_chunk", &postcard(&chunk()));
    write(dir, "device_trigger", &postcard(&trigger()));
    write(dir, "device_done", &postcard(&done(5)));
    write(
        dir,
        "device_rejected",
        &postcard(&DeviceMsg::Rejected { seq: 4, reason: FrameError::UnknownType }),
    );
}

/// Builds a `link` script (see the op list in fuzz_targets/link.rs).
struct Script(Vec<u8>);

#[allow(dead_code)]
mod op {
    pub const SEND_HOST: u8 = 0;
    pub const SEND_DEVICE: u8 = 1;
    pub const DATAGRAM_HOST: u8 = 2;
    pub const DATAGRAM_DEVICE: u8 = 3;
    pub const ADVANCE: u8 = 4;
    pub const POLL_HOST: u8 = 5;
    pub const POLL_DEVICE: u8 = 6;
    pub const DELIVER_TO_DEVICE: u8 = 7;
    pub const DELIVER_TO_HOST: u8 = 8;
    pub const DROP: u8 = 9;
    pub const DUPLICATE: u8 = 10;
    pub const SWAP: u8 = 11;
    pub const FLIP: u8 = 12;
    pub const PARTIAL: u8 = 13;
    pub const FORGE_TO_DEVICE: u8 = 14;
    pub const FORGE_TO_HOST: u8 = 15;
    pub const JUNK: u8 = 16;
    pub const ROUND: u8 = 17;
    pub const RESTART: u8 = 18;
}

/// `forge` selector bits (see fuzz_targets/link.rs): the frame kind is the low 3 bits.
#[allow(dead_code)]
mod forge {
    /// Raw packet bytes (a blob) instead of a header and body.
    pub const RAW: u8 = 8;
    /// An explicit epoch byte follows (else the receiver's epoch).
    pub const EPOCH: u8 = 16;
    /// Body selectors (the byte after seq and ack).
    pub const BODY_NONE: u8 = 0;
    pub const BODY_MESSAGE: u8 = 1;
    pub const BODY_FRAME_ERROR: u8 = 2;
    pub const BODY_RAW: u8 = 3;
    pub const BODY_SESSION_NONCE: u8 = 4;
    pub const BODY_U32: u8 = 5;
    pub const BODY_SYNC_ACK: u8 = 6;
    pub const BODY_BOOT_NONCE: u8 = 7;
}

impl Script {
    /// Header: rto - 1, epoch, device rx_reserve (low 2 bits), host nonce.
    fn new(rto: u8, epoch: u8, reserve: u8, nonce: u8) -> Self {
        Script(vec![rto, epoch, reserve, nonce])
    }
    fn op(mut self, op: u8, args: &[u8]) -> Self {
        self.0.push(op);
        self.0.extend_from_slice(args);
        self
    }
    fn blob(mut self, op: u8, prefix: &[u8], bytes: &[u8]) -> Self {
        assert!(bytes.len() < 255);
        self.0.push(op);
        self.0.extend_from_slice(prefix);
        self.0.push(bytes.len() as u8);
        self.0.extend_from_slice(bytes);
        self
    }
}

fn link_scripts(dir: &Path) {
    use op::*;
    let normal = Script::new(20, 1, 1, 9)
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .blob(SEND_DEVICE, &[], &postcard(&trigger()))
        .op(ROUND, &[])
        .op(ROUND, &[])
        .blob(SEND_HOST, &[], &postcard(&chunk()))
        .op(ROUND, &[])
        .op(ROUND, &[]);
    write(dir, "normal", &normal.0);

    let lossy = Script::new(10, 7, 0, 1)
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .op(POLL_HOST, &[])
        .op(DUPLICATE, &[0])
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[])
        .op(DROP, &[1])
        .op(ADVANCE, &[70])
        .op(POLL_HOST, &[])
        .op(SWAP, &[0, 0, 1])
        .op(FLIP, &[0, 1, 3, 0, 0x40])
        .op(ROUND, &[])
        .blob(DATAGRAM_DEVICE, &[], &postcard(&done(2)))
        .op(PARTIAL, &[1, 3])
        .op(ROUND, &[])
        .op(ADVANCE, &[255])
        .op(ROUND, &[]);
    write(dir, "lossy", &lossy.0);

    // Forged frames in the right epoch: a Data frame whose seq is not the expected one (ack 0),
    // a Nak, and a Data frame with a message body that does not decode.
    let data = FrameKind::Data as u8;
    let forged = Script::new(5, 3, 2, 4)
        .op(ROUND, &[])
        .op(ROUND, &[])
        .blob(FORGE_TO_DEVICE, &[data, 4, 0, forge::BODY_MESSAGE], &postcard(&chunk()))
        .op(FORGE_TO_HOST, &[FrameKind::Nak as u8, 0, 0, forge::BODY_FRAME_ERROR, 1])
        .blob(FORGE_TO_HOST, &[data, 9, 0, forge::BODY_RAW], &[0x00, 0x07, 0xff])
        .blob(SEND_DEVICE, &[], &postcard(&done(0)))
        .op(ROUND, &[])
        .blob(JUNK, &[0], &[0x41, 0x42, 0x00, 0x00])
        // A forged SyncAck with the session nonce and the device's boot nonce, in the host's
        // epoch, and a forged Confirm with the device's boot nonce.
        .op(FORGE_TO_HOST, &[FrameKind::SyncAck as u8, 0, 0, forge::BODY_SYNC_ACK, 0])
        .op(FORGE_TO_DEVICE, &[FrameKind::Confirm as u8, 0, 0, forge::BODY_BOOT_NONCE])
        .op(ROUND, &[]);
    write(dir, "forged", &forged.0);

    // The device restarts mid-session with two events queued; the host's next request meets a
    // device that knows no epoch (Resync), and both sides' messages flow in the new epoch.
    let restart = Script::new(20, 1, 1, 9)
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .blob(SEND_DEVICE, &[], &postcard(&trigger()))
        .op(ROUND, &[]) // Sync
        .op(ROUND, &[]) // SyncAck
        .op(ROUND, &[]) // Confirm, then data both ways
        .op(ROUND, &[])
        .op(RESTART, &[2])
        .blob(SEND_HOST, &[], &postcard(&chunk()))
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ROUND, &[]);
    write(dir, "restart", &restart.0);

    // A stale copy of the Sync reaches the device after it restarted: the device answers with its
    // new boot nonce and sends nothing before Confirm; the host starts a new epoch.
    let stale_sync = Script::new(10, 5, 0, 3)
        .op(POLL_HOST, &[]) // Sync
        .op(ADVANCE, &[70])
        .op(POLL_HOST, &[]) // Sync again, the stale copy
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[]) // SyncAck
        .op(DELIVER_TO_HOST, &[])
        .op(POLL_HOST, &[]) // Confirm, behind the stale Sync
        .op(SWAP, &[0, 0, 1])
        .op(DELIVER_TO_DEVICE, &[]) // Confirm
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .op(POLL_HOST, &[]) // the request, behind the stale Sync
        .op(RESTART, &[1])
        .op(DELIVER_TO_DEVICE, &[]) // the stale Sync reaches the new device
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ADVANCE, &[255])
        .op(ROUND, &[]);
    write(dir, "stale_sync_after_restart", &stale_sync.0);

    // The Confirm is lost: the half-open device answers the host's next data frame with
    // another SyncAck, and the host confirms again.
    let lost_confirm = Script::new(15, 0, 1, 7)
        .blob(SEND_DEVICE, &[], &postcard(&trigger()))
        .op(ROUND, &[]) // Sync
        .op(ROUND, &[]) // SyncAck
        .op(POLL_HOST, &[]) // Confirm
        .op(DROP, &[0])
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ADVANCE, &[80])
        .op(ROUND, &[])
        .op(ROUND, &[]);
    write(dir, "lost_confirm", &lost_confirm.0);

    // The Confirm is lost and the host has nothing to send: the half-open device repeats its
    // SyncAck at its timeout, the host confirms again, and the device's event goes out.
    let lost_confirm_idle = Script::new(15, 0, 1, 7)
        .blob(SEND_DEVICE, &[], &postcard(&trigger()))
        .op(ROUND, &[]) // Sync
        .op(ROUND, &[]) // SyncAck
        .op(POLL_HOST, &[]) // Confirm
        .op(DROP, &[0])
        .op(ROUND, &[])
        .op(ADVANCE, &[80])
        .op(ROUND, &[]) // SyncAck again
        .op(ROUND, &[]) // Confirm
        .op(ROUND, &[]); // the event
    write(dir, "lost_confirm_idle_host", &lost_confirm_idle.0);

    // The known zombie-epoch path (the target excludes it from its checks): after a restart
    // and a reconnection in epoch 2, a stale Sync(1) then a stale Sync(2) reach the device,
    // which restarts its epoch-2 stream; the host confirms it again and keeps its own.
    let zombie = Script::new(49, 1, 0, 5)
        .op(POLL_HOST, &[]) // Sync(1)
        .op(ADVANCE, &[255])
        .op(POLL_HOST, &[]) // its stale copy
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[])
        .op(POLL_HOST, &[]) // Confirm
        .op(SWAP, &[0, 0, 1])
        .op(DELIVER_TO_DEVICE, &[])
        .op(RESTART, &[0])
        .blob(SEND_HOST, &[], &postcard(&hello()))
        .op(POLL_HOST, &[])
        .op(SWAP, &[0, 0, 1])
        .op(DELIVER_TO_DEVICE, &[]) // data to the new device: Resync
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[]) // host: epoch 2
        .op(POLL_HOST, &[]) // Sync(2)
        .op(ADVANCE, &[255])
        .op(POLL_HOST, &[]) // its stale copy; wire: Sync(1), Sync(2), Sync(2)
        .op(SWAP, &[0, 0, 1])
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[]) // host up in 2
        .op(POLL_HOST, &[]) // Confirm, request; wire: Sync(1), Sync(2), Confirm, request
        .op(SWAP, &[0, 0, 2])
        .op(SWAP, &[0, 1, 3])
        .op(DELIVER_TO_DEVICE, &[])
        .op(DELIVER_TO_DEVICE, &[]) // device up in 2, request delivered
        .blob(SEND_DEVICE, &[], &postcard(&done(0)))
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[])
        .op(POLL_HOST, &[]) // its ack; wire: Sync(1), Sync(2), Ack
        .op(SWAP, &[0, 0, 2])
        .op(SWAP, &[0, 1, 2])
        .op(DELIVER_TO_DEVICE, &[]) // device: event 0 acknowledged
        .blob(SEND_DEVICE, &[], &postcard(&trigger()))
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[])
        .op(POLL_HOST, &[]) // the ack of event 1, lost
        .op(SWAP, &[0, 0, 2])
        .op(DROP, &[0])
        .op(SWAP, &[0, 0, 1]) // wire: Sync(1), Sync(2)
        .blob(SEND_DEVICE, &[], &postcard(&done(1)))
        .op(DELIVER_TO_DEVICE, &[]) // Sync(1)
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[])
        .op(DELIVER_TO_DEVICE, &[]) // Sync(2): a new stream in epoch 2
        .op(POLL_DEVICE, &[])
        .op(DELIVER_TO_HOST, &[]) // same nonce, same boot nonce: Confirm again
        .op(ROUND, &[])
        .op(ROUND, &[])
        .op(ADVANCE, &[255])
        .op(ROUND, &[]);
    write(dir, "zombie_epoch", &zombie.0);

    // The known premature-Confirm path (excluded as well): two incarnations answer the same
    // Sync; the host comes up with the second, then sees the first's SyncAck and reconnects,
    // but the Confirm it had queued goes out behind Sync(2), and the second incarnation comes
    // up in epoch 2 before the host did. It sends an event and restarts; the third incarnation
    // brings epoch 2 up properly, and the second's late event is taken for the third's.
    let premature = Script::new(49, 1, 0, 5)
        .op(POLL_HOST, &[]) // Sync(1)
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[]) // SyncAck of boot 0
        .op(RESTART, &[0])
        .op(ADVANCE, &[255])
        .op(POLL_HOST, &[]) // Sync(1) again
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[]) // SyncAck of boot 1
        .op(SWAP, &[1, 0, 1])
        .op(DELIVER_TO_HOST, &[]) // up with boot 1
        .op(DELIVER_TO_HOST, &[]) // boot 0: reconnect in epoch 2
        .op(POLL_HOST, &[]) // Sync(2), Confirm(2, boot 1)
        .op(DELIVER_TO_DEVICE, &[])
        .op(DELIVER_TO_DEVICE, &[]) // boot 1 up in epoch 2
        .op(POLL_DEVICE, &[])
        .op(DROP, &[1]) // its SyncAck(2) is lost
        .blob(SEND_DEVICE, &[], &postcard(&done(0)))
        .op(POLL_DEVICE, &[]) // its event, late on the wire
        .op(RESTART, &[1])
        .op(ADVANCE, &[255])
        .op(POLL_HOST, &[]) // Sync(2) again
        .op(DELIVER_TO_DEVICE, &[])
        .op(POLL_DEVICE, &[]) // SyncAck of boot 2
        .op(SWAP, &[1, 0, 1])
        .op(DELIVER_TO_HOST, &[]) // up with boot 2
        .op(POLL_HOST, &[])
        .op(DELIVER_TO_DEVICE, &[]) // Confirm(2, boot 2)
        .op(POLL_DEVICE, &[]) // boot 2's event
        .op(DELIVER_TO_HOST, &[]) // boot 1's late event, acknowledged
        .op(POLL_HOST, &[])
        .op(DELIVER_TO_DEVICE, &[]) // the ack: boot 2's event leaves its queue
        .op(ROUND, &[])
        .op(ROUND, &[]);
    write(dir, "premature_confirm", &premature.0);
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("seeds");
    for (target, gen) in
        [("decode_raw", decode_raw as fn(&Path)), ("roundtrip", roundtrip), ("link", link_scripts)]
    {
        let dir = root.join(target);
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        gen(&dir);
        let total: u64 = fs::read_dir(&dir).unwrap().map(|e| e.unwrap().metadata().unwrap().len()).sum();
        println!("{target}: {} seeds, {total} bytes", fs::read_dir(&dir).unwrap().count());
    }
}
