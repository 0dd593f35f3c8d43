//! Camera 0 configured, then a sequence of `n` triggers `delta` ticks apart from `start`, run
//! through a client over any transport: the stream the client and pseudo-terminal tests check.
//! Included as `#[path = "support/triggers.rs"] mod triggers;`.

use lightrig_host::client::{Client, SequenceOutcome};
use lightrig_host::transport::Transport;
use lightrig_protocol::config::{CameraConfig, ConfigItem, Input, Polarity};
use lightrig_protocol::sequence::{Action, Item, StartAt};
use lightrig_protocol::{Command, Event, Reply};

/// Configures camera 0 (20-tick pulses, active high, no exposure input).
pub fn configure_camera<T: Transport>(c: &mut Client<T>) {
    let cam = CameraConfig {
        camera: 0,
        pulse_ticks: 20,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    assert_eq!(c.request(Command::Configure(ConfigItem::Camera(cam))).unwrap(), Reply::Done);
}

/// Runs sequence `id`: `n` triggers of camera 0, `delta` ticks apart, the first `delta` after
/// `start`. Returns the outcome and each trigger event's `(frame, tick, host µs)`.
pub fn run_triggers<T: Transport>(
    c: &mut Client<T>,
    id: u32,
    n: u32,
    delta: u32,
    start: u64,
) -> (SequenceOutcome, Vec<(u32, u64, Option<f64>)>) {
    let items = (0..n).map(|_| Item { delta, action: Action::Trigger { camera: 0, exposure: 0 } });
    let mut triggers = Vec::new();
    let outcome = c
        .run_sequence(id, items, StartAt::Tick(start), |e| {
            if let Event::Trigger(t) = &e.event {
                triggers.push((t.frame, t.tick, e.host_us));
            }
        })
        .unwrap();
    (outcome, triggers)
}
