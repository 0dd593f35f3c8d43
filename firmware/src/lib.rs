//! The rig controller's logic, written against small hardware traits so the same code runs on
//! the microcontroller (board crates implement the traits) and on the host (simulated
//! peripherals, the virtual rig, tests).
//!
//! - [`controller`]: the protocol endpoint: the device side of the reliable link, the
//!   handshake gate, request dispatch and the event stream.
//! - [`rig`]: every peripheral's behaviour, the sequencer and the safety state machine, in
//!   integer ticks.
//! - [`hal`]: the hardware traits a board implements.
//! - [`motion`]: trapezoidal step timing, exact in integer ticks.
//! - [`synth`]: voice-coil sine synthesis in fixed point.
//! - [`galvo`]: galvo output frame formats (DAC8563, AD5689, XY2-100) and drivers.
//! - [`timer_schedule`]: compare values, capture extension and the look-ahead schedule for
//!   hardware-timed edges on a free-running timer counter.
//! - [`record`]: a no_std board that records its outputs in a ring, read over a debug port.
//! - [`update`]: firmware update over the link, over the board's flash slots; [`boot`]
//!   (feature `boot`): the slots through embassy-boot; [`memflash`]: a NOR flash in memory.
//! - [`sim`] (feature `std`): simulated peripherals that record every change with its tick.
//!
//! Logging goes through the macros of `fmt.rs` (defmt on the MCU, `log` on the host).
#![cfg_attr(not(feature = "std"), no_std)]
#![forbid(unsafe_code)]

#[macro_use]
mod fmt;

pub mod boards;
#[cfg(feature = "boot")]
pub mod boot;
pub mod controller;
pub mod galvo;
pub mod hal;
#[cfg(feature = "std")]
pub mod memflash;
pub mod motion;
pub mod record;
pub mod rig;
#[cfg(feature = "std")]
pub mod sim;
pub mod synth;
pub mod timer_schedule;
pub mod update;

pub use controller::{Clock, Controller};
pub use lightrig_protocol::Error;
pub use rig::Rig;
