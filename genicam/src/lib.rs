//! GenICam cameras (GigE Vision, USB3 Vision) as frame inputs of a session, through Aravis.
//!
//! A rig file's camera with `source = { kind = "genicam", address = "…" }` is opened here:
//! trigger mode on the configured line (or software triggers fired by the host for each
//! trigger the controller reports), pixel format and exposure from the rig file, a stream
//! with enough buffers and a receive socket sized for the payload (without it nearly every
//! frame lost packets on this machine). Frames are numbered within a step by the camera's
//! own frame id ([`ids`]): a frame the camera delivered incomplete keeps its number and is
//! named as lost ([`FrameInput::lost`](lightrig_host::acquire::FrameInput::lost)), so the
//! frames after it pair with their own triggers.
//!
//! - [`ids`]: frame-id arithmetic (GigE Vision's 16-bit block ids wrap) — plain functions.
//! - [`encode`]: a buffer's pixels as a PNG file, by pixel format.
//! - [`open`] / [`cameras`]: the Aravis side, behind the `aravis` feature.

pub mod encode;
pub mod ids;

#[cfg(feature = "aravis")]
mod input;

use lightrig_host::acquire::FrameInput;
use lightrig_host::rigfile::GenicamSource;

/// What the crate was built without.
pub const NOT_BUILT: &str = "this lightrig was built without GenICam support: install Aravis \
     (Debian: `apt install libaravis-dev libusb-1.0-0-dev`) and build with `--features genicam`";

/// A GenICam camera this host sees.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraInfo {
    /// Aravis's id (`Vendor-Model-Serial`), usable as `address` in a rig file.
    pub id: String,
    pub vendor: String,
    pub model: String,
    /// `GigEVision`, `USB3Vision`, …
    pub protocol: String,
    /// Network address (GigE Vision), else empty.
    pub address: String,
}

/// Opens camera `camera` of the rig (its trigger output) as `source` says. `min_interval_us`
/// paces software triggers (the camera's shortest time between two triggers).
pub fn open(camera: u8, source: &GenicamSource, min_interval_us: f64) -> Result<Box<dyn FrameInput>, String> {
    #[cfg(feature = "aravis")]
    {
        input::GenicamInput::open(camera, source, min_interval_us).map(|i| Box::new(i) as Box<dyn FrameInput>)
    }
    #[cfg(not(feature = "aravis"))]
    {
        let _ = (camera, min_interval_us);
        Err(format!("camera {camera} ({}): {NOT_BUILT}", source.address))
    }
}

/// The GenICam cameras discovery finds, and those at `addresses` (discovery by broadcast finds
/// nothing on loopback or across subnets: such a camera is opened by its address); an address
/// where no camera answers is an error naming it.
pub fn cameras(addresses: &[String]) -> Result<Vec<CameraInfo>, String> {
    #[cfg(feature = "aravis")]
    {
        input::cameras(addresses)
    }
    #[cfg(not(feature = "aravis"))]
    {
        let _ = addresses;
        Err(NOT_BUILT.to_string())
    }
}

/// Whether this build can open GenICam cameras.
pub const fn available() -> bool {
    cfg!(feature = "aravis")
}
