//! The host link against the firmware controller: handshake, device restart, forged frames.

use lightrig_protocol::frame::FrameError;
use lightrig_protocol::link::{self, FrameKind, Header};
use lightrig_protocol::{Command, DeviceMsg, Error, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH};
use lightrig_tests::Pair;

fn hello() -> Command {
    Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH }
}

#[test]
fn version_mismatch_is_refused_with_both_versions() {
    let mut p = Pair::new();
    let got = p.request(1, Command::Hello { protocol_version: 99, schema_hash: SCHEMA_HASH }, 10);
    assert_eq!(
        got,
        vec![DeviceMsg::Response {
            id: 1,
            result: Err(Error::VersionMismatch { device: PROTOCOL_VERSION, host: 99 })
        }]
    );
    // Still closed.
    assert_eq!(
        p.request(2, Command::Heartbeat, 10),
        vec![DeviceMsg::Response { id: 2, result: Err(Error::HandshakeRequired) }]
    );
}

#[test]
fn a_restarted_device_is_found_again_and_asks_for_a_new_hello() {
    let mut p = Pair::new();
    let got = p.request(1, hello(), 10);
    assert!(matches!(got[..], [DeviceMsg::Response { id: 1, result: Ok(Reply::Hello(_)) }]));
    p.restart_device();
    // The request sent into the restarted device is not lost: the link resyncs and resends.
    let got = p.request(2, Command::GetClock, 10);
    assert_eq!(got, vec![DeviceMsg::Response { id: 2, result: Err(Error::HandshakeRequired) }]);
    assert_eq!(p.host.epoch(), 2);
    let got = p.request(3, hello(), 10);
    assert!(matches!(got[..], [DeviceMsg::Response { id: 3, result: Ok(Reply::Hello(_)) }]));
}

#[test]
fn forged_frame_with_valid_crc_is_answered_with_rejected_and_the_device_keeps_working() {
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    // Sequence 1 is next; command variant 250 does not exist.
    let mut out = [0u8; MAX_FRAME];
    let h = Header { kind: FrameKind::Data, epoch: 1, seq: 1, ack: 1 };
    let n = link::write(&h, Some(&(9u16, 250u8)), &mut out);
    p.device.receive(&out[..n]);
    let got = p.messages(5);
    assert_eq!(got, vec![DeviceMsg::Rejected { seq: 1, reason: FrameError::UnknownType }]);
    assert_eq!(p.device.link().stats().unknown_type, 1);
    // Garbage between frames is counted and the next request is still answered.
    p.device.receive(&[0x13, 0x37, 0x00, 0xff, 0xff, 0x00]);
    assert_eq!(p.device.link().stats().rejected(), 3);
    // The host's own seq 1 collides with the forged one and is dropped as a duplicate; its
    // retransmission never succeeds. A real host never forges, so resynchronise instead:
    p.host.connect(2, 0x2157, 0);
    p.run(5);
    let got = p.request(2, hello(), 10);
    assert!(matches!(got[..], [DeviceMsg::Response { id: 2, result: Ok(Reply::Hello(_)) }]));
}

#[test]
fn every_command_gets_exactly_one_typed_answer() {
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    let commands = [
        Command::GetClock,
        Command::GetStatus,
        Command::Heartbeat,
        Command::Arm { lasers: 1 },
        Command::Disarm,
        Command::ClearFault,
        Command::SequenceAbort { sequence: 1 },
    ];
    for (i, c) in commands.into_iter().enumerate() {
        let id = 10 + i as u16;
        let got = p.request(id, c.clone(), 10);
        assert_eq!(got.len(), 1, "{c:?}");
        match &got[0] {
            DeviceMsg::Response { id: got_id, result } => {
                assert_eq!(*got_id, id);
                // Peripheral commands are not implemented by this firmware slice yet; they
                // must say so rather than pretend.
                if !matches!(c, Command::GetClock | Command::GetStatus | Command::Heartbeat) {
                    assert_eq!(*result, Err(Error::Unsupported), "{c:?}");
                }
            }
            other => panic!("{other:?}"),
        }
    }
}
