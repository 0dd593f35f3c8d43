//! Imaging foundation for the pipelines.
//!
//! - [`io`]: reading and writing 8/16-bit PNG and TIFF and half/float EXR, linear vs sRGB made
//!   explicit, errors that name the file and the problem.
//! - [`hdr`]: camera response recovery from exposure series and merging to linear radiance.
//! - [`calib`]: chessboard detection, intrinsics with distortion, pose, per-pixel rays.
//! - [`calib_file`]: the calibration file the pipelines read (TOML, versioned).
//! - [`synth`]: synthetic images with known truth (rendered chessboards).
//! - [`figure`]: report figures: maps side by side, a colour map with its scale bar.

pub mod calib;
pub mod calib_file;
pub mod figure;
pub mod hdr;
pub mod io;
pub mod linalg;
pub mod synth;
