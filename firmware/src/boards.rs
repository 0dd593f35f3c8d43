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

/// The public key of the development key pair the virtual and the emulated (QEMU) board trust:
/// its secret is public (`lightrig_sim::flash::VIRTUAL_SECRET`, `lightrig flash sign
/// --virtual-key`), so anyone can sign images for them. Never for a board on a real rig.
pub const DEVELOPMENT_PUBLIC_KEY: [u8; 32] = [
    251, 31, 22, 179, 232, 144, 98, 133, 153, 221, 29, 43, 169, 153, 200, 13, 159, 76, 218, 34, 39, 155, 240,
    0, 56, 88, 250, 71, 150, 22, 92, 149,
];

/// The emulated board's flash file (QEMU `mps2-an386`, `flash=PATH`): embassy-boot's state,
/// active and update partitions as (offset, length), 4 KiB pages. The harness programs a new
/// file as a factory would (an image in the active partition, the rest erased); the board's
/// bootloader copies the active partition to `APP_BASE` and starts it.
pub mod qemu_flash {
    /// Erase page.
    pub const PAGE: u32 = 4096;
    /// embassy-boot's state partition.
    pub const STATE: (u32, u32) = (0, 2 * PAGE);
    /// The active partition: 320 KiB, the firmware built for it (feature `slot`).
    pub const ACTIVE: (u32, u32) = (STATE.1, 80 * PAGE);
    /// The update partition: one page larger than the active one.
    pub const DFU: (u32, u32) = (ACTIVE.0 + ACTIVE.1, 81 * PAGE);
    /// The file's length.
    pub const FILE_LEN: u32 = DFU.0 + DFU.1;
    /// Where the bootloader puts the active partition in the code RAM (SSRAM1) and jumps: the
    /// address the firmware is linked at with feature `slot`.
    pub const APP_BASE: u32 = 0x0010_0000;
}
