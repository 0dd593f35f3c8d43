//! The virtual rig: the firmware core on simulated peripherals wired as a rig file says, a
//! virtual camera that renders what a real camera would see at every trigger, and the scenes
//! it looks at, each with its ground truth. A lab's program drives it exactly as it drives a
//! real rig, through `lightrig-host`'s transport and frame-input traits.
//!
//! - [`board`]: the simulated board for a rig file ([`board::board_for`]).
//! - [`flash`]: the virtual board's flash slots (embassy-boot in memory) and its update key.
//! - [`transport`]: the in-process virtual device behind the host's `Transport` trait, with
//!   byte damage and unplug; [`transport::open`] opens any `Connect` spec, the virtual one
//!   included.
//! - [`sensor`]: the camera's sensor model (response, exposure, shot and read noise,
//!   quantisation, saturation).
//! - [`camera`]: the virtual camera, a `lightrig_host::acquire::FrameInput` that renders each
//!   trigger into a numbered file in a watched directory, exactly where a real camera's
//!   software would write it, so the pipelines cannot tell the difference.
//! - [`scenes`]: what the camera looks at, one module per rig, and
//!   [`scenes::scene_for`] a rig file's scene.
//! - [`timeline`]: the simulated board's state at every tick, so the camera integrates over
//!   its whole exposure.
//! - [`pacing`]: simulated time held to the wall clock, on request.
//! - [`pty`]: the controller behind a pseudo-terminal (`lightrig sim --pty`), for clients in
//!   other processes.
//! - [`selfcheck`]: the host's link against the firmware controller over a lossy simulated
//!   wire (`lightrig selfcheck`).

pub mod board;
pub mod camera;
pub mod filter;
pub mod flash;
pub mod pacing;
#[cfg(unix)]
pub mod pty;
pub mod scenes;
pub mod selfcheck;
pub mod sensor;
pub mod soak;
pub mod timeline;
pub mod transport;
