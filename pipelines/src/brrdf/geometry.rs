//! The gonioreflectometer's geometry (thesis §4.4.3): "from simple geometric considerations we
//! can determine (ωo, ωi) for every pixel captured under a specific turntable rotation β".
//!
//! The camera looks along −z (orthographic: the spheres are small in a long lens's view); the
//! light turns about the image's vertical axis and comes from `(sin β, 0, cos β)`. The spheres
//! are found in a frame as bright discs; a pixel's normal follows from its offset to its disc's
//! centre. Angles are in the surface's frame: `θo`, `θi` from the normal, `φd` between the
//! two directions' azimuths (0 to π; the BRRDF is isotropic).

/// A sphere's outline in the image, pixels (`y` down).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Disc {
    pub cx: f64,
    pub cy: f64,
    pub r: f64,
}

/// The discs of connected pixels above `threshold` in `image` (`width × height`, one value a
/// pixel) with at least `min_pixels` pixels, top first: centre at their centroid, radius from
/// their area.
pub fn find_discs(
    image: &[f32],
    width: usize,
    height: usize,
    threshold: f32,
    min_pixels: usize,
) -> Vec<Disc> {
    let mut seen = vec![false; image.len()];
    let mut discs = Vec::new();
    let mut stack = Vec::new();
    for start in 0..image.len() {
        if seen[start] || image[start].is_nan() || image[start] <= threshold {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let (mut n, mut sx, mut sy) = (0usize, 0.0, 0.0);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % width, i / width);
            n += 1;
            sx += x as f64 + 0.5;
            sy += y as f64 + 0.5;
            let mut visit = |j: usize| {
                if !seen[j] && image[j] > threshold {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < width {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - width);
            }
            if y + 1 < height {
                visit(i + width);
            }
        }
        if n >= min_pixels {
            discs.push(Disc {
                cx: sx / n as f64,
                cy: sy / n as f64,
                r: (n as f64 / std::f64::consts::PI).sqrt(),
            });
        }
    }
    discs.sort_by(|a, b| a.cy.total_cmp(&b.cy));
    discs
}

impl Disc {
    /// The unit normal at the centre of pixel `(x, y)`, if it lies within `inner` of the radius
    /// (the rim's pixels mix sphere and background).
    pub fn normal(&self, x: usize, y: usize, inner: f64) -> Option<[f64; 3]> {
        let dx = (x as f64 + 0.5 - self.cx) / self.r;
        let dy = (self.cy - (y as f64 + 0.5)) / self.r;
        let r2 = dx * dx + dy * dy;
        (r2 < inner * inner).then(|| [dx, dy, (1.0 - r2).sqrt()])
    }
}

/// The light's direction for the arm at `degrees`.
pub fn light_dir(degrees: f64) -> [f64; 3] {
    let a = degrees.to_radians();
    [a.sin(), 0.0, a.cos()]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `(θo, θi, φd)` of unit directions `wo`, `wi` at unit normal `n`, radians; `None` when
/// either lies below the surface.
pub fn angles(n: [f64; 3], wi: [f64; 3], wo: [f64; 3]) -> Option<(f64, f64, f64)> {
    let (ci, co) = (dot(n, wi), dot(n, wo));
    if ci <= 0.0 || co <= 0.0 {
        return None;
    }
    // The two directions' tangential parts.
    let ti = [wi[0] - ci * n[0], wi[1] - ci * n[1], wi[2] - ci * n[2]];
    let to = [wo[0] - co * n[0], wo[1] - co * n[1], wo[2] - co * n[2]];
    let (li, lo) = (dot(ti, ti).sqrt(), dot(to, to).sqrt());
    let phi = if li < 1e-12 || lo < 1e-12 { 0.0 } else { (dot(ti, to) / (li * lo)).clamp(-1.0, 1.0).acos() };
    Some((co.clamp(-1.0, 1.0).acos(), ci.clamp(-1.0, 1.0).acos(), phi))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_rendered_discs_are_found_with_their_centres_and_radii() {
        let (w, h) = (160usize, 100usize);
        let truth = [Disc { cx: 80.0, cy: 27.0, r: 21.0 }, Disc { cx: 80.0, cy: 73.0, r: 21.0 }];
        let mut img = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                for d in &truth {
                    if let Some(n) = d.normal(x, y, 1.0) {
                        img[y * w + x] = 0.2 + n[2] as f32;
                    }
                }
            }
        }
        let found = find_discs(&img, w, h, 0.1, 20);
        assert_eq!(found.len(), 2);
        for (f, t) in found.iter().zip(&truth) {
            assert!((f.cx - t.cx).abs() < 0.05 && (f.cy - t.cy).abs() < 0.05, "{f:?} against {t:?}");
            assert!((f.r - t.r).abs() < 0.1, "{f:?} against {t:?}");
        }
    }

    #[test]
    fn angles_in_the_surface_frame() {
        let up = [0.0, 0.0, 1.0];
        // Light at 60° from the camera, normal facing the camera: θo 0, θi 60°.
        let (to, ti, _) = angles(up, light_dir(60.0), up).unwrap();
        assert!(to.abs() < 1e-12 && (ti - 60f64.to_radians()).abs() < 1e-12);
        // The normal halfway: θo = θi = 30°, the two on opposite sides (φd = π).
        let n = light_dir(30.0);
        let (to, ti, phi) = angles(n, light_dir(60.0), up).unwrap();
        assert!((to - ti).abs() < 1e-12 && (to - 30f64.to_radians()).abs() < 1e-12);
        assert!((phi - std::f64::consts::PI).abs() < 1e-9, "{phi}");
        // A normal tilted up (out of the plane of light and camera): φd between 0 and π.
        let t = 0.3f64;
        let n = [0.0, t.sin(), t.cos()];
        let (_, _, phi) = angles(n, light_dir(60.0), up).unwrap();
        assert!(phi > 0.1 && phi < std::f64::consts::PI - 0.1, "{phi}");
        assert!(angles(up, light_dir(100.0), up).is_none(), "light behind the surface");
    }
}
