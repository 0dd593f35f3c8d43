//! The lightrig host library: everything a lab's own program needs to drive a real rig and to
//! turn its sessions into a pipeline's inputs. It knows nothing of the virtual rig
//! (`lightrig-sim`) or of the command line (`lightrig-cli`).
//!
//! - [`transport`]: bytes to and from a device (serial, USB), and `Connect` specs.
//! - [`client`]: the device client: handshake, requests, events, heartbeat, sequences.
//! - [`clock`]: the host–device clock mapping.
//! - [`rigfile`]: the TOML rig description, validated with file:line:field errors.
//! - [`plan`]: acquisition planners, one per rig, and plans from rig files.
//! - [`bringup`]: connect, recover, configure and home a rig as its rig file says.
//! - [`frames`]: frame sources (a watched directory of numbered files).
//! - [`session`]: the session directory: manifest, journal, frames, resume, pairing.
//! - [`acquire`]: the acquisition engine: plan steps → device → journaled, paired frames.
//! - [`live`]: a running acquisition's state for those watching it from elsewhere.
//! - [`steer`]: the PCA-steered bispectral plan's choice of pairs, made inside the session.
//! - [`mesh_file`]: a lab's scanned mesh from PLY or OBJ.
//! - [`fit`]: per-rig session readers feeding `lightrig_pipelines` (`fit::lls`, `fit::firs`).

pub mod acquire;
pub mod bringup;
pub mod client;
pub mod clock;
#[cfg(unix)]
pub mod control;
pub mod disco;
pub mod filter;
pub mod fit;
pub mod flash;
pub mod frames;
pub mod live;
pub mod mesh_file;
pub mod overrides;
pub mod plan;
pub mod response;
pub mod rigfile;
pub mod session;
pub mod steer;
pub mod transport;
