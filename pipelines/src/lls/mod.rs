//! Linear light source reflectometry (Gardner et al. 2003): per-pixel diffuse and specular
//! albedo, roughness, height, normal and translucency from a gantry pass of a light tube, a
//! pass of a laser stripe, and light-box frames.
//!
//! The steps, each a plain function:
//! 1. [`register`]: the camera's pose from the board image; each pixel's viewing ray.
//! 2. [`stripe_peak`] and [`point_on_sheet`]: each pixel's surface point from the frame where
//!    the laser sheet crosses it (sub-frame, from a Gaussian through the three samples around
//!    the peak), triangulated against the sheet.
//! 3. [`normals_from_points`]: normals from the displacement map (a plane fitted to each
//!    pixel's neighbourhood).
//! 4. [`fit_trace`]: per pixel, the Ward lobes integrated over the real tube for that pixel's
//!    point, normal and view at every frame's tube position ([`TraceModel`], one integration
//!    per trial for a whole pass); `ρd`, `ρs` per channel by linear least squares for a given
//!    `α`, and `α` by a search on the residual (a start from the trace's spread, a bracket,
//!    then parabolic steps on `log α`). The light's scale comes from the diffuse calibration
//!    strip ([`strip_scale`]).
//!    [`fit_trace_tabled`] runs the same search with the specular traces looked up in tables
//!    shared across pixels ([`LobeTables`], Gardner's reflectance tables), a lookup per frame
//!    per trial.
//! 5. Translucency: backlit over light box.
//!
//! [`linear_light`] is the independent forward model: the tube integrated numerically (the
//! virtual camera renders with it; [`TraceModel`] is tested against it).
//!
//! **Vector code.** A few innermost loops (the tables' weighted sums, the bands' quintics,
//! the normal search's sums of products) are compiled twice, for the build's baseline and for
//! AVX2, and the machine's best is picked at run time (`multiversion`). Both do the same
//! operations in the same order (Rust never fuses a product and a sum into an FMA on its
//! own), so a fit gives the same maps bit for bit on any x86-64; the AVX2 copy only does
//! four lanes at a time where the baseline does two. The session fit is some 2–3 % faster
//! for it on one thread.

mod fit;
pub mod linear_light;
mod model;
mod table;

pub use model::{Sweep, TabledTraces, TraceModel};
pub use table::{lobe_geometry, AlphaLobes, LobeGeometry, LobeTables, PixelLobes, TableLobe};

pub use fit::{
    blend_normals, blend_normals_by_gloss, fit_normal, fit_tabled_traces, fit_trace, fit_trace_ggx,
    fit_trace_tabled, normals_from_points, point_on_sheet, strip_ratio, strip_scale, strip_scale_of,
    stripe_peak, PassTrace, StripTrace, TraceFit,
};

use lightrig_imaging::calib::{find_chessboard, pixel_ray, pose_from_board, Board, Intrinsics, Pose};
use lightrig_imaging::io::Image;

use crate::vec3::V3;
use linear_light::Tube;

/// The light tube on the gantry, millimetres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Radius.
    pub radius: f64,
    /// Emitting length, centred on `y = 0`.
    pub length: f64,
    /// Axis height above the reference plane.
    pub height: f64,
    /// Axis `x` minus the gantry position.
    pub offset: f64,
}

impl Light {
    /// The tube at gantry position `g`, mounted across the gantry's travel.
    pub fn at(&self, g: f64) -> Tube {
        self.mounted(g, 0.0)
    }

    /// The tube at gantry position `g` on a mount turned by `yaw` (radians, counter-clockwise
    /// seen from above) about the vertical through its centre: the diagonal passes.
    pub fn mounted(&self, g: f64, yaw: f64) -> Tube {
        Tube::through([g + self.offset, 0.0, self.height], yaw, self.radius, self.length)
    }
}

/// The laser sheet: meets `z = 0` at `x = g + offset`, tilted by `angle` (radians) from
/// vertical, so at height `z` it is at `x = g + offset + z·tan(angle)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sheet {
    /// See above, mm.
    pub offset: f64,
    /// See above, radians.
    pub angle: f64,
}

/// A rectangle of the reference plane with a known reflectance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Strip {
    /// Extent in `x`, mm.
    pub x: [f64; 2],
    /// Extent in `y`, mm.
    pub y: [f64; 2],
    /// Known albedo (diffuse for the diffuse strip, specular for the specular one).
    pub albedo: f64,
}

impl Strip {
    /// Whether `(x, y)` lies inside, at least `margin` from the edges.
    pub fn contains(&self, p: V3, margin: f64) -> bool {
        p[0] >= self.x[0] + margin
            && p[0] <= self.x[1] - margin
            && p[1] >= self.y[0] + margin
            && p[1] <= self.y[1] - margin
    }
}

/// The chessboard for the pose image: inner corners, square size, first corner's position. The
/// square before the first inner corner (towards −x, −y) is black.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardGeometry {
    /// Inner corners along `x`.
    pub cols: usize,
    /// Inner corners along `y`.
    pub rows: usize,
    /// Square, mm.
    pub square: f64,
    /// First inner corner, mm.
    pub origin: [f64; 2],
}

/// What the fit needs to know about the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct Setup {
    /// Camera intrinsics (from `lightrig calibrate`).
    pub intrinsics: Intrinsics,
    /// The light tube.
    pub light: Light,
    /// The laser sheet.
    pub sheet: Sheet,
    /// The board.
    pub board: BoardGeometry,
    /// Diffuse calibration strip.
    pub diffuse_strip: Strip,
    /// Specular calibration strip.
    pub specular_strip: Strip,
}

/// Camera pose from the board image and every pixel's ray.
#[derive(Debug, Clone)]
pub struct Registration {
    /// World → camera.
    pub pose: Pose,
    /// Reprojection RMS of the board corners, pixels.
    pub rms: f64,
    /// Per pixel, row-major: `(origin, unit direction)`.
    pub rays: Vec<(V3, V3)>,
}

/// Failures of the fit, each saying what to check.
#[derive(Debug, Clone, PartialEq)]
pub enum LlsError {
    /// The board was not found or the pose failed.
    Registration(String),
    /// Input frames are inconsistent.
    Input(String),
    /// No usable calibration-strip pixels.
    Calibration(String),
}

impl std::fmt::Display for LlsError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LlsError::Registration(m) => write!(f, "registration: {m}"),
            LlsError::Input(m) => write!(f, "input: {m}"),
            LlsError::Calibration(m) => write!(f, "calibration: {m}"),
        }
    }
}

impl std::error::Error for LlsError {}

/// The board image's grey levels as bytes, stretched to its own range.
fn grey_bytes(img: &Image) -> Vec<u8> {
    let ch = usize::from(img.channels);
    let g: Vec<f32> = img.data.chunks(ch).map(|p| p.iter().take(3).sum::<f32>() / ch.min(3) as f32).collect();
    let (lo, hi) = g.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let span = (hi - lo).max(1e-12);
    g.iter().map(|v| ((v - lo) / span * 255.0).round() as u8).collect()
}

/// Whether the board image agrees with `pose` on the board's colours: the square before the
/// first inner corner (towards −x, −y) is black, its neighbour along +x white. (A board of even
/// × even squares looks the same turned by 180°, so boards must have an odd number of squares
/// along one side: inner corners odd × even.)
fn colours_agree(setup: &Setup, pose: &Pose, img: &Image) -> bool {
    let b = &setup.board;
    let h = b.square / 2.0;
    let grey = |x: f64, y: f64| -> Option<f32> {
        let (u, v) = lightrig_imaging::calib::project(&setup.intrinsics, pose, [x, y, 0.0])?;
        let (u, v) = (u.round(), v.round());
        if u < 0.0 || v < 0.0 || u >= f64::from(img.width) || v >= f64::from(img.height) {
            return None;
        }
        let p = img.pixel(u as u32, v as u32);
        Some(p.iter().take(3).sum())
    };
    let (o0, o1) = (b.origin[0], b.origin[1]);
    matches!((grey(o0 - h, o1 - h), grey(o0 + h, o1 - h)), (Some(black), Some(white)) if white > black)
}

/// Step 1: the pose from the board image, and every pixel's viewing ray.
pub fn register(setup: &Setup, board_image: &Image) -> Result<Registration, LlsError> {
    let (w, h) = (board_image.width as usize, board_image.height as usize);
    let b = &setup.board;
    let corners = find_chessboard(&grey_bytes(board_image), w, h, (b.cols, b.rows))
        .map_err(|e| LlsError::Registration(format!("the {}×{} board was not found: {e}", b.cols, b.rows)))?;
    let board = Board {
        points: (0..b.rows)
            .flat_map(|r| (0..b.cols).map(move |c| (r, c)))
            .map(|(r, c)| [b.origin[0] + c as f64 * b.square, b.origin[1] + r as f64 * b.square])
            .collect(),
    };
    // The detector's corner order may start at any corner of the grid: try the four, keep the
    // pose that puts the camera above the plane with the smallest residual.
    let (cols, rows) = (b.cols, b.rows);
    let mut best: Option<(Pose, f64)> = None;
    for (flip_r, flip_c) in [(false, false), (true, true), (true, false), (false, true)] {
        let pts: Vec<(f64, f64)> = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (r, c)))
            .map(|(r, c)| {
                let (r, c) = (if flip_r { rows - 1 - r } else { r }, if flip_c { cols - 1 - c } else { c });
                corners[r * cols + c]
            })
            .collect();
        if let Ok((pose, rms)) = pose_from_board(&setup.intrinsics, &pts, &board) {
            let above = pose.camera_centre()[2] > 0.0;
            if above && colours_agree(setup, &pose, board_image) && best.as_ref().is_none_or(|b| rms < b.1) {
                best = Some((pose, rms));
            }
        }
    }
    let (pose, rms) =
        best.ok_or_else(|| LlsError::Registration("no pose puts the camera above the board".into()))?;
    let mut rays = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let r = pixel_ray(&setup.intrinsics, &pose, (x as f64, y as f64))
                .ok_or_else(|| LlsError::Registration(format!("pixel ({x}, {y}) has no ray")))?;
            rays.push(r);
        }
    }
    Ok(Registration { pose, rms, rays })
}
