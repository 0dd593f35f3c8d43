//! The virtual camera integrates over its whole exposure: the simulated board's state at every
//! tick (the timeline), not only the trigger's snapshot.

mod common;

use std::path::Path;

use lightrig_firmware::sim::virtual_device_info;
use lightrig_firmware::sim::SimBoard;
use lightrig_host::bringup::bring_up_on;
use lightrig_host::client::Client;
use lightrig_host::rigfile::RigFile;
use lightrig_host::transport::Transport;
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::TriggerEvent;
use lightrig_protocol::sequence::{Action, Item, Profile, StartAt};
use lightrig_protocol::Event;
use lightrig_sim::camera::{RigState, Scene, VirtualCamera, MAX_EXPOSURE_STATES};
use lightrig_sim::sensor::Sensor;
use lightrig_sim::timeline::Timeline;
use lightrig_sim::transport::VirtualTransport;

/// One pixel that shows what the camera sees: laser 0, galvo x code, gantry position.
struct Probe;

impl Scene for Probe {
    fn size(&self) -> (u32, u32) {
        (1, 1)
    }
    fn radiance(&self, _: u32, _: u32, s: &RigState) -> [f64; 3] {
        let galvo = s.galvos.first().map_or(0.0, |g| f64::from(g[0]));
        [f64::from(s.lasers & 1), galvo, s.axes.first().copied().unwrap_or(0.0)]
    }
}

/// Runs `items` on the rig of `common::setup` with a timeline, and returns the camera and
/// the trigger events.
fn run(items: Vec<Item>) -> (VirtualCamera<Probe>, Vec<TriggerEvent>) {
    let mut t = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let timeline = t.timeline();
    let c = common::setup(Client::connect(t, 9).unwrap());
    let rig = RigFile::parse("[rig]\nname = \"probe\"\nmethod = \"disco\"\n", Path::new("rig.toml")).unwrap();
    shoot(c, &rig, timeline, &format!("setup-{}", items.len()), items)
}

/// Runs `items` on a connected rig with a camera following `timeline`; returns the camera and
/// the trigger events.
fn shoot<T: Transport>(
    mut c: Client<T>,
    rig: &RigFile,
    timeline: Timeline,
    name: &str,
    items: Vec<Item>,
) -> (VirtualCamera<Probe>, Vec<TriggerEvent>) {
    let dir = std::env::temp_dir().join(format!("lightrig-exposure-{}-{name}", std::process::id()));
    let mut cam = VirtualCamera::new(rig, 0, Probe, Sensor::default(), 1_000_000, &dir).unwrap();
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

/// Runs `items` on the virtual rig of the example rig file `file`, brought up as
/// `lightrig acquire` does, with a camera following the timeline.
fn run_rig(file: &str, items: Vec<Item>) -> (VirtualCamera<Probe>, Vec<TriggerEvent>) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs").join(file);
    let rig = RigFile::load(&path).unwrap();
    let (t, timeline) = lightrig_sim::transport::connect_for_camera(&rig, virtual_device_info(), false);
    let c = bring_up_on(&rig, Box::new(t)).unwrap();
    shoot(c, &rig, timeline, file, items)
}

#[test]
fn a_filter_wheel_turning_mid_exposure_has_no_slot_until_it_settles_on_the_next() {
    // The bispectral rig's excitation wheel (8 slots, 3200 steps per turn), homed to slot 0:
    // one slot on is 400 steps, about 0.35 s; the exposure opens 0.1 s before the move starts
    // and lasts 0.6 s.
    let items = vec![
        Item { delta: 0, action: trigger(600_000) },
        Item { delta: 100_000, action: Action::FilterWheel { wheel: 0, slot: 1 } },
        Item { delta: 900_000, action: trigger(1_000) },
    ];
    let (cam, triggers) = run_rig("bispectral.toml", items);
    assert_eq!(triggers[0].snapshot.filters[0], Some(0));
    assert_eq!(triggers[1].snapshot.filters[0], Some(1));
    let states = cam.exposure_states(&triggers[0], &cam.state(&triggers[0]));
    let slots: Vec<Option<u8>> = states.iter().map(|(_, s)| s.filters[0]).collect();
    // Sampled (hundreds of steps): slot 0 before the move, none while turning, slot 1 after.
    assert_eq!(states.len(), MAX_EXPOSURE_STATES);
    let n = MAX_EXPOSURE_STATES;
    let first_moving = slots.iter().position(|s| s.is_none()).unwrap();
    let settled = slots.iter().position(|s| *s == Some(1)).unwrap();
    assert_eq!(first_moving, 3, "{slots:?}"); // slice 3's middle (0.131 s) is after the start
    assert!(slots[..first_moving].iter().all(|s| *s == Some(0)), "{slots:?}");
    assert!(slots[first_moving..settled].iter().all(|s| s.is_none()), "{slots:?}");
    assert!(slots[settled..].iter().all(|s| *s == Some(1)), "{slots:?}");
    assert!(settled < n, "{slots:?}");
}

#[test]
fn the_voice_coil_samples_playing_during_an_exposure_reach_the_camera() {
    use lightrig_firmware::synth::Synth;
    use lightrig_protocol::sequence::Partial;
    // The BRDF display's coil 0 at 48 kHz: one partial, then a 10 ms exposure 50 ms later.
    let partial = Partial { freq_mhz: 1_234_567, amplitude: 20_000, phase: 0 };
    let mut partials = heapless::Vec::new();
    partials.push(partial).unwrap();
    let items = vec![
        Item { delta: 0, action: Action::VoiceCoil { channel: 0, ramp: 0, partials } },
        Item { delta: 50_000, action: trigger(10_000) },
    ];
    let (cam, triggers) = run_rig("brdf-display.toml", items);
    let states = cam.exposure_states(&triggers[0], &cam.state(&triggers[0]));
    let window = &states[0].1.coils[0];
    // 10 ms at 48 kHz: 480 samples play inside the exposure.
    assert_eq!(window.len(), 480);
    assert!(states[0].1.coils[1].iter().all(|&s| s == 0), "coil 1 is silent");
    // They are a run of the synthesiser's own output for that partial, in order.
    let mut synth = Synth::new(48_000);
    synth.set(&[partial], 0).unwrap();
    let mut reference = vec![0i16; 48_000];
    synth.fill(&mut reference);
    let at = (0..reference.len() - window.len()).find(|&k| reference[k..k + window.len()] == window[..]);
    // ... starting where it should: 50 ms (2 400 samples) after the setting took effect, less
    // the two 64-sample blocks a sample waits in the DMA double buffer before it plays.
    let expected = 2_400 - 2 * 64;
    assert!(at.is_some_and(|k| k.abs_diff(expected) <= 1), "run starts at {at:?}, expected {expected} ± 1");
}
