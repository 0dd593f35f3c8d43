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

/// `controller` scripts (layout: the module doc of fuzz_targets/controller.rs; the op and
/// setup numbers are its `op`, `setup`, `cop` and `csetup` modules).
mod ctl {
    // Rig-mode ops.
    pub const CONFIG: u8 = 0;
    pub const ARM: u8 = 2;
    pub const DISARM: u8 = 3;
    pub const IMMEDIATE: u8 = 4;
    pub const HOME: u8 = 6;
    pub const LOAD: u8 = 8;
    pub const START: u8 = 10;
    pub const ABORT: u8 = 11;
    pub const ESTOP: u8 = 12;
    pub const CLEAR_FAULT: u8 = 13;
    pub const HOST_SEEN: u8 = 14;
    pub const ADVANCE: u8 = 15;
    pub const INTERLOCK: u8 = 16;
    pub const SWITCH: u8 = 17;
    pub const GALVO_FAILS: u8 = 19;
    pub const DRAIN: u8 = 20;
    pub const LATE_WAKE: u8 = 21;
    // Rig-mode setup flags.
    pub const GALVO: u16 = 1 << 0;
    pub const LASERS: u16 = 1 << 1;
    pub const CAMERAS: u16 = 1 << 2;
    pub const STEPPERS: u16 = 1 << 3;
    pub const WHEEL: u16 = 1 << 4;
    pub const COILS: u16 = 1 << 5;
    pub const SWITCHES: u16 = 1 << 6;
    pub const EXPOSURE: u16 = 1 << 7;
    pub const WATCHDOG: u16 = 1 << 8;
    pub const ARMED: u16 = 1 << 9;
    pub const HOMED: u16 = 1 << 10;
    // Controller-mode ops and setup flags.
    pub const C_SEND: u8 = 0;
    pub const C_DATAGRAM: u8 = 2;
    pub const C_ADVANCE: u8 = 3;
    pub const C_INTERLOCK: u8 = 4;
    pub const C_HELLO: u8 = 1 << 0;
    pub const C_CONFIGURE: u8 = 1 << 1;
    pub const C_SWITCHES: u8 = 1 << 2;
    pub const C_EXPOSURE: u8 = 1 << 3;
    // Friendly commands (controller mode).
    pub const GET_STATUS: u8 = 1;
    pub const HEARTBEAT: u8 = 2;
    pub const CONFIGURE: u8 = 3;
    pub const ARM_CMD: u8 = 4;
    pub const IMMEDIATE_CMD: u8 = 6;
    pub const HOME_CMD: u8 = 7;
    pub const LOAD_CMD: u8 = 8;
    pub const START_CMD: u8 = 9;
    pub const ESTOP_CMD: u8 = 11;
    pub const CLEAR_FAULT_CMD: u8 = 12;
}

/// A friendly action for the `controller` target, as bytes (see its `friendly_action`).
#[derive(Clone, Copy)]
enum Act {
    /// Galvo 0 to (x, y) (codes; must be 1000..=64000).
    Point(u16, u16),
    /// Galvo 0 sweep to (x, y) over `duration` ticks in `steps` (1..=256) updates.
    Line(u16, u16, u16, u16),
    Laser(u8, bool),
    /// Axis, target, optional (speed, accel / 8).
    Move(u8, i16, Option<(u16, u16)>),
    Wheel(u8),
    /// Channel, ramp ticks, partials (mHz, amplitude).
    Coil(u8, u16, &'static [(u32, u16)]),
    /// Camera, exposure ticks (0: the camera's pulse).
    Trigger(u8, u16),
    /// 0: MoveDone(stepper i), 1: MoveDone(wheel), 2: LaserReady(i), 3: ExposureEnd(i); timeout.
    Wait(u8, u8, u32),
    Marker(u8),
}

impl Act {
    fn bytes(self) -> Vec<u8> {
        let mut b = Vec::new();
        let xy = |b: &mut Vec<u8>, x: u16, y: u16| {
            b.extend_from_slice(&(x - 1000).to_le_bytes());
            b.extend_from_slice(&(y - 1000).to_le_bytes());
        };
        match self {
            Act::Point(x, y) => {
                b.extend_from_slice(&[0, 0]);
                xy(&mut b, x, y);
            }
            Act::Line(x, y, duration, steps) => {
                b.extend_from_slice(&[1, 0]);
                xy(&mut b, x, y);
                b.extend_from_slice(&duration.to_le_bytes());
                b.push((steps - 1) as u8);
            }
            Act::Laser(ch, on) => b.extend_from_slice(&[2, ch | if on { 0 } else { 0x80 }]),
            Act::Move(axis, target, profile) => {
                b.extend_from_slice(&[3, axis | if profile.is_some() { 0x80 } else { 0 }]);
                b.extend_from_slice(&target.to_le_bytes());
                if let Some((speed, accel)) = profile {
                    b.extend_from_slice(&speed.to_le_bytes());
                    b.extend_from_slice(&accel.to_le_bytes());
                }
            }
            Act::Wheel(slot) => b.extend_from_slice(&[4, 0, slot]),
            Act::Coil(ch, ramp, partials) => {
                b.extend_from_slice(&[5, ch]);
                b.extend_from_slice(&ramp.to_le_bytes());
                b.push(partials.len() as u8);
                for &(mhz, amplitude) in partials {
                    b.extend_from_slice(&(mhz - 1000).to_le_bytes());
                    b.extend_from_slice(&(amplitude * 4).to_le_bytes());
                    b.extend_from_slice(&0u16.to_le_bytes());
                }
            }
            Act::Trigger(cam, exposure) => {
                b.extend_from_slice(&[6, cam | if exposure > 0 { 0x80 } else { 0 }]);
                if exposure > 0 {
                    b.extend_from_slice(&exposure.to_le_bytes());
                }
            }
            Act::Wait(kind, i, timeout) => {
                b.extend_from_slice(&[7, i, kind]);
                b.extend_from_slice(&timeout.to_le_bytes());
            }
            Act::Marker(id) => b.extend_from_slice(&[8, 0, id]),
        }
        b
    }
}

/// A friendly chunk: the next chunk of the loaded sequence (`next`) or chunk 0 of sequence
/// `id` (0..=3); `last`; items as (delta, action).
fn chunk_bytes(next: bool, id: u8, last: bool, items: &[(u16, Act)]) -> Vec<u8> {
    let mut b = vec![u8::from(next) | u8::from(last) << 1 | id << 2, items.len() as u8];
    for &(delta, act) in items {
        b.extend_from_slice(&delta.to_le_bytes());
        b.extend_from_slice(&act.bytes());
    }
    b
}

struct Ctl(Vec<u8>);

impl Ctl {
    fn rig(setup: u16) -> Self {
        let mut b = vec![0];
        b.extend_from_slice(&setup.to_le_bytes());
        Ctl(b)
    }
    fn controller(setup: u8) -> Self {
        Ctl(vec![1, setup])
    }
    fn op(mut self, op: u8, args: &[u8]) -> Self {
        self.0.push(op);
        self.0.extend_from_slice(args);
        self
    }
    fn act(self, op: u8, act: Act) -> Self {
        self.op(op, &act.bytes())
    }
    /// Advances `ticks` (rig or controller mode: `op`).
    fn advance(self, op: u8, ticks: u32) -> Self {
        match ticks {
            0..=0xff => self.op(op, &[0, ticks as u8]),
            0x100..=0xffff => self.op(op, &[1, ticks as u8, (ticks >> 8) as u8]),
            _ => self.op(op, &[&[2][..], &ticks.to_le_bytes()].concat()),
        }
    }
    /// Starts the loaded sequence now.
    fn start_now(self) -> Self {
        self.op(ctl::START, &[1])
    }
    /// Controller mode: a friendly command (reliable, or as a datagram).
    fn send(self, datagram: bool, command: u8, args: &[u8]) -> Self {
        let op = if datagram { ctl::C_DATAGRAM } else { ctl::C_SEND };
        self.op(op, &[&[command][..], args].concat())
    }
}

fn controller_scripts(dir: &Path) {
    use ctl::*;
    use Act::*;

    // A scan line: galvo jump, laser on, wait for its warm-up, a triggered exposure waited for,
    // a galvo sweep, laser off; then the heartbeat keeps the watchdog quiet.
    let items = [
        (0, Point(30_000, 31_000)),
        (10, Laser(0, true)),
        (0, Wait(2, 0, 100_000)),
        (250, Trigger(0, 500)),
        (0, Wait(3, 0, 10_000)),
        (100, Line(40_000, 31_000, 2_000, 20)),
        (2_500, Laser(0, false)),
        (10, Marker(7)),
    ];
    let scan = Ctl::rig(GALVO | LASERS | CAMERAS | EXPOSURE | ARMED | WATCHDOG)
        .op(LOAD, &chunk_bytes(false, 1, true, &items))
        .start_now()
        .advance(ADVANCE, 50_000)
        .op(DRAIN, &[])
        .op(HOST_SEEN, &[1])
        .advance(ADVANCE, 500_000)
        .op(DISARM, &[]);
    write(dir, "rig_scan_line", &scan.0);

    // Homed axes: a jog, a filter change, a sequence of a move and a filter change waited for,
    // then a max limit placed ahead of axis 0 and a move into it (a limit fault), cleared and
    // homed again.
    let items = [
        (0, Move(1, -14_000, Some((5_000, 5_000)))),
        (0, Wait(0, 1, 1_000_000)),
        (0, Wheel(5)),
        (0, Wait(1, 0, 1_000_000)),
        (100, Move(0, 0, None)),
    ];
    let motion = Ctl::rig(STEPPERS | WHEEL | SWITCHES | HOMED)
        .act(IMMEDIATE, Move(0, 1_000, None))
        .advance(ADVANCE, 1_000_000)
        .act(IMMEDIATE, Wheel(3))
        .advance(ADVANCE, 60_000)
        .op(LOAD, &chunk_bytes(false, 2, true, &items))
        .start_now()
        .advance(ADVANCE, 1_000_000)
        .op(DRAIN, &[])
        .op(SWITCH, &[1 << 3, 50, 0, 1, 0])
        .act(IMMEDIATE, Move(0, 5_000, None))
        .advance(ADVANCE, 60_000)
        .op(CLEAR_FAULT, &[])
        .op(HOME, &[0])
        .advance(ADVANCE, 300_000);
    write(dir, "rig_motion", &motion.0);

    // Voice coils: a chord on coil 0, a sequence that starts coil 1, fades coil 0 and
    // triggers camera 1, then an emergency stop (every coil fades).
    let items =
        [(0, Coil(1, 500, &[(220_000, 10_000)])), (5_000, Coil(0, 2_000, &[])), (5_000, Trigger(1, 0))];
    let coils = Ctl::rig(COILS | CAMERAS)
        .act(IMMEDIATE, Coil(0, 1_000, &[(440_000, 8_000), (1_000_000, 4_000)]))
        .advance(ADVANCE, 20_000)
        .op(LOAD, &chunk_bytes(false, 0, true, &items))
        .start_now()
        .advance(ADVANCE, 30_000)
        .op(ESTOP, &[])
        .advance(ADVANCE, 30_000)
        .op(DRAIN, &[]);
    write(dir, "rig_coils", &coils.0);

    // One fault after another: an interlock opening under a lit laser, the on-time limit of an
    // active-low laser, an underrun, a late wake-up in a sequence, a failing galvo converter and
    // a lapsed heartbeat.
    let markers = [(1_000, Marker(1)), (1_000, Marker(2)), (1_000, Marker(3)), (1_000, Marker(4))];
    let faults = Ctl::rig(GALVO | LASERS | ARMED | WATCHDOG)
        .act(IMMEDIATE, Laser(1, true))
        .advance(ADVANCE, 10_000)
        .op(INTERLOCK, &[0x81])
        .op(CLEAR_FAULT, &[])
        .op(INTERLOCK, &[0x01])
        .op(CONFIG, &[12, 0])
        .op(ARM, &[0b111])
        .act(IMMEDIATE, Laser(2, true))
        .advance(ADVANCE, 30_000)
        .op(CLEAR_FAULT, &[])
        .op(LOAD, &chunk_bytes(false, 3, false, &markers[..2]))
        .start_now()
        .advance(ADVANCE, 5_000)
        .op(CLEAR_FAULT, &[])
        .op(LOAD, &chunk_bytes(false, 3, true, &markers))
        .start_now()
        .op(LATE_WAKE, &[0x88, 0x13])
        .op(CLEAR_FAULT, &[])
        .op(GALVO_FAILS, &[1])
        .act(IMMEDIATE, Point(5_000, 5_000))
        .op(CLEAR_FAULT, &[])
        .op(GALVO_FAILS, &[0])
        .op(HOST_SEEN, &[1])
        .advance(ADVANCE, 1_000_000)
        .op(DRAIN, &[]);
    write(dir, "rig_faults", &faults.0);

    // A long sequence streamed in chunks under credit, then aborted.
    let train = [(1_000, Trigger(0, 0)); 32];
    let mut stream = Ctl::rig(CAMERAS | EXPOSURE).op(LOAD, &chunk_bytes(false, 1, false, &train)).start_now();
    for _ in 0..6 {
        stream = stream
            .advance(ADVANCE, 20_000)
            .op(DRAIN, &[])
            .op(LOAD, &chunk_bytes(true, 0, false, &train[..20]));
    }
    let stream = stream.advance(ADVANCE, 10_000).op(ABORT, &[1]).op(DRAIN, &[]);
    write(dir, "rig_stream", &stream.0);

    // The controller: a session (Hello, every preset configured), arm, a lit laser, a sequence,
    // status, an emergency stop as a datagram, clear, home, heartbeats.
    let items =
        [(100, Laser(1, true)), (0, Wait(2, 1, 100_000)), (200, Trigger(0, 0)), (1_000, Laser(1, false))];
    let session = Ctl::controller(C_HELLO | C_CONFIGURE | C_SWITCHES | C_EXPOSURE)
        .send(false, ARM_CMD, &[0b11])
        .send(false, IMMEDIATE_CMD, &Laser(0, true).bytes())
        .advance(C_ADVANCE, 10_000)
        .send(false, GET_STATUS, &[])
        .send(false, LOAD_CMD, &chunk_bytes(false, 2, true, &items))
        .send(false, START_CMD, &[0])
        .advance(C_ADVANCE, 50_000)
        .send(true, ESTOP_CMD, &[])
        .advance(C_ADVANCE, 100)
        .send(false, CLEAR_FAULT_CMD, &[])
        .send(false, HOME_CMD, &[0])
        .advance(C_ADVANCE, 300_000)
        .send(false, HEARTBEAT, &[])
        .advance(C_ADVANCE, 300_000)
        .send(false, GET_STATUS, &[]);
    write(dir, "controller_session", &session.0);

    // The controller with a 50 ms heartbeat timeout (preset 11) that lapses, an interlock
    // opening, and the fault cleared.
    let watchdog = Ctl::controller(C_HELLO | C_CONFIGURE)
        .send(false, CONFIGURE, &[11, 0])
        .send(false, ARM_CMD, &[0b1])
        .send(false, IMMEDIATE_CMD, &Laser(0, true).bytes())
        .op(C_INTERLOCK, &[0x80])
        .advance(C_ADVANCE, 200_000)
        .send(false, CLEAR_FAULT_CMD, &[])
        .send(false, GET_STATUS, &[]);
    write(dir, "controller_watchdog", &watchdog.0);
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("seeds");
    let targets = [
        ("decode_raw", decode_raw as fn(&Path)),
        ("roundtrip", roundtrip),
        ("link", link_scripts),
        ("controller", controller_scripts),
    ];
    for (target, gen) in targets {
        let dir = root.join(target);
        // Generated seeds are rewritten; minimised crash reproducers (`regression-*`, copied
        // from artifacts/ once fixed) stay.
        fs::create_dir_all(&dir).unwrap();
        for entry in fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            let keep =
                path.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("regression-"));
            if !keep {
                fs::remove_file(&path).unwrap();
            }
        }
        gen(&dir);
        let total: u64 = fs::read_dir(&dir).unwrap().map(|e| e.unwrap().metadata().unwrap().len()).sum();
        println!("{target}: {} seeds, {total} bytes", fs::read_dir(&dir).unwrap().count());
    }
}
