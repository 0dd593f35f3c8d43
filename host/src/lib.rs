//! The lightrig host toolkit.
//!
//! - [`transport`]: bytes to and from a device (serial, the in-process virtual device).
//! - [`client`]: the device client: handshake, requests, events, heartbeat, sequences.
//! - [`clock`]: the host–device clock mapping.
//! - [`selfcheck`]: the protocol self-check over a lossy simulated wire.

pub mod client;
pub mod clock;
pub mod selfcheck;
pub mod session;
pub mod transport;
