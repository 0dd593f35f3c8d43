//! `lightrig fit firs-surface`: a fluorescent-immersion session → surface points and meshes.
//!
//! The glue between a session on disk and [`lightrig_pipelines::firs`]:
//!
//! 1. **Rays.** Each `target-board` step's frame shows the chessboard target at the depth its
//!    `meta.pose.z_mm` gives (what the operator typed into the rig file); its corners
//!    ([`find_chessboard`]) with their world positions (`[plan.fit].target`) give a world point
//!    per pixel ([`target_world_map`]); two or more positions give a line per pixel
//!    ([`fit_pixel_rays`]), straight through the liquid whatever the wall does.
//! 2. **Sheets.** Each `target-sweep` step's sweep cuts off on the target: the surface detector
//!    finds that cut-off per pixel, and the pixel's point on the target at that sheet (galvo
//!    code, from the trigger's snapshot) is a sample of the sheet family ([`Sheet18::fit`]).
//! 3. **Surface.** Each `scan` step (one turntable orientation) is a space-time stack; the
//!    detector's cut-off per pixel, triangulated against the sheets, is the surface point.
//!    Orientations are merged with the turntable angle from the trigger snapshots about the
//!    axis in `[plan.fit].turntable`.
//!
//! Stacks are read in bands of image rows within a memory budget, transposed into the
//! detector's scanline slabs: a band's frames are decoded once per band.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use lightrig_imaging::calib::find_chessboard;
use lightrig_imaging::io::{read_with, Encoding, Image, ReadOptions};
use lightrig_pipelines::firs::calib::{
    fit_pixel_rays, target_world_map, Aabb, PixelRays, Sheet18, SheetSample, TargetView,
};
use lightrig_pipelines::firs::mesh::{
    edge_defects, enclosed_volume, write_ply, Grid, MarchingCubes, Mesh, Solid,
};
use lightrig_pipelines::firs::surface::{
    depth_to_points, grid_mesh, merge_turntable, DepthMap, SurfaceDetector, SurfaceParams,
};
use lightrig_pipelines::firs::volume::{
    median_reference, Laser, RawVolumeWriter, SliceMap, VolumeParams, ISO,
};
use lightrig_pipelines::firs::volume_stream::{ResampleStream, SegmentStream};
use lightrig_pipelines::vec3::{add, dot, normalize, scale, sub, V3};
use lightrig_protocol::event::TriggerEvent;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::fit::{fail, FitError};
use crate::session::{trigger_events, Session};

/// The `[plan.fit]` table of a fluorescent-immersion rig file: what a lab measures once.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct FirsFitSpec {
    /// The calibration target.
    pub target: TargetGeom,
    /// The calibrated working volume, mm: triangulated points must lie inside.
    pub volume: VolumeGeom,
    /// Roughly the way the laser travels across the tank (world), e.g. `[1, 0, 0]` for a laser
    /// coming in from the `−x` side; the fit turns it into the sheet's own direction.
    pub laser_dir: [f64; 3],
    /// The turntable's axis in the world frame.
    pub turntable: AxisGeom,
    /// Keep the first cut-off along the sweep (transparent objects) rather than the strongest.
    #[serde(default)]
    pub first_surface: bool,
    /// Volume mode: the world voxel size, mm (default: the slices' pixel size).
    #[serde(default)]
    pub voxel_mm: Option<f64>,
}

/// Chessboard target: `cols × rows` inner corners; corner `(i, j)` lies at
/// `(origin.x + i·square, origin.y + j·square, z)` with `z` the position's `z_mm`.
#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TargetGeom {
    pub cols: usize,
    pub rows: usize,
    pub square_mm: f64,
    pub origin_mm: [f64; 2],
}

/// An axis-aligned box, mm.
#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeGeom {
    pub min_mm: [f64; 3],
    pub max_mm: [f64; 3],
}

/// An axis: a point and a direction (turns are right-handed about it).
#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct AxisGeom {
    pub point_mm: [f64; 3],
    pub dir: [f64; 3],
}

/// One orientation's result.
#[derive(Debug, Clone)]
pub struct OrientationScan {
    /// Turntable angle, degrees (from the trigger snapshots).
    pub angle_deg: f64,
    /// Per pixel (row-major), the surface point.
    pub points: Vec<Option<V3>>,
}

/// Everything the fit produced.
#[derive(Debug, Clone)]
pub struct FirsSurface {
    /// Image size.
    pub width: usize,
    /// See `width`.
    pub height: usize,
    /// The per-pixel rays.
    pub rays: PixelRays,
    /// Pixels with a ray.
    pub ray_pixels: usize,
    /// RMS of the per-pixel line fits over pixels with more than two views, mm (0 with two).
    pub ray_rms: f64,
    /// The sheet family.
    pub sheets: Sheet18,
    /// Its samples and their RMS residual in `z`, mm.
    pub sheet_samples: usize,
    /// See `sheet_samples`.
    pub sheet_rms: f64,
    /// The laser's direction in the image, for the detector.
    pub laser_image_dir: [f64; 2],
    /// Each orientation.
    pub scans: Vec<OrientationScan>,
    /// All orientations' points in the frame of turntable angle 0.
    pub merged: Vec<V3>,
}

/// A step of the plan, as the manifest records it.
struct StepInfo {
    id: u32,
    pass: String,
    z_mm: Option<f64>,
    tilt_deg: f64,
    target: Option<u64>,
}

/// Frames of a step with their triggers, in frame order.
fn step_frames(
    session: &Session,
    dir: &Path,
    step: u32,
    triggers: &HashMap<(u32, u32), TriggerEvent>,
) -> Result<Vec<(PathBuf, TriggerEvent)>, FitError> {
    // One camera's frames (a rig may fire several together): the lowest-numbered.
    let camera = session.pipeline_camera(None).map_err(fail)?;
    let frames = session.camera_frames_of(step, camera);
    frames
        .iter()
        .map(|f| {
            let t = triggers.get(&(f.sequence, f.item)).ok_or_else(|| {
                fail(format!(
                    "{}: frame {} has no trigger record in the journal; re-acquire step {step} (`lightrig resume`)",
                    dir.display(),
                    f.file
                ))
            })?;
            Ok((dir.join(&f.file), t.clone()))
        })
        .collect()
}

fn read_frame(path: &Path) -> Result<Image, FitError> {
    let img = read_with(path, ReadOptions { assume: Encoding::Linear, expect_depth: None })
        .map_err(|e| fail(format!("{}: {e}", path.display())))?;
    if img.channels == 0 {
        return Err(fail(format!("{}: an image without channels", path.display())));
    }
    Ok(img)
}

/// Refuses a frame whose size differs from the `w × h` of `than` (the frames it is stacked
/// with): a session's stack comes from one camera at one resolution.
fn check_size(img: &Image, path: &Path, (w, h): (usize, usize), than: &str) -> Result<(), FitError> {
    if (img.width as usize, img.height as usize) == (w, h) {
        return Ok(());
    }
    Err(fail(format!(
        "{}: image size {}×{} differs from {than} ({w}×{h}); a stack needs one camera at one resolution",
        path.display(),
        img.width,
        img.height
    )))
}

/// The brightest channel's values of `img` for rows `r0..r1` (green on an RGB camera: the dye's
/// emission), or the only one.
fn channel_rows(img: &Image, r0: usize, r1: usize) -> Vec<f32> {
    let ch = usize::from(img.channels);
    let c = if ch >= 3 { 1 } else { 0 };
    let w = img.width as usize;
    (r0 * w..r1 * w).map(|i| img.data[i * ch + c]).collect()
}

/// The memory budget for one band of a stack, bytes.
const BAND_BYTES: usize = 256 << 20;

/// Runs the detector over a step's sweep (the frames with the laser on), reading the frames in
/// bands of rows. Returns the depth map in galvo codes and the image size.
fn detect_sweep(
    frames: &[(PathBuf, TriggerEvent)],
    laser_bit: u8,
    galvo: usize,
    params: SurfaceParams,
    what: &str,
    band_bytes: usize,
) -> Result<(DepthMap, (usize, usize)), FitError> {
    let lit: Vec<&(PathBuf, TriggerEvent)> =
        frames.iter().filter(|(_, t)| t.snapshot.lasers & laser_bit != 0).collect();
    if lit.len() < 5 {
        return Err(fail(format!(
            "{what}: {} frames with the sheet laser on; the sweep needs at least 5 (check [plan] sheet_positions)",
            lit.len()
        )));
    }
    let codes: Vec<f64> =
        lit.iter()
            .map(|(p, t)| {
                t.snapshot.galvos.get(galvo).map(|g| f64::from(g.x)).ok_or_else(|| {
                    fail(format!("{}: the trigger snapshot has no galvo {galvo}", p.display()))
                })
            })
            .collect::<Result<_, _>>()?;
    if codes.windows(2).any(|w| w[1] == w[0])
        || !(codes.windows(2).all(|w| w[1] > w[0]) || codes.windows(2).all(|w| w[1] < w[0]))
    {
        return Err(fail(format!("{what}: the sheet's galvo codes do not sweep monotonically")));
    }
    let first = read_frame(&lit[0].0)?;
    let (w, h) = (first.width as usize, first.height as usize);
    let n = lit.len();
    let mut det = SurfaceDetector::new(w, h, n, params).map_err(|e| fail(format!("{what}: {e}")))?;
    let band = (band_bytes / (w * n * 4).max(1)).clamp(1, h);
    let mut r0 = 0;
    let mut cache = Some(first);
    while r0 < h {
        let r1 = (r0 + band).min(h);
        let mut stack = vec![0f32; (r1 - r0) * w * n];
        for (t, (path, _)) in lit.iter().enumerate() {
            let img = match (t, cache.take()) {
                (0, Some(i)) => i,
                _ => read_frame(path)?,
            };
            check_size(&img, path, (w, h), "the sweep's first frame")?;
            for (k, v) in channel_rows(&img, r0, r1).into_iter().enumerate() {
                let (row, u) = (k / w, k % w);
                stack[(row * w + u) * n + t] = v;
            }
        }
        for row in 0..r1 - r0 {
            det.push_scanline(&stack[row * w * n..(row + 1) * w * n])
                .map_err(|e| fail(format!("{what}: {e}")))?;
        }
        r0 = r1;
    }
    let mut depth = det.finish().map_err(|e| fail(format!("{what}: {e}")))?;
    // Frame index → galvo code, linear between the frames' codes.
    for t in depth.t.iter_mut() {
        *t = t.map(|f| {
            let k = (f.floor().max(0.0) as usize).min(n - 2);
            codes[k] + (f - k as f64) * (codes[k + 1] - codes[k])
        });
    }
    Ok((depth, (w, h)))
}

/// The target's corners to a hundredth of a pixel: each detected corner is moved to the
/// saddle point of the Gaussian-blurred image. A chessboard corner is point-symmetric (two
/// straight edges crossing, whatever the perspective or the wall's local distortion), so the
/// blurred image is even about it and its gradient vanishes there: a quadratic fitted to a
/// window sampled symmetrically about the estimate has its stationary point at the corner.
/// Iterated from the detector's estimate; a corner whose fit is not a saddle or runs away
/// keeps the detector's position.
pub fn refine_saddles(
    img: &[f32],
    w: usize,
    h: usize,
    corners: &[(f64, f64)],
    sigma: f64,
) -> Vec<(f64, f64)> {
    let blurred = blur(img, w, h, sigma);
    let at = |x: f64, y: f64| -> Option<f64> {
        if x < 0.0 || y < 0.0 || x > (w - 1) as f64 || y > (h - 1) as f64 {
            return None;
        }
        let (x0, y0) = ((x.floor() as usize).min(w - 2), (y.floor() as usize).min(h - 2));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let v = |xx: usize, yy: usize| f64::from(blurred[yy * w + xx]);
        Some(
            v(x0, y0) * (1.0 - fx) * (1.0 - fy)
                + v(x0 + 1, y0) * fx * (1.0 - fy)
                + v(x0, y0 + 1) * (1.0 - fx) * fy
                + v(x0 + 1, y0 + 1) * fx * fy,
        )
    };
    let r = sigma.ceil() as i32 + 1;
    corners
        .iter()
        .map(|&(cx, cy)| {
            let (mut x, mut y) = (cx, cy);
            for _ in 0..8 {
                // Normal equations of v = a·u² + b·u·w + c·w² + d·u + e·w + f.
                let mut ata = [[0.0f64; 6]; 6];
                let mut atb = [0.0f64; 6];
                for j in -r..=r {
                    for i in -r..=r {
                        let (u, v) = (f64::from(i), f64::from(j));
                        let Some(val) = at(x + u, y + v) else { return (cx, cy) };
                        let m = [u * u, u * v, v * v, u, v, 1.0];
                        for p in 0..6 {
                            atb[p] += m[p] * val;
                            for q in 0..6 {
                                ata[p][q] += m[p] * m[q];
                            }
                        }
                    }
                }
                let Some(c) = lightrig_pipelines::linalg::solve(ata, atb) else { return (cx, cy) };
                let (a, b, cc, d, e) = (c[0], c[1], c[2], c[3], c[4]);
                let det = 4.0 * a * cc - b * b;
                // A saddle: the Hessian's determinant is negative.
                if det >= 0.0 {
                    return (cx, cy);
                }
                let dx = (-2.0 * cc * d + b * e) / det;
                let dy = (-2.0 * a * e + b * d) / det;
                x += dx;
                y += dy;
                if (x - cx).hypot(y - cy) > 2.0 {
                    return (cx, cy);
                }
                if dx.hypot(dy) < 1e-4 {
                    break;
                }
            }
            (x, y)
        })
        .collect()
}

/// Separable Gaussian blur, edges clamped.
fn blur(img: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f64> = (-r..=r).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let ks: f64 = k.iter().sum();
    let pass = |src: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (o, kv) in (-r..=r).zip(&k) {
                    let (xx, yy) = if horizontal {
                        ((x as i64 + o).clamp(0, w as i64 - 1) as usize, y)
                    } else {
                        (x, (y as i64 + o).clamp(0, h as i64 - 1) as usize)
                    };
                    acc += kv * f64::from(src[yy * w + xx]);
                }
                out[y * w + x] = (acc / ks) as f32;
            }
        }
        out
    };
    pass(&pass(img, true), false)
}

/// Mean of the colour channels, per pixel.
fn luminance(img: &Image) -> Vec<f32> {
    let ch = usize::from(img.channels);
    img.data.chunks(ch).map(|p| p.iter().take(3).sum::<f32>() / ch.min(3) as f32).collect()
}

fn gray8(img: &Image) -> Vec<u8> {
    let ch = usize::from(img.channels);
    let vals: Vec<f32> =
        img.data.chunks(ch).map(|p| p.iter().take(3).sum::<f32>() / ch.min(3) as f32).collect();
    let max = vals.iter().copied().fold(0f32, f32::max).max(1e-6);
    vals.iter().map(|v| (v / max * 255.0).round().clamp(0.0, 255.0) as u8).collect()
}

/// The detector's parameters for `spec` (thresholds relative to the lit brightness, which the
/// frames give as `[0, 1]` values).
fn params(spec: &FirsFitSpec, laser: Option<[f64; 2]>) -> SurfaceParams {
    // A transparent object casts no laser shadow and is cut by the sheet whichever way it
    // faces: no laser-direction criterion.
    let laser = if spec.first_surface { None } else { laser };
    SurfaceParams {
        strong: 0.12,
        weak: 0.05,
        max_slope: 2.0,
        laser_dir: laser,
        laser_min_descent: 0.03,
        max_step: 2.0,
        first_surface: spec.first_surface,
        min_segment: 30,
        trim: 1,
        max_kink: 1.0,
        min_dark: 3,
        min_brightness: 0.05,
    }
}

/// The laser's image direction at the volume's centre: the sheet's horizontal direction there
/// (`(1, 0, ∂f/∂x)`, signed like `rough`), mapped into the image through the rays' Jacobian.
fn laser_image_dir(
    rays: &PixelRays,
    sheets: &Sheet18,
    t_mid: f64,
    centre: V3,
    rough: V3,
) -> Option<[f64; 2]> {
    let e = 1e-3;
    let dfdx = (sheets.eval(centre[0] + e, centre[1], t_mid) - sheets.eval(centre[0] - e, centre[1], t_mid))
        / (2.0 * e);
    let mut l = normalize([1.0, 0.0, dfdx]);
    if dot(l, rough) < 0.0 {
        l = scale(l, -1.0);
    }
    let nearest = |x: usize, y: usize| -> Option<V3> {
        let r = rays.get(x, y)?;
        Some(r.at(dot(sub(centre, r.origin), r.dir)))
    };
    // The pixel whose ray passes nearest the centre.
    let (mut best, mut bd) = (None, f64::INFINITY);
    for y in 1..rays.height.saturating_sub(1) {
        for x in 1..rays.width.saturating_sub(1) {
            if let Some(p) = nearest(x, y) {
                let d = lightrig_pipelines::vec3::norm(sub(p, centre));
                if d < bd {
                    (best, bd) = (Some((x, y)), d);
                }
            }
        }
    }
    let (x, y) = best?;
    let ju = scale(sub(nearest(x + 1, y)?, nearest(x - 1, y)?), 0.5);
    let jv = scale(sub(nearest(x, y + 1)?, nearest(x, y - 1)?), 0.5);
    let d = rays.get(x, y)?.dir;
    let lp = sub(l, scale(d, dot(l, d)));
    // Least squares [ju jv]·(a, b) = lp.
    let (a11, a12, a22) = (dot(ju, ju), dot(ju, jv), dot(jv, jv));
    let (b1, b2) = (dot(ju, lp), dot(jv, lp));
    let det = a11 * a22 - a12 * a12;
    if det.abs() < 1e-300 {
        return None;
    }
    let (a, b) = ((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
    let n = a.hypot(b);
    (n > 0.0).then(|| [a / n, b / n])
}

/// Fits a fluorescent-immersion session's surface. `progress(done, total)` is called after each
/// sweep.
pub fn fit_surface(dir: &Path, progress: &dyn Fn(u64, u64)) -> Result<FirsSurface, FitError> {
    fit_surface_banded(dir, BAND_BYTES, progress)
}

/// [`fit_surface`] reading each stack in bands of at most `band_bytes` of samples (at least
/// one image row per band).
pub fn fit_surface_banded(
    dir: &Path,
    band_bytes: usize,
    progress: &dyn Fn(u64, u64),
) -> Result<FirsSurface, FitError> {
    let c = calibrate(dir, band_bytes, progress)?;
    let (w, h, mut done) = (c.w, c.h, c.done);
    // 3. Surface per orientation.
    let centre = scale(add(c.volume.min, c.volume.max), 0.5);
    let laser = laser_image_dir(&c.rays, &c.sheets, c.t_mid, centre, c.spec.laser_dir).ok_or_else(|| {
        fail(format!(
            "{}: no ray passes near the volume's centre {centre:?}; check [plan.fit].volume",
            dir.display()
        ))
    })?;
    let mut scans = Vec::new();
    for s in c.steps.iter().filter(|s| s.pass == "scan") {
        let frames = step_frames(&c.session, dir, s.id, &c.triggers)?;
        let Some((_, t0)) = frames.first() else { continue };
        let steps_at = t0.snapshot.axes.get(usize::from(c.table.axis)).copied().unwrap_or(0);
        let angle_deg = c.table.units(i64::from(steps_at)).unwrap_or(f64::from(steps_at));
        let what = format!("{}: step {}", dir.display(), s.id);
        let (depth, size) =
            detect_sweep(&frames, c.laser_bit, c.galvo, params(&c.spec, Some(laser)), &what, band_bytes)?;
        if size != (w, h) {
            return Err(fail(format!("{what}: frame size differs from the board frames'")));
        }
        let points = depth_to_points(&depth, &c.rays, &c.sheets, &c.volume)
            .map_err(|e| fail(format!("{what}: {e}")))?;
        scans.push(OrientationScan { angle_deg, points });
        done += 1;
        progress(done, c.sweeps);
    }
    if scans.is_empty() {
        return Err(fail(format!("{}: the session has no scan steps with frames", dir.display())));
    }
    let flat: Vec<(f64, Vec<V3>)> = scans
        .iter()
        .map(|s| (s.angle_deg.to_radians(), s.points.iter().flatten().copied().collect()))
        .collect();
    let refs: Vec<(f64, &[V3])> = flat.iter().map(|(a, p)| (*a, p.as_slice())).collect();
    let merged = merge_turntable(&refs, c.spec.turntable.point_mm, c.spec.turntable.dir);
    Ok(FirsSurface {
        width: w,
        height: h,
        rays: c.rays,
        ray_pixels: c.ray_pixels,
        ray_rms: c.ray_rms,
        sheets: c.sheets,
        sheet_samples: c.sheet_samples,
        sheet_rms: c.sheet_rms,
        laser_image_dir: laser,
        scans,
        merged,
    })
}

fn calibrate(dir: &Path, band_bytes: usize, progress: &dyn Fn(u64, u64)) -> Result<Calibration, FitError> {
    let (session, _) = Session::read(dir).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let manifest = session.manifest().clone();
    let rig = crate::fit::session_rig(&manifest.rig, dir)?;
    let spec: FirsFitSpec = crate::fit::plan_fit(&rig)
        .ok_or_else(|| {
            fail(format!(
                "{}: the rig file has no [plan.fit] table (target, volume, laser_dir, turntable); see docs/rigs/fluorescent-immersion.toml",
                dir.display()
            ))
        })?
        .map_err(|e| fail(e.to_string()))?;
    let galvo = rig
        .galvos
        .first()
        .map(|g| usize::from(g.galvo))
        .ok_or_else(|| fail("the rig file has no [[galvo]]"))?;
    let laser_bit =
        rig.lasers.first().map(|l| 1u8 << l.channel).ok_or_else(|| fail("the rig file has no [[laser]]"))?;
    let table = rig
        .stepper_named("turntable")
        .or_else(|| rig.steppers.first())
        .ok_or_else(|| fail("the rig file has no turntable stepper"))?
        .clone();
    let triggers = trigger_events(dir).map_err(|e| fail(e.to_string()))?;
    let steps: Vec<StepInfo> = manifest
        .plan
        .steps
        .iter()
        .map(|s| {
            let m = &s.extra["meta"];
            StepInfo {
                id: s.id,
                pass: m["pass"].as_str().or_else(|| m["kind"].as_str()).unwrap_or("").to_string(),
                z_mm: m["pose"]["z_mm"].as_f64(),
                tilt_deg: m["pose"]["tilt_deg"].as_f64().unwrap_or(0.0),
                target: m["target"].as_u64(),
            }
        })
        .collect();
    let volume = Aabb { min: spec.volume.min_mm, max: spec.volume.max_mm };
    let sweeps = steps.iter().filter(|s| s.pass == "target-sweep" || s.pass == "scan").count() as u64;
    let mut done = 0;

    // 1. Rays from the target's board frames, front to back.
    let mut boards: Vec<&StepInfo> = steps.iter().filter(|s| s.pass == "target-board").collect();
    boards.sort_by(|a, b| a.z_mm.unwrap_or(0.0).total_cmp(&b.z_mm.unwrap_or(0.0)));
    if boards.len() < 2 {
        return Err(fail(format!(
            "{}: {} calibration target positions; the per-pixel rays need at least 2 (add [plan] calibration_targets = [{{ z_mm = … }}, {{ z_mm = … }}] and re-acquire)",
            dir.display(),
            boards.len()
        )));
    }
    let tg = spec.target;
    let mut maps: HashMap<u64, Vec<Option<V3>>> = HashMap::new();
    let mut ordered = Vec::new();
    let (mut w, mut h) = (0, 0);
    for b in &boards {
        let z = b.z_mm.ok_or_else(|| {
            fail(format!("{}: step {}: the target's pose has no z_mm", dir.display(), b.id))
        })?;
        let tilt = b.tilt_deg;
        let frames = step_frames(&session, dir, b.id, &triggers)?;
        let (path, _) = frames.first().ok_or_else(|| {
            fail(format!(
                "{}: step {} (target board) has no frame; re-acquire it (`lightrig resume`)",
                dir.display(),
                b.id
            ))
        })?;
        let img = read_frame(path)?;
        (w, h) = (img.width as usize, img.height as usize);
        let corners = find_chessboard(&gray8(&img), w, h, (tg.cols, tg.rows)).map_err(|e| {
            fail(format!(
                "{}: the {}×{} target's corners: {e}; check [plan.fit].target and that the whole board is in view",
                path.display(),
                tg.cols,
                tg.rows
            ))
        })?;
        // Blur on the scale of a fifth of a square (in pixels, from the detected grid).
        let pitch = corners
            .windows(2)
            .take(tg.cols - 1)
            .map(|p| (p[1].0 - p[0].0).hypot(p[1].1 - p[0].1))
            .sum::<f64>()
            / (tg.cols - 1) as f64;
        let corners = refine_saddles(&luminance(&img), w, h, &corners, (pitch / 5.0).clamp(1.0, 4.0));
        let view = TargetView {
            cols: tg.cols,
            rows: tg.rows,
            pixels: corners.iter().map(|&(x, y)| [x, y]).collect(),
            // The plate through (0, 0, z), turned by the pose's tilt about y: its x' axis runs
            // along (cos, 0, sin).
            world: (0..tg.rows)
                .flat_map(|j| {
                    let a = tilt.to_radians();
                    (0..tg.cols).map(move |i| {
                        let xp = tg.origin_mm[0] + i as f64 * tg.square_mm;
                        [xp * a.cos(), tg.origin_mm[1] + j as f64 * tg.square_mm, z + xp * a.sin()]
                    })
                })
                .collect(),
        };
        let map = target_world_map(&view, w, h).map_err(|e| fail(format!("{}: {e}", path.display())))?;
        ordered.push(map.clone());
        if let Some(k) = b.target {
            maps.insert(k, map);
        }
    }
    let rays = fit_pixel_rays(w, h, &ordered).map_err(|e| fail(format!("{}: rays: {e}", dir.display())))?;
    let ray_pixels = rays.rays.iter().flatten().count();
    let ray_rms = if ordered.len() > 2 {
        let v: Vec<f64> = rays.rays.iter().flatten().map(|r| r.rms * r.rms).collect();
        (v.iter().sum::<f64>() / v.len().max(1) as f64).sqrt()
    } else {
        0.0
    };

    // 2. Sheets from the cut-off on the target.
    let mut samples = Vec::new();
    for s in steps.iter().filter(|s| s.pass == "target-sweep") {
        let map = s.target.and_then(|k| maps.get(&k)).ok_or_else(|| {
            fail(format!("{}: step {}: a target sweep without its target's board frame", dir.display(), s.id))
        })?;
        let frames = step_frames(&session, dir, s.id, &triggers)?;
        let (depth, size) = detect_sweep(
            &frames,
            laser_bit,
            galvo,
            params(&spec, None),
            &format!("{}: step {}", dir.display(), s.id),
            band_bytes,
        )?;
        if size != (w, h) {
            return Err(fail(format!(
                "{}: step {}: frame size differs from the board frames'",
                dir.display(),
                s.id
            )));
        }
        for (i, t) in depth.t.iter().enumerate() {
            if let (Some(t), Some(p)) = (t, map[i]) {
                samples.push(SheetSample { p, t: *t });
            }
        }
        done += 1;
        progress(done, sweeps);
    }
    let mut sheets = Sheet18::fit(&samples).map_err(|e| {
        fail(format!(
            "{}: sheets: {e}; the target sweeps must show the sheet on the target at both positions",
            dir.display()
        ))
    })?;
    // One pass of outlier rejection: detections off the target's edge.
    let rms0 = sheets.residual_rms(&samples);
    let kept: Vec<SheetSample> = samples
        .iter()
        .copied()
        .filter(|s| (s.p[2] - sheets.eval(s.p[0], s.p[1], s.t)).abs() <= 4.0 * rms0)
        .collect();
    if kept.len() >= 18 && kept.len() < samples.len() {
        sheets = Sheet18::fit(&kept).map_err(|e| fail(format!("{}: sheets: {e}", dir.display())))?;
    }
    let sheet_rms = sheets.residual_rms(&kept);

    let t_mid = samples.iter().map(|s| s.t).sum::<f64>() / samples.len().max(1) as f64;
    Ok(Calibration {
        session,
        triggers,
        steps,
        spec,
        galvo,
        laser_bit,
        table,
        volume,
        rays,
        ray_pixels,
        ray_rms,
        sheets,
        sheet_samples: kept.len(),
        sheet_rms,
        t_mid,
        w,
        h,
        done,
        sweeps,
    })
}

/// What the calibration steps give both modes.
struct Calibration {
    session: Session,
    triggers: HashMap<(u32, u32), TriggerEvent>,
    steps: Vec<StepInfo>,
    spec: FirsFitSpec,
    galvo: usize,
    laser_bit: u8,
    table: crate::rigfile::Stepper,
    volume: Aabb,
    rays: PixelRays,
    ray_pixels: usize,
    ray_rms: f64,
    sheets: Sheet18,
    sheet_samples: usize,
    sheet_rms: f64,
    /// Mean sheet parameter of the samples.
    t_mid: f64,
    w: usize,
    h: usize,
    /// Sweeps processed so far, of `sweeps`.
    done: u64,
    sweeps: u64,
}

/// Writes `orientation_NN.ply` (a mesh per orientation, edges up to 1 mm), `merged.ply` (all
/// points in the frame of turntable angle 0, no faces) and `summary.json` into `out`.
pub fn write_outputs(s: &FirsSurface, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    let io = |p: &Path, e: std::io::Error| fail(format!("{}: {e}", p.display()));
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let mut files = Vec::new();
    let write = |path: PathBuf, mesh: &Mesh| -> Result<PathBuf, FitError> {
        let f = std::fs::File::create(&path).map_err(|e| io(&path, e))?;
        let mut b = std::io::BufWriter::new(f);
        write_ply(mesh, &mut b).map_err(|e| io(&path, e))?;
        Ok(path)
    };
    for (k, scan) in s.scans.iter().enumerate() {
        let mesh = grid_mesh(&scan.points, s.width, s.height, 1.0).map_err(|e| fail(e.to_string()))?;
        files.push(write(out.join(format!("orientation_{k:02}.ply")), &mesh)?);
    }
    files.push(write(out.join("merged.ply"), &Mesh { vertices: s.merged.clone(), triangles: Vec::new() })?);
    let summary = serde_json::json!({
        "image": [s.width, s.height],
        "ray_pixels": s.ray_pixels,
        "ray_rms_mm": s.ray_rms,
        "sheet_samples": s.sheet_samples,
        "sheet_rms_mm": s.sheet_rms,
        "laser_image_dir": s.laser_image_dir,
        "orientations": s.scans.iter().map(|o| serde_json::json!({
            "angle_deg": o.angle_deg,
            "points": o.points.iter().flatten().count(),
        })).collect::<Vec<_>>(),
        "merged_points": s.merged.len(),
    });
    let p = out.join("summary.json");
    let text = serde_json::to_string_pretty(&summary).map_err(|e| fail(e.to_string()))?;
    std::fs::write(&p, text + "\n").map_err(|e| io(&p, e))?;
    files.push(p);
    Ok(files)
}

/// Volume mode's result. The occupancy volume itself went to `volume.raw` as it was computed.
#[derive(Debug, Clone)]
pub struct FirsVolume {
    /// Pixels with a ray.
    pub ray_pixels: usize,
    /// The sheet family's samples and RMS residual, mm.
    pub sheet_samples: usize,
    /// See `sheet_samples`.
    pub sheet_rms: f64,
    /// Where the slices' samples sit in the world (fitted to the rays and sheets).
    pub map: SliceMap,
    /// RMS distance of the rays' and sheets' points from that affine map, mm.
    pub map_rms: f64,
    /// The world grid.
    pub grid: Grid,
    /// The surface at occupancy 0.5.
    pub mesh: Mesh,
    /// The volume it encloses, mm³.
    pub enclosed_mm3: f64,
    /// `volume.raw`, the occupancy per voxel (x fastest), 0 liquid, 1 object, and its
    /// descriptions `volume.json` and `volume.nhdr` (a detached NRRD header).
    pub raw: [PathBuf; 3],
    /// What the streamed steps held (slices of the sweep).
    pub held: VolumeMemory,
}

/// What volume mode held at most: the reference pass's band of rows over the whole sweep, then
/// float slices per streamed step (none of it grows with the sweep's length but the band, which
/// the budget bounds).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct VolumeMemory {
    /// Image rows per band of the reference pass (the per-pixel median needs a pixel's whole
    /// sweep); bands of `rows × width × frames` floats within the memory budget.
    pub reference_band_rows: usize,
    /// Bands of the reference pass (each decodes the sweep's frames once).
    pub reference_bands: usize,
    /// Frames decoded together in the segmentation pass (one per thread).
    pub batch_frames: usize,
    /// The blocked-streak fill's slab, slices.
    pub fill_slices: usize,
    /// Slices waiting for the small-region decision.
    pub clean_slices: usize,
    /// Slices the resampling held.
    pub resample_slices: usize,
    /// Blocked streaks deeper than the fill's slab (filled approximately).
    pub forced_fills: usize,
}

/// Fits a volume-mode session (index-matched object, sheet and camera at about 90°): the
/// calibration as for the surface, then the first scan step's sweep segmented slice by slice
/// against the median of the sweep (the reference: the object must cover each pixel in fewer
/// than half the sheets), resampled to world voxels through the affine slice map fitted to
/// the calibrated rays and sheets, and meshed by marching cubes. Streamed: the reference is
/// taken in bands of rows, then the frames go through the steps a few at a time and the
/// occupancy volume is written to `out/volume.raw` (+ `volume.json`, `volume.nhdr`) z-slice by z-slice.
pub fn fit_volume(dir: &Path, out: &Path, progress: &dyn Fn(u64, u64)) -> Result<FirsVolume, FitError> {
    fit_volume_banded(dir, out, BAND_BYTES, progress)
}

/// [`fit_volume`] with the reference pass's band budget in bytes (tests use a small one).
pub fn fit_volume_banded(
    dir: &Path,
    out: &Path,
    band_bytes: usize,
    progress: &dyn Fn(u64, u64),
) -> Result<FirsVolume, FitError> {
    let c = calibrate(dir, BAND_BYTES, progress)?;
    let (w, h) = (c.w, c.h);
    let s = c.steps.iter().find(|s| s.pass == "scan").ok_or_else(|| {
        fail(format!("{}: the session has no scan step; acquire with [plan] views = 1", dir.display()))
    })?;
    let what = format!("{}: step {}", dir.display(), s.id);
    let frames = step_frames(&c.session, dir, s.id, &c.triggers)?;
    let lit: Vec<&PathBuf> =
        frames.iter().filter(|(_, t)| t.snapshot.lasers & c.laser_bit != 0).map(|(p, _)| p).collect();
    let codes: Vec<f64> = frames
        .iter()
        .filter(|(_, t)| t.snapshot.lasers & c.laser_bit != 0)
        .map(|(_, t)| t.snapshot.galvos.get(c.galvo).map_or(f64::NAN, |g| f64::from(g.x)))
        .collect();
    let n = codes.len();
    if n < 5 || codes.iter().any(|c| !c.is_finite()) {
        return Err(fail(format!(
            "{what}: {n} frames with the sheet on and its galvo code; the volume needs a sweep"
        )));
    }
    let step = (codes[n - 1] - codes[0]) / (n - 1) as f64;
    if codes.iter().enumerate().any(|(k, &c)| (c - codes[0] - step * k as f64).abs() > 0.01 * step.abs()) {
        return Err(fail(format!(
            "{what}: the sheets are not evenly spaced (codes {} to {} in {n}); make max_code − min_code a multiple of sheet_positions − 1",
            codes[0],
            codes[n - 1]
        )));
    }
    let centre = scale(add(c.volume.min, c.volume.max), 0.5);
    let laser_img =
        laser_image_dir(&c.rays, &c.sheets, c.t_mid, centre, c.spec.laser_dir).ok_or_else(|| {
            fail(format!(
                "{what}: no ray passes near the volume's centre {centre:?}; check [plan.fit].volume"
            ))
        })?;
    if laser_img[0].abs() < 0.9 {
        return Err(fail(format!(
            "{what}: the laser runs along image direction {laser_img:?}; volume mode needs it along the image rows (turn the camera)"
        )));
    }
    let laser = if laser_img[0] > 0.0 { Laser::PlusU } else { Laser::MinusU };
    let params = VolumeParams { laser, ..VolumeParams::default() };
    let (map, map_rms) = slice_map(&c, &codes, &what)?;
    let voxel = c.spec.voxel_mm.unwrap_or_else(|| lightrig_pipelines::vec3::norm(map.u_step));
    if !voxel.is_finite() || voxel <= 0.0 || map_rms > 0.25 * voxel {
        return Err(fail(format!(
            "{what}: the slices are not an affine map of the world ({:.3} mm RMS off it, voxel {voxel:.3} mm): volume mode needs a telecentric camera at about 90° to parallel sheets",
            map_rms
        )));
    }
    // The grid: the stack's world box within the calibrated volume.
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for (u, v, k) in [(0, 0, 0), (w - 1, 0, 0), (0, h - 1, 0), (w - 1, h - 1, 0)]
        .into_iter()
        .flat_map(|(u, v, _)| [(u, v, 0), (u, v, n - 1)])
    {
        let q = add(
            add(map.origin, scale(map.u_step, u as f64)),
            add(scale(map.v_step, v as f64), scale(map.slice_step, k as f64)),
        );
        for d in 0..3 {
            lo[d] = lo[d].min(q[d]).max(c.volume.min[d]);
            hi[d] = hi[d].max(q[d]).min(c.volume.max[d]);
        }
    }
    let dims = [0, 1, 2].map(|d| (((hi[d] - lo[d]) / voxel).floor() as usize + 1).max(2));
    let grid = Grid { dims, voxel: [voxel; 3], origin: lo };

    // Pass 1, the reference: the per-pixel median over the sweep, in bands of rows.
    let band = (band_bytes / (w * n * 4).max(1)).clamp(1, h);
    let mut reference = Vec::with_capacity(w * h);
    let mut bands = 0;
    let mut r0 = 0;
    while r0 < h {
        let r1 = (r0 + band).min(h);
        let rows: Vec<Vec<f32>> = lit
            .iter()
            .map(|path| {
                let img = read_frame(path)?;
                check_size(&img, path, (w, h), "the board frames'")?;
                Ok(channel_rows(&img, r0, r1))
            })
            .collect::<Result<_, _>>()?;
        let refs: Vec<&[f32]> = rows.iter().map(Vec::as_slice).collect();
        reference.extend(median_reference(&refs, w, r1 - r0).map_err(|e| fail(format!("{what}: {e}")))?);
        bands += 1;
        r0 = r1;
    }

    // Pass 2: the frames through the streamed steps, a thread's worth at a time, in the order
    // the world grid's z-slices read them; each z-slice out to marching cubes and the file.
    let mut resampler =
        ResampleStream::new(&map, &grid, w, h, n).map_err(|e| fail(format!("{what}: resampling: {e}")))?;
    let reverse = resampler.reversed();
    let mut seg = SegmentStream::new(reference, w, h, n, reverse, &params)
        .map_err(|e| fail(format!("{what}: segmentation: {e}")))?;
    let mut mc = MarchingCubes::new(grid, ISO, Solid::Above).map_err(|e| fail(format!("{what}: {e:?}")))?;
    std::fs::create_dir_all(out).map_err(|e| fail(format!("{}: {e}", out.display())))?;
    let stem = out.join("volume");
    let mut raw =
        RawVolumeWriter::create(&stem, &grid).map_err(|e| fail(format!("{}: {e}", stem.display())))?;
    let mut zslice = vec![0f32; dims[0] * dims[1]];
    let mut drain =
        |seg: &mut SegmentStream, rs: &mut ResampleStream, finished: bool| -> Result<(), FitError> {
            let mut emit = |rs: &mut ResampleStream, finished: bool| -> Result<(), FitError> {
                while rs.next(&mut zslice, finished).map_err(|e| fail(format!("{what}: {e}")))?.is_some() {
                    mc.push(&zslice).map_err(|e| fail(format!("{what}: {e:?}")))?;
                    raw.push(&zslice).map_err(|e| fail(format!("{}: {e}", stem.display())))?;
                }
                Ok(())
            };
            while let Some((k, o)) = seg.pop() {
                rs.push(k, o).map_err(|e| fail(format!("{what}: {e}")))?;
                emit(rs, false)?;
            }
            if finished {
                emit(rs, true)?;
            }
            Ok(())
        };
    let order: Vec<&PathBuf> = if reverse { lit.iter().rev().copied().collect() } else { lit.clone() };
    let batch = rayon::current_num_threads().max(1);
    for paths in order.chunks(batch) {
        let imgs: Vec<Vec<f32>> = paths
            .par_iter()
            .map(|path| {
                let img = read_frame(path)?;
                check_size(&img, path, (w, h), "the board frames'")?;
                Ok(channel_rows(&img, 0, h))
            })
            .collect::<Result<_, _>>()?;
        let refs: Vec<&[f32]> = imgs.iter().map(Vec::as_slice).collect();
        seg.push_many(&refs).map_err(|e| fail(format!("{what}: {e}")))?;
        drain(&mut seg, &mut resampler, false)?;
    }
    seg.finish().map_err(|e| fail(format!("{what}: {e}")))?;
    drain(&mut seg, &mut resampler, true)?;
    let mesh = mc.finish().map_err(|e| fail(format!("{what}: {e:?}")))?;
    raw.finish().map_err(|e| fail(format!("{}: {e}", stem.display())))?;
    let st = seg.stats();
    progress(c.sweeps, c.sweeps);
    Ok(FirsVolume {
        ray_pixels: c.ray_pixels,
        sheet_samples: c.sheet_samples,
        sheet_rms: c.sheet_rms,
        map,
        map_rms,
        grid,
        enclosed_mm3: enclosed_volume(&mesh),
        mesh,
        raw: [out.join("volume.raw"), out.join("volume.json"), out.join("volume.nhdr")],
        held: VolumeMemory {
            reference_band_rows: band,
            reference_bands: bands,
            batch_frames: batch,
            fill_slices: st.max_fill_slices,
            clean_slices: st.max_clean_slices,
            resample_slices: resampler.max_window(),
            forced_fills: st.forced_fills,
        },
    })
}

/// The slice map: least squares of the calibrated rays against the calibrated sheets,
/// `p = o + u·a + v·b + s·c`, and its RMS residual, mm.
fn slice_map(c: &Calibration, codes: &[f64], what: &str) -> Result<(SliceMap, f64), FitError> {
    let (w, h, n) = (c.w, c.h, codes.len());
    let mut ata = [[0.0f64; 4]; 4];
    let mut atb = [[0.0f64; 3]; 4];
    let mut pts = Vec::new();
    for v in (0..h).step_by(4) {
        for u in (0..w).step_by(4) {
            let Some(r) = c.rays.get(u, v) else { continue };
            for k in [0, n / 4, n / 2, 3 * n / 4, n - 1] {
                let Some((_, p)) = c.sheets.intersect(r, codes[k], &c.volume) else { continue };
                let m = [1.0, u as f64, v as f64, k as f64];
                for i in 0..4 {
                    for j in 0..4 {
                        ata[i][j] += m[i] * m[j];
                    }
                    for d in 0..3 {
                        atb[i][d] += m[i] * p[d];
                    }
                }
                pts.push((m, p));
            }
        }
    }
    let column =
        |d: usize| lightrig_pipelines::linalg::solve(ata, [atb[0][d], atb[1][d], atb[2][d], atb[3][d]]);
    let (sx, sy, sz) = match (column(0), column(1), column(2)) {
        (Some(x), Some(y), Some(z)) => (x, y, z),
        _ => return Err(fail(format!("{what}: the rays and sheets do not determine the slice map"))),
    };
    let col = |i: usize| [sx[i], sy[i], sz[i]];
    let map = SliceMap { origin: col(0), u_step: col(1), v_step: col(2), slice_step: col(3) };
    let map_rms = (pts
        .iter()
        .map(|(m, p)| {
            let q = add(
                add(map.origin, scale(map.u_step, m[1])),
                add(scale(map.v_step, m[2]), scale(map.slice_step, m[3])),
            );
            lightrig_pipelines::vec3::norm(sub(q, *p)).powi(2)
        })
        .sum::<f64>()
        / pts.len().max(1) as f64)
        .sqrt();
    Ok((map, map_rms))
}

/// Writes `volume.ply` (the closed surface) and `summary.json` into `out`, beside the
/// `volume.raw` + `volume.json` + `volume.nhdr` (the occupancy volume, see [`RawVolumeWriter`]) the fit wrote;
/// returns the four files.
pub fn write_volume_outputs(v: &FirsVolume, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    let io = |p: &Path, e: std::io::Error| fail(format!("{}: {e}", p.display()));
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let ply = out.join("volume.ply");
    let f = std::fs::File::create(&ply).map_err(|e| io(&ply, e))?;
    write_ply(&v.mesh, &mut std::io::BufWriter::new(f)).map_err(|e| io(&ply, e))?;
    let d = edge_defects(&v.mesh);
    let summary = serde_json::json!({
        "ray_pixels": v.ray_pixels,
        "sheet_samples": v.sheet_samples,
        "sheet_rms_mm": v.sheet_rms,
        "slice_map": { "origin": v.map.origin, "u_step": v.map.u_step, "v_step": v.map.v_step, "slice_step": v.map.slice_step, "rms_mm": v.map_rms },
        "grid": { "dims": v.grid.dims, "voxel_mm": v.grid.voxel, "origin_mm": v.grid.origin },
        "triangles": v.mesh.triangles.len(),
        "enclosed_mm3": v.enclosed_mm3,
        "closed": d.boundary == 0 && d.non_manifold == 0 && d.misoriented == 0,
        "held": v.held,
    });
    let p = out.join("summary.json");
    let text = serde_json::to_string_pretty(&summary).map_err(|e| fail(e.to_string()))?;
    std::fs::write(&p, text + "\n").map_err(|e| io(&p, e))?;
    let [raw, json, nhdr] = v.raw.clone();
    Ok(vec![ply, raw, json, nhdr, p])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_of_another_size_is_refused_with_both_sizes() {
        let img = Image { width: 4, height: 3, channels: 1, data: vec![0.0; 12], encoding: Encoding::Linear };
        let path = Path::new("frames/f_0007.png");
        assert!(check_size(&img, path, (4, 3), "the board frames'").is_ok());
        let e = check_size(&img, path, (5, 3), "the board frames'").unwrap_err();
        assert_eq!(
            e.0,
            "frames/f_0007.png: image size 4×3 differs from the board frames' (5×3); a stack needs one \
             camera at one resolution"
        );
    }
}
