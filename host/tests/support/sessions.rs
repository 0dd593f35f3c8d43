//! Sessions built by hand for tests: a plan, its manifest, the triggers a step fires and their
//! events.

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::client::EventRecord;
use lightrig_host::session::{CameraTriggers, Manifest, PlanStep, PlanSummary, Trigger};
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::{Snapshot, TriggerEvent};
use lightrig_protocol::Event;

/// `steps` steps (ids from 10), each `frames` frames from each of `cameras` cameras.
pub fn plan(steps: u32, cameras: u8, frames: u32) -> PlanSummary {
    PlanSummary {
        steps: (0..steps)
            .map(|id| PlanStep {
                id: 10 + id,
                name: format!("view {id}"),
                triggers: (0..cameras).map(|camera| CameraTriggers { camera, count: frames }).collect(),
                extra: serde_json::json!({ "turntable_deg": id * 30 }),
            })
            .collect(),
        extra: serde_json::json!({ "planner": "test", "exposure_us": 1000 }),
    }
}

/// A manifest of the virtual device for `plan`.
pub fn manifest(plan: PlanSummary) -> Manifest {
    Manifest::new("[rig]\nname = \"test rig\"\n", &virtual_device_info(), plan)
}

/// The device's event for trigger `t`.
pub fn trigger_event(t: &Trigger) -> Event {
    Event::Trigger(TriggerEvent {
        sequence: t.sequence,
        item: t.item,
        frame: t.frame,
        camera: t.camera,
        tick: t.tick,
        width: 100,
        snapshot: Snapshot {
            galvos: heapless::Vec::from_slice(&[Xy { x: 100, y: 200 }]).unwrap(),
            axes: heapless::Vec::from_slice(&[1200, -5]).unwrap(),
            filters: heapless::Vec::from_slice(&[Some(2)]).unwrap(),
            lasers: 0b101,
        },
    })
}

/// The triggers a plan step fires in `sequence`: cameras interleaved, 1 ms apart.
pub fn triggers_of(step: &PlanStep, sequence: u32) -> Vec<Trigger> {
    let frames = step.triggers.iter().map(|t| t.count).max().unwrap_or(0);
    let mut out = Vec::new();
    for frame in 0..frames {
        for t in step.triggers.iter().filter(|t| frame < t.count) {
            let item = out.len() as u32;
            let tick = 1_000_000 + u64::from(item) * 1000;
            out.push(Trigger { sequence, item, camera: t.camera, frame, tick, host_us: Some(tick as f64) });
        }
    }
    out
}

/// Event `index` of device `boot_id`, as the client hands it to the session.
pub fn event_record(boot_id: u32, index: u32, event: Event) -> EventRecord {
    let host_us = lightrig_host::client::event_tick(&event).map(|t| t as f64 + 0.25);
    EventRecord { index, boot_id, event, host_us }
}
