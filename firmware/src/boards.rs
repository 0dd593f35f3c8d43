//! What each reference board offers, in the protocol's terms. The board crate reports it in
//! its `DeviceInfo`; the host's tests check every shipped rig file against it, so the pin map
//! (docs/boards/), the firmware and the rig files cannot drift apart.

use lightrig_protocol::session::Capabilities;
use lightrig_protocol::MAX_PACKET;

/// The NUCLEO-G474RE's peripherals (docs/boards/nucleo-g474re.md, "Pin map"): one pin map that
/// runs any of the five published rigs without rewiring the controller —
/// DISCO (3 lasers + spotlight, galvo pair, turntable, camera), bispectral (2 rotary stages,
/// LED wheel, camera), LLS (gantry, light tube, stripe laser, backlight, camera), BRDF display
/// (2 voice coils, camera), immersion scanning (galvo, sheet laser, turntable, camera).
pub const NUCLEO_G474RE: Capabilities = Capabilities {
    galvos: 1,
    lasers: 4,
    steppers: 2,
    filter_wheels: 1,
    voice_coils: 2,
    partials_per_coil: 8,
    cameras: 1,
    // The controller fills these in from its own sizes.
    sequence_buffer: 0,
    event_queue: 0,
    link_window: 0,
    max_packet: MAX_PACKET as u16,
};

/// The NUCLEO-G474RE's tick rate (embassy-time on TIM2).
pub const NUCLEO_G474RE_TICK_HZ: u32 = 1_000_000;

/// The one voice-coil sample rate the NUCLEO-G474RE plays (168 MHz / 3500, TIM6).
pub const NUCLEO_G474RE_VOICE_COIL_HZ: u32 = 48_000;
