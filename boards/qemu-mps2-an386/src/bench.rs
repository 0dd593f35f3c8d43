//! Benchmarks on the emulated Cortex-M4 (`bench` on the semihosting command line): the same
//! workloads as the host benches (`firmware/benches/{synth,rig,motion}.rs`), timed with the
//! 25 MHz cycle counter. Under `qemu -icount shift=N` a cycle is 40 ns of virtual time and an
//! instruction 2^N ns, so a cycle count converts to instructions; the `calibrate` line (a loop
//! of exactly 3 instructions per turn) lets the host check that factor.
//!
//! Output on UART0, one line per figure: `BENCH <name> <units> <cycles>`, then `BENCH done`.

use core::fmt::Write;
use core::hint::black_box;

use lightrig_firmware::hal::{Cameras, Capture, Galvos, HwError, Lasers, Motors, VoiceCoils};
use lightrig_firmware::motion::Trapezoid;
use lightrig_firmware::synth::Synth;
use lightrig_firmware::Rig;
use lightrig_protocol::config::*;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::{Action, AxisRef, Chunk, Item, Partial, Profile, StartAt};
use lightrig_protocol::session::Capabilities;

use crate::time::cycles;
use crate::uart::UART0;

/// Outputs that cost nothing but a call: the figures are the logic's own cost, as on the host.
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

/// A line of text for the UART.
struct Line(heapless::String<96>);

impl Write for Line {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        self.0.push_str(s).map_err(|_| core::fmt::Error)
    }
}

fn report(name: &str, units: u64, cycles: u64) {
    let mut line = Line(heapless::String::new());
    let _ = writeln!(line, "BENCH {name} {units} {cycles}");
    while !UART0.write(line.0.as_bytes()) {}
}

fn timed(f: impl FnOnce()) -> u64 {
    let t0 = cycles();
    f();
    cycles() - t0
}

/// Runs every benchmark and reports it.
pub fn run() {
    // 3 instructions per turn (nop, subs, bne).
    const TURNS: u32 = 1_000_000;
    let c = timed(|| {
        // SAFETY: a register-only countdown loop.
        unsafe {
            core::arch::asm!("2:", "nop", "subs {0}, {0}, #1", "bne 2b", inout(reg) TURNS => _,
                options(nomem, nostack));
        }
    });
    report("calibrate_instructions", 3 * u64::from(TURNS), c);

    synth("synth_steady_2x8", false);
    synth("synth_crossfade_2x16", true);
    galvo_points();
    triggers();
    steps();
    step_times();
    report("done", 0, 0);
}

const RATE: u32 = 48_000;
const BUFFER: usize = 256;

fn partials(base_mhz: u32) -> [Partial; 8] {
    core::array::from_fn(|i| Partial {
        freq_mhz: base_mhz + 13_579 * i as u32 * (i as u32 + 1),
        amplitude: 8_000 - 300 * i as u16,
        phase: 7_919 * i as u16,
    })
}

/// Two channels, 8 partials each (or 16 voices all ramping): one unit is one sample of both.
fn synth(name: &str, crossfade: bool) {
    let mut chans = [20_000, 31_000].map(|base| {
        let mut s = Synth::new(RATE);
        let _ = s.set(&partials(base), 0);
        if crossfade {
            let _ = s.set(&partials(base + 500_000), u32::MAX);
        }
        s
    });
    let mut out = [[0i16; BUFFER]; 2];
    const ROUNDS: u64 = 64;
    let c = timed(|| {
        for _ in 0..ROUNDS {
            for (s, o) in chans.iter_mut().zip(out.iter_mut()) {
                s.fill(black_box(o));
            }
            black_box(&out);
        }
    });
    report(name, ROUNDS * BUFFER as u64, c);
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

/// Streams `chunks` × 32 items (made by `item`) through the sequencer and runs them; one unit is
/// one item loaded, scheduled and executed.
fn stream(rig: &mut Rig<NullBoard>, chunks: u32, item: impl Fn(u32) -> Item) {
    for k in 0..chunks {
        let items = (0..32).map(|i| item(k * 32 + i)).collect();
        let chunk = Chunk { sequence: 1, chunk: k, last: k + 1 == chunks, items };
        let _ = rig.load(&chunk);
        if k == 0 {
            let _ = rig.start(1, StartAt::Tick(0), 0);
        }
        while let Some(t) = rig.next_due() {
            if rig.buffer().is_some_and(|b| b.free >= 32) && k + 1 < chunks {
                break;
            }
            rig.poll(t);
            while rig.pop_event().is_some() {}
        }
    }
}

/// Galvo points at 100 kpoints/s (10 ticks apart at 1 MHz), as `firmware/benches/rig.rs`.
fn galvo_points() {
    const CHUNKS: u32 = 64;
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
    let _ = rig.configure(&ConfigItem::Galvo(g), 0);
    let c = timed(|| {
        stream(&mut rig, CHUNKS, |n| Item {
            delta: 10,
            action: Action::GalvoPoint { galvo: 0, to: Xy { x: n as u16, y: (n % 32) as u16 } },
        });
    });
    black_box(rig.galvo_position(0));
    report("sequencer_galvo_point", u64::from(CHUNKS) * 32, c);
}

/// Camera triggers 100 µs apart: each emits an event with a snapshot, and ends a pulse.
fn triggers() {
    const CHUNKS: u32 = 32;
    let mut rig = Rig::new(NullBoard, caps(), 1_000_000);
    let cam = CameraConfig {
        camera: 0,
        pulse_ticks: 20,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    let _ = rig.configure(&ConfigItem::Camera(cam), 0);
    let c = timed(|| {
        stream(&mut rig, CHUNKS, |_| Item { delta: 100, action: Action::Trigger { camera: 0, exposure: 0 } });
    });
    report("sequencer_trigger", u64::from(CHUNKS) * 32, c);
}

/// One axis at 200 k steps/s through the rig, as `firmware/benches/rig.rs`.
fn steps() {
    const STEPS: i32 = 200_000;
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
    let _ = rig.configure(&ConfigItem::Stepper(s), 0);
    let c = timed(|| {
        let mv = Action::StepperMove { axis: 0, target: STEPS, profile: Profile::default() };
        let _ = rig.immediate(&mv, 0);
        while let Some(t) = rig.next_due() {
            rig.poll(t);
            while rig.pop_event().is_some() {}
        }
    });
    black_box(rig.axis_position(0));
    report("rig_step", STEPS as u64, c);
}

/// The step-time generator alone (`StepTimes`), at 170 MHz ticks as on the reference board.
fn step_times() {
    const STEPS: u32 = 200_000;
    let Ok(plan) = Trapezoid::new(STEPS, 200_000, 4_000_000, 170_000_000) else { return };
    let mut gen = plan.stepper();
    let c = timed(|| {
        while let Some(t) = gen.next_tick() {
            black_box(t);
        }
    });
    report("step_times", u64::from(STEPS), c);
}
