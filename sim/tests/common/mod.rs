//! A virtual rig configured like a small lab's, shared by the host's integration tests.
#![allow(dead_code)]

use lightrig_firmware::sim::virtual_device_info;
use lightrig_firmware::sim::SimBoard;
use lightrig_host::client::Client;
use lightrig_protocol::config::*;
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::Command;
use lightrig_sim::transport::VirtualTransport;

pub fn laser(channel: u8) -> ConfigItem {
    ConfigItem::Laser(LaserConfig {
        channel,
        wavelength_nm: 635,
        warmup_ticks: 2_000,
        max_on_ticks: 600_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    })
}

/// A connected, configured virtual rig.
pub fn rig_client() -> Client<VirtualTransport> {
    let c = Client::connect(VirtualTransport::new(virtual_device_info(), SimBoard::default()), 9).unwrap();
    setup(c)
}

/// Configures, homes and arms a connected rig: a gantry (axis 0), a turntable (1), three lasers,
/// a galvo pair and a camera.
pub fn setup<T: lightrig_host::transport::Transport>(mut c: Client<T>) -> Client<T> {
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

/// Three LLS passes of 21 positions, 1 mm apart, on the gantry of [`setup`].
pub fn lls_params() -> lightrig_host::plan::lls::LlsParams {
    use lightrig_host::plan::lls::{LlsParams, Pass};
    LlsParams {
        axis: 0,
        start: -800,
        step: 80,
        count: 21,
        cameras: vec![0],
        exposures: vec![2_000],
        settle: 5_000,
        frame_gap: 3_000,
        light: 1,
        stripe: 0,
        backlight: Some(2),
        // Two sweeping passes and a second reflectance pass (backlit is one frame now).
        passes: vec![Pass::REFLECTANCE, Pass::Stripe, Pass::REFLECTANCE],
        timeout: 2_000_000,
        frame_bytes: 1 << 20,
        tick_hz: 1_000_000,
    }
}
