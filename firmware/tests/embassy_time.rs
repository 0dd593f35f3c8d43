//! The controller on embassy-time's clock, under its mock driver: the board run loop's timing
//! (sleep until `next_deadline`, then poll) gives the same exact edges as the simulation.
//!
//! The mock clock is process-wide, so this file holds a single test.

mod common;

use common::*;
use embassy_time::{Duration, Instant, MockDriver};
use lightrig_firmware::controller::EmbassyClock;
use lightrig_firmware::sim::{Output, SimBoard};
use lightrig_firmware::Controller;
use lightrig_protocol::config::ConfigItem;
use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
use lightrig_protocol::sequence::{Action, StartAt};
use lightrig_protocol::session::{BoardId, DeviceInfo, ResetCause, Version};
use lightrig_protocol::{
    Command, DeviceMsg, Event, HostMsg, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
};

#[test]
fn a_trigger_train_over_the_link_on_embassy_mock_time() {
    let info = DeviceInfo {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
        firmware: Version { major: 0, minor: 1, patch: 0 },
        board: BoardId::Virtual,
        serial: 1,
        tick_hz: TICK_HZ, // embassy-time's mock driver ticks at 1 MHz
        reset_cause: ResetCause::PowerOn,
        boot_id: 7,
        capabilities: caps(),
    };
    let driver = MockDriver::get();
    let mut device = Controller::new(EmbassyClock, SimBoard::default(), info, 1_000);
    let mut host: Link<HostMsg, DeviceMsg, 8> =
        Link::new(Role::Initiator, LinkConfig { rto: 1_000, rx_reserve: 0, nonce: 3 });
    host.connect(0);

    let mut got = Vec::new();
    let pump =
        |device: &mut Controller<EmbassyClock, SimBoard>, host: &mut Link<_, _, 8>, got: &mut Vec<_>| {
            let mut out = [0u8; MAX_FRAME];
            for _ in 0..4 {
                let now = Instant::now().as_ticks();
                while let Some(n) = host.poll_transmit(now, &mut out) {
                    device.receive(&out[..n]);
                }
                device.poll();
                while let Some(n) = device.poll_transmit(&mut out) {
                    host.receive_all(&out[..n], now, |d| got.push(d));
                }
            }
        };
    let commands = [
        Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH },
        Command::Configure(ConfigItem::Camera(camera(0))),
        Command::SequenceLoad(chunk(
            1,
            0,
            true,
            &[
                item(1_000, Action::Trigger { camera: 0, exposure: 250 }),
                item(1_000, Action::Trigger { camera: 0, exposure: 0 }),
            ],
        )),
        Command::SequenceStart { sequence: 1, at: StartAt::Tick(100_000) },
    ];
    for (id, command) in commands.into_iter().enumerate() {
        host.send(HostMsg { id: id as u16, command }).unwrap();
        pump(&mut device, &mut host, &mut got);
        driver.advance(Duration::from_ticks(10));
    }
    // The run loop: sleep until the controller's next deadline, wake, poll.
    while Instant::now().as_ticks() < 110_000 {
        let next = device.next_deadline().unwrap_or(u64::MAX).min(110_000);
        let now = Instant::now().as_ticks();
        driver.advance(Duration::from_ticks(next.saturating_sub(now).max(1)));
        pump(&mut device, &mut host, &mut got);
    }
    let responses = got
        .iter()
        .filter(|d| matches!(d, Delivery::Message(DeviceMsg::Response { result: Ok(_), .. })))
        .count();
    assert_eq!(responses, 4, "{got:?}");
    assert!(got
        .iter()
        .any(|d| matches!(d, Delivery::Message(DeviceMsg::Response { result: Ok(Reply::Buffer(_)), .. }))));
    let ticks: Vec<(u64, u32)> = got
        .iter()
        .filter_map(|d| match d {
            Delivery::Message(DeviceMsg::Event { event: Event::Trigger(t), .. }) => Some((t.tick, t.width)),
            _ => None,
        })
        .collect();
    assert_eq!(ticks, [(101_000, 250), (102_000, 100)]);
    let edges: Vec<(u64, bool)> = device
        .rig()
        .board()
        .changes(|o| matches!(o, Output::Trigger { .. }))
        .into_iter()
        .map(|c| match c.output {
            Output::Trigger { level, .. } => (c.tick, level),
            _ => unreachable!(),
        })
        .collect();
    assert_eq!(edges[1..], [(101_000, true), (101_250, false), (102_000, true), (102_100, false)]);
}
