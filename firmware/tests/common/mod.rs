//! A rig on the simulated board, with one configuration of every peripheral, for the rig tests.
#![allow(dead_code)] // each test file uses its own part

use heapless::Vec as HVec;
use lightrig_firmware::sim::SimBoard;
use lightrig_firmware::Rig;
use lightrig_protocol::config::*;
use lightrig_protocol::sequence::{Action, Chunk, Item};
use lightrig_protocol::session::Capabilities;
use lightrig_protocol::Event;

/// 1 tick = 1 µs.
pub const TICK_HZ: u32 = 1_000_000;

pub fn caps() -> Capabilities {
    Capabilities {
        galvos: 1,
        lasers: 3,
        steppers: 2,
        filter_wheels: 1,
        voice_coils: 2,
        partials_per_coil: 8,
        cameras: 2,
        sequence_buffer: 256,
        event_queue: 64,
        link_window: 8,
        max_packet: 504,
    }
}

pub fn rig() -> Rig<SimBoard> {
    let mut rig = Rig::new(SimBoard::default(), caps(), TICK_HZ);
    rig.host_seen(0, false);
    rig
}

pub fn galvo() -> GalvoConfig {
    let axis = GalvoAxis { min_code: 1000, max_code: 64000, zero_code: 32768, nanorad_per_code: 5000 };
    GalvoConfig {
        galvo: 0,
        dac: DacKind::Dac8563,
        x: axis,
        y: axis,
        park: Xy { x: 1000, y: 1000 },
        settle_ticks: 200,
    }
}

pub fn laser(channel: u8) -> LaserConfig {
    LaserConfig {
        channel,
        wavelength_nm: 635,
        warmup_ticks: 5_000,
        max_on_ticks: 1_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Wired(Polarity::ActiveHigh),
    }
}

pub fn camera(camera: u8) -> CameraConfig {
    CameraConfig {
        camera,
        pulse_ticks: 100,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Wired(Polarity::ActiveHigh),
        min_interval_ticks: 500,
    }
}

/// A linear gantry axis: 80 steps/mm, ±200 mm soft limits, homing to the min switch.
pub fn stepper(axis: u8) -> StepperConfig {
    StepperConfig {
        axis,
        kind: AxisKind::Linear,
        steps_per_unit: Ratio { num: 80, den: 1 },
        max_speed: 20_000,
        accel: 100_000,
        limits: Some(StepRange { min: -16_000, max: 16_000 }),
        homing: Homing { mode: HomingMode::ToMinLimit, speed: 2_000, backoff: 100, position: -16_000 },
        invert_dir: false,
        enable: Polarity::ActiveLow,
        limit_min: Input::Wired(Polarity::ActiveHigh),
        limit_max: Input::Wired(Polarity::ActiveHigh),
        index: Input::Unused,
    }
}

/// A six-slot wheel, 1200 steps per turn, index 50 steps before slot 0.
pub fn wheel() -> FilterWheelConfig {
    FilterWheelConfig {
        wheel: 0,
        slots: 6,
        steps_per_rev: 1200,
        max_speed: 10_000,
        accel: 200_000,
        index: Input::Wired(Polarity::ActiveHigh),
        index_offset: 50,
        invert_dir: false,
        enable: Polarity::ActiveHigh,
    }
}

pub fn coil(channel: u8) -> VoiceCoilConfig {
    VoiceCoilConfig { channel, sample_rate_hz: 48_000, max_amplitude: u16::MAX }
}

pub fn configure_all(rig: &mut Rig<SimBoard>) {
    let items = [
        ConfigItem::Galvo(galvo()),
        ConfigItem::Laser(laser(0)),
        ConfigItem::Laser(laser(1)),
        ConfigItem::Camera(camera(0)),
        ConfigItem::Stepper(stepper(0)),
        ConfigItem::FilterWheel(wheel()),
    ];
    for item in items {
        rig.configure(&item, 0).unwrap();
    }
}

pub fn item(delta: u32, action: Action) -> Item {
    Item { delta, action }
}

pub fn chunk(sequence: u32, chunk: u32, last: bool, items: &[Item]) -> Chunk {
    Chunk { sequence, chunk, last, items: HVec::from_slice(items).unwrap() }
}

/// Loads `items` as one sequence in as many chunks as needed (all must fit the buffer).
pub fn load_all(rig: &mut Rig<SimBoard>, sequence: u32, items: &[Item]) {
    let chunks: std::vec::Vec<_> = items.chunks(lightrig_protocol::MAX_CHUNK_ITEMS).collect();
    if chunks.is_empty() {
        rig.load(&chunk(sequence, 0, true, &[])).unwrap();
    }
    for (i, c) in chunks.iter().enumerate() {
        rig.load(&chunk(sequence, i as u32, i + 1 == chunks.len(), c)).unwrap();
    }
}

pub fn triggers(events: &[Event]) -> std::vec::Vec<&lightrig_protocol::event::TriggerEvent> {
    events
        .iter()
        .filter_map(|e| match e {
            Event::Trigger(t) => Some(t),
            _ => None,
        })
        .collect()
}
