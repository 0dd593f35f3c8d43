//! The rig's behaviour on the simulated board: every edge at its exact tick.

mod common;

use common::*;
use lightrig_firmware::motion::Trapezoid;
use lightrig_firmware::sim::{Change, Output, SimExposure};
use lightrig_protocol::config::{ConfigItem, Xy};
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::{DeviceState, Event, FaultCause, Switch};
use lightrig_protocol::sequence::{Action, AxisRef, Profile, StartAt, WaitFor};
use lightrig_protocol::Error;

fn trigger(camera: u8) -> Action {
    Action::Trigger { camera, exposure: 0 }
}

fn edges(rig: &lightrig_firmware::Rig<lightrig_firmware::sim::SimBoard>, cam: u8) -> Vec<(u64, bool)> {
    rig.board()
        .changes(|o| matches!(o, Output::Trigger { camera, .. } if *camera == cam))
        .into_iter()
        .map(|c| match c.output {
            Output::Trigger { level, .. } => (c.tick, level),
            _ => unreachable!(),
        })
        .collect()
}

fn laser_levels(rig: &lightrig_firmware::Rig<lightrig_firmware::sim::SimBoard>, ch: u8) -> Vec<(u64, bool)> {
    rig.board()
        .changes(|o| matches!(o, Output::Laser { channel, .. } if *channel == ch))
        .into_iter()
        .map(|c| match c.output {
            Output::Laser { level, .. } => (c.tick, level),
            _ => unreachable!(),
        })
        .collect()
}

#[test]
fn trigger_train_edges_are_exact_and_each_reports_its_snapshot() {
    let mut rig = rig();
    configure_all(&mut rig);
    let items: Vec<_> = (0..10).map(|_| item(1_000, trigger(0))).collect();
    load_all(&mut rig, 7, &items);
    rig.start(7, StartAt::Tick(50_000), 0).unwrap();
    rig.run_until(100_000);
    let mut want = vec![(0, false)]; // configuration drives the output inactive
    for k in 1..=10u64 {
        want.push((50_000 + 1_000 * k, true));
        want.push((50_000 + 1_000 * k + 100, false));
    }
    assert_eq!(edges(&rig, 0), want);
    let events = rig.drain_events();
    let t = triggers(&events);
    assert_eq!(t.len(), 10);
    for (k, e) in t.iter().enumerate() {
        assert_eq!((e.sequence, e.item, e.frame, e.camera), (7, k as u32, k as u32, 0));
        assert_eq!(e.tick, 51_000 + 1_000 * k as u64);
        assert_eq!(e.width, 100);
        assert_eq!(e.snapshot.galvos.as_slice(), &[Xy { x: 1000, y: 1000 }]);
        assert_eq!(e.snapshot.axes.as_slice(), &[0, 0]);
        assert_eq!(e.snapshot.filters.as_slice(), &[None]);
        assert_eq!(e.snapshot.lasers, 0);
    }
    assert!(events.contains(&Event::SequenceDone { sequence: 7, items: 10, tick: 60_000 }));
    assert_eq!(rig.state(), DeviceState::Ready);
}

#[test]
fn a_million_triggers_streamed_under_credit_keep_exact_ticks_and_lose_no_event() {
    const N: u32 = 1_000_000;
    const PERIOD: u32 = 1_000;
    let mut rig = rig();
    rig.configure(&ConfigItem::Camera(camera(0)), 0).unwrap();
    let mut sent = 0u32;
    let mut chunk_no = 0u32;
    let mut frames = 0u32;
    let mut started = false;
    let mut now = 0u64;
    let mut done = None;
    while done.is_none() {
        // The host: refill whenever a whole chunk fits.
        while sent < N && rig.buffer().is_none_or(|b| b.free >= 32) {
            let n = (N - sent).min(32);
            let items: Vec<_> = (0..n).map(|_| item(PERIOD, trigger(0))).collect();
            rig.load(&chunk(1, chunk_no, sent + n == N, &items)).unwrap();
            sent += n;
            chunk_no += 1;
        }
        if !started {
            rig.start(1, StartAt::Now, 0).unwrap();
            started = true;
        }
        now += 20_000;
        rig.run_until(now);
        for e in rig.drain_events() {
            match e {
                Event::Trigger(t) => {
                    assert_eq!(t.frame, frames, "no trigger lost");
                    assert_eq!(t.tick, u64::from(frames + 1) * u64::from(PERIOD), "no drift");
                    frames += 1;
                }
                Event::SequenceDone { items, tick, .. } => done = Some((items, tick)),
                Event::Buffer(_) | Event::State { .. } => {}
                other => panic!("unexpected {other:?}"),
            }
        }
    }
    assert_eq!(frames, N);
    assert_eq!(done, Some((N, u64::from(N) * u64::from(PERIOD))));
    assert_eq!(rig.fault(), None);
}

#[test]
fn galvo_points_lines_and_blanking() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.arm(0b01, 0).unwrap();
    rig.board_mut().record.clear();
    let to = Xy { x: 2000, y: 3000 };
    let items = [
        item(0, Action::Laser { channel: 0, on: true }),
        // Jump: blank for settle_ticks = 200.
        item(1_000, Action::GalvoPoint { galvo: 0, to }),
        // Sweep with the laser on: 4 updates over 1000 ticks.
        item(1_000, Action::GalvoLine { galvo: 0, to: Xy { x: 2400, y: 2999 }, duration: 1_000, steps: 4 }),
        item(2_000, Action::Laser { channel: 0, on: false }),
    ];
    load_all(&mut rig, 1, &items);
    rig.start(1, StartAt::Tick(10), 0).unwrap();
    rig.run_until(10_000);
    let galvo: Vec<_> = rig
        .board()
        .changes(|o| matches!(o, Output::Galvo { .. }))
        .into_iter()
        .map(|c| match c.output {
            Output::Galvo { to, .. } => (c.tick, to.x, to.y),
            _ => unreachable!(),
        })
        .collect();
    assert_eq!(
        galvo,
        [
            (1_010, 2000, 3000),
            (2_260, 2100, 3000), // y: 3000 - 1/4 rounds towards `from`
            (2_510, 2200, 3000),
            (2_760, 2300, 3000),
            (3_010, 2400, 2999),
        ]
    );
    // The laser: on at 10, dark from the jump at 1010 until settled at 1210, off at 4010.
    assert_eq!(laser_levels(&rig, 0), [(10, true), (1_010, false), (1_210, true), (4_010, false)]);
}

#[test]
fn laser_warmup_max_on_time_and_arming() {
    let mut rig = rig();
    configure_all(&mut rig);
    // Not armed: refused, nothing emitted.
    let on = Action::Laser { channel: 1, on: true };
    assert_eq!(rig.immediate(&on, 0), Err(Error::NotArmed { channel: 1 }));
    assert_eq!(rig.arm(0b100, 0), Err(Error::NotConfigured { kind: Peripheral::Laser, index: 2 }));
    assert_eq!(
        rig.arm(0b1000, 0),
        Err(Error::NoSuchPeripheral { kind: Peripheral::Laser, index: 3, count: 3 })
    );
    rig.arm(0b10, 100).unwrap();
    rig.immediate(&on, 1_000).unwrap();
    rig.host_seen(1_000, false);
    rig.run_until(6_000);
    let events = rig.drain_events();
    assert!(events.contains(&Event::LaserReady { channel: 1, tick: 6_000 }), "{events:?}");
    // Keep the host alive; the laser hits its maximum on-time 1 s after switching on.
    for t in (100_000..=1_000_000).step_by(100_000) {
        rig.host_seen(t, false);
        rig.run_until(t);
    }
    assert_eq!(rig.fault(), None);
    rig.run_until(1_001_000);
    assert_eq!(rig.fault(), Some(FaultCause::LaserOnTime { channel: 1 }));
    assert_eq!(laser_levels(&rig, 1), [(0, false), (1_000, true), (1_001_000, false)]);
    assert_eq!(rig.armed(), 0);
    let events = rig.drain_events();
    assert!(events.contains(&Event::Fault { cause: FaultCause::LaserOnTime { channel: 1 }, tick: 1_001_000 }));
}

#[test]
fn an_open_interlock_blocks_and_trips_the_laser() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.arm(0b1, 0).unwrap();
    rig.immediate(&Action::Laser { channel: 0, on: true }, 10).unwrap();
    assert_eq!(rig.lasers_on(), 1);
    rig.board_mut().interlocks[0] = false;
    rig.poll(500);
    assert_eq!(rig.fault(), Some(FaultCause::Interlock { channel: 0 }));
    assert_eq!(rig.lasers_on(), 0);
    assert_eq!(laser_levels(&rig, 0).last(), Some(&(500, false)));
    // Cleared but the interlock still open: switching on faults again at once.
    rig.clear_fault(600).unwrap();
    rig.arm(0b1, 600).unwrap();
    rig.immediate(&Action::Laser { channel: 0, on: true }, 700).unwrap();
    assert_eq!(rig.fault(), Some(FaultCause::Interlock { channel: 0 }));
    assert_eq!(laser_levels(&rig, 0).last(), Some(&(500, false)), "never emitted");
}

fn step_ticks(rig: &lightrig_firmware::Rig<lightrig_firmware::sim::SimBoard>, motor: AxisRef) -> Vec<u64> {
    rig.board()
        .changes(|o| matches!(o, Output::Step { motor: m } if *m == motor))
        .into_iter()
        .map(|c| c.tick)
        .collect()
}

/// Homes axis 0 against a min switch placed at physical position -20 steps.
fn homed_rig() -> lightrig_firmware::Rig<lightrig_firmware::sim::SimBoard> {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.board_mut().steppers[0].limit_min_at = Some(-20);
    rig.home(AxisRef::Stepper(0), 0).unwrap();
    rig.run_until(1_000_000);
    let events = rig.drain_events();
    assert!(
        events.iter().any(|e| matches!(
            e,
            Event::Switch { axis: AxisRef::Stepper(0), switch: Switch::Min, position: -20, .. }
        )),
        "{events:?}"
    );
    assert!(events
        .iter()
        .any(|e| matches!(e, Event::Homed { axis: AxisRef::Stepper(0), position: -16_000, .. })));
    // Backed off 100 steps: physically at +80, logically at the homing position.
    assert_eq!(rig.board().steppers[0].position, 80);
    assert_eq!(rig.axis_position(0), Some(-16_000));
    rig
}

#[test]
fn stepper_steps_land_on_the_analytic_trapezoid() {
    let mut rig = homed_rig();
    rig.board_mut().record.clear();
    let start = 2_000_000;
    rig.host_seen(start, false);
    let target = -16_000 + 12_345;
    let mv = Action::StepperMove { axis: 0, target, profile: Profile { max_speed: 15_000, accel: 0 } };
    rig.immediate(&mv, start).unwrap();
    rig.run_until(start + 2_000_000);
    let plan = Trapezoid::new(12_345, 15_000, 100_000, TICK_HZ).unwrap();
    let want: Vec<u64> = (1..=12_345).map(|k| start + plan.step_tick(k)).collect();
    assert_eq!(step_ticks(&rig, AxisRef::Stepper(0)), want);
    // Direction set at the start, before the first step; enable untouched.
    let dir = rig.board().changes(|o| matches!(o, Output::Dir { .. }));
    assert_eq!(
        dir,
        [Change { tick: start, output: Output::Dir { motor: AxisRef::Stepper(0), level: true } }]
    );
    let done = start + plan.duration();
    assert!(rig.drain_events().contains(&Event::MoveDone {
        axis: AxisRef::Stepper(0),
        position: target,
        tick: done
    }));
    assert_eq!(rig.board().steppers[0].position, 80 + 12_345);
}

#[test]
fn soft_limits_homing_and_busy_axes_are_refused_with_typed_errors() {
    let mut rig = rig();
    configure_all(&mut rig);
    let mv = |target| Action::StepperMove { axis: 0, target, profile: Profile::default() };
    assert_eq!(rig.immediate(&mv(0), 0), Err(Error::NotHomed { axis: AxisRef::Stepper(0) }));
    let mut rig = homed_rig();
    assert_eq!(rig.immediate(&mv(16_001), 0), Err(Error::OutOfRange { kind: Peripheral::Stepper, index: 0 }));
    let fast = Action::StepperMove { axis: 0, target: 0, profile: Profile { max_speed: 20_001, accel: 0 } };
    assert_eq!(rig.immediate(&fast, 0), Err(Error::OutOfRange { kind: Peripheral::Stepper, index: 0 }));
    rig.immediate(&mv(0), 2_000_000).unwrap();
    assert_eq!(rig.immediate(&mv(10), 2_000_001), Err(Error::Busy { axis: AxisRef::Stepper(0) }));
    assert_eq!(rig.immediate(&mv(0), 2_000_002), Err(Error::Busy { axis: AxisRef::Stepper(0) }));
}

#[test]
fn a_limit_switch_during_a_move_stops_at_once_and_faults() {
    let mut rig = homed_rig();
    rig.board_mut().steppers[0].limit_max_at = Some(1_080); // 1000 steps ahead
    rig.host_seen(2_000_000, false);
    rig.immediate(&Action::StepperMove { axis: 0, target: 0, profile: Profile::default() }, 2_000_000)
        .unwrap();
    rig.run_until(4_000_000);
    assert_eq!(rig.fault(), Some(FaultCause::Limit { axis: AxisRef::Stepper(0) }));
    assert_eq!(rig.board().steppers[0].position, 1_080, "not one step past the switch");
    let events = rig.drain_events();
    assert!(events.iter().any(|e| matches!(e, Event::Switch { switch: Switch::Max, position: -15_000, .. })));
}

#[test]
fn filter_wheel_homes_on_its_index_and_takes_the_shorter_way() {
    let mut rig = rig();
    configure_all(&mut rig);
    // Index mark 300 steps ahead of power-up position; 1200 steps per turn.
    rig.board_mut().wheels[0].index_at = Some((300, 1200));
    rig.home(AxisRef::FilterWheel(0), 0).unwrap();
    rig.run_until(1_000_000);
    let events = rig.drain_events();
    assert!(events
        .iter()
        .any(|e| matches!(e, Event::Homed { axis: AxisRef::FilterWheel(0), position: 0, .. })));
    // Slot 0 lies 50 steps past the mark.
    assert_eq!(rig.board().wheels[0].position, 350);
    // Slot 5 is one slot (200 steps) backwards, not five forwards.
    rig.host_seen(1_000_000, false);
    rig.immediate(&Action::FilterWheel { wheel: 0, slot: 5 }, 1_000_000).unwrap();
    rig.run_until(2_000_000);
    assert_eq!(rig.board().wheels[0].position, 150);
    let events = rig.drain_events();
    assert!(events
        .iter()
        .any(|e| matches!(e, Event::MoveDone { axis: AxisRef::FilterWheel(0), position: 5, .. })));
    let snapshot_slot = {
        rig.immediate(&trigger(0), 2_000_000).unwrap();
        let events = rig.drain_events();
        triggers(&events)[0].snapshot.filters[0]
    };
    assert_eq!(snapshot_slot, Some(5));
}

#[test]
fn wait_for_exposure_end_resumes_at_the_captured_edge() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.board_mut().exposure[0] = Some(SimExposure { delay: 30, length: 4_000, ..Default::default() });
    let items = [
        item(100, trigger(0)),
        item(0, Action::Wait { until: WaitFor::ExposureEnd(0), timeout: 10_000 }),
        item(700, trigger(0)),
    ];
    load_all(&mut rig, 3, &items);
    rig.start(3, StartAt::Tick(0), 0).unwrap();
    rig.run_until(50_000);
    // Exposure ends at 100 + 30 + 4000 = 4130; the next trigger 700 ticks later.
    assert_eq!(edges(&rig, 0), [(0, false), (100, true), (200, false), (4_830, true), (4_930, false)]);
    let events = rig.drain_events();
    assert!(events.contains(&Event::Exposure { camera: 0, active: true, tick: 130 }));
    assert!(events.contains(&Event::Exposure { camera: 0, active: false, tick: 4_130 }));
}

#[test]
fn a_wait_that_never_holds_faults_at_its_timeout() {
    let mut rig = rig();
    configure_all(&mut rig);
    let items =
        [item(100, trigger(0)), item(0, Action::Wait { until: WaitFor::ExposureEnd(0), timeout: 10_000 })];
    load_all(&mut rig, 3, &items);
    rig.start(3, StartAt::Tick(0), 0).unwrap();
    rig.run_until(50_000);
    assert_eq!(rig.fault(), Some(FaultCause::WaitTimeout { sequence: 3, item: 1 }));
    assert!(rig
        .drain_events()
        .contains(&Event::Fault { cause: FaultCause::WaitTimeout { sequence: 3, item: 1 }, tick: 10_100 }));
}

#[test]
fn underrun_stops_in_the_safe_state_and_says_so() {
    let mut rig = homed_rig();
    rig.arm(0b1, 0).unwrap();
    rig.host_seen(2_000_000, false);
    let items = [
        item(0, Action::Laser { channel: 0, on: true }),
        item(0, Action::GalvoPoint { galvo: 0, to: Xy { x: 5000, y: 5000 } }),
        item(0, Action::StepperMove { axis: 0, target: 0, profile: Profile::default() }),
        item(100_000, trigger(0)),
    ];
    rig.load(&chunk(9, 0, false, &items)).unwrap(); // more promised, never sent
    rig.start(9, StartAt::Tick(2_000_000), 2_000_000).unwrap();
    rig.run_until(2_100_000);
    let events = rig.drain_events();
    assert!(events.contains(&Event::Underrun { sequence: 9, item: 4, tick: 2_100_000 }), "{events:?}");
    assert_eq!(rig.fault(), Some(FaultCause::Underrun { sequence: 9 }));
    assert_eq!(rig.lasers_on(), 0);
    assert_eq!(rig.galvo_position(0), Some(Xy { x: 1000, y: 1000 }), "parked");
    assert_eq!(laser_levels(&rig, 0).last(), Some(&(2_100_000, false)));
    // The stepper decelerates to a stop rather than halting: steps continue after the fault,
    // spaced ever wider, and end with a MoveDone short of the target.
    let steps = step_ticks(&rig, AxisRef::Stepper(0));
    let before = steps.iter().filter(|&&t| t <= 2_100_000).count();
    rig.run_until(3_000_000);
    let steps = step_ticks(&rig, AxisRef::Stepper(0));
    assert!(steps.len() > before);
    let gaps: Vec<u64> = steps[before..].windows(2).map(|w| w[1] - w[0]).collect();
    // Integer ticks: each gap is the analytic one floored, so neighbours may differ by a tick.
    assert!(gaps.windows(2).all(|g| g[1] + 1 >= g[0]), "decelerating: {gaps:?}");
    assert!(gaps.last() > gaps.first().map(|g| g * 2).as_ref(), "{gaps:?}");
    let events = rig.drain_events();
    assert!(events
        .iter()
        .any(|e| matches!(e, Event::MoveDone { axis: AxisRef::Stepper(0), position, .. } if *position < 0)));
    // Refused until cleared.
    assert_eq!(rig.load(&chunk(10, 0, true, &[])), Err(Error::Faulted(FaultCause::Underrun { sequence: 9 })));
}

#[test]
fn heartbeat_loss_is_a_fault_at_the_exact_tick() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.configure(
        &ConfigItem::Safety(lightrig_protocol::config::SafetyConfig { heartbeat_timeout_ticks: 50_000 }),
        0,
    )
    .unwrap();
    rig.arm(0b1, 0).unwrap();
    rig.host_seen(1_000, true);
    rig.immediate(&Action::Laser { channel: 0, on: true }, 1_000).unwrap();
    rig.run_until(40_000);
    rig.host_seen(40_000, true);
    rig.run_until(200_000);
    assert_eq!(rig.fault(), Some(FaultCause::HeartbeatLost));
    assert_eq!(laser_levels(&rig, 0), [(0, false), (1_000, true), (90_000, false)]);
}

#[test]
fn an_emergency_stop_replaces_a_latched_fault_a_host_may_clear_by_itself() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.configure(
        &ConfigItem::Safety(lightrig_protocol::config::SafetyConfig { heartbeat_timeout_ticks: 50_000 }),
        0,
    )
    .unwrap();
    rig.host_seen(1_000, true);
    rig.run_until(100_000);
    assert_eq!(rig.fault(), Some(FaultCause::HeartbeatLost));
    // The host's stop arrives after the watchdog fired: the stop is what stays latched.
    rig.emergency_stop(100_000);
    assert_eq!(rig.fault(), Some(FaultCause::EmergencyStop));
}

#[test]
fn emergency_stop_halts_steppers_without_deceleration() {
    let mut rig = homed_rig();
    rig.host_seen(2_000_000, false);
    rig.immediate(&Action::StepperMove { axis: 0, target: 0, profile: Profile::default() }, 2_000_000)
        .unwrap();
    rig.run_until(2_050_000);
    let at = rig.board().steppers[0].position;
    rig.emergency_stop(2_050_000);
    rig.run_until(3_000_000);
    assert_eq!(rig.board().steppers[0].position, at, "no step after the stop");
    assert_eq!(rig.fault(), Some(FaultCause::EmergencyStop));
    assert_eq!(rig.clear_fault(3_000_000), Ok(()));
    assert_eq!(rig.armed(), 0, "lasers stay disarmed");
}

#[test]
fn chunks_obey_order_and_credit() {
    let mut rig = rig();
    configure_all(&mut rig);
    // Galvo points: items that report nothing, so only `Buffer` events come.
    let point = Action::GalvoPoint { galvo: 0, to: Xy { x: 2000, y: 2000 } };
    let t = |n: usize| (0..n).map(|_| item(1_000, point.clone())).collect::<Vec<_>>();
    for c in 0..8 {
        rig.load(&chunk(4, c, false, &t(32))).unwrap();
    }
    assert_eq!(rig.load(&chunk(4, 8, false, &t(1))), Err(Error::BufferFull { free: 0 }));
    assert_eq!(
        rig.load(&chunk(4, 9, false, &t(1))),
        Err(Error::ChunkOutOfOrder { sequence: 4, expected: 8 })
    );
    assert_eq!(
        rig.load(&chunk(5, 8, false, &t(1))),
        Err(Error::ChunkOutOfOrder { sequence: 4, expected: 8 })
    );
    assert_eq!(rig.start(5, StartAt::Now, 0), Err(Error::NoSuchSequence { sequence: 5 }));
    assert_eq!(rig.start(4, StartAt::Tick(10), 20), Err(Error::StartInPast { now: 20 }));
    // A bad item refuses the whole chunk, naming the peripheral.
    let bad = [item(0, Action::GalvoPoint { galvo: 0, to: Xy { x: 10, y: 2000 } })];
    rig.start(4, StartAt::Now, 20).unwrap();
    rig.run_until(70_020);
    assert_eq!(rig.fault(), None);
    let status = rig.buffer().unwrap();
    assert_eq!((status.free, status.executed, status.next_chunk), (70, 70, 8));
    assert_eq!(
        rig.load(&chunk(4, 8, false, &bad)),
        Err(Error::OutOfRange { kind: Peripheral::Galvo, index: 0 })
    );
    assert_eq!(rig.buffer().unwrap().next_chunk, 8);
    // Buffer events report the drained credit in quarters.
    let reports: Vec<_> = rig
        .drain_events()
        .into_iter()
        .filter_map(|e| match e {
            Event::Buffer(b) => Some(b.free),
            _ => None,
        })
        .collect();
    assert_eq!(reports, [64]);
}

#[test]
fn voice_coil_settings_land_on_their_sample_and_faults_fade_to_silence() {
    use lightrig_protocol::sequence::Partial;
    let mut rig = rig();
    rig.configure(&ConfigItem::VoiceCoil(coil(0)), 0).unwrap();
    let partials =
        heapless::Vec::from_slice(&[Partial { freq_mhz: 440_000, amplitude: 20_000, phase: 16_384 }])
            .unwrap();
    // Due at tick 10_000 = sample 480 exactly (48 kHz, 1 MHz ticks); no ramp, phase 90°.
    rig.immediate(&Action::VoiceCoil { channel: 0, ramp: 0, partials }, 10_000).unwrap();
    rig.run_until(30_000);
    let s = &rig.board().samples[0];
    assert!(s.len() >= 1_024, "blocks keep coming: {}", s.len());
    assert!(s[..480].iter().all(|&v| v == 0));
    // cos(0) at full amplitude 20000/65535 of full scale.
    let peak = (20_000.0 / 65_535.0 * 32_767.0) as i16;
    assert!((s[480] - peak).abs() <= 2, "{} vs {peak}", s[480]);
    rig.emergency_stop(30_000);
    rig.run_until(100_000);
    let s = &rig.board().samples[0];
    // The fade starts at sample 1440 and lasts 20 ms = 960 samples; silence after.
    assert!(s[1_440..1_460].iter().any(|&v| v != 0), "fades, does not cut");
    assert!(s[1_440 + 960..].iter().all(|&v| v == 0));
}

#[test]
fn a_host_that_stops_taking_events_faults_the_rig_with_event_overflow() {
    let mut rig = rig();
    configure_all(&mut rig);
    let items: Vec<_> = (0..100).map(|_| item(1_000, trigger(0))).collect();
    load_all(&mut rig, 2, &items);
    rig.start(2, StartAt::Tick(0), 0).unwrap();
    rig.run_until(200_000);
    assert_eq!(rig.fault(), Some(FaultCause::EventOverflow));
    let events = rig.drain_events();
    assert_eq!(events.len(), lightrig_firmware::rig::EVENT_QUEUE);
    // The queue kept room for the fault's own events: they come last, nothing after them.
    let n = events.len();
    assert!(matches!(events[n - 2], Event::Fault { cause: FaultCause::EventOverflow, .. }));
    assert!(matches!(
        events[n - 1],
        Event::State { state: DeviceState::Faulted(FaultCause::EventOverflow), .. }
    ));
    assert_eq!(triggers(&events).len(), n - 3, "state event first, then the triggers that fit");
    assert_eq!(rig.dropped_events(), 1);
}

#[test]
fn a_run_loop_that_wakes_too_late_faults_instead_of_drifting() {
    let mut rig = rig();
    configure_all(&mut rig);
    let items = [item(1_000, trigger(0)), item(1_000, trigger(0))];
    load_all(&mut rig, 6, &items);
    rig.start(6, StartAt::Tick(0), 0).unwrap();
    // On time (within 1 ms = 1000 ticks): runs, with its exact tick on the output.
    rig.poll(1_900);
    assert_eq!(edges(&rig, 0)[1], (1_000, true));
    // 1001 ticks late: refused.
    rig.poll(3_001);
    assert_eq!(rig.fault(), Some(FaultCause::Late { sequence: 6, item: 1 }));
    assert_eq!(edges(&rig, 0).len(), 3, "second trigger never fired");
}

#[test]
fn an_axis_resting_on_its_switch_may_leave_it_but_not_pass_it() {
    let mut rig = rig();
    configure_all(&mut rig);
    let mut c = stepper(0);
    c.homing.backoff = 0;
    rig.configure(&ConfigItem::Stepper(c), 0).unwrap();
    rig.board_mut().steppers[0].limit_min_at = Some(-20);
    rig.home(AxisRef::Stepper(0), 0).unwrap();
    rig.run_until(1_000_000);
    assert_eq!(rig.board().steppers[0].position, -20, "rests on the switch");
    assert_eq!(rig.axis_position(0), Some(-16_000));
    // Away from the switch: the min limit is behind, no fault.
    rig.host_seen(1_000_000, false);
    rig.immediate(&Action::StepperMove { axis: 0, target: -15_000, profile: Profile::default() }, 1_000_000)
        .unwrap();
    rig.run_until(2_000_000);
    assert_eq!(rig.fault(), None);
    // Back past the homed position onto the switch: the limit ahead trips.
    rig.host_seen(2_000_000, false);
    rig.immediate(&Action::StepperMove { axis: 0, target: -16_000, profile: Profile::default() }, 2_000_000)
        .unwrap();
    rig.run_until(3_000_000);
    assert_eq!(rig.fault(), None, "reaching the homed position is fine");
    assert_eq!(rig.board().steppers[0].position, -20);
}

#[test]
fn homing_interrupted_by_a_stop_leaves_the_axis_unhomed() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.board_mut().steppers[0].limit_min_at = Some(-20);
    rig.home(AxisRef::Stepper(0), 0).unwrap();
    let mut t = 0;
    loop {
        t += 1_000;
        rig.run_until(t);
        if rig.drain_events().iter().any(|e| matches!(e, Event::Switch { .. })) {
            break;
        }
        assert!(t < 1_000_000, "switch never reached");
    }
    rig.run_until(t + 10_000); // backing off (100 steps at 2000/s take 50 ms)
    rig.emergency_stop(t + 10_000);
    rig.run_until(t + 1_000_000);
    assert!(!rig.drain_events().iter().any(|e| matches!(e, Event::Homed { .. })));
    rig.clear_fault(t + 1_000_000).unwrap();
    let mv = Action::StepperMove { axis: 0, target: 0, profile: Profile::default() };
    assert_eq!(rig.immediate(&mv, t + 1_000_000), Err(Error::NotHomed { axis: AxisRef::Stepper(0) }));
}

#[test]
fn starting_an_empty_sequence_ends_it_at_once_stamped_now() {
    let mut rig = rig();
    configure_all(&mut rig);
    load_all(&mut rig, 11, &[]);
    rig.start(11, StartAt::Tick(5_000), 100).unwrap();
    let events = rig.drain_events();
    assert!(events.contains(&Event::SequenceDone { sequence: 11, items: 0, tick: 100 }), "{events:?}");
    rig.load(&chunk(12, 0, false, &[])).unwrap();
    rig.start(12, StartAt::Now, 200).unwrap();
    assert!(rig.drain_events().contains(&Event::Underrun { sequence: 12, item: 0, tick: 200 }));
}

#[test]
fn a_late_fault_keeps_outputs_in_tick_order() {
    // Found by the controller fuzz target: the safe state was stamped with the wake-up tick,
    // then earlier work of the same catch-up (voice-coil blocks) followed with earlier ticks.
    let mut rig = rig();
    rig.configure(&ConfigItem::Galvo(galvo()), 0).unwrap();
    rig.configure(&ConfigItem::VoiceCoil(coil(0)), 0).unwrap();
    load_all(&mut rig, 1, &[item(2_000, Action::Marker { id: 1 })]);
    rig.start(1, StartAt::Now, 0).unwrap();
    rig.poll(5_000); // the run loop woke 3 ms late
    assert_eq!(rig.fault(), Some(FaultCause::Late { sequence: 1, item: 0 }));
    let ticks: Vec<u64> = rig.board().record.iter().map(|c| c.tick).collect();
    assert!(ticks.windows(2).all(|w| w[0] <= w[1]), "{ticks:?}");
    assert!(rig
        .drain_events()
        .contains(&Event::Fault { cause: FaultCause::Late { sequence: 1, item: 0 }, tick: 2_000 }));
}

#[test]
fn a_sequence_is_checked_again_at_start_against_the_configuration_of_then() {
    let mut rig = rig();
    configure_all(&mut rig);
    rig.arm(0b01, 0).unwrap();
    let far = Xy { x: 60_000, y: 3_000 };
    let items = [
        item(0, Action::Laser { channel: 0, on: true }),
        item(1_000, Action::GalvoPoint { galvo: 0, to: far }),
        item(1_000, Action::Laser { channel: 0, on: false }),
    ];
    load_all(&mut rig, 1, &items);
    // After loading, the galvo's range narrows below the loaded point ...
    let mut narrow = galvo();
    narrow.x.max_code = 50_000;
    rig.configure(&ConfigItem::Galvo(narrow), 0).unwrap();
    rig.board_mut().record.clear();
    // ... so the start is refused, and nothing moves or shines.
    assert_eq!(
        rig.start(1, StartAt::Tick(10), 0),
        Err(Error::OutOfRange { kind: Peripheral::Galvo, index: 0 })
    );
    rig.run_until(10_000);
    assert!(rig.board().changes(|o| matches!(o, Output::Galvo { .. } | Output::Laser { .. })).is_empty());
    // The range back, but the laser disarmed since the load: refused too.
    rig.configure(&ConfigItem::Galvo(galvo()), 0).unwrap();
    rig.disarm(0);
    assert_eq!(rig.start(1, StartAt::Tick(20_000), 10_000), Err(Error::NotArmed { channel: 0 }));
    // Armed again, it starts and runs as loaded.
    rig.arm(0b01, 10_000).unwrap();
    rig.start(1, StartAt::Tick(20_000), 10_000).unwrap();
    rig.run_until(30_000);
    assert_eq!(laser_levels(&rig, 0), [(20_000, true), (21_000, false), (21_200, true), (22_000, false)]);
}

#[test]
fn a_voice_coil_rate_the_board_cannot_play_is_refused_with_the_rates_it_can() {
    use lightrig_firmware::sim::SimBoard;
    use lightrig_firmware::Rig;
    use lightrig_protocol::config::{ConfigError, ConfigField, InvalidReason, VoiceCoilConfig};
    // A board whose DAC timer plays 48 kHz only (the NUCLEO-G474RE).
    let board = SimBoard { sample_rates: (48_000, 48_000), ..SimBoard::default() };
    let mut rig = Rig::new(board, caps(), TICK_HZ);
    rig.host_seen(0, false);
    let at_96k = VoiceCoilConfig { sample_rate_hz: 96_000, ..coil(1) };
    assert_eq!(
        rig.configure(&ConfigItem::VoiceCoil(at_96k), 0),
        Err(Error::InvalidConfig(ConfigError {
            field: ConfigField::VoiceCoilSampleRate,
            index: 1,
            reason: InvalidReason::OutsideRange { min: 48_000, max: 48_000 },
        }))
    );
    rig.configure(&ConfigItem::VoiceCoil(coil(1)), 0).unwrap();
    // The simulated board by default plays the protocol's whole range.
    common::rig().configure(&ConfigItem::VoiceCoil(at_96k), 0).unwrap();
}
