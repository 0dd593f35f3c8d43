//! The fluorescent-immersion scene (Hullin et al. 2008): a glass tank of fluorescent liquid
//! seen through its flat front wall, a galvo-swept laser sheet, an opaque sphere on a
//! turntable, and a planar chessboard target for the calibration passes.
//!
//! World frame, mm: `x` across the tank, `y` down (as the camera sees it), `z` into the tank
//! (away from the camera). The liquid fills the box [`FirsSceneSpec::tank`]; its front face
//! `z = tank.min.z` is the inner face of the front wall.
//!
//! - **Camera.** A pinhole in air, turned by `yaw_deg` about `y`. Each pixel's ray is refracted
//!   (Snell's law, vector form) at both faces of the wall: air → glass → liquid. Inside the
//!   liquid the ray is straight, which is what the pipeline's per-pixel line calibration relies
//!   on; the pinhole model does not hold there, which is why the pipeline fits lines per pixel.
//! - **Sheets.** The laser leaves the galvo mirror, whose image through the side wall sits at
//!   `mirror` (the side wall's refraction is folded into that virtual position). Galvo code `c`
//!   turns the sheet to the angle `θ = θ₀ + (c − zero)·urad_per_code` about the vertical line
//!   through the mirror: sheet `c` is the plane through that line with horizontal direction
//!   `(cos θ, 0, sin θ)`, so `z = m_z + tan θ·(x − m_x)`, a family the pipeline's 18-coefficient
//!   model represents to microns (its `x` slope `tan θ` is quadratic in the code to `θ³`).
//! - **Glow.** The liquid emits `glow` per mm of path with a Gaussian profile of width `σ`
//!   about the sheet; a pixel integrates it along its ray over the lit liquid:
//!   `glow/|n·d|·Σ[Φ(h(b)/σ) − Φ(h(a)/σ)]` over the lit stretches `[a, b]`, `h` the signed
//!   distance from the sheet. The camera's long-pass filter blocks the laser's own scatter,
//!   so only this fluorescence (and a weak stray term, below) reaches it.
//! - **Object.** The sphere is opaque: the ray stops at it, and the liquid in its laser shadow
//!   (the cone from the mirror point tangent to the sphere, beyond the tangent circle) is dark.
//!   The turntable turns it about `turntable_axis`.
//! - **Nuisance.** Fluorescence scattered back by the tank's back wall: a weak, smooth term
//!   `stray·glow` varying slowly over the image and the sweep.
//! - **Calibration target.** A chessboard plate parallel to the front wall at the `z` the
//!   step's `meta.pose.z_mm` says (the position the operator typed into the rig file). The
//!   `target-board` pass shows it under a lamp (laser off; 64 samples per pixel, for clean
//!   corners); the `target-sweep` pass sweeps the sheet with the plate, not the sphere, in the
//!   tank, so the glow cuts off on the plate.

use serde::{Deserialize, Serialize};

use crate::camera::{RigState, Scene};
use lightrig_imaging::synth::normal_cdf;
use lightrig_pipelines::vec3::{add, dot, norm, normalize, scale, sub, V3};

/// The pinhole camera in air.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FirsCamera {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Centre of projection, mm.
    pub position: V3,
    /// Turn about `y`, degrees: the optical axis is `(sin ψ, 0, cos ψ)`.
    pub yaw_deg: f64,
    /// A telecentric lens instead of the pinhole: every pixel's ray runs along the optical
    /// axis from `position` offset by this many mm per pixel (volume mode).
    #[serde(default)]
    pub telecentric_mm: Option<f64>,
}

/// The flat front wall and the liquid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FirsTank {
    /// The liquid's box; its `min.z` face is the wall's inner face.
    pub min: V3,
    /// See `min`.
    pub max: V3,
    /// Wall thickness, mm.
    pub wall_mm: f64,
    /// Refractive index of the wall (glass).
    pub n_wall: f64,
    /// Refractive index of the liquid.
    pub n_liquid: f64,
}

/// The galvo-swept laser sheet.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FirsSheet {
    /// Virtual position of the mirror (its image through the side wall), mm.
    pub mirror: V3,
    /// Sheet angle at the galvo's zero code, degrees (from `+x` towards `+z`).
    pub angle0_deg: f64,
    /// Galvo zero code.
    pub zero_code: u16,
    /// Optical angle per code, µrad.
    pub urad_per_code: f64,
    /// Sheet thickness: Gaussian σ across the sheet, mm.
    pub sigma_mm: f64,
    /// A telecentric scanner instead of the fan (volume mode): the sheets stay at the angle of
    /// the zero code and move along their normal by this many mm per code.
    #[serde(default)]
    pub parallel_mm_per_code: Option<f64>,
    /// The flat glass side wall (its inner face the liquid's `x = tank.min.x` face) the fanned
    /// sheet crosses into the liquid: then `mirror` is the real mirror in air, `angle0_deg` the
    /// sheet's angle in air, and each ray of the fan refracts at both faces by its own
    /// incidence, so the sheet in the liquid is curved. `None`: `mirror` is the mirror's
    /// virtual image (the wall folded in) and the sheets are planes.
    #[serde(default)]
    pub side_wall: Option<FirsSideWall>,
    /// Fluorescence per mm of path through the sheet's centre, radiance units.
    pub glow: f64,
    /// The stray term's size relative to `glow`.
    pub stray: f64,
    /// Laser channel.
    pub laser: u8,
    /// Galvo index.
    pub galvo: u8,
}

/// The side wall the laser crosses: flat glass, faces normal to `x`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FirsSideWall {
    /// Thickness, mm.
    pub wall_mm: f64,
    /// Refractive index.
    pub n_wall: f64,
}

/// A refracted laser path (see `FirsSceneSpec::refraction`).
#[derive(Debug, Clone, Copy)]
struct Refraction {
    /// Sine of the air ray's angle to the wall normal (times the index: the Snell invariant).
    k: f64,
    /// Air and glass stretches along the wall normal, mm.
    a: f64,
    g: f64,
    /// The lateral offset of the point from the mirror and its `y`, `z` parts.
    lat: f64,
    ey: f64,
    ez: f64,
    /// tan of the angle to the normal in air, glass, liquid.
    tan: [f64; 3],
    /// d(lateral reach)/dk.
    reach_dk: f64,
}

/// The chessboard target: `cols × rows` inner corners, corner `(i, j)` at
/// `(origin.x + i·square, origin.y + j·square, z)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FirsTarget {
    /// Inner corners per row.
    pub cols: usize,
    /// Rows of inner corners.
    pub rows: usize,
    /// Square size, mm.
    pub square_mm: f64,
    /// World `(x, y)` of inner corner `(0, 0)`, mm.
    pub origin_mm: [f64; 2],
    /// Lamp radiance on the white squares.
    pub lamp: f64,
}

/// What stands on the turntable.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum FirsObject {
    /// An opaque sphere.
    Sphere {
        /// Centre at turntable angle 0, mm.
        centre: V3,
        /// Radius, mm.
        radius: f64,
    },
    /// A transparent, convex, faceted solid of revolution about a vertical axis: `facets`
    /// vertical faces at distance `radius` from the axis over `|y| ≤ band`, a ring of faces
    /// bevelled by `bevel_deg` above and below each, and flat caps at `|y| = height`.
    Faceted {
        /// Centre at turntable angle 0, mm.
        centre: V3,
        /// Faces around.
        facets: usize,
        /// Distance of the vertical faces from the axis, mm.
        radius: f64,
        /// Half-height of the vertical faces, mm.
        band: f64,
        /// Tilt of the bevelled faces from vertical, degrees.
        bevel_deg: f64,
        /// Half-height to the caps, mm.
        height: f64,
        /// Azimuth of the first face, degrees.
        phase_deg: f64,
        /// Refractive index.
        n: f64,
    },
    /// A sphere index-matched to the liquid (volume mode): invisible to refraction, carrying
    /// no dye, absorbing the sheet by `absorb` per mm, so the liquid behind it along the laser
    /// is dimmer.
    Matched {
        /// Centre at turntable angle 0, mm.
        centre: V3,
        /// Radius, mm.
        radius: f64,
        /// Absorption coefficient, 1/mm.
        absorb: f64,
    },
}

impl FirsObject {
    /// The object's size for relative errors: the sphere's diameter, the faceted solid's
    /// largest extent (twice the circumradius, or its height).
    pub fn size_mm(&self) -> f64 {
        match *self {
            FirsObject::Sphere { radius, .. } | FirsObject::Matched { radius, .. } => 2.0 * radius,
            FirsObject::Faceted { facets, radius, height, .. } => {
                (2.0 * radius / (std::f64::consts::PI / facets.max(3) as f64).cos()).max(2.0 * height)
            }
        }
    }

    /// Whether light passes through it.
    pub fn transparent(&self) -> bool {
        matches!(self, FirsObject::Faceted { .. })
    }
}

/// The faceted solid's faces `(outward normal, a point on the face)`.
type Planes = Vec<(V3, V3)>;

/// The whole scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FirsSceneSpec {
    /// The camera.
    pub camera: FirsCamera,
    /// The tank.
    pub tank: FirsTank,
    /// The sheet.
    pub sheet: FirsSheet,
    /// The target.
    pub target: FirsTarget,
    /// The object on the turntable (at turntable angle 0).
    pub object: FirsObject,
    /// Turntable axis: a point and a direction (right-handed turns), mm.
    pub turntable_point: V3,
    /// See `turntable_point`.
    pub turntable_dir: V3,
    /// Turntable stepper axis index.
    pub turntable_axis: u8,
}

impl FirsSceneSpec {
    /// The volume-mode scene (Hullin et al.'s second mode): the camera, telecentric with
    /// 0.3 mm pixels, looks straight through the front wall (normal incidence: no bending)
    /// along the sheets' normal; a telecentric scanner moves the sheets (σ 0.3 mm, parallel to
    /// the wall) 0.3 mm per 20 codes; a 20 mm sphere index-matched to the liquid (n 1.45)
    /// without dye, absorbing 2 %/mm of the sheet.
    pub fn volume(width: u32, height: u32) -> Self {
        let mut s = Self::new(width, height);
        s.camera.yaw_deg = 0.0;
        s.camera.telecentric_mm = Some(0.3);
        s.camera.position = [0.0, 0.0, -150.0];
        s.tank.n_liquid = 1.45;
        s.sheet.angle0_deg = 0.0;
        s.sheet.mirror = [-700.0, 0.0, 0.0];
        s.sheet.parallel_mm_per_code = Some(0.3 / 20.0);
        s.sheet.side_wall = None;
        s.sheet.urad_per_code = 13.3158;
        s.sheet.sigma_mm = 0.3;
        s.target = FirsTarget { cols: 7, rows: 5, square_mm: 3.0, origin_mm: [-9.0, -6.0], lamp: 1.0 };
        s.object = FirsObject::Matched { centre: [0.8, 0.3, 0.0], radius: 10.0, absorb: 0.02 };
        s
    }

    /// The standard scene with the transparent faceted solid instead of the sphere: 8 faces
    /// 13 mm from the axis, ±5 mm high, bevels at 40°, caps at ±11 mm, glass of n 1.5 (the
    /// liquid's 1.40 does not match it: the camera sees the liquid behind it displaced).
    pub fn faceted(width: u32, height: u32) -> Self {
        let mut s = Self::new(width, height);
        s.object = FirsObject::Faceted {
            centre: [1.5, 0.0, 0.0],
            facets: 8,
            radius: 13.0,
            band: 5.0,
            bevel_deg: 40.0,
            height: 11.0,
            phase_deg: 11.0,
            n: 1.5,
        };
        s
    }

    /// The standard scene: a 32 mm sphere in a 100 × 80 × 90 mm tank behind 6 mm of glass
    /// (n 1.5) in water–glycerol (n 1.40), seen at 25° from 0.3 mm pixels; the sheet 0.14 mm
    /// thick from a mirror 700 mm to the left, about 27° across the front wall.
    pub fn new(width: u32, height: u32) -> Self {
        let mut s = FirsSceneSpec {
            camera: FirsCamera {
                width,
                height,
                focal_px: 960.0,
                position: [0.0, 0.0, 0.0],
                yaw_deg: 25.0,
                telecentric_mm: None,
            },
            tank: FirsTank {
                min: [-50.0, -40.0, -40.0],
                max: [50.0, 40.0, 50.0],
                wall_mm: 6.0,
                n_wall: 1.5,
                n_liquid: 1.40,
            },
            sheet: FirsSheet {
                mirror: [-700.0, 0.0, -350.0],
                angle0_deg: 0.5f64.atan().to_degrees(),
                zero_code: 32768,
                urad_per_code: 13.3158,
                sigma_mm: 0.14,
                parallel_mm_per_code: None,
                side_wall: None,
                glow: 1.0,
                stray: 0.01,
                laser: 0,
                galvo: 0,
            },
            target: FirsTarget { cols: 13, rows: 10, square_mm: 4.0, origin_mm: [-24.0, -18.0], lamp: 1.0 },
            object: FirsObject::Sphere { centre: [1.5, 0.0, 0.0], radius: 16.0 },
            turntable_point: [0.0, 0.0, 0.0],
            turntable_dir: [0.0, -1.0, 0.0],
            turntable_axis: 0,
        };
        s.set_side_wall(FirsSideWall { wall_mm: 6.0, n_wall: 1.5 });
        // Aim the optical axis at the world origin through the wall: trace it from a camera
        // 280 mm away along the axis, then shift the camera by the miss.
        let psi = s.camera.yaw_deg.to_radians();
        s.camera.position = [-280.0 * psi.sin(), 0.0, -280.0 * psi.cos()];
        for _ in 0..3 {
            if let Some((o, d)) = s.liquid_ray_dir(s.forward()) {
                let at = add(o, scale(d, -o[2] / d[2]));
                s.camera.position[0] -= at[0];
            }
        }
        s
    }

    fn forward(&self) -> V3 {
        let psi = self.camera.yaw_deg.to_radians();
        [psi.sin(), 0.0, psi.cos()]
    }

    /// The camera ray of image point `(x, y)` (pixel centres at integers), in air.
    pub fn air_dir(&self, x: f64, y: f64) -> V3 {
        let psi = self.camera.yaw_deg.to_radians();
        let (f, r, d) = (self.forward(), [psi.cos(), 0.0, -psi.sin()], [0.0, 1.0, 0.0]);
        let c = &self.camera;
        let u = (x - (f64::from(c.width) - 1.0) / 2.0) / c.focal_px;
        let v = (y - (f64::from(c.height) - 1.0) / 2.0) / c.focal_px;
        normalize(add(f, add(scale(r, u), scale(d, v))))
    }

    /// The ray in the liquid for a ray in air from `c` along `dir`: the point on the wall's
    /// inner face and the unit direction; `None` if it misses the wall or reflects totally.
    fn trace(&self, c: V3, dir: V3) -> Option<(V3, V3)> {
        let t = &self.tank;
        let (z_in, z_out) = (t.min[2], t.min[2] - t.wall_mm);
        if dir[2] <= 0.0 {
            return None;
        }
        let n = [0.0, 0.0, -1.0];
        let p1 = add(c, scale(dir, (z_out - c[2]) / dir[2]));
        let d1 = refract(dir, n, 1.0 / t.n_wall)?;
        let p2 = add(p1, scale(d1, (z_in - p1[2]) / d1[2]));
        let d2 = refract(d1, n, t.n_wall / t.n_liquid)?;
        Some((p2, d2))
    }

    fn liquid_ray_dir(&self, dir: V3) -> Option<(V3, V3)> {
        self.trace(self.camera.position, dir)
    }

    /// The ray in the liquid of image point `(x, y)`.
    pub fn liquid_ray(&self, x: f64, y: f64) -> Option<(V3, V3)> {
        let c = &self.camera;
        match c.telecentric_mm {
            Some(pitch) => {
                let psi = c.yaw_deg.to_radians();
                let (r, d) = ([psi.cos(), 0.0, -psi.sin()], [0.0, 1.0, 0.0]);
                let u = (x - (f64::from(c.width) - 1.0) / 2.0) * pitch;
                let v = (y - (f64::from(c.height) - 1.0) / 2.0) * pitch;
                self.trace(add(c.position, add(scale(r, u), scale(d, v))), self.forward())
            }
            None => self.liquid_ray_dir(self.air_dir(x, y)),
        }
    }

    /// Sheet `code`'s plane: unit normal (towards `+z`) and a point on it.
    pub fn sheet_plane(&self, code: u16) -> (V3, V3) {
        let sh = &self.sheet;
        match sh.parallel_mm_per_code {
            Some(k) => {
                let th = sh.angle0_deg.to_radians();
                let n = [-th.sin(), 0.0, th.cos()];
                (n, add(sh.mirror, scale(n, (f64::from(code) - f64::from(sh.zero_code)) * k)))
            }
            None => {
                let th = self.sheet_angle(code);
                ([-th.sin(), 0.0, th.cos()], sh.mirror)
            }
        }
    }

    /// Puts the fanned sheet's mirror behind the glass side wall `wall`, keeping the sheets
    /// in the liquid where they were: the zero code's central ray crosses the origin at the
    /// liquid angle the virtual mirror gave (from `+x` towards `+z`), the real mirror sits at
    /// the same `x` in air, and the galvo's step is scaled so the sheets keep their spacing in
    /// the liquid at the origin.
    pub fn set_side_wall(&mut self, wall: FirsSideWall) {
        let sh = &mut self.sheet;
        let nl = self.tank.n_liquid;
        let th_l = sh.angle0_deg.to_radians();
        let sin_a = (nl * th_l.sin()).min(0.999);
        let th_a = sin_a.asin();
        let th_g = (sin_a / wall.n_wall).asin();
        let (x_in, x_out) = (self.tank.min[0], self.tank.min[0] - wall.wall_mm);
        let z_in = th_l.tan() * x_in;
        let z_out = z_in - wall.wall_mm * th_g.tan();
        let mx = sh.mirror[0];
        sh.mirror = [mx, sh.mirror[1], z_out - (x_out - mx) * th_a.tan()];
        // dθ_liquid/dθ_air in the horizontal plane, from sin θ_a = n_l sin θ_l.
        sh.urad_per_code *= nl * th_l.cos() / th_a.cos();
        sh.angle0_deg = th_a.to_degrees();
        sh.side_wall = Some(wall);
    }

    /// The laser's path from the mirror to the liquid point `p` through the side wall (Fermat:
    /// Snell's law at both faces): the mirror, the points on the outer and inner faces, `p`.
    /// `None` without a side wall or for a point not beyond the wall.
    pub fn laser_path(&self, p: V3) -> Option<[V3; 4]> {
        let r = self.refraction(p, None)?;
        let m = self.sheet.mirror;
        let (uy, uz) = if r.lat > 0.0 { (r.ey / r.lat, r.ez / r.lat) } else { (0.0, 0.0) };
        let (ta, tg) = (r.a * r.tan[0], r.g * r.tan[1]);
        let pa = [m[0] + r.a, m[1] + uy * ta, m[2] + uz * ta];
        let pb = [pa[0] + r.g, pa[1] + uy * tg, pa[2] + uz * tg];
        Some([m, pa, pb, p])
    }

    /// The refracted path to `p` in the plane of the wall normal and `p − mirror`'s lateral
    /// part: Newton (bracketed) on the invariant `k = sin` of the air ray's angle to the wall
    /// normal, from `guess`.
    fn refraction(&self, p: V3, guess: Option<f64>) -> Option<Refraction> {
        let wall = self.sheet.side_wall?;
        let m = self.sheet.mirror;
        let (x_in, x_out) = (self.tank.min[0], self.tank.min[0] - wall.wall_mm);
        let (a, g, l) = (x_out - m[0], wall.wall_mm, (p[0] - x_in).max(0.0));
        if a <= 0.0 {
            return None;
        }
        let (ey, ez) = (p[1] - m[1], p[2] - m[2]);
        let lat = ey.hypot(ez);
        let n = [1.0, wall.n_wall, self.tank.n_liquid];
        let len = [a, g, l];
        // tan of the angle in medium i and its derivative in k.
        let tans = |k: f64| {
            let mut t = [0.0; 3];
            let mut dt = [0.0; 3];
            for i in 0..3 {
                let s = k / n[i];
                let c2 = 1.0 - s * s;
                let c = c2.sqrt();
                t[i] = s / c;
                dt[i] = 1.0 / (n[i] * c2 * c);
            }
            (t, dt)
        };
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        let mut k = guess.unwrap_or(lat / lat.hypot(a + g + l)).clamp(0.0, 0.999_999);
        for _ in 0..60 {
            let (t, dt) = tans(k);
            let f = (0..3).map(|i| len[i] * t[i]).sum::<f64>() - lat;
            if f > 0.0 {
                hi = k;
            } else {
                lo = k;
            }
            let step = f / (0..3).map(|i| len[i] * dt[i]).sum::<f64>();
            if step.abs() < 1e-15 {
                break;
            }
            let next = k - step;
            k = if next > lo && next < hi { next } else { 0.5 * (lo + hi) };
            if hi - lo < 1e-15 {
                break;
            }
        }
        let (tan, dtan) = tans(k);
        let reach_dk = (0..3).map(|i| len[i] * dtan[i]).sum::<f64>();
        Some(Refraction { k, a, g, lat, ey, ez, tan, reach_dk })
    }

    /// The fractional galvo code whose sheet passes through the liquid point `p`.
    pub fn code_at(&self, p: V3) -> f64 {
        self.code_grad(p, None).0
    }

    /// The code at `p`, its gradient (codes per mm) and the path's `k` (warm start for a
    /// neighbouring point).
    fn code_grad(&self, p: V3, guess: Option<f64>) -> (f64, V3, Option<f64>) {
        let s = &self.sheet;
        let per_rad = 1.0 / (s.urad_per_code * 1e-6);
        let zero = f64::from(s.zero_code);
        let th0 = s.angle0_deg.to_radians();
        if let Some(step) = s.parallel_mm_per_code {
            let n = [-th0.sin(), 0.0, th0.cos()];
            return (zero + dot(n, sub(p, s.mirror)) / step, scale(n, 1.0 / step), None);
        }
        let Some(r) = self.refraction(p, guess) else {
            // The plane through the vertical line through the (virtual) mirror.
            let (dx, dz) = (p[0] - s.mirror[0], p[2] - s.mirror[2]);
            let r2 = dx * dx + dz * dz;
            return (zero + (dz.atan2(dx) - th0) * per_rad, scale([-dz / r2, 0.0, dx / r2], per_rad), None);
        };
        // θ = atan2(k·e_z, √(1 − k²)), e = the lateral unit vector; k(lat, l) from the reach
        // equation: ∂k/∂lat = 1/R', ∂k/∂l = −tan_l/R'.
        let (k, lat) = (r.k, r.lat.max(1e-12));
        let ezu = r.ez / lat;
        let (f, g) = (k * ezu, (1.0 - k * k).sqrt());
        let theta = f.atan2(g);
        let dk = [-r.tan[2] / r.reach_dk, (r.ey / lat) / r.reach_dk, (r.ez / lat) / r.reach_dk];
        let lat3 = lat * lat * lat;
        let dezu = [0.0, -r.ez * r.ey / lat3, r.ey * r.ey / lat3];
        let q = f * f + g * g;
        let grad: V3 = std::array::from_fn(|i| {
            let df = ezu * dk[i] + k * dezu[i];
            let dg = -k / g * dk[i];
            (g * df - f * dg) / q * per_rad
        });
        (zero + (theta - th0) * per_rad, grad, Some(k))
    }

    /// The laser's direction at the liquid point `p` (unit).
    pub fn laser_dir_at(&self, p: V3) -> V3 {
        let s = &self.sheet;
        if s.parallel_mm_per_code.is_some() {
            let th = s.angle0_deg.to_radians();
            return [th.cos(), 0.0, th.sin()];
        }
        match self.laser_path(p) {
            Some([_, _, b, _]) => normalize(sub(p, b)),
            None => normalize(sub(p, s.mirror)),
        }
    }

    /// The `z` of sheet `code` (fractional) at `(x, y)`: the root of `code_at` along `z`.
    pub fn sheet_z(&self, code: f64, x: f64, y: f64) -> Option<f64> {
        let f = |z: f64| self.code_at([x, y, z]) - code;
        let (mut z0, mut z1) = (0.0, 1.0);
        let (mut f0, mut f1) = (f(z0), f(z1));
        for _ in 0..50 {
            if f1 == f0 {
                break;
            }
            let z2 = z1 - f1 * (z1 - z0) / (f1 - f0);
            (z0, f0) = (z1, f1);
            z1 = z2;
            f1 = f(z1);
            if (z1 - z0).abs() < 1e-10 {
                return Some(z1);
            }
        }
        (f1.abs() < 1e-6).then_some(z1)
    }

    /// The sheet `code` near the liquid ray `o + s·d`: its unit normal and the point where the
    /// ray crosses it (the sheet's tangent plane there; the sheet is the level set of
    /// [`code_at`](Self::code_at), found by Newton's method along the ray from `s0`).
    fn sheet_crossing(&self, o: V3, d: V3, code: u16, s0: f64) -> Option<(V3, V3)> {
        let c = f64::from(code);
        let mut s = s0;
        let mut guess = None;
        for _ in 0..30 {
            let p = add(o, scale(d, s));
            let (v, g, k) = self.code_grad(p, guess);
            guess = k;
            let slope = dot(g, d);
            if slope == 0.0 || !slope.is_finite() {
                return None;
            }
            let step = (v - c) / slope;
            s -= step;
            if step.abs() < 1e-9 {
                let p = add(o, scale(d, s));
                let (_, g, _) = self.code_grad(p, guess);
                return (norm(g) > 0.0).then(|| (normalize(g), p));
            }
        }
        None
    }

    /// Sheet angle of galvo code `code`, radians.
    pub fn sheet_angle(&self, code: u16) -> f64 {
        let s = &self.sheet;
        s.angle0_deg.to_radians() + (f64::from(code) - f64::from(s.zero_code)) * s.urad_per_code * 1e-6
    }

    /// The galvo code whose sheet crosses `x = 0, y = 0` at depth `z` (fractional).
    pub fn code_for_depth(&self, z: f64) -> f64 {
        self.code_at([0.0, 0.0, z])
    }

    /// The sheets' slope `dz/dx` in the liquid at the origin, along `y = 0`.
    pub fn liquid_slope(&self) -> f64 {
        let c = self.code_at([0.0; 3]);
        match (self.sheet_z(c, -10.0, 0.0), self.sheet_z(c, 10.0, 0.0)) {
            (Some(a), Some(b)) => (b - a) / 20.0,
            _ => self.sheet.angle0_deg.to_radians().tan(),
        }
    }

    /// The object's centre at turntable angle `deg`.
    pub fn centre_at(&self, deg: f64) -> V3 {
        let c = match self.object {
            FirsObject::Sphere { centre, .. }
            | FirsObject::Faceted { centre, .. }
            | FirsObject::Matched { centre, .. } => centre,
        };
        rotate(c, self.turntable_point, self.turntable_dir, deg.to_radians())
    }

    /// The faceted solid's faces at turntable angle `deg` (empty for the sphere).
    pub fn planes_at(&self, deg: f64) -> Planes {
        let FirsObject::Faceted { centre, facets, radius, band, bevel_deg, height, phase_deg, .. } =
            self.object
        else {
            return Vec::new();
        };
        let b = bevel_deg.to_radians();
        let mut planes = Vec::new();
        for k in 0..facets {
            let phi = phase_deg.to_radians() + std::f64::consts::TAU * k as f64 / facets as f64;
            let hz = [phi.cos(), 0.0, phi.sin()];
            let rim = add(centre, scale(hz, radius));
            planes.push((hz, rim));
            planes.push((
                normalize(add(scale(hz, b.cos()), [0.0, -b.sin(), 0.0])),
                add(rim, [0.0, -band, 0.0]),
            ));
            planes
                .push((normalize(add(scale(hz, b.cos()), [0.0, b.sin(), 0.0])), add(rim, [0.0, band, 0.0])));
        }
        planes.push(([0.0, -1.0, 0.0], add(centre, [0.0, -height, 0.0])));
        planes.push(([0.0, 1.0, 0.0], add(centre, [0.0, height, 0.0])));
        let a = deg.to_radians();
        planes
            .into_iter()
            .map(|(n, q)| {
                (
                    rotate(n, [0.0; 3], self.turntable_dir, a),
                    rotate(q, self.turntable_point, self.turntable_dir, a),
                )
            })
            .collect()
    }

    /// The first point where pixel `(x, y)`'s ray meets the object at turntable angle `deg`,
    /// inside the tank.
    pub fn object_hit(&self, x: f64, y: f64, deg: f64) -> Option<V3> {
        let (o, d) = self.liquid_ray(x, y)?;
        let (_, exit) = box_interval(o, d, self.tank.min, self.tank.max)?;
        let e0 = match self.object {
            FirsObject::Sphere { radius, .. } | FirsObject::Matched { radius, .. } => {
                sphere_interval(o, d, self.centre_at(deg), radius)?.0
            }
            FirsObject::Faceted { .. } => convex_interval(o, d, &self.planes_at(deg))?.0,
        };
        (e0 > 0.0 && e0 < exit).then(|| add(o, scale(d, e0)))
    }

    /// The outward normal of the object's surface at (or near) `p`, at turntable angle `deg`.
    pub fn normal_at(&self, p: V3, deg: f64) -> V3 {
        match self.object {
            FirsObject::Sphere { .. } | FirsObject::Matched { .. } => normalize(sub(p, self.centre_at(deg))),
            FirsObject::Faceted { .. } => self
                .planes_at(deg)
                .into_iter()
                .max_by(|a, b| dot(a.0, sub(p, a.1)).total_cmp(&dot(b.0, sub(p, b.1))))
                .map_or([0.0, 0.0, 1.0], |(n, _)| n),
        }
    }

    /// Distance of `p` from the object's surface at turntable angle `deg`: exact for the
    /// sphere; for the faceted solid the distance to the nearest face whose foot point lies on
    /// the solid (exact off a face's interior), else the largest plane distance.
    pub fn distance(&self, p: V3, deg: f64) -> f64 {
        match self.object {
            FirsObject::Sphere { radius, .. } | FirsObject::Matched { radius, .. } => {
                (norm(sub(p, self.centre_at(deg))) - radius).abs()
            }
            FirsObject::Faceted { .. } => {
                let planes = self.planes_at(deg);
                let side = |q: V3| planes.iter().map(|(n, a)| dot(*n, sub(q, *a))).fold(f64::MIN, f64::max);
                let on_face = planes
                    .iter()
                    .map(|(n, a)| {
                        let h = dot(*n, sub(p, *a));
                        (h.abs(), sub(p, scale(*n, h)))
                    })
                    .filter(|(_, foot)| side(*foot) <= 1e-9)
                    .map(|(d, _)| d)
                    .fold(f64::INFINITY, f64::min);
                if on_face.is_finite() {
                    on_face
                } else {
                    side(p).abs()
                }
            }
        }
    }

    /// Whether world `(x, y)` on the target plate is a white square (outside the board's
    /// squares the plate is white too).
    fn target_white(&self, x: f64, y: f64) -> bool {
        let t = &self.target;
        let a = ((x - t.origin_mm[0]) / t.square_mm).floor() as i64 + 1;
        let b = ((y - t.origin_mm[1]) / t.square_mm).floor() as i64 + 1;
        let inside = (0..=t.cols as i64).contains(&a) && (0..=t.rows as i64).contains(&b);
        // Square (1, 1), the one between corners 0, 1, cols and cols + 1, is dark.
        !(inside && (a + b).rem_euclid(2) == 0)
    }

    /// The plate's extent in `x` and `y`: the board plus one square all round.
    fn plate(&self) -> ([f64; 2], [f64; 2]) {
        let t = &self.target;
        let (w, h) = ((t.cols + 3) as f64 * t.square_mm, (t.rows + 3) as f64 * t.square_mm);
        let (x0, y0) = (t.origin_mm[0] - 2.0 * t.square_mm, t.origin_mm[1] - 2.0 * t.square_mm);
        ([x0, x0 + w], [y0, y0 + h])
    }

    /// Where the ray meets the plate through `(0, 0, z)` turned by `tilt` (radians) about `y`:
    /// the ray parameter and the plate coordinates `(x', y)` (`x'` along `(cos, 0, sin)`).
    fn plate_hit(&self, o: V3, d: V3, z: f64, tilt: f64) -> Option<(f64, f64, f64)> {
        let (axis, nrm) = ([tilt.cos(), 0.0, tilt.sin()], [-tilt.sin(), 0.0, tilt.cos()]);
        let den = dot(nrm, d);
        if den <= 0.0 {
            return None;
        }
        let c = [0.0, 0.0, z];
        let s = dot(nrm, sub(c, o)) / den;
        let p = add(o, scale(d, s));
        let (xp, y) = (dot(axis, sub(p, c)), p[1]);
        let (xr, yr) = self.plate();
        (s > 0.0 && xp >= xr[0] && xp <= xr[1] && y >= yr[0] && y <= yr[1]).then_some((s, xp, y))
    }

    /// Fluorescence seen along the liquid ray `(o, d)` with sheet code `code`, when the
    /// opaque thing in the tank is `what`.
    fn glow(&self, o: V3, d: V3, code: u16, what: Occluder<'_>) -> f64 {
        let sh = &self.sheet;
        let Some((_, exit)) = box_interval(o, d, self.tank.min, self.tank.max) else { return 0.0 };
        // The sheet where the ray crosses it: its tangent plane (a plane of the family without
        // a side wall), and the apex of the sphere's shadow cone (the mirror; with a side wall,
        // the virtual source of the liquid ray through the crossing, as far back as the mirror).
        let sheet = match (sh.side_wall, sh.parallel_mm_per_code) {
            (Some(_), None) => self.sheet_crossing(o, d, code, 0.5 * exit).map(|(n, x)| {
                let l = self.laser_dir_at(x);
                (n, x, sub(x, scale(l, norm(sub(x, sh.mirror)))))
            }),
            _ => {
                let (n, q) = self.sheet_plane(code);
                Some((n, q, sh.mirror))
            }
        };
        let Some((n, q, apex)) = sheet else { return 0.0 };
        let mut end = exit;
        let mut shadow: Option<(f64, f64)> = None;
        let mut behind = 0.0;
        let mut matched = None;
        match what {
            Occluder::Sphere(c, r) => {
                if let Some((e0, _)) = sphere_interval(o, d, c, r) {
                    if e0 > 0.0 {
                        end = end.min(e0);
                    }
                }
                shadow = cone_shadow(o, d, apex, c, r);
            }
            Occluder::Glass(planes, n) => {
                if let Some((e0, _, i0, _)) =
                    convex_interval(o, d, planes).filter(|v| v.0 > 0.0 && v.0 < exit)
                {
                    end = e0;
                    // Through the glass and out into the liquid behind; 0.9 for the two
                    // surfaces' Fresnel losses. The glass itself does not fluoresce.
                    let p0 = add(o, scale(d, e0));
                    let n_l = self.tank.n_liquid;
                    if let Some(d1) = refract(d, planes[i0].0, n_l / n) {
                        if let Some((_, e1, _, i1)) = convex_interval(p0, d1, planes) {
                            let p1 = add(p0, scale(d1, e1));
                            if let Some(d2) = refract(d1, scale(planes[i1].0, -1.0), n / n_l) {
                                behind = 0.9 * self.glow(p1, d2, code, Occluder::None);
                            }
                        }
                    }
                }
            }
            Occluder::Matched(c, r, mu) => {
                if let Some((e0, e1)) = sphere_interval(o, d, c, r) {
                    matched = Some((e0, e1, c, r, mu));
                }
            }
            Occluder::None => {}
            Occluder::Plate(z, tilt) => {
                if let Some((s, _, _)) = self.plate_hit(o, d, z, tilt) {
                    end = end.min(s);
                }
            }
        }
        let mut segs: Vec<(f64, f64)> = vec![(0.0, end)];
        if let Some((s0, s1)) = shadow {
            segs = segs
                .into_iter()
                .flat_map(|(a, b)| {
                    let (lo, hi) = (a.max(s0), b.min(s1));
                    if lo < hi {
                        vec![(a, lo), (hi, b)]
                    } else {
                        vec![(a, b)]
                    }
                })
                .filter(|(a, b)| b > a)
                .collect();
        }
        let th = self.sheet_angle(code);
        let nd = dot(n, d);
        if nd.abs() < 1e-9 {
            return 0.0;
        }
        let h = |s: f64| dot(n, sub(add(o, scale(d, s)), q)) / sh.sigma_mm;
        let mut lit: f64 = segs.iter().map(|&(a, b)| (normal_cdf(h(b)) - normal_cdf(h(a))).abs()).sum();
        if let Some((e0, e1, c, r, mu)) = matched {
            // The undyed sphere glows not; the liquid behind it along the laser (+x within
            // the sheet) is lit through the sphere's absorption, taken where the ray crosses
            // the sheet's centre.
            lit -= (normal_cdf(h(e1.min(end))) - normal_cdf(h(e0.max(0.0)))).abs()
                * f64::from(u8::from(e1 > 0.0 && e0 < end));
            let p = add(o, scale(d, -dot(n, sub(o, q)) / nd));
            let l = [th.cos(), 0.0, th.sin()];
            let chord = sphere_interval(p, scale(l, -1.0), c, r)
                .map_or(0.0, |(a, b)| (b.max(0.0) - a.max(0.0)).max(0.0));
            lit *= (-mu * chord).exp();
        }
        // The back wall's scattered fluorescence: smooth in the image and over the sweep.
        let stray = sh.stray * (1.0 + 0.5 * (0.05 * o[0] + 3.0 * th).sin() * (0.04 * o[1]).cos());
        let stray = if matches!(what, Occluder::None) { 0.0 } else { stray };
        sh.glow * (lit / nd.abs() + stray) + behind
    }
}

#[derive(Debug, Clone, Copy)]
enum Occluder<'a> {
    /// Nothing in the way.
    None,
    /// Opaque sphere: centre, radius.
    Sphere(V3, f64),
    /// Transparent convex solid: faces, refractive index.
    Glass(&'a [(V3, V3)], f64),
    /// The target plate at depth `z`, tilted about `y`.
    Plate(f64, f64),
    /// Index-matched absorbing sphere: centre, radius, absorption per mm.
    Matched(V3, f64, f64),
}

/// The parameter interval of the ray inside the convex solid `{p : n·(p − q) ≤ 0}` and the
/// faces it enters and leaves by.
fn convex_interval(o: V3, d: V3, planes: &[(V3, V3)]) -> Option<(f64, f64, usize, usize)> {
    let (mut lo, mut hi, mut ilo, mut ihi) = (f64::NEG_INFINITY, f64::INFINITY, 0, 0);
    for (i, (n, q)) in planes.iter().enumerate() {
        let (num, den) = (dot(*n, sub(*q, o)), dot(*n, d));
        if den == 0.0 {
            if num < 0.0 {
                return None;
            }
        } else if den > 0.0 {
            if num / den < hi {
                (hi, ihi) = (num / den, i);
            }
        } else if num / den > lo {
            (lo, ilo) = (num / den, i);
        }
    }
    (lo < hi && lo.is_finite() && hi.is_finite()).then_some((lo, hi, ilo, ihi))
}

/// Snell's law: `i` (unit) crossing into a medium with relative index `1/eta`, `n` the unit
/// normal facing the incoming ray; `None` on total internal reflection.
pub fn refract(i: V3, n: V3, eta: f64) -> Option<V3> {
    let cosi = -dot(n, i);
    let k = 1.0 - eta * eta * (1.0 - cosi * cosi);
    (k >= 0.0).then(|| normalize(add(scale(i, eta), scale(n, eta * cosi - k.sqrt()))))
}

/// `p` turned by `angle` (right-handed) about the axis through `a` along `dir`.
pub fn rotate(p: V3, a: V3, dir: V3, angle: f64) -> V3 {
    lightrig_pipelines::firs::surface::rotate_about_axis(p, a, dir, angle)
}

fn box_interval(o: V3, d: V3, min: V3, max: V3) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < min[i] || o[i] > max[i] {
                return None;
            }
            continue;
        }
        let (a, b) = ((min[i] - o[i]) / d[i], (max[i] - o[i]) / d[i]);
        lo = lo.max(a.min(b));
        hi = hi.min(a.max(b));
    }
    (lo <= hi && hi > 0.0).then_some((lo.max(0.0), hi))
}

fn sphere_interval(o: V3, d: V3, c: V3, r: f64) -> Option<(f64, f64)> {
    let oc = sub(o, c);
    let b = dot(oc, d);
    let disc = b * b - (dot(oc, oc) - r * r);
    (disc > 0.0).then(|| (-b - disc.sqrt(), -b + disc.sqrt()))
}

/// The stretch of the ray `o + s·d` in the laser shadow of the sphere `(c, r)` lit from the
/// point `m`: inside the cone from `m` tangent to the sphere and beyond the plane of the
/// tangent circle.
fn cone_shadow(o: V3, d: V3, m: V3, c: V3, r: f64) -> Option<(f64, f64)> {
    let axis = sub(c, m);
    let dist = norm(axis);
    if dist <= r {
        return None;
    }
    let u = scale(axis, 1.0 / dist);
    let cos2 = 1.0 - (r / dist).powi(2);
    // (w·u)² − cos²α·|w|² ≥ 0 with w = o + s·d − m.
    let w0 = sub(o, m);
    let (wu, du) = (dot(w0, u), dot(d, u));
    let qa = du * du - cos2 * dot(d, d);
    let qb = 2.0 * (wu * du - cos2 * dot(w0, d));
    let qc = wu * wu - cos2 * dot(w0, w0);
    let plane = dist * cos2;
    // Axial position along the ray: wu + s·du > plane.
    let behind = |s: f64| wu + s * du > plane;
    let disc = qb * qb - 4.0 * qa * qc;
    if disc < 0.0 || qa == 0.0 {
        return None;
    }
    let (s1, s2) = {
        let (a, b) = ((-qb - disc.sqrt()) / (2.0 * qa), (-qb + disc.sqrt()) / (2.0 * qa));
        (a.min(b), a.max(b))
    };
    // The quadric's roots bound the double cone; which stretch lies in the forward nappe
    // depends on the sign of `qa`, so test a point of each candidate.
    let inside = |s: f64| {
        let w = add(w0, scale(d, s));
        let wu = dot(w, u);
        wu > 0.0 && wu * wu >= cos2 * dot(w, w)
    };
    let mid = 0.5 * (s1 + s2);
    let (lo, hi) = if inside(mid) {
        (s1, s2)
    } else if inside(s2 + 1.0) {
        (s2, f64::INFINITY)
    } else if inside(s1 - 1.0) {
        (f64::NEG_INFINITY, s1)
    } else {
        return None;
    };
    // Clip to the part beyond the tangent plane.
    let (lo, hi) = if du > 0.0 {
        (lo.max((plane - wu) / du), hi)
    } else if du < 0.0 {
        (lo, hi.min((plane - wu) / du))
    } else if behind(0.0) {
        (lo, hi)
    } else {
        return None;
    };
    (lo < hi).then_some((lo, hi))
}

/// The scene for the virtual camera.
pub struct FirsScene {
    /// Its definition (written beside the session as the ground truth).
    pub spec: FirsSceneSpec,
    /// Per pixel: the ray in the liquid.
    rays: Vec<Option<(V3, V3)>>,
    /// The faceted solid's faces at the last turntable angle (by its bits): a frame's pixels
    /// share them.
    planes: std::sync::Mutex<Option<(u64, std::sync::Arc<Planes>)>>,
}

impl FirsScene {
    /// The scene of `spec`, with its per-pixel rays traced once.
    pub fn new(spec: FirsSceneSpec) -> Self {
        let (w, h) = (spec.camera.width, spec.camera.height);
        let rays = (0..w * h).map(|i| spec.liquid_ray(f64::from(i % w), f64::from(i / w))).collect();
        FirsScene { spec, rays, planes: std::sync::Mutex::new(None) }
    }

    fn planes_for(&self, deg: f64) -> std::sync::Arc<Planes> {
        let key = deg.to_bits();
        let mut cache = self.planes.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        match cache.as_ref() {
            Some((k, p)) if *k == key => p.clone(),
            _ => {
                let p = std::sync::Arc::new(self.spec.planes_at(deg));
                *cache = Some((key, p.clone()));
                p
            }
        }
    }

    fn board(&self, x: u32, y: u32, z: f64, tilt: f64) -> f64 {
        // 8×8 samples, each row's offset by an eighth of the column pitch (and each column's
        // by an eighth of the row pitch): 64 distinct x and 64 distinct y positions, so an
        // edge along a pixel row or column is not quantised to the grid's quarter pixels.
        const N: u32 = 8;
        let mut white = 0;
        for j in 0..N {
            for i in 0..N {
                let (fi, fj, n) = (f64::from(i), f64::from(j), f64::from(N));
                let (sx, sy) = (
                    f64::from(x) + (fi + (fj + 0.5) / n) / n - 0.5,
                    f64::from(y) + (fj + (fi + 0.5) / n) / n - 0.5,
                );
                let hit = self.spec.liquid_ray(sx, sy).and_then(|(o, d)| self.spec.plate_hit(o, d, z, tilt));
                // Behind the plate: the dark tank.
                if hit.is_some_and(|(_, xp, yp)| self.spec.target_white(xp, yp)) {
                    white += 1;
                }
            }
        }
        let f = f64::from(white) / f64::from(N * N);
        self.spec.target.lamp * (0.9 * f + 0.05 * (1.0 - f))
    }
}

impl Scene for FirsScene {
    fn size(&self) -> (u32, u32) {
        (self.spec.camera.width, self.spec.camera.height)
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        let s = &self.spec;
        let laser = state.lasers & (1u8 << s.sheet.laser) != 0;
        let pose = state.meta.get("pose");
        let target_z = pose.and_then(|p| p.get("z_mm")).and_then(|z| z.as_f64());
        let tilt = pose.and_then(|p| p.get("tilt_deg")).and_then(|t| t.as_f64()).unwrap_or(0.0).to_radians();
        let Some((o, d)) = self.rays[(y * s.camera.width + x) as usize] else { return [0.0; 3] };
        let code = state.galvos.get(usize::from(s.sheet.galvo)).map(|g| g[0]).unwrap_or(s.sheet.zero_code);
        let v = match (state.pass.as_deref(), target_z) {
            (Some("target-board"), Some(z)) => self.board(x, y, z, tilt),
            (Some("target-sweep"), Some(z)) if laser => self.spec.glow(o, d, code, Occluder::Plate(z, tilt)),
            (Some("scan"), _) if laser => {
                let deg = state.axes.get(usize::from(s.turntable_axis)).copied().unwrap_or(0.0);
                match s.object {
                    FirsObject::Sphere { radius, .. } => {
                        self.spec.glow(o, d, code, Occluder::Sphere(s.centre_at(deg), radius))
                    }
                    FirsObject::Faceted { n, .. } => {
                        let planes = self.planes_for(deg);
                        self.spec.glow(o, d, code, Occluder::Glass(&planes, n))
                    }
                    FirsObject::Matched { radius, absorb, .. } => {
                        self.spec.glow(o, d, code, Occluder::Matched(s.centre_at(deg), radius, absorb))
                    }
                }
            }
            _ => 0.0,
        };
        // Eosin's emission is green-yellow: weights of a colour camera's channels.
        [0.55 * v, v, 0.12 * v]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refraction_obeys_snell() {
        let i = normalize([0.5, 0.0, 1.0]);
        let t = refract(i, [0.0, 0.0, -1.0], 1.0 / 1.5).unwrap();
        let (si, st) = (i[0].hypot(i[1]), t[0].hypot(t[1]));
        assert!((si - 1.5 * st).abs() < 1e-12, "{si} {st}");
        // Total internal reflection.
        assert!(refract(normalize([2.0, 0.0, 1.0]), [0.0, 0.0, -1.0], 1.5).is_none());
    }

    #[test]
    fn the_optical_axis_meets_the_origin_and_rays_bend_at_the_wall() {
        let s = FirsSceneSpec::new(201, 151);
        let (o, d) = s.liquid_ray(100.0, 75.0).unwrap();
        let at = add(o, scale(d, -o[2] / d[2]));
        assert!(norm(at) < 1e-6, "{at:?}");
        // In the liquid the ray is steeper than in air (n 1.40 > 1): sin ratio = 1/1.40.
        let a = s.air_dir(100.0, 75.0);
        assert!((a[0] / d[0] - 1.40).abs() < 1e-9, "{} {}", a[0], d[0]);
    }

    #[test]
    fn the_refracted_sheet_follows_snell_at_both_faces_and_is_curved() {
        let s = FirsSceneSpec::new(64, 48);
        let wall = s.sheet.side_wall.unwrap();
        let (nl, ng) = (s.tank.n_liquid, wall.n_wall);
        // The zero code's central ray still crosses the origin at the old liquid angle.
        assert!((s.code_at([0.0; 3]) - f64::from(s.sheet.zero_code)).abs() < 1e-6, "{}", s.code_at([0.0; 3]));
        let (n, x) = (0.5f64.atan(), [0.0; 3]);
        let d = s.laser_dir_at(x);
        assert!((d[2].atan2(d[0]) - n).abs() < 1e-9, "{d:?}");
        for p in [[12.0, -25.0, 8.0], [-30.0, 30.0, -20.0], [40.0, 3.0, 35.0]] {
            let [m, a, b, q] = s.laser_path(p).unwrap();
            assert_eq!(q, p);
            assert!(
                (a[0] - (s.tank.min[0] - wall.wall_mm)).abs() < 1e-12 && (b[0] - s.tank.min[0]).abs() < 1e-12
            );
            let (d0, d1, d2) = (normalize(sub(a, m)), normalize(sub(b, a)), normalize(sub(p, b)));
            // Snell: the tangential (y, z) part of n·d is the same in air, glass and liquid
            // (same direction and size), at both faces.
            for i in [1, 2] {
                assert!((d0[i] - ng * d1[i]).abs() < 1e-12, "outer face, {i}: {d0:?} {d1:?}");
                assert!((ng * d1[i] - nl * d2[i]).abs() < 1e-12, "inner face, {i}: {d1:?} {d2:?}");
            }
            // The air ray lies in the air sheet of the code found for p: the vertical plane
            // through the mirror at that code's angle.
            let c = s.code_at(p);
            let th = s.sheet.angle0_deg.to_radians()
                + (c - f64::from(s.sheet.zero_code)) * s.sheet.urad_per_code * 1e-6;
            let normal = [-th.sin(), 0.0, th.cos()];
            assert!(dot(normal, d0).abs() < 1e-12, "{c}: {d0:?}");
            // The analytic gradient (the sheet's normal) against central differences.
            let (_, g, _) = s.code_grad(p, None);
            for i in 0..3 {
                let (mut u, mut v) = (p, p);
                u[i] += 1e-4;
                v[i] -= 1e-4;
                let fd = (s.code_at(u) - s.code_at(v)) / 2e-4;
                assert!((fd - g[i]).abs() < 1e-5 * norm(g), "{i}: {fd} vs {}", g[i]);
            }
            // And the sheet through p, as z(x, y), gives p back.
            let z = s.sheet_z(c, p[0], p[1]).unwrap();
            assert!((z - p[2]).abs() < 1e-8, "{z} vs {}", p[2]);
        }
        // Curved: sheet 32768's z at x = 0 bends by tens of µm from y = 0 to ±35 mm (a plane
        // through the vertical would not), evenly in y.
        let c = f64::from(s.sheet.zero_code);
        let z = |y: f64| s.sheet_z(c, 0.0, y).unwrap();
        let bend = z(35.0) - z(0.0);
        assert!(bend.abs() > 0.01, "{bend}");
        eprintln!("sheet {c} at x = 0: z(35) − z(0) = {bend} mm");
        assert!((z(-35.0) - z(35.0)).abs() < 1e-9);
        // The rendered glow peaks where the pixel's ray crosses that curved sheet.
        let (o, dir) = s.liquid_ray(10.0, 5.0).unwrap();
        let (nrm, xp) = s.sheet_crossing(o, dir, 32768, 50.0).unwrap();
        assert!((s.code_at(xp) - c).abs() < 1e-6);
        assert!(nrm[1].abs() > 1e-5, "the normal tilts with the bend: {nrm:?}");
    }

    #[test]
    fn the_shadow_cone_is_dark_behind_the_sphere_only() {
        let (m, c, r) = ([-700.0, 0.0, -350.0], [0.0, 0.0, 0.0], 16.0);
        let u = normalize(sub(c, m));
        // A ray across the axis 30 mm behind the centre crosses the shadow; 30 mm in front
        // (between mirror and sphere) does not.
        let behind = add(c, scale(u, 30.0));
        let s = cone_shadow(add(behind, [0.0, -50.0, 0.0]), [0.0, 1.0, 0.0], m, c, r).unwrap();
        assert!((s.0 - 50.0).abs() < 17.0 && (s.1 - 50.0).abs() < 17.0, "{s:?}");
        let front = sub(c, scale(u, 30.0));
        assert!(cone_shadow(add(front, [0.0, -50.0, 0.0]), [0.0, 1.0, 0.0], m, c, r).is_none());
    }
}
