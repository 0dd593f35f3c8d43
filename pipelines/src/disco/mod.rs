//! DISCO (Goesele et al. 2004): a translucent object's diffuse subsurface reflectance measured
//! with a laser spot, as a vertex-to-vertex throughput factor matrix `F` (the global term) and
//! local kernels.
//!
//! - [`mesh`]: the object's surface with its one-rings; the virtual rig's test object.
//! - [`dipole`]: Jensen et al. 2001's dipole and Fresnel transmittance (the virtual object's
//!   physics, and what kernels are compared with).
//! - [`optics`]: turntable, pinhole camera, galvo projector, which surface point a pixel sees.
//! - [`resample`]: per view once, per frame into columns of `F` (sections 5 and 6.1).
//! - [`interpolate`]: filling `F` on the mesh (section 6.2), and [`falloff`]: the fall-off with
//!   distance taken out while it does.
//! - [`atlas`]: the texture atlas the local term's 7×7 kernels live on (section 7): axis-projected
//!   charts with stretch ≤ √3, a gutter, and boundary texels linked across charts.
//! - [`detail`]: the detail texture `T_ρ` (section 6.3): surface detail finer than the mesh,
//!   from frames where a texel is smoothly lit, relative to its triangle's vertices.
//! - [`kernel`]: the local term's `m(d)` fitted per spot in section 7.1's stages, through the
//!   beam's blur.
//! - [`local`]: section 7 on the atlas: per-spot data and fits, the parameter and correction
//!   textures filled where no spot fell, a texel's 7 × 7 kernel.
//! - [`projector_pose`]: the laser projector's pivot and orientation from the spots' hit points.
//! - [`register`]: the object's pose on the turntable from the registration frames' silhouettes,
//!   and [`hull`]: coarse guesses for it from the views' visual hull, where the scan's frame is far
//!   from how the object stands.
//! - [`relight`]: the model under a light no frame used (the global term rendered).

pub mod atlas;
pub mod detail;
pub mod dipole;
pub mod falloff;
pub mod hull;
pub mod interpolate;
pub mod kernel;
pub mod local;
pub mod mesh;
pub mod optics;
pub mod projector_pose;
pub mod register;
pub mod relight;
pub mod resample;
pub mod scan;
