//! The virtual rig: the firmware core on simulated peripherals wired as a rig file says, and a
//! virtual camera that renders what a real camera would see at every trigger.
//!
//! - [`board_for`] builds the simulated board for a rig file: switches where the axes' homing
//!   expects them and with the file's polarities, interlocks closed, cameras answering their
//!   triggers with exposure edges.
//! - [`sensor`]: the camera's sensor model (response, exposure, shot and read noise,
//!   quantisation, saturation).
//! - [`camera`]: the virtual camera, a [`crate::acquire::FrameInput`] that renders each trigger
//!   into a numbered file in a watched directory, exactly where a real camera's software would
//!   write it, so the pipelines cannot tell the difference.
//! - [`scene_for`] picks what a rig file's virtual camera looks at (`lightrig acquire` with
//!   `source = { kind = "virtual" }`).
//! - [`lls_scene`]: the linear-light-source scene and its ground truth.
//! - [`firs_scene`]: the fluorescent-immersion tank scene and its ground truth.
//! - [`pacing`]: simulated time held to the wall clock, on request.
//! - [`timeline`]: the simulated board's state at every tick, so the camera integrates over
//!   its whole exposure.
//! - [`pty`]: the controller behind a pseudo-terminal (`lightrig sim --pty`), for clients in
//!   other processes.

pub mod camera;
pub mod card_scene;
pub mod firs_scene;
pub mod lls_scene;
pub mod pacing;
#[cfg(unix)]
pub mod pty;
pub mod sensor;
pub mod timeline;

use lightrig_firmware::sim::{SimBoard, SimExposure};
use lightrig_protocol::config::{HomingMode, Input, Polarity};
use lightrig_protocol::session::DeviceInfo;

use crate::rigfile::{Method, RigFile};
use crate::transport::VirtualTransport;
use camera::Scene;
use lightrig_protocol::config::AxisKind;
use sensor::Sensor;

fn wired_low(i: Input) -> bool {
    i == Input::Wired(Polarity::ActiveLow)
}

/// The simulated board a rig file describes. Physical and logical positions agree once an
/// axis is homed: the homing switch sits where the homing procedure (switch, back-off, call it
/// `position`) puts the file's `position`.
pub fn board_for(rig: &RigFile) -> SimBoard {
    let mut board = SimBoard { record_steps: false, ..SimBoard::default() };
    for s in &rig.steppers {
        let Some(m) = board.steppers.get_mut(usize::from(s.axis)) else { continue };
        m.active_low = [wired_low(s.limit_min), wired_low(s.limit_max), wired_low(s.index)];
        let at = |units: f64| s.steps(units).unwrap_or(0);
        let (p, b) = (s.homing.position, s.homing.backoff);
        match s.homing.mode {
            HomingMode::ToMinLimit => m.limit_min_at = Some(at(p - b)),
            HomingMode::ToMaxLimit => m.limit_max_at = Some(at(p + b)),
            HomingMode::ToIndex => {
                let rev = at(360.0).max(1);
                m.index_at = Some((at(p).rem_euclid(rev), rev));
            }
            HomingMode::None => {}
        }
        // Limit switches not used for homing sit just beyond the soft limits.
        if let Some((lo, hi)) = s.limits {
            if m.limit_min_at.is_none() && s.limit_min != Input::Unused {
                m.limit_min_at = Some(at(lo) - at(2.0).abs().max(1));
            }
            if m.limit_max_at.is_none() && s.limit_max != Input::Unused {
                m.limit_max_at = Some(at(hi) + at(2.0).abs().max(1));
            }
        }
    }
    for w in &rig.filter_wheels {
        if let Some(m) = board.wheels.get_mut(usize::from(w.wheel)) {
            m.active_low[2] = wired_low(w.index);
            m.index_at = Some((0, i64::from(w.steps_per_rev.max(1))));
        }
    }
    for l in &rig.lasers {
        if let (Some(level), Input::Wired(p)) =
            (board.interlocks.get_mut(usize::from(l.channel)), l.interlock)
        {
            // Closed: the level the device reads as "safe".
            *level = p == Polarity::ActiveHigh;
        }
    }
    for c in &rig.cameras {
        if let Some(e) = board.exposure.get_mut(usize::from(c.camera)) {
            if let Input::Wired(p) = c.exposure_input {
                *e = Some(SimExposure {
                    delay: 0,
                    length: c.pulse_us.round().max(1.0) as u64,
                    trigger_active_low: c.polarity == Polarity::ActiveLow,
                    output_active_low: p == Polarity::ActiveLow,
                });
            }
        }
    }
    board
}

/// The virtual device for a rig file, in this process.
pub fn connect(rig: &RigFile, info: DeviceInfo) -> VirtualTransport {
    VirtualTransport::new(info, board_for(rig))
}

/// [`connect`] for a virtual acquisition: paced in real time if `real_time`, and with the
/// board's [`Timeline`](timeline::Timeline) for the camera to
/// [`follow`](camera::VirtualCamera::follow), so each frame sees the rig over its whole
/// exposure.
pub fn connect_for_camera(
    rig: &RigFile,
    info: DeviceInfo,
    real_time: bool,
) -> (VirtualTransport, timeline::Timeline) {
    let mut transport = connect(rig, info);
    if real_time {
        transport.pace_in_real_time();
    }
    let timeline = transport.timeline();
    (transport, timeline)
}

/// What the virtual camera of `rig` looks at, and a sensor exposed for it (noise seed
/// `seed`):
///
/// - linear light source: the demo's sample ([`lls_scene::LlsScene`], 128 × 96), its tube,
///   stripe and light box on the lasers named `light-tube` (or `tube`), `stripe` and
///   `backlight` (or `light-box`), the gantry on the first linear axis;
/// - fluorescent immersion: the demo's tank and sphere ([`firs_scene::FirsScene`], 208 × 160),
///   the sheet from `[plan] laser` (else the first laser) on the first galvo pair, the
///   turntable on the first rotary axis;
/// - DISCO, bispectral, BRDF display: the [`card_scene::CardScene`] test card (160 × 120).
pub fn scene_for(rig: &RigFile, seed: u64) -> (Box<dyn Scene + Send>, Sensor) {
    let laser = |names: &[&str]| {
        rig.lasers.iter().find(|l| l.name.as_deref().is_some_and(|n| names.contains(&n))).map(|l| l.channel)
    };
    let axis = |kind: AxisKind| rig.steppers.iter().find(|s| s.kind == kind).map(|s| s.axis);
    match rig.method {
        Method::LinearLightSource => {
            let mut spec = lls_scene::LlsSceneSpec::new(128, 96);
            spec.tube_channel = laser(&["light-tube", "tube"]).unwrap_or(spec.tube_channel);
            spec.stripe_channel = laser(&["stripe"]).unwrap_or(spec.stripe_channel);
            spec.backlight_channel = laser(&["backlight", "light-box"]).unwrap_or(spec.backlight_channel);
            spec.gantry_axis = axis(AxisKind::Linear).unwrap_or(spec.gantry_axis);
            // As the demo's: a white tile under the tube fills about half the well in 4 ms.
            let sensor = Sensor { gain: 30_000.0 / (0.16 * 0.004), seed, ..Sensor::default() };
            (Box::new(lls_scene::LlsScene::new(spec)), sensor)
        }
        Method::FluorescentImmersion => {
            let mut spec = firs_scene::FirsSceneSpec::new(208, 160);
            let named = rig.plan.get("laser").and_then(|n| n.as_str());
            spec.sheet.laser = rig
                .lasers
                .iter()
                .find(|l| named.is_none_or(|n| l.name.as_deref() == Some(n)))
                .map_or(spec.sheet.laser, |l| l.channel);
            spec.sheet.galvo = rig.galvos.first().map_or(spec.sheet.galvo, |g| g.galvo);
            spec.turntable_axis = axis(AxisKind::Rotary).unwrap_or(spec.turntable_axis);
            let sensor = Sensor { gain: 20_000.0 / (1.3 * 0.02), seed, ..Sensor::default() };
            (Box::new(firs_scene::FirsScene::new(spec)), sensor)
        }
        Method::Disco | Method::Bispectral | Method::BrdfDisplay => {
            let card = card_scene::CardScene::new(rig, 160, 120);
            // A laser spot on white fills half the well at the camera's own pulse width.
            let pulse_s = rig.cameras.first().map_or(1e-3, |c| c.pulse_us * 1e-6).max(1e-6);
            let sensor = Sensor { gain: 15_000.0 / (card.spot * pulse_s), seed, ..Sensor::default() };
            (Box::new(card), sensor)
        }
    }
}
