//! The rig controller's logic, written against small hardware traits so the same code runs on
//! the microcontroller (board crates implement the traits) and on the host (simulated
//! peripherals, the virtual rig, tests).
//!
//! This first slice is the protocol endpoint: the device side of the reliable link, the
//! handshake gate, the clock and the heartbeat. Peripherals, the sequencer and the safety
//! state machine come with the firmware-core issue; until then their commands are answered
//! with [`Error::Unsupported`], never silently accepted.
#![no_std]
#![forbid(unsafe_code)]

pub mod controller;

pub use controller::{Clock, Controller};
pub use lightrig_protocol::Error;
