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
