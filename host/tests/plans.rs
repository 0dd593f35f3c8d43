//! Planners against the firmware core in-process: the right edges and events come out, in the
//! right order, the right count.

use lightrig_firmware::sim::{Output, SimBoard};
use lightrig_host::client::Client;
use lightrig_host::plan::{disco, lls, Plan};
use lightrig_host::selfcheck::virtual_device_info;
use lightrig_host::transport::VirtualTransport;
use lightrig_protocol::config::*;
use lightrig_protocol::sequence::{AxisRef, StartAt};
use lightrig_protocol::{Command, Event};

fn laser(channel: u8) -> ConfigItem {
    ConfigItem::Laser(LaserConfig {
        channel,
        wavelength_nm: 635,
        warmup_ticks: 2_000,
        max_on_ticks: 600_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    })
}

fn rig_client() -> Client<VirtualTransport> {
    let mut c =
        Client::connect(VirtualTransport::new(virtual_device_info(), SimBoard::default()), 9).unwrap();
    let axis = |axis, kind| StepperConfig {
        axis,
        kind,
        steps_per_unit: Ratio { num: 80, den: 1 },
        max_speed: 16_000,
        accel: 160_000,
        limits: Some(StepRange { min: -40_000, max: 40_000 }),
        homing: Homing { mode: HomingMode::None, speed: 1_000, backoff: 0, position: 0 },
        invert_dir: false,
        enable: Polarity::ActiveHigh,
        limit_min: Input::Unused,
        limit_max: Input::Unused,
        index: Input::Unused,
    };
    let g = GalvoAxis { min_code: 0, max_code: 65535, zero_code: 32768, nanorad_per_code: 10_000 };
    let items = [
        ConfigItem::Stepper(axis(0, AxisKind::Linear)),
        ConfigItem::Stepper(axis(1, AxisKind::Rotary)),
        laser(0),
        laser(1),
        laser(2),
        ConfigItem::Galvo(GalvoConfig {
            galvo: 0,
            dac: DacKind::Dac8563,
            x: g,
            y: g,
            park: Xy { x: 32768, y: 32768 },
            settle_ticks: 300,
        }),
        ConfigItem::Camera(CameraConfig {
            camera: 0,
            pulse_ticks: 100,
            polarity: Polarity::ActiveHigh,
            exposure_input: Input::Unused,
            min_interval_ticks: 1_000,
        }),
    ];
    for item in items {
        c.request(Command::Configure(item)).unwrap();
    }
    c.request(Command::Home(AxisRef::Stepper(0))).unwrap();
    c.request(Command::Home(AxisRef::Stepper(1))).unwrap();
    c.request(Command::Arm { lasers: 0b111 }).unwrap();
    c
}

/// Runs every step; returns the trigger events.
fn run(c: &mut Client<VirtualTransport>, plan: &Plan) -> Vec<lightrig_protocol::event::TriggerEvent> {
    let mut triggers = Vec::new();
    for step in &plan.steps {
        let out = c
            .run_sequence(100 + step.id, step.items.clone(), StartAt::Now, |e| {
                if let Event::Trigger(t) = &e.event {
                    triggers.push(t.clone());
                }
            })
            .unwrap();
        assert_eq!(out.items as usize, step.items.len());
    }
    triggers
}

#[test]
fn lls_passes_take_one_frame_per_millimetre_at_rest() {
    let mut c = rig_client();
    let p = lls::LlsParams {
        axis: 0,
        start: -800,
        step: 80,
        count: 21,
        camera: 0,
        exposure: 2_000,
        settle: 5_000,
        frame_gap: 3_000,
        light: 1,
        stripe: 0,
        backlight: Some(2),
        passes: vec![lls::Pass::Reflectance, lls::Pass::Stripe, lls::Pass::Backlit],
        timeout: 2_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    };
    let plan = lls::plan(&p).unwrap();
    let s = plan.summary();
    assert_eq!((s.steps, s.triggers, s.bytes), (3, 63, 63 << 20));
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers.len(), 63);
    for (k, t) in triggers.iter().enumerate() {
        let (pass, i) = (k / 21, (k % 21) as i32);
        // The gantry sits exactly at its position, and only the pass's light is on.
        assert_eq!(t.snapshot.axes[0], -800 + 80 * i, "frame {k}");
        assert_eq!(t.snapshot.lasers, [0b010, 0b001, 0b100][pass], "frame {k}");
        assert_eq!(t.frame, i as u32);
        assert_eq!(t.width, 2_000);
    }
    // Never a step while the shutter is open: every step tick lies outside every exposure.
    let board = c.transport().device().rig().board();
    let steps: Vec<u64> =
        board.changes(|o| matches!(o, Output::Step { .. })).iter().map(|c| c.tick).collect();
    for t in &triggers {
        let inside = steps.iter().filter(|&&s| s >= t.tick && s < t.tick + u64::from(t.width)).count();
        assert_eq!(inside, 0);
    }
}

#[test]
fn disco_never_triggers_while_the_mirrors_move() {
    let mut c = rig_client();
    let grid: Vec<Xy> = (0..3)
        .flat_map(|i| (0..3).map(move |j| Xy { x: 20_000 + 10_000 * i, y: 20_000 + 10_000 * j }))
        .collect();
    let p = disco::DiscoParams {
        turntable: 1,
        views: vec![0, 2_000, 4_000],
        lasers: vec![0, 1],
        galvo: 0,
        grid: grid.clone(),
        camera: 0,
        exposure: 1_000,
        settle: 300,
        frame_gap: 1_500,
        spotlight: Some(2),
        timeout: 2_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    };
    let plan = disco::plan(&p).unwrap();
    assert_eq!(plan.summary().triggers, 3 * (1 + 2 * 9));
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers.len(), 57);
    let board = c.transport().device().rig().board();
    let jumps: Vec<u64> =
        board.changes(|o| matches!(o, Output::Galvo { .. })).iter().map(|c| c.tick).collect();
    for (k, t) in triggers.iter().enumerate() {
        let (view, r) = (k / 19, k % 19);
        assert_eq!(t.snapshot.axes[1], [0, 2_000, 4_000][view]);
        if r == 0 {
            assert_eq!(t.snapshot.lasers, 0b100, "registration under the spotlight");
            continue;
        }
        let (laser, point) = ((r - 1) / 9, (r - 1) % 9);
        assert_eq!(t.snapshot.galvos[0], grid[point]);
        assert_eq!(t.snapshot.lasers, 1 << laser, "one laser at a time, emitting");
        // The last jump before this trigger was at least `settle` earlier.
        let last_jump = jumps.iter().filter(|&&j| j <= t.tick).max().unwrap();
        assert!(t.tick - last_jump >= 300, "trigger {k} {} ticks after a jump", t.tick - last_jump);
    }
}
