//! The lightrig host toolkit.
//!
//! - [`acquire`]: the acquisition engine: plan steps → device → journaled, paired frames.
//! - [`transport`]: bytes to and from a device (serial, the in-process virtual device).
//! - [`client`]: the device client: handshake, requests, events, heartbeat, sequences.
//! - [`clock`]: the host–device clock mapping.
//! - [`frames`]: frame sources (a watched directory of numbered files).
//! - [`plan`]: acquisition planners, one per rig.
//! - [`rigfile`]: the TOML rig description, validated with file:line:field errors.
//! - [`selfcheck`]: the protocol self-check over a lossy simulated wire.
//! - [`virtual_rig`]: the virtual rig: simulated board from a rig file, virtual camera, scenes;
//!   [`cli_sim`]: `lightrig sim --pty`, the virtual controller for other processes.
//! - [`firs_fit`], [`firs_demo`]: fluorescent immersion range scanning: `lightrig fit
//!   firs-surface` and `lightrig demo firs`.

pub mod acquire;
pub mod cli_acquire;
pub mod cli_calibrate;
pub mod cli_hdr;
pub mod cli_sim;
pub mod client;
pub mod clock;
pub mod demo;
pub mod firs_demo;
pub mod firs_fit;
pub mod fit_error;
pub mod frames;
pub mod lls_fit;
pub mod lls_stack;
pub mod plan;
pub mod rigfile;
pub mod selfcheck;
pub mod session;
pub mod transport;
pub mod virtual_rig;
