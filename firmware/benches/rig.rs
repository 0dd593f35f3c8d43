//! How fast the rig's logic can feed its outputs, on a board whose outputs cost nothing:
//! galvo points streamed through the sequencer, and steps of one axis.
//!
//! `cargo bench -p lightrig-firmware --bench rig`

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_firmware::hal::{Cameras, Capture, Galvos, HwError, Lasers, Motors, VoiceCoils};
use lightrig_firmware::Rig;
use lightrig_protocol::config::*;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::{Action, AxisRef, Chunk, Item, Profile, StartAt};
use lightrig_protocol::session::Capabilities;

/// Outputs that do nothing: the figures are the logic's own cost.
struct NullBoard;

impl Galvos for NullBoard {
    fn set_galvo(&mut self, _: u8, to: Xy, _: u64) -> Result<(), HwError> {
        black_box(to);
        Ok(())
    }
}
impl Lasers for NullBoard {
    fn set_laser(&mut self, _: u8, _: bool, _: u64) {}
    fn interlock_level(&mut self, _: u8) -> bool {
        true
    }
}
impl Motors for NullBoard {
    fn step(&mut self, m: AxisRef, at: u64) {
        black_box((m, at));
    }
    fn set_dir(&mut self, _: AxisRef, _: bool, _: u64) {}
    fn set_enable(&mut self, _: AxisRef, _: bool, _: u64) {}
    fn switch_level(&mut self, _: AxisRef, _: Switch) -> bool {
        false
    }
}
impl Cameras for NullBoard {
    fn set_trigger(&mut self, _: u8, _: bool, _: u64) {}
    fn take_capture(&mut self, _: u64) -> Option<Capture> {
        None
    }
}
impl lightrig_firmware::hal::FirmwareSlots for NullBoard {}

impl VoiceCoils for NullBoard {
    fn write_samples(&mut self, _: u8, _: u64, _: &[i16], _: u64) {}
}

fn caps() -> Capabilities {
    Capabilities {
        galvos: 1,
        lasers: 1,
        steppers: 1,
        filter_wheels: 0,
        voice_coils: 0,
        partials_per_coil: 8,
        cameras: 1,
        sequence_buffer: 256,
        event_queue: 64,
        link_window: 8,
        max_packet: 504,
    }
}

fn galvo_rig() -> Rig<NullBoard> {
    let mut rig = Rig::new(NullBoard, caps(), 1_000_000);
    let axis = GalvoAxis { min_code: 0, max_code: 65535, zero_code: 32768, nanorad_per_code: 5000 };
    let g = GalvoConfig {
        galvo: 0,
        dac: DacKind::Xy2_100,
        x: axis,
        y: axis,
        park: Xy::default(),
        settle_ticks: 0,
    };
    rig.configure(&ConfigItem::Galvo(g), 0).unwrap();
    rig
}

/// 100 kpoints/s (one point every 10 ticks at 1 MHz): the cost per point of loading, scheduling
/// and writing it.
fn galvo_points(c: &mut Criterion) {
    const POINTS: u32 = 32 * 64;
    let mut g = c.benchmark_group("rig");
    g.throughput(Throughput::Elements(u64::from(POINTS)));
    g.bench_function("galvo_point_stream", |b| {
        b.iter(|| {
            let mut rig = galvo_rig();
            for k in 0..POINTS / 32 {
                let items = (0..32)
                    .map(|i| Item {
                        delta: 10,
                        action: Action::GalvoPoint {
                            galvo: 0,
                            to: Xy { x: (k * 32 + i) as u16, y: i as u16 },
                        },
                    })
                    .collect();
                let chunk = Chunk { sequence: 1, chunk: k, last: k + 1 == POINTS / 32, items };
                rig.load(&chunk).unwrap();
                if k == 0 {
                    rig.start(1, StartAt::Tick(0), 0).unwrap();
                }
                while let Some(t) = rig.next_due() {
                    if rig.buffer().is_some_and(|b| b.free >= 32) && k + 1 < POINTS / 32 {
                        break;
                    }
                    rig.poll(t);
                    while rig.pop_event().is_some() {}
                }
            }
            black_box(rig.galvo_position(0))
        })
    });
    g.finish();
}

/// One axis at 200 k steps/s: the cost per step of timing and issuing it.
fn steps(c: &mut Criterion) {
    const STEPS: i32 = 200_000;
    let mut g = c.benchmark_group("rig");
    g.throughput(Throughput::Elements(STEPS as u64));
    g.bench_function("stepper_200k_steps_per_s", |b| {
        b.iter(|| {
            let mut rig = Rig::new(NullBoard, caps(), 1_000_000);
            let s = StepperConfig {
                axis: 0,
                kind: AxisKind::Rotary,
                steps_per_unit: Ratio { num: 1, den: 1 },
                max_speed: 200_000,
                accel: 4_000_000,
                limits: None,
                homing: Homing { mode: HomingMode::None, speed: 1, backoff: 0, position: 0 },
                invert_dir: false,
                enable: Polarity::ActiveHigh,
                limit_min: Input::Unused,
                limit_max: Input::Unused,
                index: Input::Unused,
            };
            rig.configure(&ConfigItem::Stepper(s), 0).unwrap();
            let mv = Action::StepperMove { axis: 0, target: STEPS, profile: Profile::default() };
            rig.immediate(&mv, 0).unwrap();
            while let Some(t) = rig.next_due() {
                rig.poll(t);
                while rig.pop_event().is_some() {}
            }
            black_box(rig.axis_position(0))
        })
    });
    g.finish();
}

criterion_group!(benches, galvo_points, steps);
criterion_main!(benches);
