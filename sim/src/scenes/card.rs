//! The test card: what the virtual camera looks at on a rig with no scene of its own (DISCO),
//! so that `lightrig acquire` runs end to end on every rig file with
//! `source = { kind = "virtual" }` and its frames show that the rig did what the plan said.
//!
//! A matte card fills the view: an 8 × 8 checker (albedo 0.8 and 0.2) on the rig's first
//! rotary axis (the turntable), so it turns with it about the image centre, under a room
//! light. Each laser that is on puts a Gaussian spot of its colour where galvo pair 0 points:
//! code `(x, y)` lands on pixel `(x·w/65536, y·h/65536)`. A filter wheel between slots blocks
//! the light. The host's camera filter (a step's `meta.host.camera_filter_nm`, set by
//! [`lightrig_host::acquire::StepPreparation`]) passes only the colour band around its wavelength.
//! The voice coils are not modelled (the card does not ripple).

use crate::camera::{RigState, Scene};
use lightrig_host::rigfile::RigFile;
use lightrig_protocol::config::AxisKind;

/// The test card for a rig.
#[derive(Debug, Clone, PartialEq)]
pub struct CardScene {
    width: u32,
    height: u32,
    /// Radiance of a white patch under the room light.
    pub room: f64,
    /// Peak radiance of a laser spot on a white patch.
    pub spot: f64,
    /// Spot σ, pixels.
    pub spot_sigma: f64,
    /// Each laser's channel and its colour (linear RGB weights).
    lasers: Vec<(u8, [f64; 3])>,
    /// The turntable: the first rotary stepper axis.
    turntable: Option<u8>,
    /// The rig's filter wheels (the device reports every wheel it has, configured or not).
    wheels: Vec<u8>,
    /// The room light is off while the beam is on (the DISCO rig works in the dark).
    dark_room_with_lasers: bool,
}

/// Linear RGB weights of a wavelength: three Gaussian bands at 610, 545 and 465 nm.
pub fn colour_of(nm: f64) -> [f64; 3] {
    let band = |c: f64| (-((nm - c) / 40.0).powi(2) / 2.0).exp();
    [band(610.0), band(545.0), band(465.0)]
}

impl CardScene {
    /// The card for `rig`, `width × height` pixels.
    pub fn new(rig: &RigFile, width: u32, height: u32) -> Self {
        let turntable = rig.steppers.iter().find(|s| s.kind == AxisKind::Rotary).map(|s| s.axis);
        CardScene {
            width,
            height,
            room: 0.2,
            spot: 1.0,
            spot_sigma: f64::from(width.max(height)) / 60.0,
            lasers: rig.lasers.iter().map(|l| (l.channel, colour_of(f64::from(l.wavelength_nm)))).collect(),
            turntable,
            wheels: rig.filter_wheels.iter().map(|w| w.wheel).collect(),
            dark_room_with_lasers: !rig.galvos.is_empty(),
        }
    }

    /// The pixel galvo code `code` points at (continuous coordinates, pixel centres at +0.5).
    pub fn spot_at(&self, code: [u16; 2]) -> [f64; 2] {
        [
            f64::from(code[0]) * f64::from(self.width) / 65536.0,
            f64::from(code[1]) * f64::from(self.height) / 65536.0,
        ]
    }

    /// The card's albedo at pixel centre `(x, y)` with the turntable at `deg`.
    pub fn albedo(&self, x: f64, y: f64, deg: f64) -> f64 {
        let (cx, cy) = (f64::from(self.width) / 2.0, f64::from(self.height) / 2.0);
        let (s, c) = deg.to_radians().sin_cos();
        let (dx, dy) = (x - cx, y - cy);
        // Turn the point back into the card's frame.
        let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
        let square = f64::from(self.width.min(self.height)) / 8.0;
        let (i, j) = ((u / square).floor() as i64, (v / square).floor() as i64);
        if (i + j).rem_euclid(2) == 0 {
            0.8
        } else {
            0.2
        }
    }
}

impl Scene for CardScene {
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        let between_slots = |&w: &u8| state.filters.get(usize::from(w)).is_some_and(Option::is_none);
        if self.wheels.iter().any(between_slots) {
            return [0.0; 3];
        }
        let (px, py) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
        let deg = self.turntable.and_then(|a| state.axes.get(usize::from(a))).copied().unwrap_or(0.0);
        let albedo = self.albedo(px, py, deg);
        let beam = self.lasers.iter().any(|&(ch, _)| state.lasers & (1 << ch) != 0);
        let room = if beam && self.dark_room_with_lasers { 0.0 } else { self.room };
        let mut out = [room * albedo; 3];
        if let Some(&code) = state.galvos.first() {
            let [sx, sy] = self.spot_at(code);
            let r2 = (px - sx).powi(2) + (py - sy).powi(2);
            let g = self.spot * (-r2 / (2.0 * self.spot_sigma.powi(2))).exp();
            for &(ch, colour) in &self.lasers {
                if state.lasers & (1 << ch) != 0 {
                    for c in 0..3 {
                        out[c] += g * albedo * colour[c];
                    }
                }
            }
        }
        if let Some(nm) = state.meta.pointer("/host/camera_filter_nm").and_then(|v| v.as_f64()) {
            let pass = colour_of(nm);
            for c in 0..3 {
                out[c] *= pass[c];
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rig() -> RigFile {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/disco.toml");
        RigFile::load(&path).unwrap()
    }

    #[test]
    fn the_spot_is_where_the_galvo_points_in_the_lasers_colour() {
        let card = CardScene::new(&rig(), 160, 120);
        let red = rig().lasers.iter().find(|l| l.wavelength_nm == 635).unwrap().channel;
        let state = RigState {
            lasers: 1 << red,
            galvos: vec![[16384, 49152]],
            axes: vec![0.0],
            ..RigState::default()
        };
        assert_eq!(card.spot_at([16384, 49152]), [40.0, 90.0]);
        let at = card.radiance(39, 89, &state);
        let off = card.radiance(70, 60, &state);
        // Red dominates at the spot; the room is dark while a laser is on.
        assert!(at[0] > 0.15 && at[0] > 3.0 * at[1] && at[0] > 3.0 * at[2], "{at:?}");
        assert!(off.iter().all(|&v| v < 1e-6), "{off:?}");
    }

    #[test]
    fn the_checker_turns_with_the_turntable() {
        let card = CardScene::new(&rig(), 160, 120);
        // Square 15 px; (87.5, 67.5) is in square (0, 0) of the card's frame (white).
        assert_eq!(card.albedo(87.5, 67.5, 0.0), 0.8);
        // Turned by 90°, the point's card coordinates become (7.5, −7.5): square (0, −1).
        assert_eq!(card.albedo(87.5, 67.5, 90.0), 0.2);
    }
}
