//! The linear-light-source scene (Gardner et al. 2003): a flat sample with spatially varying
//! Ward materials, a height map and a translucency map on a light box, calibration strips of
//! known reflectance beside it, a chessboard for the camera's pose, under a light tube and a
//! laser stripe carried by the gantry.
//!
//! Geometry, millimetres, world frame: the reference plane is `z = 0`, the gantry moves the
//! tube along `x`, the tube's axis runs along `y` at height `light.height`. The camera looks
//! down at the sample from the −x side at `camera.tilt_deg` from vertical, so the tube passes
//! between camera and sample (those frames see the tube itself).
//!
//! Each pixel looks at one surface point (the first hit of its ray on the height field), so
//! its ground truth is the material, height and normal at that point, exact.

use lightrig_imaging::calib::{pixel_ray, Intrinsics, Pose};
use lightrig_pipelines::lls::linear_light::{hides, response, Quadrature, Tube};
use lightrig_pipelines::vec3::{add, normalize, scale, sub, V3};
use lightrig_pipelines::ward::Ward;
use serde::{Deserialize, Serialize};

use crate::camera::{RigState, Scene};

/// The light tube on the gantry.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LightSpec {
    /// Tube diameter, mm.
    pub diameter_mm: f64,
    /// Emitting length, mm (centred on `y = 0`).
    pub length_mm: f64,
    /// Axis height above the reference plane, mm.
    pub height_mm: f64,
    /// Axis `x` minus the gantry position, mm.
    pub offset_mm: f64,
    /// Radiance.
    pub radiance: f64,
}

/// The laser stripe on the gantry: a sheet along `y`, tilted about `y` by `angle_deg` from
/// vertical; it meets the reference plane at `x = gantry + offset_mm`, and height `z` at
/// `x = gantry + offset_mm + z·tan(angle)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StripeSpec {
    /// Where the sheet meets `z = 0`, relative to the gantry, mm.
    pub offset_mm: f64,
    /// Tilt from vertical, degrees.
    pub angle_deg: f64,
    /// Gaussian half-width (σ) of the sheet, mm.
    pub sigma_mm: f64,
    /// Radiance of a white surface in the sheet's centre (red channel).
    pub radiance: f64,
}

/// A strip of known reflectance on the reference plane.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StripSpec {
    /// Extent in `x`, mm.
    pub x_mm: [f64; 2],
    /// Extent in `y`, mm.
    pub y_mm: [f64; 2],
    /// Diffuse albedo.
    pub diffuse: f64,
    /// Specular albedo.
    pub specular: f64,
    /// Roughness.
    pub alpha: f64,
}

/// The chessboard laid on the reference plane for the pose image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoardSpec {
    /// Inner corners along `x`.
    pub cols: usize,
    /// Inner corners along `y`.
    pub rows: usize,
    /// Square size, mm.
    pub square_mm: f64,
    /// World position of the first inner corner, mm.
    pub origin_mm: [f64; 2],
}

/// The camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraSpec {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Distance from the camera to the world origin, mm.
    pub distance_mm: f64,
    /// Tilt from vertical towards −x, degrees.
    pub tilt_deg: f64,
}

impl CameraSpec {
    /// Intrinsics (no distortion) and the world → camera pose.
    pub fn model(&self) -> (Intrinsics, Pose) {
        let k = Intrinsics::pinhole(
            self.focal_px,
            self.focal_px,
            (f64::from(self.width) - 1.0) / 2.0,
            (f64::from(self.height) - 1.0) / 2.0,
        );
        let t = self.tilt_deg.to_radians();
        let centre = [-self.distance_mm * t.sin(), 0.0, self.distance_mm * t.cos()];
        // Camera axes in world coordinates: z looks at the origin, x along world +x tilted, y
        // along world −y (image rows run towards −y).
        let zc = normalize(scale(centre, -1.0));
        let yc = [0.0, -1.0, 0.0];
        let xc =
            [yc[1] * zc[2] - yc[2] * zc[1], yc[2] * zc[0] - yc[0] * zc[2], yc[0] * zc[1] - yc[1] * zc[0]];
        let r = [xc, yc, zc];
        let tvec = [0, 1, 2].map(|i| -(r[i][0] * centre[0] + r[i][1] * centre[1] + r[i][2] * centre[2]));
        (k, Pose::from_rotation(r, tvec))
    }
}

/// A smooth bump of the height map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bump {
    /// Centre, mm.
    pub at: [f64; 2],
    /// Height, mm (negative: a dent).
    pub height: f64,
    /// Gaussian σ, mm.
    pub sigma: f64,
}

/// Everything that defines the scene; saved beside the session as `scene.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LlsSceneSpec {
    /// The camera.
    pub camera: CameraSpec,
    /// The sample's extent in `x`, mm.
    pub sample_x: [f64; 2],
    /// The sample's extent in `y`, mm.
    pub sample_y: [f64; 2],
    /// Material tiles, row-major, `tiles_x` per row.
    pub tiles: Vec<Ward>,
    /// Tiles per row.
    pub tiles_x: usize,
    /// Relative amplitude of the diffuse colour's variation within a tile.
    pub texture: f64,
    /// The height map.
    pub bumps: Vec<Bump>,
    /// The light tube.
    pub light: LightSpec,
    /// The laser stripe.
    pub stripe: StripeSpec,
    /// The diffuse calibration strip.
    pub diffuse_strip: StripSpec,
    /// The specular calibration strip.
    pub specular_strip: StripSpec,
    /// The pose board.
    pub board: BoardSpec,
    /// Room light on the board, radiance of a white surface.
    pub room_radiance: f64,
    /// Light box radiance.
    pub lightbox_radiance: f64,
    /// Gantry axis.
    pub gantry_axis: u8,
    /// Laser channel of the tube.
    pub tube_channel: u8,
    /// Laser channel of the stripe.
    pub stripe_channel: u8,
    /// Laser channel of the light box.
    pub backlight_channel: u8,
}

/// Ward (1992)-like materials covering the roughness range the fit must handle.
pub fn ward_palette() -> Vec<Ward> {
    let m = |d: [f64; 3], s: f64, alpha: f64| Ward { diffuse: d, specular: [s, s * 0.97, s * 0.93], alpha };
    vec![
        m([0.30, 0.21, 0.12], 0.060, 0.040), // varnished wood
        m([0.70, 0.70, 0.66], 0.050, 0.071), // white ceramic tile
        m([0.29, 0.29, 0.31], 0.083, 0.082), // glossy grey paper
        m([0.62, 0.56, 0.40], 0.070, 0.092), // plastic laminate
        m([0.45, 0.42, 0.35], 0.060, 0.130), // ivory plastic
        m([0.12, 0.20, 0.45], 0.100, 0.160), // blue enamel
        m([0.50, 0.16, 0.10], 0.120, 0.220), // red paint
        m([0.16, 0.40, 0.16], 0.150, 0.300), // green satin
    ]
}

impl LlsSceneSpec {
    /// The default scene at `width × height` pixels.
    pub fn new(width: u32, height: u32) -> Self {
        LlsSceneSpec {
            camera: CameraSpec {
                width,
                height,
                // 110 mm of the reference plane across the image at the origin.
                focal_px: f64::from(width) * 350.0 / 110.0,
                distance_mm: 350.0,
                tilt_deg: 30.0,
            },
            sample_x: [-40.0, 40.0],
            sample_y: [-24.0, 24.0],
            tiles: ward_palette(),
            tiles_x: 4,
            texture: 0.15,
            bumps: vec![
                Bump { at: [-18.0, -8.0], height: 1.6, sigma: 9.0 },
                Bump { at: [15.0, 10.0], height: -1.2, sigma: 11.0 },
                Bump { at: [22.0, -12.0], height: 0.9, sigma: 6.0 },
                Bump { at: [-5.0, 14.0], height: 0.7, sigma: 7.0 },
            ],
            light: LightSpec {
                diameter_mm: 12.0,
                length_mm: 300.0,
                height_mm: 50.0,
                offset_mm: 0.0,
                radiance: 1.0,
            },
            stripe: StripeSpec { offset_mm: -20.0, angle_deg: 30.0, sigma_mm: 1.0, radiance: 0.12 },
            diffuse_strip: StripSpec {
                x_mm: [-40.0, 40.0],
                y_mm: [26.0, 32.0],
                diffuse: 0.8,
                specular: 0.0,
                alpha: 0.1,
            },
            specular_strip: StripSpec {
                x_mm: [-40.0, 40.0],
                y_mm: [-32.0, -26.0],
                diffuse: 0.0,
                specular: 0.04,
                alpha: 0.04,
            },
            board: BoardSpec { cols: 7, rows: 4, square_mm: 10.0, origin_mm: [-30.0, -15.0] },
            room_radiance: 0.15,
            lightbox_radiance: 0.12,
            gantry_axis: 0,
            tube_channel: 1,
            stripe_channel: 0,
            backlight_channel: 2,
        }
    }

    /// The height map, mm.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        if !self.on_sample(x, y) {
            return 0.0;
        }
        self.bumps
            .iter()
            .map(|b| {
                let (dx, dy) = (x - b.at[0], y - b.at[1]);
                b.height * (-(dx * dx + dy * dy) / (2.0 * b.sigma * b.sigma)).exp()
            })
            .sum()
    }

    /// The surface normal (from the height map's analytic gradient).
    pub fn normal(&self, x: f64, y: f64) -> V3 {
        if !self.on_sample(x, y) {
            return [0.0, 0.0, 1.0];
        }
        let (mut gx, mut gy) = (0.0, 0.0);
        for b in &self.bumps {
            let (dx, dy) = (x - b.at[0], y - b.at[1]);
            let s2 = b.sigma * b.sigma;
            let e = b.height * (-(dx * dx + dy * dy) / (2.0 * s2)).exp();
            gx -= e * dx / s2;
            gy -= e * dy / s2;
        }
        normalize([-gx, -gy, 1.0])
    }

    /// Whether `(x, y)` is on the sample.
    pub fn on_sample(&self, x: f64, y: f64) -> bool {
        x >= self.sample_x[0] && x <= self.sample_x[1] && y >= self.sample_y[0] && y <= self.sample_y[1]
    }

    fn in_strip(s: &StripSpec, x: f64, y: f64) -> bool {
        x >= s.x_mm[0] && x <= s.x_mm[1] && y >= s.y_mm[0] && y <= s.y_mm[1]
    }

    /// What is at `(x, y)`: region and material.
    pub fn material(&self, x: f64, y: f64) -> (Region, Ward) {
        let strip =
            |s: &StripSpec| Ward { diffuse: [s.diffuse; 3], specular: [s.specular; 3], alpha: s.alpha };
        if Self::in_strip(&self.diffuse_strip, x, y) {
            return (Region::DiffuseStrip, strip(&self.diffuse_strip));
        }
        if Self::in_strip(&self.specular_strip, x, y) {
            return (Region::SpecularStrip, strip(&self.specular_strip));
        }
        if !self.on_sample(x, y) {
            return (Region::Background, Ward { diffuse: [0.02; 3], specular: [0.0; 3], alpha: 0.3 });
        }
        let rows = self.tiles.len().div_ceil(self.tiles_x.max(1)).max(1);
        let u = ((x - self.sample_x[0]) / (self.sample_x[1] - self.sample_x[0])).clamp(0.0, 0.999_999);
        let v = ((y - self.sample_y[0]) / (self.sample_y[1] - self.sample_y[0])).clamp(0.0, 0.999_999);
        let (tx, ty) = ((u * self.tiles_x as f64) as usize, (v * rows as f64) as usize);
        let mut w = self.tiles[(ty * self.tiles_x + tx).min(self.tiles.len() - 1)];
        // A smooth texture on the diffuse colour, so albedo varies within tiles too.
        let t = 1.0 + self.texture * (x * 0.31).sin() * (y * 0.23 + 0.5).cos();
        w.diffuse = w.diffuse.map(|d| (d * t).min(0.95));
        (Region::Sample, w)
    }

    /// Translucency (light-box transmission) at `(x, y)`.
    pub fn translucency(&self, x: f64, y: f64) -> f64 {
        if !self.on_sample(x, y) {
            return 0.0;
        }
        0.3 + 0.2 * (x * 0.12).sin() * (y * 0.09).cos()
    }

    /// The tube for gantry position `g` on a mount turned by `yaw` radians (0: across the
    /// gantry's travel).
    pub fn tube(&self, g: f64, yaw: f64) -> Tube {
        let l = &self.light;
        Tube::through([g + l.offset_mm, 0.0, l.height_mm], yaw, l.diameter_mm / 2.0, l.length_mm)
    }
}

/// What a pixel sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Region {
    /// Nothing of interest.
    Background,
    /// The sample.
    Sample,
    /// The diffuse calibration strip.
    DiffuseStrip,
    /// The specular calibration strip.
    SpecularStrip,
}

/// One pixel's ground truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelTruth {
    /// The surface point seen, mm.
    pub point: V3,
    /// Its normal.
    pub normal: V3,
    /// Unit direction from the point to the camera.
    pub view: V3,
    /// Region.
    pub region: Region,
    /// Material.
    pub material: Ward,
    /// Light-box transmission.
    pub translucency: f64,
}

/// The scene, with every pixel's surface point found once.
pub struct LlsScene {
    /// The definition.
    pub spec: LlsSceneSpec,
    /// Per pixel, row-major.
    pub truth: Vec<PixelTruth>,
    /// Plane points of the board image, per pixel (ray ∩ z = 0), with 4×4 supersampling.
    board_points: Vec<[[f64; 2]; 16]>,
    quad: Quadrature,
}

/// First hit of the ray `o + t·d` on `z = h(x, y)`: fixed-point iteration from the plane
/// `z = 0`, which converges for surfaces whose slope along the ray is below the ray's.
fn hit_height_field(spec: &LlsSceneSpec, o: V3, d: V3) -> V3 {
    let mut t = -o[2] / d[2];
    for _ in 0..60 {
        let p = add(o, scale(d, t));
        let h = spec.height(p[0], p[1]);
        let next = (h - o[2]) / d[2];
        if (next - t).abs() < 1e-10 {
            t = next;
            break;
        }
        t = next;
    }
    add(o, scale(d, t))
}

impl LlsScene {
    /// Builds the scene: traces every pixel.
    pub fn new(spec: LlsSceneSpec) -> Self {
        let (k, pose) = spec.camera.model();
        let (w, h) = (spec.camera.width, spec.camera.height);
        let mut truth = Vec::with_capacity((w * h) as usize);
        let mut board_points = Vec::with_capacity((w * h) as usize);
        for y in 0..h {
            for x in 0..w {
                let (o, d) = pixel_ray(&k, &pose, (f64::from(x), f64::from(y)))
                    .unwrap_or(([0.0; 3], [0.0, 0.0, -1.0]));
                let p = hit_height_field(&spec, o, d);
                let (region, material) = spec.material(p[0], p[1]);
                truth.push(PixelTruth {
                    point: p,
                    normal: spec.normal(p[0], p[1]),
                    view: normalize(sub(o, p)),
                    region,
                    material,
                    translucency: spec.translucency(p[0], p[1]),
                });
                let mut sub_points = [[0.0; 2]; 16];
                for (i, s) in sub_points.iter_mut().enumerate() {
                    let (du, dv) = ((i % 4) as f64 / 4.0 - 0.375, (i / 4) as f64 / 4.0 - 0.375);
                    let (o, d) = pixel_ray(&k, &pose, (f64::from(x) + du, f64::from(y) + dv))
                        .unwrap_or(([0.0; 3], [0.0, 0.0, -1.0]));
                    let t = -o[2] / d[2];
                    *s = [o[0] + t * d[0], o[1] + t * d[1]];
                }
                board_points.push(sub_points);
            }
        }
        LlsScene { spec, truth, board_points, quad: Quadrature::render() }
    }

    /// The true sample as the camera sees it under an isotropic point light at `light` (mm) of
    /// radiant `intensity`: per pixel (row-major) the true Ward BRDF at the pixel centre's
    /// surface point times `n·ωi`·intensity/distance², unshadowed. The check for renderers'
    /// exports: a light no frame of the session used.
    pub fn point_lit(&self, light: V3, intensity: f64) -> Vec<[f64; 3]> {
        self.truth
            .iter()
            .map(|t| {
                let to = sub(light, t.point);
                let d2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2];
                let wi = normalize(to);
                let f = t.material.eval(t.normal, wi, t.view);
                let cos = (t.normal[0] * wi[0] + t.normal[1] * wi[1] + t.normal[2] * wi[2]).max(0.0);
                f.map(|v| v * cos * intensity / d2)
            })
            .collect()
    }

    fn board_white(&self, x: f64, y: f64) -> bool {
        let b = &self.spec.board;
        let (i, j) =
            (((x - b.origin_mm[0]) / b.square_mm).floor(), ((y - b.origin_mm[1]) / b.square_mm).floor());
        // The board has one square of margin beyond the inner corners; outside it, the white
        // border.
        if i < -1.0 || j < -1.0 || i > b.cols as f64 - 1.0 || j > b.rows as f64 - 1.0 {
            return true;
        }
        (i + j).rem_euclid(2.0) == 1.0
    }
}

impl Scene for LlsScene {
    fn size(&self) -> (u32, u32) {
        (self.spec.camera.width, self.spec.camera.height)
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        let i = (y * self.spec.camera.width + x) as usize;
        let s = &self.spec;
        let on = |ch: u8| state.lasers & (1u8 << ch) != 0;
        match state.pass.as_deref() {
            Some("board") => {
                let white = self.board_points[i].iter().filter(|p| self.board_white(p[0], p[1])).count();
                let r = (0.9 * white as f64 + 0.05 * (16 - white) as f64) / 16.0 * s.room_radiance;
                return [r; 3];
            }
            Some("light-box") => {
                let p = self.truth[i].point;
                let inside = p[0] >= s.sample_x[0] - 5.0
                    && p[0] <= s.sample_x[1] + 5.0
                    && p[1] >= s.sample_y[0] - 1.0
                    && p[1] <= s.sample_y[1] + 1.0;
                return [if inside && on(s.backlight_channel) { s.lightbox_radiance } else { 0.0 }; 3];
            }
            _ => {}
        }
        let t = &self.truth[i];
        let g = state.axes.get(usize::from(s.gantry_axis)).copied().unwrap_or(0.0);
        let mut out = [0.0; 3];
        if on(s.tube_channel) {
            let tube = s.tube(g, state.mount_deg.to_radians());
            if hides(t.point, t.view, &tube) {
                return [s.light.radiance; 3];
            }
            let r = response(t.point, t.normal, t.view, &tube, Some(t.material.alpha), &self.quad);
            for (c, o) in out.iter_mut().enumerate() {
                *o += s.light.radiance
                    * (t.material.diffuse[c] * r.diffuse + t.material.specular[c] * r.specular);
            }
        }
        if on(s.stripe_channel) {
            let st = &s.stripe;
            let a = st.angle_deg.to_radians();
            let e = (t.point[0] - g - st.offset_mm - t.point[2] * a.tan()) * a.cos();
            let lit = st.radiance * (-(e * e) / (2.0 * st.sigma_mm * st.sigma_mm)).exp();
            // A red laser: the camera's green and blue filters pass a little of it.
            for (c, f) in [1.0, 0.04, 0.01].into_iter().enumerate() {
                out[c] += lit * f * t.material.diffuse[c].max(t.material.diffuse[0] * 0.5);
            }
        }
        if on(s.backlight_channel) {
            let b = s.lightbox_radiance * t.translucency;
            for o in &mut out {
                *o += b;
            }
        }
        out
    }
}
