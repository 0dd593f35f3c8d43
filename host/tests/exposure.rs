//! The virtual camera integrates over its whole exposure: the simulated board's state at every
//! tick (the timeline), not only the trigger's snapshot.

mod common;

use std::path::Path;

use lightrig_firmware::sim::SimBoard;
use lightrig_host::client::Client;
use lightrig_host::rigfile::RigFile;
use lightrig_host::selfcheck::virtual_device_info;
use lightrig_host::transport::VirtualTransport;
use lightrig_host::virtual_rig::camera::{RigState, Scene, VirtualCamera, MAX_EXPOSURE_STATES};
use lightrig_host::virtual_rig::sensor::Sensor;
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::TriggerEvent;
use lightrig_protocol::sequence::{Action, Item, Profile, StartAt};
use lightrig_protocol::Event;

/// One pixel that shows what the camera sees: laser 0, galvo x code, gantry position.
struct Probe;

impl Scene for Probe {
    fn size(&self) -> (u32, u32) {
        (1, 1)
    }
    fn radiance(&self, _: u32, _: u32, s: &RigState) -> [f64; 3] {
        [f64::from(s.lasers & 1), f64::from(s.galvos[0][0]), s.axes[0]]
    }
}

/// Runs `items` on the rig of `common::setup` with a timeline, and returns the camera and
/// the trigger events.
fn run(items: Vec<Item>) -> (VirtualCamera<Probe>, Vec<TriggerEvent>) {
    let mut t = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let timeline = t.timeline();
    let mut c = common::setup(Client::connect(t, 9).unwrap());
    let rig = RigFile::parse("[rig]\nname = \"probe\"\nmethod = \"disco\"\n", Path::new("rig.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("lightrig-exposure-{}-{}", std::process::id(), items.len()));
    let mut cam = VirtualCamera::new(&rig, 0, Probe, Sensor::default(), 1_000_000, &dir).unwrap();
    cam.follow(timeline);
    let mut triggers = Vec::new();
    c.run_sequence(1, items, StartAt::Now, |e| {
        if let Event::Trigger(t) = &e.event {
            triggers.push(t.clone());
        }
    })
    .unwrap();
    c.idle(50_000).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    (cam, triggers)
}

fn trigger(width: u32) -> Action {
    Action::Trigger { camera: 0, exposure: width }
}

#[test]
fn a_shutter_and_a_galvo_moving_mid_exposure_split_it_exactly() {
    let items = vec![
        Item { delta: 0, action: Action::Laser { channel: 0, on: true } },
        Item { delta: 10_000, action: Action::GalvoPoint { galvo: 0, to: Xy { x: 1_000, y: 0 } } },
        Item { delta: 1_000, action: trigger(1_000) },
        // 400 ticks into the exposure the laser goes off; 700 ticks in the galvo jumps.
        Item { delta: 400, action: Action::Laser { channel: 0, on: false } },
        Item { delta: 300, action: Action::GalvoPoint { galvo: 0, to: Xy { x: 3_000, y: 0 } } },
        Item { delta: 5_000, action: trigger(1_000) },
    ];
    let (cam, triggers) = run(items);
    assert_eq!(triggers.len(), 2);
    let states = cam.exposure_states(&triggers[0], &cam.state(&triggers[0]));
    let seen: Vec<(f64, u8, u16)> = states.iter().map(|(w, s)| (*w, s.lasers & 1, s.galvos[0][0])).collect();
    assert_eq!(seen, vec![(0.4, 1, 1_000), (0.3, 0, 1_000), (0.3, 0, 3_000)]);
    // A still exposure is its snapshot alone.
    let still = cam.exposure_states(&triggers[1], &cam.state(&triggers[1]));
    assert_eq!(still.len(), 1);
    assert_eq!((still[0].0, still[0].1.lasers & 1, still[0].1.galvos[0][0]), (1.0, 0, 3_000));
}

#[test]
fn a_gantry_moving_through_an_exposure_is_sampled_at_evenly_spaced_instants() {
    // 10 mm (800 steps) at the configured speed; the exposure opens as the move starts and
    // lasts 20 ms, so 32 steps fall inside it: more states than are rendered one by one.
    let items = vec![
        Item { delta: 0, action: Action::StepperMove { axis: 0, target: 800, profile: Profile::default() } },
        Item { delta: 0, action: trigger(20_000) },
        Item { delta: 200_000, action: trigger(1_000) },
    ];
    let (cam, triggers) = run(items);
    let states = cam.exposure_states(&triggers[0], &cam.state(&triggers[0]));
    assert_eq!(states.len(), MAX_EXPOSURE_STATES);
    assert!(states.iter().all(|(w, _)| *w == 1.0 / MAX_EXPOSURE_STATES as f64));
    // Without units in the rig file, positions are in steps. The move starts with the
    // exposure and accelerates at 160 000 steps/s² (common::setup): at t seconds in, the
    // trapezoid has made ⌊a·t²/2⌋ steps (its step times are exact to a tick).
    let n = MAX_EXPOSURE_STATES as f64;
    for (k, (_, s)) in states.iter().enumerate() {
        let mid = 20_000.0 * (2.0 * k as f64 + 1.0) / (2.0 * n);
        let steps = |us: f64| (0.5 * 160_000.0 * (us * 1e-6).powi(2)).floor();
        assert!(s.axes[0] >= steps(mid - 1.0) && s.axes[0] <= steps(mid + 1.0), "slice {k}: {}", s.axes[0]);
    }
    assert_eq!(triggers[1].snapshot.axes[0], 800, "the move ended where it was sent");
}
