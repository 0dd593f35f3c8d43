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
    // The device still describes itself, so the host can explain the mismatch ...
    let got = p.request(1, Command::Hello { protocol_version: 99, schema_hash: SCHEMA_HASH }, 10);
    assert!(matches!(
        &got[..],
        [DeviceMsg::Response { id: 1, result: Ok(Reply::Hello(i)) }] if i.protocol_version == PROTOCOL_VERSION
    ));
    // ... but refuses to work, naming both versions.
    let refused = Err(Error::VersionMismatch { device: PROTOCOL_VERSION, host: 99 });
    assert_eq!(p.request(2, Command::Heartbeat, 10), vec![DeviceMsg::Response { id: 2, result: refused }]);
    // A matching Hello opens the session.
    p.request(3, hello(), 10);
    assert_eq!(
        p.request(4, Command::Heartbeat, 10),
        vec![DeviceMsg::Response { id: 4, result: Ok(Reply::Done) }]
    );
}

#[test]
fn emergency_stop_acts_before_the_handshake_and_stays_latched_across_reconnection() {
    use lightrig_protocol::event::{DeviceState, Event, FaultCause};
    let mut p = Pair::new();
    p.run(3);
    // As a datagram (no answer) before any Hello.
    let mut out = [0u8; MAX_FRAME];
    let h = Header { kind: FrameKind::Datagram, epoch: 1, seq: 0, ack: 0 };
    let estop = lightrig_protocol::HostMsg { id: 1, command: Command::EmergencyStop };
    let n = link::write(&h, Some(&estop), &mut out);
    p.device.receive(&out[..n]);
    assert_eq!(p.device.state(), DeviceState::Faulted(FaultCause::EmergencyStop));
    // No answer to a datagram, but the fault is reported as events, numbered from 0.
    let state = DeviceState::Faulted(FaultCause::EmergencyStop);
    assert_eq!(
        p.messages(5),
        vec![
            DeviceMsg::Event { index: 0, event: Event::Fault { cause: FaultCause::EmergencyStop, tick: 3 } },
            DeviceMsg::Event { index: 1, event: Event::State { state, armed: 0, tick: 3 } },
        ]
    );
    // The host reconnects: the fault is still latched.
    p.host.connect(0);
    p.run(5);
    p.request(2, hello(), 10);
    assert_eq!(p.device.state(), DeviceState::Faulted(FaultCause::EmergencyStop));
    let got = p.request(3, Command::Arm { lasers: 1 }, 10);
    assert_eq!(
        got,
        vec![DeviceMsg::Response { id: 3, result: Err(Error::Faulted(FaultCause::EmergencyStop)) }]
    );
    p.request(4, Command::ClearFault, 10);
    assert_eq!(p.device.state(), DeviceState::Ready);
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
    let n = link::write(&h, Some(&(9u16, 250u32)), &mut out);
    p.device.receive(&out[..n]);
    let got = p.messages(5);
    assert_eq!(got, vec![DeviceMsg::Rejected { seq: 1, reason: FrameError::UnknownType }]);
    assert_eq!(p.device.link().stats().unknown_type, 1);
    // Garbage between frames is counted and the next request is still answered.
    p.device.receive(&[0x13, 0x37, 0x00, 0xff, 0xff, 0x00]);
    assert_eq!(p.device.link().stats().rejected(), 3);
    // The host's own seq 1 collides with the forged one and is dropped as a duplicate; its
    // retransmission never succeeds. A real host never forges, so resynchronise instead:
    p.host.connect(0);
    p.run(5);
    let got = p.request(2, hello(), 10);
    assert!(matches!(got[..], [DeviceMsg::Response { id: 2, result: Ok(Reply::Hello(_)) }]));
}

#[test]
fn every_command_gets_exactly_one_typed_answer() {
    use lightrig_protocol::error::Peripheral;
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    let cases: [(Command, Option<Result<Reply, Error>>); 7] = [
        (Command::GetClock, None),
        (Command::GetStatus, None),
        (Command::Heartbeat, Some(Ok(Reply::Done))),
        (Command::ClearFault, Some(Ok(Reply::Done))),
        (Command::Arm { lasers: 1 }, Some(Err(Error::NotConfigured { kind: Peripheral::Laser, index: 0 }))),
        (Command::Disarm, Some(Ok(Reply::Done))),
        (Command::SequenceAbort { sequence: 1 }, Some(Err(Error::NoSuchSequence { sequence: 1 }))),
    ];
    for (i, (c, want)) in cases.into_iter().enumerate() {
        let id = 10 + i as u16;
        // Events (Disarm reports the state) travel alongside; exactly one response comes.
        let got: Vec<_> = p
            .request(id, c.clone(), 10)
            .into_iter()
            .filter(|m| matches!(m, DeviceMsg::Response { .. }))
            .collect();
        let [DeviceMsg::Response { id: got_id, result }] = &got[..] else { panic!("{c:?}: {got:?}") };
        assert_eq!(*got_id, id);
        match (&c, want) {
            (Command::GetClock, _) => assert!(matches!(result, Ok(Reply::Clock { .. }))),
            (Command::GetStatus, _) => assert!(matches!(result, Ok(Reply::Status(_)))),
            (_, Some(want)) => assert_eq!(*result, want, "{c:?}"),
            (_, None) => unreachable!(),
        }
    }
}

#[test]
fn a_datagram_other_than_an_emergency_stop_is_dropped_unanswered() {
    use lightrig_protocol::config::{ConfigItem, Input, LaserConfig, Polarity};
    use lightrig_protocol::event::DeviceState;
    use lightrig_protocol::sequence::Action;
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    let laser = LaserConfig {
        channel: 0,
        wavelength_nm: 635,
        warmup_ticks: 0,
        max_on_ticks: 1_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    };
    let got = p.request(2, Command::Configure(ConfigItem::Laser(laser)), 10);
    assert_eq!(got, vec![DeviceMsg::Response { id: 2, result: Ok(Reply::Done) }]);
    // CRC-valid datagrams, as a replay or a stray sender would make them, in the open session:
    // arm laser 0, then switch it on.
    let mut out = [0u8; MAX_FRAME];
    let h = Header { kind: FrameKind::Datagram, epoch: p.host.epoch(), seq: 0, ack: 0 };
    for (id, command) in [
        (90, Command::Arm { lasers: 1 }),
        (91, Command::Immediate(Action::Laser { channel: 0, on: true })),
        (92, Command::ClearFault),
    ] {
        let n = link::write(&h, Some(&lightrig_protocol::HostMsg { id, command }), &mut out);
        p.device.receive(&out[..n]);
    }
    assert_eq!(p.device.ignored_datagrams(), 3);
    // Counted in the link's counters too, which the host reads with GetStatus.
    assert_eq!(p.device.link().stats().datagrams_dropped, 3);
    assert_eq!(p.device.rig().armed(), 0, "a datagram armed a laser");
    assert_eq!(p.device.state(), DeviceState::Ready);
    // Nothing answers them, and the session goes on.
    assert_eq!(p.messages(10), vec![]);
    let got = p.request(3, Command::Immediate(Action::Laser { channel: 0, on: true }), 10);
    assert_eq!(got, vec![DeviceMsg::Response { id: 3, result: Err(Error::NotArmed { channel: 0 }) }]);
}

#[test]
fn events_lost_to_a_full_queue_leave_a_gap_in_the_numbers_exactly_where_they_were_lost() {
    use lightrig_protocol::config::{CameraConfig, ConfigItem, Input, Polarity};
    use lightrig_protocol::event::{Event, FaultCause};
    use lightrig_protocol::sequence::{Action, Chunk, Item, StartAt};
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    let cam = CameraConfig {
        camera: 0,
        pulse_ticks: 2,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    p.request(2, Command::Configure(ConfigItem::Camera(cam)), 10);
    // 160 triggers 5 ticks apart: far more events than the link window and the event queue hold.
    let trigger = Item { delta: 5, action: Action::Trigger { camera: 0, exposure: 0 } };
    for k in 0..5u32 {
        let items = std::iter::repeat_n(trigger.clone(), 32).collect();
        let load = Command::SequenceLoad(Chunk { sequence: 7, chunk: k, last: k == 4, items });
        p.request(10 + k as u16, load, 10);
    }
    p.request(20, Command::SequenceStart { sequence: 7, at: StartAt::Now }, 10);
    // The host stops reading: the device runs on alone until its queue overflows.
    for _ in 0..2_000 {
        p.clock.advance(1);
        p.device.poll();
    }
    let dropped = p.device.rig().dropped_events();
    assert!(dropped > 0, "the queue overflowed");
    // The host reads again: the event numbers skip exactly the lost ones, right before the
    // overflow fault.
    let events: Vec<(u32, Event)> = p
        .messages(5_000)
        .into_iter()
        .filter_map(|m| match m {
            DeviceMsg::Event { index, event } => Some((index, event)),
            _ => None,
        })
        .collect();
    let gaps: Vec<(usize, u32)> = events
        .windows(2)
        .enumerate()
        .filter(|(_, w)| w[1].0 != w[0].0 + 1)
        .map(|(i, w)| (i + 1, w[1].0 - w[0].0 - 1))
        .collect();
    assert_eq!(gaps.len(), 1, "one gap: {gaps:?}");
    let (at, size) = gaps[0];
    assert_eq!(size, dropped, "the gap is the number dropped");
    assert!(
        matches!(events[at].1, Event::Fault { cause: FaultCause::EventOverflow, .. }),
        "the overflow fault follows the gap: {:?}",
        events[at]
    );
}

/// §6.4: the events an earlier host session left unacknowledged reach the next host, even after
/// the answer to its Hello; their tick, before the fence the new host takes with `GetClock`, is
/// what marks them (neither the sequence id nor the event index nor the boot id does).
#[test]
fn an_earlier_host_sessions_sequence_done_after_the_new_hello_is_before_the_fence() {
    use lightrig_firmware::Clock;
    use lightrig_host::client::event_tick;
    use lightrig_protocol::config::{CameraConfig, ConfigItem, Input, Polarity};
    use lightrig_protocol::event::Event;
    use lightrig_protocol::link::{Link, LinkConfig, Role};
    use lightrig_protocol::sequence::{Action, Chunk, Item, StartAt};
    use lightrig_protocol::HostMsg;
    let mut p = Pair::new();
    p.request(1, hello(), 10);
    let cam = CameraConfig {
        camera: 0,
        pulse_ticks: 2,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    p.request(2, Command::Configure(ConfigItem::Camera(cam)), 10);
    // Sequence 1, twelve triggers: more events than the device's link window holds.
    let trigger = Item { delta: 10, action: Action::Trigger { camera: 0, exposure: 0 } };
    let items = std::iter::repeat_n(trigger, 12).collect::<heapless::Vec<_, 32>>();
    let load = Command::SequenceLoad(Chunk { sequence: 1, chunk: 0, last: true, items });
    let start = Command::SequenceStart { sequence: 1, at: StartAt::Now };
    p.request(3, load.clone(), 10);
    // The first host program starts it and dies: nothing the device sends from now on is
    // acknowledged, and the device runs the sequence to its end alone.
    p.host.send(HostMsg { id: 4, command: start.clone() }).expect("window");
    let mut out = [0u8; MAX_FRAME];
    while let Some(n) = p.host.poll_transmit(p.clock.now(), &mut out) {
        p.device.receive(&out[..n]);
    }
    for _ in 0..1_000 {
        p.clock.advance(1);
        p.device.poll();
        while p.device.poll_transmit(&mut out).is_some() {}
    }
    // The next host program (another nonce) queues its Hello and its fence, a GetClock, while
    // the link syncs, as the reference client does.
    p.host =
        Link::new(Role::Initiator, LinkConfig { rto: lightrig_tests::RTO, rx_reserve: 0, nonce: 0x2d0c });
    p.host.connect(p.clock.now());
    p.host.send(HostMsg { id: 100, command: hello() }).expect("window");
    p.host.send(HostMsg { id: 101, command: Command::GetClock }).expect("window");
    let stream = p.messages(3 * lightrig_tests::RTO);
    let at =
        |f: &dyn Fn(&DeviceMsg) -> bool| stream.iter().position(f).unwrap_or_else(|| panic!("{stream:?}"));
    let hello_at = at(&|m| matches!(m, DeviceMsg::Response { id: 100, result: Ok(Reply::Hello(_)) }));
    let fence_at = at(&|m| matches!(m, DeviceMsg::Response { id: 101, result: Ok(Reply::Clock { .. }) }));
    let DeviceMsg::Response { result: Ok(Reply::Clock { tick: fence }), .. } = stream[fence_at] else {
        unreachable!()
    };
    let done =
        |m: &DeviceMsg| matches!(m, DeviceMsg::Event { event: Event::SequenceDone { sequence: 1, .. }, .. });
    let old_at = at(&done);
    let DeviceMsg::Event { index: old_index, event: old } = stream[old_at].clone() else { unreachable!() };
    // The device resent what the earlier session left unacknowledged (its answer to request 4
    // among them) ahead of the answer to the new Hello ...
    assert!(stream[..hello_at].iter().any(|m| matches!(m, DeviceMsg::Response { id: 4, .. })), "{stream:?}");
    // ... and the rest of its events after it: the earlier session's SequenceDone arrives after
    // the answer to the new Hello. Its place in the stream does not mark it; its tick, before
    // the fence, does.
    assert!(old_at > hello_at, "{stream:?}");
    assert!(event_tick(&old).expect("a tick") < fence, "{old:?} against the fence {fence}");
    // The new session runs its own sequence 1: same sequence id, a SequenceDone after the fence.
    p.request(102, load, 10);
    let mine = p.request(103, start, 500);
    let Some(DeviceMsg::Event { index, event: new }) = mine.into_iter().find(done) else {
        panic!("no SequenceDone")
    };
    assert!(event_tick(&new).expect("a tick") >= fence, "{new:?} against the fence {fence}");
    assert!(index > old_index);
}
