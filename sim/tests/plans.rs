//! Planners against the firmware core in-process: the right edges and events come out, in the
//! right order, the right count.

use lightrig_firmware::sim::{Output, SimBoard};
mod common;

use common::rig_client;
use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::client::Client;
use lightrig_host::plan::{disco, lls, Plan};
use lightrig_protocol::config::*;
use lightrig_protocol::sequence::{AxisRef, StartAt};
use lightrig_protocol::{Command, Event};
use lightrig_sim::transport::VirtualTransport;

/// Runs every step; returns the trigger events.
fn run(c: &mut Client<VirtualTransport>, plan: &Plan) -> Vec<lightrig_protocol::event::TriggerEvent> {
    let mut triggers = Vec::new();
    for step in &plan.steps {
        let out = c
            .run_sequence(100 + step.id, step.items(), StartAt::Now, |e| {
                if let Event::Trigger(t) = &e.event {
                    triggers.push(t.clone());
                }
            })
            .unwrap();
        assert_eq!(out.items as usize, step.items().len());
    }
    triggers
}

#[test]
fn lls_passes_take_one_frame_per_millimetre_at_rest() {
    let mut c = rig_client();
    let plan = lls::plan(&common::lls_params()).unwrap();
    let s = plan.summary();
    assert_eq!((s.steps, s.triggers, s.bytes), (3, 63, 63 << 20));
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers.len(), 63);
    for (k, t) in triggers.iter().enumerate() {
        let (pass, i) = (k / 21, (k % 21) as i32);
        // The gantry sits exactly at its position, and only the pass's light is on.
        assert_eq!(t.snapshot.axes[0], -800 + 80 * i, "frame {k}");
        assert_eq!(t.snapshot.lasers, [0b010, 0b001, 0b010][pass], "frame {k}");
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
fn lls_board_light_box_and_backlit_frames_are_single_shots_at_the_start() {
    use lightrig_host::plan::lls::Pass;
    let mut c = rig_client();
    let params =
        lls::LlsParams { passes: vec![Pass::Board, Pass::LightBox, Pass::Backlit], ..common::lls_params() };
    let plan = lls::plan(&params).unwrap();
    assert_eq!(plan.steps.iter().map(|s| s.shot_count()).collect::<Vec<_>>(), [1, 1, 1]);
    assert_eq!(plan.steps[0].meta["operator"], "place the calibration board on the reference plane");
    assert_eq!(plan.steps[1].meta["pass"], "light-box");
    let triggers = run(&mut c, &plan);
    let lasers: Vec<u8> = triggers.iter().map(|t| t.snapshot.lasers).collect();
    // The board in room light (no source), then the light box alone, twice.
    assert_eq!(lasers, [0b000, 0b100, 0b100]);
    assert!(triggers.iter().all(|t| t.snapshot.axes[0] == -800));
}

#[test]
fn lls_diagonal_passes_carry_their_mount_and_ask_for_the_turn() {
    use lightrig_host::plan::lls::Pass;
    assert_eq!(Pass::parse("reflectance+15"), Some(Pass::Reflectance { mount_deg: 15 }));
    assert_eq!(Pass::parse("reflectance-15"), Some(Pass::Reflectance { mount_deg: -15 }));
    assert_eq!(Pass::parse("reflectance"), Some(Pass::REFLECTANCE));
    for bad in ["reflectance15", "reflectance+46", "reflectance+x", "reflect"] {
        assert_eq!(Pass::parse(bad), None, "{bad}");
    }
    let passes =
        vec![Pass::REFLECTANCE, Pass::Reflectance { mount_deg: 15 }, Pass::Reflectance { mount_deg: -15 }];
    let plan = lls::plan(&lls::LlsParams { passes, ..common::lls_params() }).unwrap();
    let meta: Vec<_> =
        plan.steps.iter().map(|s| (s.meta["pass"].clone(), s.meta["mount_deg"].clone())).collect();
    assert_eq!(
        meta,
        [("reflectance", 0), ("reflectance", 15), ("reflectance", -15)]
            .map(|(p, m)| (serde_json::json!(p), serde_json::json!(m)))
    );
    assert!(plan.steps[0].meta.get("operator").is_none());
    assert_eq!(plan.steps[1].meta["operator"], "turn the linear light's mount to +15°");
    assert_eq!(plan.steps[2].meta["operator"], "turn the linear light's mount to -15°");
    assert_eq!(plan.steps[1].name, "pass reflectance +15°");
    // Each sweeps the whole pass.
    assert!(plan.steps.iter().all(|s| s.shot_count() == 21));
}

#[test]
fn disco_never_triggers_while_the_mirrors_move() {
    let mut c = rig_client();
    let grid: Vec<Xy> = (0..3)
        .flat_map(|i| (0..3).map(move |j| Xy { x: 20_000 + 10_000 * i, y: 20_000 + 10_000 * j }))
        .collect();
    let white = Xy { x: 32_768, y: 32_768 };
    let p = disco::DiscoParams {
        turntable: 1,
        views: vec![0, 2_000, 4_000],
        lasers: vec![0, 1],
        positions: vec!["front".into(), "left".into()],
        frames_per_spot: 2,
        white: Some(white),
        galvo: 0,
        grid: grid.clone(),
        cameras: vec![0],
        exposure: 1_000,
        settle: 300,
        frame_gap: 1_500,
        spotlight: Some(2),
        timeout: 2_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    };
    let plan = disco::plan(&p).unwrap();
    // The white balance (one frame per laser), then per position and view: the registration
    // frame and two frames per spot and laser.
    let per_view = 1 + 2 * 9 * 2;
    assert_eq!(plan.summary().triggers, 2 + 2 * 3 * per_view);
    // The operator places the white target, then the object, then moves the camera once.
    let ops: Vec<(u32, String)> = plan
        .steps
        .iter()
        .filter_map(|s| s.meta.get("operator").and_then(|o| o.as_str()).map(|o| (s.id, o.to_string())))
        .collect();
    assert_eq!(ops.len(), 3, "{ops:?}");
    assert_eq!((ops[0].0, ops[1].0, ops[2].0), (0, 1, 4));
    assert!(ops[2].1.contains("`left`"), "{}", ops[2].1);
    assert_eq!(plan.steps[4].meta["camera_position"], 1);
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers.len(), 2 + 6 * per_view);
    let board = c.transport().device().rig().board();
    let jumps: Vec<u64> =
        board.changes(|o| matches!(o, Output::Galvo { .. })).iter().map(|c| c.tick).collect();
    for (k, t) in triggers[..2].iter().enumerate() {
        assert_eq!(t.snapshot.galvos[0], white);
        assert_eq!(t.snapshot.lasers, 1 << k, "white balance: one laser at a time");
    }
    for (k, t) in triggers[2..].iter().enumerate() {
        let (view, r) = ((k / per_view) % 3, k % per_view);
        assert_eq!(t.snapshot.axes[1], [0, 2_000, 4_000][view]);
        if r == 0 {
            assert_eq!(t.snapshot.lasers, 0b100, "registration under the spotlight");
            continue;
        }
        let (laser, point) = ((r - 1) / 18, ((r - 1) % 18) / 2);
        assert_eq!(t.snapshot.galvos[0], grid[point]);
        assert_eq!(t.snapshot.lasers, 1 << laser, "one laser at a time, emitting");
        // The last jump before this trigger was at least `settle` earlier.
        let last_jump = jumps.iter().filter(|&&j| j <= t.tick).max().unwrap();
        assert!(t.tick - last_jump >= 300, "trigger {k} {} ticks after a jump", t.tick - last_jump);
    }
}

#[test]
fn immersion_sweeps_one_frame_per_sheet_per_orientation() {
    use lightrig_host::plan::firs;
    let mut c = rig_client();
    let p = firs::ImmersionParams {
        turntable: 1,
        orientations: vec![0, 4_000],
        laser: 0,
        galvo: 0,
        sweep: (10_000, 50_000, 11),
        sheet_y: 32_768,
        cameras: vec![0],
        exposure: 1_000,
        settle: 300,
        frame_gap: 1_200,
        calibration: true,
        timeout: 2_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    };
    let plan = firs::plan(&p).unwrap();
    assert_eq!(plan.summary().triggers, (1 + 11) + 2 * 11);
    let codes = firs::sheet_codes(10_000, 50_000, 11);
    assert_eq!((codes[0], codes[1], codes[10]), (10_000, 14_000, 50_000));
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers[0].snapshot.lasers, 0, "dark frame");
    for (k, t) in triggers[1..].iter().enumerate() {
        let sheet = k % 11;
        assert_eq!(t.snapshot.galvos[0], Xy { x: codes[sheet], y: 32_768 });
        assert_eq!(t.snapshot.lasers, 0b001);
        // Calibration and the first orientation at 0, the second at 4000.
        assert_eq!(t.snapshot.axes[1], if k < 22 { 0 } else { 4_000 });
    }
}

#[test]
fn bispectral_takes_an_exposure_series_per_pair_with_the_right_slot() {
    use lightrig_host::plan::brrdf;
    let mut board = SimBoard::default();
    board.wheels[0].index_at = Some((0, 1_200));
    let mut c = Client::connect(VirtualTransport::new(virtual_device_info(), board), 4).unwrap();
    let axis = |axis| StepperConfig {
        axis,
        kind: AxisKind::Rotary,
        steps_per_unit: Ratio { num: 100, den: 1 },
        max_speed: 20_000,
        accel: 200_000,
        limits: None,
        homing: Homing { mode: HomingMode::None, speed: 1_000, backoff: 0, position: 0 },
        invert_dir: false,
        enable: Polarity::ActiveHigh,
        limit_min: Input::Unused,
        limit_max: Input::Unused,
        index: Input::Unused,
    };
    let wheel = FilterWheelConfig {
        wheel: 0,
        slots: 6,
        steps_per_rev: 1_200,
        max_speed: 10_000,
        accel: 100_000,
        index: Input::Wired(Polarity::ActiveHigh),
        index_offset: 0,
        invert_dir: false,
        enable: Polarity::ActiveHigh,
    };
    let cam = CameraConfig {
        camera: 0,
        pulse_ticks: 100,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    for item in [
        ConfigItem::Stepper(axis(0)),
        ConfigItem::Stepper(axis(1)),
        ConfigItem::FilterWheel(wheel),
        ConfigItem::Camera(cam),
    ] {
        c.request(Command::Configure(item)).unwrap();
    }
    for a in [AxisRef::Stepper(0), AxisRef::Stepper(1), AxisRef::FilterWheel(0)] {
        c.request(Command::Home(a)).unwrap();
    }
    c.idle(2_000_000).unwrap();
    let grid = [400, 500, 600];
    // Near-UV excitation through the LED in slot 1, the rest through the open slot 0.
    let pairs = brrdf::full_pairs(&grid, |ex| if ex < 450 { 1 } else { 0 });
    assert_eq!(pairs.len(), 6, "excitation <= emission only");
    let p = brrdf::BispectralParams {
        sample_axis: 0,
        light_axis: 1,
        geometries: vec![(0, 3_000), (1_500, 4_500)],
        wheel: 0,
        pairs: pairs.clone(),
        cameras: vec![0],
        exposures: vec![1_000, 4_000, 16_000],
        readout: 2_000,
        min_interval: 10_000,
        timeout: 3_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    };
    let plan = brrdf::plan(&p).unwrap();
    assert_eq!(plan.summary().triggers, 2 * 6 * 3);
    let triggers = run(&mut c, &plan);
    for (k, t) in triggers.iter().enumerate() {
        let (step, e) = (k / 3, k % 3);
        let (g, pair) = (step / 6, pairs[step % 6]);
        assert_eq!(t.width, [1_000, 4_000, 16_000][e]);
        assert_eq!(t.snapshot.axes.as_slice(), [[0, 3_000], [1_500, 4_500]][g]);
        assert_eq!(t.snapshot.filters[0], Some(pair.slot));
        // Exposure + readout (3 000 and 6 000 ticks) is shorter than the camera's minimum
        // interval: the series waits for the camera.
        if e < 2 {
            assert_eq!(triggers[k + 1].tick - t.tick, 10_000, "trigger {k}");
        }
    }
}

#[test]
fn brdf_display_ramps_the_coils_then_captures_then_fades() {
    use lightrig_host::plan::display::{self, partial, Target};
    let mut c = rig_client();
    for ch in 0..2 {
        let coil = VoiceCoilConfig { channel: ch, sample_rate_hz: 48_000, max_amplitude: u16::MAX };
        c.request(Command::Configure(ConfigItem::VoiceCoil(coil))).unwrap();
    }
    let targets: Vec<Target> = [0.05, 0.2]
        .iter()
        .map(|&drive| Target {
            name: format!("drive {drive}"),
            channels: (0..2)
                .map(|ch| {
                    (
                        ch,
                        [101.0, 103.0, 109.0]
                            .iter()
                            .map(|&f| partial(f + f64::from(ch), drive, 0.0))
                            .collect(),
                    )
                })
                .collect(),
            meta: serde_json::json!({ "drive": drive }),
        })
        .collect();
    let p = display::DisplayParams {
        targets,
        ramp: 50_000,
        settle: 200_000,
        cameras: vec![0],
        captures: 3,
        exposure: 5_000,
        frame_gap: 10_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
        meta: serde_json::Value::Null,
    };
    let plan = display::plan(&p).unwrap();
    assert_eq!(plan.steps[1].meta["drive"], 0.2, "the target's meta is the step's");
    let triggers = run(&mut c, &plan);
    assert_eq!(triggers.len(), 6);
    // Samples leave with a fixed latency of two blocks: let the last ones out.
    c.idle(20_000).unwrap();
    let board = c.transport().device().rig().board();
    // The coil is sounding at every capture and silent at the end.
    for t in &triggers {
        let sample = (t.tick * 48_000 / 1_000_000) as usize;
        let window = &board.samples[0][sample..sample + 480];
        assert!(window.iter().any(|&v| v.unsigned_abs() > 10), "sounding at tick {}", t.tick);
    }
    let tail = &board.samples[0][board.samples[0].len() - 64..];
    assert!(tail.iter().all(|&v| v == 0), "faded to silence");
}
