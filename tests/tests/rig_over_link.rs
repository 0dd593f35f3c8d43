//! The rig driven through the protocol: configuration, a sequence and its events over the
//! acknowledged link, and the heartbeat watchdog.

use lightrig_protocol::config::{CameraConfig, ConfigItem, Input, Polarity, SafetyConfig};
use lightrig_protocol::event::{DeviceState, FaultCause};
use lightrig_protocol::sequence::{Action, Chunk, Item, StartAt};
use lightrig_protocol::{Command, DeviceMsg, Event, Reply, PROTOCOL_VERSION, SCHEMA_HASH};
use lightrig_tests::Pair;

fn hello() -> Command {
    Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH }
}

fn camera() -> ConfigItem {
    ConfigItem::Camera(CameraConfig {
        camera: 0,
        pulse_ticks: 50,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 100,
    })
}

fn ok(msgs: &[DeviceMsg], id: u16) -> Reply {
    msgs.iter()
        .find_map(|m| match m {
            DeviceMsg::Response { id: i, result } if *i == id => Some(result.clone().expect("ok")),
            _ => None,
        })
        .unwrap_or_else(|| panic!("no response {id} in {msgs:?}"))
}

#[test]
fn a_sequence_over_the_link_reports_every_trigger_in_order() {
    let mut p = Pair::new();
    ok(&p.request(1, hello(), 10), 1);
    ok(&p.request(2, Command::Configure(camera()), 10), 2);
    let items: heapless::Vec<Item, 32> =
        (0..32).map(|_| Item { delta: 200, action: Action::Trigger { camera: 0, exposure: 0 } }).collect();
    let buffer =
        ok(&p.request(3, Command::SequenceLoad(Chunk { sequence: 8, chunk: 0, last: true, items }), 10), 3);
    let Reply::Buffer(b) = buffer else { panic!("{buffer:?}") };
    assert_eq!((b.sequence, b.free, b.next_chunk), (8, 256 - 32, 1));
    let start = 1_000;
    ok(&p.request(4, Command::SequenceStart { sequence: 8, at: StartAt::Tick(start) }, 10), 4);
    let msgs = p.messages(8_000);
    let mut index = None;
    let mut triggers = Vec::new();
    for m in &msgs {
        if let DeviceMsg::Event { index: i, event } = m {
            // Numbered without gaps: nothing lost, nothing duplicated.
            if let Some(prev) = index {
                assert_eq!(*i, prev + 1);
            }
            index = Some(*i);
            if let Event::Trigger(t) = event {
                triggers.push((t.frame, t.tick));
            }
        }
    }
    let want: Vec<(u32, u64)> = (0..32).map(|k| (k, start + 200 * u64::from(k + 1))).collect();
    assert_eq!(triggers, want);
    assert!(msgs.iter().any(|m| matches!(
        m,
        DeviceMsg::Event { event: Event::SequenceDone { sequence: 8, items: 32, tick }, .. } if *tick == start + 6_400
    )));
    assert_eq!(p.device.state(), DeviceState::Ready);
}

#[test]
fn a_silent_host_trips_the_heartbeat_at_the_configured_tick() {
    let mut p = Pair::new();
    ok(&p.request(1, hello(), 10), 1);
    let safety = ConfigItem::Safety(SafetyConfig { heartbeat_timeout_ticks: 20_000 });
    ok(&p.request(2, Command::Configure(safety), 10), 2);
    // The device handled request 2 at some tick; the host then says nothing.
    let last = p.device.last_heartbeat();
    let msgs = p.messages(25_000);
    assert!(msgs.iter().any(|m| matches!(
        m,
        DeviceMsg::Event { event: Event::Fault { cause: FaultCause::HeartbeatLost, tick }, .. } if *tick == last + 20_000
    )), "{msgs:?}");
    assert_eq!(p.device.state(), DeviceState::Faulted(FaultCause::HeartbeatLost));
}
