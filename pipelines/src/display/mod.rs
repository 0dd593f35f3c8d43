//! BRDF display (Hullin et al. 2011; thesis chapter 5): travelling capillary waves on a
//! liquid, excited by one voice coil per axis with sums of sines at prime frequency ratios,
//! whose time-averaged slopes make the surface reflect a chosen Ward-like highlight.
//!
//! - [`calibration`]: the calibration file: responses, the still beam, the closed loop's pairs.
//! - [`liquid`]: the dispersion relation of capillary–gravity waves and their viscous damping
//!   (water, and the gallium alloy of section 5.5.4).
//! - [`mapping`]: Ward `α` → facet-tilt variance `α²/2` → each partial's roughness → wave number →
//!   surface amplitude → coil drive through the measured response, with the reachable range.
//! - [`screen`]: the flat screen the reflected beam lands on: each camera pixel's facet tilt.
//! - [`lobe`]: the displayed lobe read off a camera picture of the screen: its moments, and
//!   Ward's lobe fitted to it.
//! - [`slopes`]: the single sine's arcsine law (Eq. 5.6) and the distance of a slope
//!   distribution from a Gaussian.

pub mod calibration;
pub mod liquid;
pub mod lobe;
pub mod mapping;
pub mod screen;
pub mod slopes;

pub use calibration::{AxisCalibration, Calibration};
pub use liquid::Liquid;
pub use mapping::{Axis, DisplayError, PartialDrive, Response};
pub use screen::Screen;
