//! The rig controller's logic, written against small hardware traits so the same code runs on
//! the microcontroller (board crates implement the traits) and on the host (simulated
//! peripherals, the virtual rig, tests).
//!
//! What exists so far:
//! - [`controller`]: the protocol endpoint: the device side of the reliable link, the
//!   handshake gate, the clock, the heartbeat and the latched emergency stop.
//! - [`galvo`]: the galvo output frame formats (DAC8563, AD5689, XY2-100) and the SPI DAC
//!   driver behind the [`galvo::GalvoOutput`] trait.
//!
//! The other peripherals, the sequencer and the rest of the safety state machine come with the
//! firmware-core issue; until then their commands are answered with [`Error::Unsupported`],
//! never silently accepted.
#![no_std]
#![forbid(unsafe_code)]

pub mod controller;
pub mod galvo;
pub mod motion;
pub mod synth;

pub use controller::{Clock, Controller};
pub use lightrig_protocol::Error;
