//! Fluorescent immersion range scanning (Hullin et al. 2008): the object sits in a tank of
//! fluorescent liquid; a galvo sweeps a laser sheet through the tank, one camera frame per
//! sheet. Where the sheet meets the object the fluorescence stops: the surface is the sheet's
//! cut-off (surface mode), or, in an index-matched liquid, the object is the dark region of
//! each slice (volume mode).
//!
//! - [`mesh`]: triangle meshes, PLY output, marching cubes, and mesh-to-mesh distances.
//! - [`volume`]: volume mode, slices to a segmented voxel volume.
//! - [`volume_stream`]: volume mode streamed, frame by frame, in bounded memory.
//! - [`calib`]: calibration through the tank wall, per-pixel rays, the curved sheets, and
//!   triangulation of a ray against a sheet.
//! - [`surface`]: surface mode, the sheet's cut-off in the space-time stack.

pub mod calib;
pub mod mesh;
pub mod surface;
pub mod volume;
pub mod volume_stream;
