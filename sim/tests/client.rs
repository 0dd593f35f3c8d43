//! The device client against the firmware controller in-process (the virtual transport).

use lightrig_firmware::sim::virtual_device_info;
use lightrig_firmware::sim::SimBoard;
use lightrig_host::client::{Client, ClientError};
use lightrig_protocol::config::{ConfigItem, Input, LaserConfig, Polarity};
use lightrig_protocol::event::DeviceState;
use lightrig_protocol::{Command, Reply, SCHEMA_HASH};
use lightrig_sim::transport::VirtualTransport;

#[path = "support/triggers.rs"]
mod triggers;

fn client() -> Client<VirtualTransport> {
    Client::connect(VirtualTransport::new(virtual_device_info(), SimBoard::default()), 0x5eed).unwrap()
}

#[test]
fn connects_and_maps_the_clock() {
    let c = client();
    assert_eq!(c.info().schema_hash, SCHEMA_HASH);
    // Host and virtual device share simulated time: the mapping is the identity.
    assert!((c.clock().rate().unwrap() - 1.0).abs() < 1e-9);
    assert!(c.clock().residual().unwrap() < 1.0);
    assert_eq!(c.clock().host_us(123_456).map(|h| h.round()), Some(123_456.0));
}

#[test]
fn a_schema_mismatch_says_both_hashes_and_what_to_do() {
    let t = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let Err(e) = Client::connect_as(t, 1, 1, 0x1234) else { panic!("connected") };
    assert!(matches!(e, ClientError::Incompatible { device_schema, .. } if device_schema == SCHEMA_HASH));
    let msg = e.to_string();
    assert!(msg.contains(&format!("0x{SCHEMA_HASH:016x}")), "{msg}");
    assert!(msg.contains("flash firmware built from the same lightrig release"), "{msg}");
}

#[test]
fn a_refused_configuration_names_the_field() {
    let mut c = client();
    let bad = LaserConfig {
        channel: 0,
        wavelength_nm: 635,
        warmup_ticks: 0,
        max_on_ticks: 0,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    };
    let e = c.request(Command::Configure(ConfigItem::Laser(bad))).unwrap_err();
    assert_eq!(e.to_string(), "virtual rig (in-process) refused Configure: invalid configuration: laser.max_on_ticks[0]: must not be zero");
}

#[test]
fn heartbeats_keep_an_idle_device_out_of_the_safe_state() {
    let mut c = client();
    c.idle(5_000_000).unwrap();
    assert_eq!(c.transport().device().state(), DeviceState::Ready);
    // ... and every heartbeat was one more clock sample.
    assert!(c.clock().counts().0 > 20);
}

#[test]
fn streams_a_sequence_larger_than_the_buffer_and_gets_every_trigger() {
    let mut c = client();
    triggers::configure_camera(&mut c);
    const N: u32 = 2_000;
    let start = c.transport().device().rig().next_due().unwrap_or(0).max(1) + 100_000;
    let (outcome, frames) = triggers::run_triggers(&mut c, 3, N, 500, start);
    assert_eq!(outcome.items, N);
    assert_eq!(outcome.tick, start + 500 * u64::from(N));
    assert_eq!(frames.len(), N as usize);
    for (k, (frame, tick, host)) in frames.iter().enumerate() {
        assert_eq!(*frame, k as u32);
        assert_eq!(*tick, start + 500 * (k as u64 + 1));
        assert_eq!(host.map(|h| h.round() as u64), Some(*tick), "host time of the trigger");
    }
}

#[test]
fn answers_resent_after_a_reconnection_never_answer_the_new_clients_requests() {
    // Client A's last answer arrives, but the cable is pulled before A acknowledges it: the
    // device still holds that answer and, as the link promises, sends it again on the new
    // epoch. The new client must not take it for the answer to one of its own requests.
    let mut a = client();
    assert!(matches!(a.request(Command::GetStatus).unwrap(), Reply::Status(_)));
    let mut t = a.into_transport();
    let now = lightrig_host::transport::Transport::now_us(&t);
    t.unplug_at(now);
    t.replug();
    let mut b = Client::connect(t, 0x5eee).unwrap();
    // B's requests, numbered as A's were up to A's GetStatus, must each get their own answer.
    for _ in 0..4 {
        assert!(matches!(b.request(Command::GetClock).unwrap(), Reply::Clock { .. }));
        assert!(matches!(b.request(Command::GetStatus).unwrap(), Reply::Status(_)));
    }
}

#[test]
fn paced_in_real_time_a_sequence_takes_as_long_as_on_a_real_rig_and_keeps_its_ticks() {
    let mut t = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    // Device tick 0 is now on the wall clock.
    let wall = std::time::Instant::now();
    t.pace_in_real_time();
    let mut c = Client::connect(t, 0x5eed).unwrap();
    triggers::configure_camera(&mut c);
    let Reply::Clock { tick: now } = c.request(Command::GetClock).unwrap() else { panic!("no clock") };
    let start = now + 50_000;
    let (outcome, triggers) = triggers::run_triggers(&mut c, 1, 100, 2_000, start);
    let ticks: Vec<u64> = triggers.iter().map(|t| t.1).collect();
    assert_eq!(outcome.tick, start + 200_000);
    // Paced, the device cannot reach a tick before the wall clock has (a lower bound only: a
    // loaded machine makes it later, never earlier). Unpaced, this takes a few milliseconds.
    assert!(wall.elapsed() >= std::time::Duration::from_micros(outcome.tick), "{:?}", wall.elapsed());
    assert_eq!(ticks, (1..=100).map(|k| start + 2_000 * k).collect::<Vec<_>>());
}

/// A copy of an earlier host run's `Sync` (another session nonce) naming `epoch`, as a
/// reordering wire (a USB–UART bridge's buffer) may deliver it after this host connected.
fn stale_sync(epoch: u8) -> Vec<u8> {
    use lightrig_protocol::link::{self, FrameKind, Header};
    let mut out = [0u8; lightrig_protocol::MAX_FRAME];
    let h = Header { kind: FrameKind::Sync, epoch, seq: 0, ack: 0 };
    let n = link::write(&h, Some(&0x0bad_5eed_u32), &mut out);
    out[..n].to_vec()
}

#[test]
fn a_stale_hosts_sync_costs_this_host_neither_its_session_nor_more_than_a_heartbeat_period() {
    // §4.6.1: the stale Sync knocks the device's link back to half-open in the old session;
    // naming the current epoch it has the device answer this host with SyncAcks for that
    // session, naming another one with Resync. Either way this host connects to a new epoch
    // within a heartbeat period, says Hello again (§6.2) and keeps its session: the device did
    // not restart, its configuration and armed lasers are as they were.
    for ahead in [0u8, 5] {
        let mut c = client();
        c.set_heartbeat_us(200_000);
        let laser = LaserConfig {
            channel: 0,
            wavelength_nm: 635,
            warmup_ticks: 0,
            max_on_ticks: 1_000_000,
            enable: Polarity::ActiveHigh,
            interlock: Input::Unused,
        };
        c.request(Command::Configure(ConfigItem::Laser(laser))).unwrap();
        c.request(Command::Arm { lasers: 1 }).unwrap();
        let boot = c.info().boot_id;
        let device = c.transport().device().link();
        let (epoch, syncs) = (device.epoch(), device.stats().syncs);
        c.transport_mut().device_mut().receive(&stale_sync(epoch.wrapping_add(ahead)));
        // One heartbeat period (200 ms) and a few round trips.
        c.idle(250_000).unwrap_or_else(|e| panic!("stale Sync of epoch +{ahead}: {e}"));
        let d = c.transport().device();
        assert_eq!(d.state(), DeviceState::Ready, "stale Sync of epoch +{ahead}: session open again");
        assert_eq!(d.rig().armed(), 1, "nothing but the link was reset");
        // The stale half-open epoch, then this host's new one.
        assert_eq!(d.link().stats().syncs, syncs + 2);
        assert_eq!(d.link().epoch(), epoch + 1, "the host's next epoch, whatever the stale one named");
        assert_eq!(c.link_stats().syncs, 2, "the host connected once more");
        assert_eq!(c.info().boot_id, boot);
        // The session goes on.
        let Reply::Status(s) = c.request(Command::GetStatus).unwrap() else { panic!("no status") };
        assert_eq!((s.state, s.armed), (DeviceState::Ready, 1));
        c.idle(2_000_000).unwrap();
        assert_eq!(c.transport().device().state(), DeviceState::Ready, "no HeartbeatLost");
    }
}

#[test]
fn datagrams_the_device_drops_show_in_its_status() {
    use lightrig_protocol::link::{self, FrameKind, Header};
    use lightrig_protocol::sequence::Action;
    use lightrig_protocol::HostMsg;
    let mut c = client();
    let Reply::Status(before) = c.request(Command::GetStatus).unwrap() else { panic!("no status") };
    assert_eq!(before.link.datagrams_dropped, 0);
    // Datagrams from a stray sender or a replay: two commands the device takes only
    // sequenced, one body that does not decode (§4.7, §4.8).
    let mut out = [0u8; lightrig_protocol::MAX_FRAME];
    let h = Header { kind: FrameKind::Datagram, epoch: 0, seq: 0, ack: 0 };
    let now = lightrig_host::transport::Transport::now_us(c.transport());
    for command in [Command::Arm { lasers: 1 }, Command::Immediate(Action::Laser { channel: 0, on: true })] {
        let n = link::write(&h, Some(&HostMsg { id: 7, command }), &mut out);
        c.transport_mut().inject_at(now + 1_000, &out[..n]);
    }
    let n = link::write(&h, Some(&[0x07u8, 0x7f]), &mut out);
    c.transport_mut().inject_at(now + 2_000, &out[..n]);
    c.idle(10_000).unwrap();
    let Reply::Status(s) = c.request(Command::GetStatus).unwrap() else { panic!("no status") };
    assert_eq!(s.link.datagrams_dropped, 3);
    assert_eq!(c.transport().device().ignored_datagrams(), 2);
    // An emergency stop as a datagram is acted on, not dropped.
    let n = link::write(&h, Some(&HostMsg { id: 8, command: Command::EmergencyStop }), &mut out);
    c.transport_mut().device_mut().receive(&out[..n]);
    let Reply::Status(s) = c.request(Command::GetStatus).unwrap() else { panic!("no status") };
    assert_eq!(s.link.datagrams_dropped, 3);
    assert_eq!(s.state, DeviceState::Faulted(lightrig_protocol::event::FaultCause::EmergencyStop));
}
