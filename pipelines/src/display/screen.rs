//! The screen the reflected beam lands on, as labs build it: a flat diffuse screen at a
//! measured distance from the displayed spot, facing the mirror direction (or turned from it
//! by a measured angle), seen by a camera whose pixels each cover the same patch of screen (a
//! camera behind a translucent screen, or a rectified view of it).
//!
//! Frame: the spot at the origin, `z` the still liquid's normal, the beam arriving in the
//! `x`–`z` plane at incidence `β` from `−x`. Image `x` runs along the screen's horizontal
//! axis (towards `+x` of the frame when the screen is not turned), image `y` along `+y`.
//!
//! What the pipeline needs of a pixel is the **facet tilt** that sends the beam into it: the
//! reflecting facet's normal is the half vector `h` of the beam's direction and the pixel's,
//! and its tilt is `(hx/hz, hy/hz)`, exactly (no small angles). Ward's lobe is a Gaussian in
//! those coordinates ([`super::mapping`]). A pixel's value is the beam's power landing on its
//! patch, so each pixel holds the probability of the facet tilts that reach it.

use crate::vec3::{add, dot, norm, normalize, scale, V3};

/// A flat screen as the rig file gives it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Screen {
    /// Distance from the spot to the screen along the mirror direction, m.
    pub distance_m: f64,
    /// Side of the screen patch one camera pixel sees, m.
    pub pitch_m: f64,
    /// The beam's angle of incidence on the still liquid, rad.
    pub incidence_rad: f64,
    /// The screen's turn away from facing the mirror direction, about its vertical axis, rad.
    pub tilt_rad: f64,
    /// The image position (pixels, `0` the left edge of the first pixel) where the mirror
    /// direction meets the screen.
    pub centre_px: [f64; 2],
}

impl Screen {
    /// Unit vector from the spot towards the light.
    pub fn incident(&self) -> V3 {
        let b = self.incidence_rad;
        [-b.sin(), 0.0, b.cos()]
    }

    /// The screen's axes: the image's `x` and `y` directions (unit) and the screen's normal
    /// (towards the spot's side, unit), in the spot's frame.
    fn axes(&self) -> (V3, V3, V3) {
        let b = self.incidence_rad;
        let mirror = [b.sin(), 0.0, b.cos()];
        let across = [b.cos(), 0.0, -b.sin()];
        let (c, s) = (self.tilt_rad.cos(), self.tilt_rad.sin());
        let normal = add(scale(mirror, c), scale(across, s));
        let u = add(scale(across, c), scale(mirror, -s));
        (u, [0.0, 1.0, 0.0], normal)
    }

    /// The point of the screen at image position `(x, y)` (continuous pixels), m.
    pub fn point(&self, x: f64, y: f64) -> V3 {
        let b = self.incidence_rad;
        let centre = scale([b.sin(), 0.0, b.cos()], self.distance_m);
        let (u, v, _) = self.axes();
        let du = (x - self.centre_px[0]) * self.pitch_m;
        let dv = (y - self.centre_px[1]) * self.pitch_m;
        add(centre, add(scale(u, du), scale(v, dv)))
    }

    /// Unit direction from the spot to pixel `(x, y)`'s centre.
    pub fn direction(&self, x: usize, y: usize) -> V3 {
        normalize(self.point(x as f64 + 0.5, y as f64 + 0.5))
    }

    /// The facet tilt `(hx/hz, hy/hz)` that reflects the beam into pixel `(x, y)`'s centre.
    pub fn tilt(&self, x: usize, y: usize) -> [f64; 2] {
        let h = normalize(add(self.incident(), self.direction(x, y)));
        [h[0] / h[2], h[1] / h[2]]
    }

    /// Solid angle pixel `(x, y)` spans seen from the spot, sr (its patch foreshortened).
    pub fn solid_angle(&self, x: usize, y: usize) -> f64 {
        let p = self.point(x as f64 + 0.5, y as f64 + 0.5);
        let r = norm(p);
        let (_, _, normal) = self.axes();
        self.pitch_m * self.pitch_m * dot(normal, p).abs() / (r * r * r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::sub;

    fn screen(tilt: f64) -> Screen {
        Screen {
            distance_m: 0.05,
            pitch_m: 0.6e-3,
            incidence_rad: 0.3,
            tilt_rad: tilt,
            centre_px: [96.0, 96.0],
        }
    }

    /// Reflects `wi` (towards the light) about the facet of tilt `t`: the direction the beam
    /// leaves in (written apart from the module's half-vector route).
    fn reflect(wi: V3, t: [f64; 2]) -> V3 {
        let n = normalize([t[0], t[1], 1.0]);
        sub(scale(n, 2.0 * dot(wi, n)), wi)
    }

    #[test]
    fn a_pixels_tilt_reflects_the_beam_into_that_pixel() {
        for tilt in [0.0, 0.2] {
            let s = screen(tilt);
            // The mirror direction lands on the centre.
            let c = s.point(96.0, 96.0);
            let m = reflect(s.incident(), [0.0, 0.0]);
            assert!(norm(sub(normalize(c), m)) < 1e-12);
            for (x, y) in [(0, 0), (10, 150), (191, 40), (96, 96)] {
                let t = s.tilt(x, y);
                let out = reflect(s.incident(), t);
                let d = s.direction(x, y);
                assert!(norm(sub(out, d)) < 1e-12, "({x}, {y}): {out:?} vs {d:?}");
            }
        }
    }

    #[test]
    fn the_pixels_solid_angles_sum_to_the_screens() {
        // A screen facing the spot square on, 2 m wide at 1 m: the solid angle of a square of
        // half-side a at distance d is 4·asin(a²/(a² + d²)).
        let s = Screen {
            distance_m: 1.0,
            pitch_m: 0.01,
            incidence_rad: 0.0,
            tilt_rad: 0.0,
            centre_px: [100.0, 100.0],
        };
        let total: f64 =
            (0..200).flat_map(|y| (0..200).map(move |x| (x, y))).map(|(x, y)| s.solid_angle(x, y)).sum();
        let want = 4.0 * (1.0f64 / 2.0).asin();
        assert!((total / want - 1.0).abs() < 1e-4, "{total} vs {want}");
    }
}
