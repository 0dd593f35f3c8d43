//! `lightrig fit lls`: a linear-light-source session → per-pixel reflectance maps.
//!
//! This module is the glue between a session on disk and the maths in
//! [`lightrig_pipelines::lls`]: it reads the rig file from the session's manifest (the fit's
//! geometry lives in its `[plan.fit]` table), the camera's calibration file (from
//! `lightrig calibrate`), the frames of each pass with their trigger records (the gantry
//! position of every frame comes from the trigger's snapshot, not from the plan), merges
//! exposure brackets, runs the fit and writes the maps.
//!
//! With diagonal passes (`reflectance+15`, `reflectance-15` in the rig file's passes) the
//! normals from the displacement map are refined by the reflectance traces of those passes
//! ([`fit_normal`]), blended ([`blend_normals`]), and the straight pass is fitted once more
//! with the blended normals, as Gardner et al. do.

pub mod export;
pub mod gltf;
pub mod quality;
pub mod stack;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use lightrig_imaging::calib::{Intrinsics, Pose};
use lightrig_imaging::io::{write_exr_layers, write_png, BitDepth, Encoding, ExrPrecision, Image, Layer};
use lightrig_pipelines::lls::{
    blend_normals, blend_normals_by_gloss, fit_normal, fit_tabled_traces, fit_trace_ggx, normals_from_points,
    point_on_sheet, register, strip_ratio, strip_scale_of, stripe_peak, BoardGeometry, Light, LobeTables,
    PassTrace, Registration, Setup, Sheet, Strip, Sweep, TabledTraces, TraceFit, TraceModel,
};
use lightrig_pipelines::vec3::{normalize, sub, V3};
use lightrig_pipelines::ward::Ward;
use rayon::prelude::*;
use serde::Deserialize;

use crate::fit::{fail, FitError};
use crate::response::CameraResponse;
use crate::session::{trigger_events, Session};
use stack::{block_pixels, Block, Gathered, TraceStack};

/// The `[plan.fit]` table of a linear-light-source rig file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FitSpec {
    /// Camera intrinsics, pixels, without distortion: for rigs without a calibration file
    /// (`lightrig fit lls --calibration cam.toml` takes precedence).
    pub camera: Option<CameraIntrinsics>,
    /// The light tube.
    pub light: LightGeom,
    /// The laser sheet.
    pub stripe: SheetGeom,
    /// The pose board.
    pub board: BoardGeom,
    /// The diffuse calibration strip.
    pub diffuse_strip: StripGeom,
    /// The specular calibration strip.
    pub specular_strip: StripGeom,
    /// How the diagonal passes' normals and the displacement map's are combined: `"split"`
    /// (default: the displacement map's low frequencies, the specular normals' detail) or
    /// `"gloss"` (Gardner et al. §7.2: by `ρs/α`, specular above 0.5, displacement below 0.2).
    pub normal_blend: Option<NormalBlend>,
    /// The reflectance models fitted: `"both"` (default: Ward, then GGX on the same traces
    /// and normals) or `"ward"` (Ward alone: GGX integrates its long tails per pixel and
    /// trial, a few seconds on the demo, minutes on a megapixel camera).
    /// `lightrig fit lls --model` overrides it.
    pub models: Option<Models>,
}

/// Which reflectance models a fit gives ([`FitSpec::models`]). There is no GGX-only fit: GGX
/// starts from the Ward fit, whose traces also give the normals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Models {
    /// Ward, then GGX ([`lightrig_pipelines::ggx`]) fitted to the same traces.
    #[default]
    Both,
    /// Ward alone.
    Ward,
}

impl std::str::FromStr for Models {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "both" => Ok(Models::Both),
            "ward" => Ok(Models::Ward),
            other => Err(format!("`{other}` is not a model set: `both` (Ward and GGX) or `ward`")),
        }
    }
}

/// How the two normal estimates are combined ([`FitSpec::normal_blend`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormalBlend {
    /// Frequency split: `G_σ∗n_geom + (n_photo − G_σ∗n_photo)` in slope space, σ 2 px.
    #[default]
    Split,
    /// By `ρs/α` per pixel (the paper's §7.2).
    Gloss,
}

/// Pinhole intrinsics.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraIntrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// The light tube, mm.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightGeom {
    pub diameter_mm: f64,
    pub length_mm: f64,
    pub height_mm: f64,
    pub offset_mm: f64,
}

/// The laser sheet.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SheetGeom {
    pub offset_mm: f64,
    pub angle_deg: f64,
}

/// The board.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardGeom {
    pub cols: usize,
    pub rows: usize,
    pub square_mm: f64,
    pub origin_mm: [f64; 2],
}

/// A calibration strip.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StripGeom {
    pub x_mm: [f64; 2],
    pub y_mm: [f64; 2],
    pub albedo: f64,
}

impl FitSpec {
    /// The pipeline's view of it, with the camera's intrinsics.
    pub fn setup(&self, intrinsics: Intrinsics) -> Setup {
        let strip = |s: &StripGeom| Strip { x: s.x_mm, y: s.y_mm, albedo: s.albedo };
        Setup {
            intrinsics,
            light: Light {
                radius: self.light.diameter_mm / 2.0,
                length: self.light.length_mm,
                height: self.light.height_mm,
                offset: self.light.offset_mm,
            },
            sheet: Sheet { offset: self.stripe.offset_mm, angle: self.stripe.angle_deg.to_radians() },
            board: BoardGeometry {
                cols: self.board.cols,
                rows: self.board.rows,
                square: self.board.square_mm,
                origin: self.board.origin_mm,
            },
            diffuse_strip: strip(&self.diffuse_strip),
            specular_strip: strip(&self.specular_strip),
        }
    }
}

/// One position of a pass: exposure-normalised values (value per second), NaN where clipped in
/// every exposure of the bracket.
#[derive(Debug, Clone)]
pub struct PassFrame {
    /// Image size, pixels.
    pub size: (u32, u32),
    /// Gantry position, mm.
    pub gantry: f64,
    /// Interleaved RGB, value per second of exposure.
    pub rate: Vec<f32>,
}

/// The fitted maps, row-major, `width × height`.
#[derive(Debug, Clone)]
pub struct LlsMaps {
    pub width: u32,
    pub height: u32,
    /// Pixels fitted (on neither strip, with a surface point).
    pub fitted: Vec<bool>,
    /// The Ward fit ([`lightrig_pipelines::ward`]).
    pub fit: Vec<TraceFit>,
    /// The GGX fit of the same traces with the same normals ([`lightrig_pipelines::ggx`]),
    /// where [`FitSpec::models`] asks for it.
    pub ggx: Option<Vec<TraceFit>>,
    /// Surface points, mm.
    pub points: Vec<Option<V3>>,
    /// Where the stripe's crossing gave the point (elsewhere it is on the plane z = 0).
    pub height_measured: Vec<bool>,
    /// Which maps the session's passes measured at all.
    pub measured: Measured,
    /// The normals the final fit used (blended when there were diagonal passes).
    pub normals: Vec<Option<V3>>,
    /// Normals from the displacement map alone.
    pub geometric_normals: Vec<Option<V3>>,
    /// Normals from the diagonal passes' traces (all `None` without diagonal passes).
    pub photometric_normals: Vec<Option<V3>>,
    /// The two blends of those with the geometric normals (all `None` without diagonal
    /// passes): the frequency split and the paper's `ρs/α` blend. `normals` is the one
    /// [`FitSpec::normal_blend`] chose.
    pub split_normals: Vec<Option<V3>>,
    pub gloss_normals: Vec<Option<V3>>,
    /// The blend the final fit used.
    pub normal_blend: NormalBlend,
    /// The mount angles of the diagonal passes used, degrees.
    pub diagonal_mounts: Vec<i64>,
    /// Backlit over light-box brightness (NaN where the light box lit nothing; 0 everywhere
    /// when not [`Measured::translucency`]).
    pub translucency: Vec<f32>,
    /// The camera registration: its reprojection RMS, pixels; the intrinsics the fit used and
    /// the pose (world → camera) from the board frame.
    pub registration_rms: f64,
    pub intrinsics: Intrinsics,
    pub pose: Pose,
    /// The light's scale per channel from the diffuse strip.
    pub scale: [f64; 3],
    /// The specular strip's fitted specular albedo (median), against its known value.
    pub specular_strip: (f64, f64),
    /// A reflectance frame as captured and as the fitted maps predict it (value per second).
    pub check_frame: (f64, Vec<f32>, Vec<f32>),
    /// The most bytes of traces the streamed fit held at once (its blocks; see
    /// [`Streaming::block_bytes`]).
    pub resident_trace_bytes: usize,
    /// Where the time went.
    pub timing: FitTiming,
    /// What became of the kept lobe tables ([`Streaming::tables`]), for the user: read,
    /// written, or why not.
    pub tables_note: String,
}

/// The maps a session's passes can measure: without a pass, its map is an assumption (the
/// plane z = 0, a flat sample, no translucency), and is neither written nor flagged valid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Measured {
    /// The stripe pass gave heights (it was acquired and crossed pixels).
    pub height: bool,
    /// The stripe pass or the diagonal reflectance passes gave normals.
    pub normals: bool,
    /// The backlit and light-box passes gave the translucency.
    pub translucency: bool,
}

/// Wall-clock time of the fit's two phases, to see which one bounds it on this machine.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitTiming {
    /// Frames (every exposure) of the streamed passes (reflectance, diagonal, stripe) decoded.
    pub frames: usize,
    /// Decoding those frames, merging their exposure brackets and writing them block-major to
    /// the scratch files (one thread), s.
    pub read_s: f64,
    /// Everything after: registration, reading the blocks back, the per-pixel fits (on
    /// `threads` threads), normals and the refit, s.
    pub fit_s: f64,
    /// The fit's thread pool.
    pub threads: usize,
}

/// One gantry position of a pass: its images (an exposure bracket) and their exposures, s.
struct Position {
    steps: i32,
    images: Vec<(PathBuf, f64)>,
}

/// The positions of plan step `step` from the frames' trigger records, without decoding.
fn positions_of(
    session: &Session,
    dir: &Path,
    (step, camera): (u32, u8),
    triggers: &std::collections::HashMap<(u32, u32), lightrig_protocol::event::TriggerEvent>,
    gantry: &crate::rigfile::Stepper,
    tick_hz: f64,
) -> Result<Vec<Position>, FitError> {
    let frames = session.camera_frames_of(step, camera);
    let mut out: Vec<Position> = Vec::new();
    for f in &frames {
        let t = triggers.get(&(f.sequence, f.item)).ok_or_else(|| {
            fail(format!("{}: frame {} has no trigger record in the journal", dir.display(), f.file))
        })?;
        let steps = t.snapshot.axes.get(usize::from(gantry.axis)).copied().unwrap_or(0);
        let exposure = f64::from(t.width) / tick_hz;
        if out.last().is_none_or(|l| l.steps != steps) {
            out.push(Position { steps, images: Vec::new() });
        }
        if let Some(last) = out.last_mut() {
            last.images.push((dir.join(&f.file), exposure));
        }
    }
    Ok(out)
}

/// Decodes a position's bracket and merges it ([`crate::fit::bracket::merge`], RGB).
fn merge(
    pos: &Position,
    size: Option<(u32, u32)>,
    response: &CameraResponse,
) -> Result<((u32, u32), Vec<f32>), FitError> {
    crate::fit::bracket::merge(&pos.images, size, 3, response)
}

fn gantry_mm(gantry: &crate::rigfile::Stepper, steps: i32) -> f64 {
    gantry.units(i64::from(steps)).unwrap_or(f64::from(steps))
}

/// The first position of a pass (the board, backlit and light-box passes use one).
fn first_frame(
    positions: &[Position],
    gantry: &crate::rigfile::Stepper,
    response: &CameraResponse,
) -> Result<Option<PassFrame>, FitError> {
    positions
        .first()
        .map(|p| {
            merge(p, None, response).map(|(size, rate)| PassFrame {
                size,
                gantry: gantry_mm(gantry, p.steps),
                rate,
            })
        })
        .transpose()
}

/// A pass streamed into a [`TraceStack`] (each image decoded once), its gantry positions and,
/// if asked, the merged values of position `keep` (the check frame).
struct StreamedPass {
    stack: TraceStack,
    gantry: Vec<f64>,
    kept: Option<Vec<f32>>,
}

fn stream_pass(
    positions: &[Position],
    (gantry, response): (&crate::rigfile::Stepper, &CameraResponse),
    size: (u32, u32),
    name: &str,
    scratch: &Path,
    block_pixels: usize,
    keep: Option<usize>,
) -> Result<StreamedPass, FitError> {
    let pixels = size.0 as usize * size.1 as usize;
    let path = scratch.join(format!("lls-{name}-{}.stack", std::process::id()));
    let io = |e: std::io::Error| {
        fail(format!(
            "{}: {e}: the fit streams each pass through a scratch file there; check the space and \
             permissions of the output directory",
            path.display()
        ))
    };
    let mut stack = TraceStack::create(&path, pixels, positions.len(), block_pixels).map_err(io)?;
    let (mut bytes, mut kept) = (Vec::new(), None);
    for (k, pos) in positions.iter().enumerate() {
        let (_, rate) = merge(pos, Some(size), response).map_err(|e| {
            fail(format!("the {name} pass: {e} (the board frame's size: one camera, one size)"))
        })?;
        stack.write_position(k, &rate, &mut bytes).map_err(io)?;
        if keep == Some(k) {
            kept = Some(rate);
        }
    }
    Ok(StreamedPass { stack, gantry: positions.iter().map(|p| gantry_mm(gantry, p.steps)).collect(), kept })
}

/// The camera's intrinsics: from the calibration file if given (its image size must match the
/// frames'), else from `[plan.fit].camera`.
fn intrinsics(spec: &FitSpec, calibration: Option<&Path>, size: (u32, u32)) -> Result<Intrinsics, FitError> {
    if let Some(path) = calibration {
        let c = lightrig_imaging::calib_file::read(path).map_err(|e| fail(e.to_string()))?;
        if c.image_size != size {
            return Err(fail(format!(
                "{}: the calibration is for {}×{} images but the session's frames are {}×{}: \
                 calibrate the camera at the resolution it captures with",
                path.display(),
                c.image_size.0,
                c.image_size.1,
                size.0,
                size.1
            )));
        }
        return Ok(c.intrinsics);
    }
    let k = spec.camera.ok_or_else(|| {
        fail(
            "no camera intrinsics: pass `--calibration cam.toml` (from `lightrig calibrate`) or give \
             `camera = { fx, fy, cx, cy }` in the rig file's [plan.fit]",
        )
    })?;
    // A principal point outside the frames is a camera of another size (a lab's 1280 × 1024
    // intrinsics on the virtual rig's 128 × 96 frames fitted to nonsense before).
    let (w, h) = (f64::from(size.0), f64::from(size.1));
    if !(0.0..=w).contains(&k.cx) || !(0.0..=h).contains(&k.cy) || k.fx <= 0.0 || k.fy <= 0.0 {
        return Err(fail(format!(
            "[plan.fit] camera = {{ fx = {}, fy = {}, cx = {}, cy = {} }} is not a camera of the session's \
             {}×{} frames (the principal point must lie inside them, near ({:.1}, {:.1})): give that camera's \
             intrinsics, or pass `--calibration cam.toml` from `lightrig calibrate` on its board images",
            k.fx,
            k.fy,
            k.cx,
            k.cy,
            size.0,
            size.1,
            (w - 1.0) / 2.0,
            (h - 1.0) / 2.0
        )));
    }
    Ok(Intrinsics::pinhole(k.fx, k.fy, k.cx, k.cy))
}

/// Where and in what blocks the fit streams the passes ([`TraceStack`]).
#[derive(Debug, Clone, Copy)]
pub struct Streaming<'a> {
    /// Directory for the scratch files (one per streamed pass, removed when the fit ends).
    pub scratch: &'a Path,
    /// Bytes of traces resident at a time: the pixels of a block times the positions of the
    /// streamed passes (reflectance, diagonal, stripe) times RGB `f32`.
    pub block_bytes: usize,
    /// The specular lobe's tables kept between fits (`lls::LobeTables::save`): read before
    /// the fit where the file is usable, written after it where the fit built more. The
    /// tables are the same in every fit (they depend on no session), so this only saves
    /// building them: about a fifth of the command's CPU time on the demo's session
    /// (docs/benchmarks.md).
    pub tables: Option<&'a Path>,
}

/// Pixels a trace gather takes at once ([`Block::gather`]): enough that the block's cache
/// lines (five pixels each) are read once.
const GATHER: usize = 16;

/// The pixels `px` in runs of [`GATHER`], the fit's batches of traces.
fn gathers_of(px: std::ops::Range<usize>) -> Vec<std::ops::Range<usize>> {
    px.clone().step_by(GATHER).map(|s| s..(s + GATHER).min(px.end)).collect()
}

/// The pixels `px` split at the image's rows (`w` pixels wide): the fit's rows, each taken in
/// order so that a pixel's search can start from its left neighbour's result.
fn rows_of(px: std::ops::Range<usize>, w: usize) -> Vec<std::ops::Range<usize>> {
    (px.start / w..px.end.div_ceil(w)).map(|r| (r * w).max(px.start)..((r + 1) * w).min(px.end)).collect()
}

/// How far apart two upward normals are in slope (`(−nx/nz, −ny/nz)`), the normal search's
/// variable.
fn slope_distance(a: V3, b: V3) -> f64 {
    (a[0] / a[2] - b[0] / b[2]).hypot(a[1] / a[2] - b[1] / b[2])
}

/// The lobe tables kept at `path` ([`Streaming::tables`]), or empty ones where there are none
/// or they cannot be used; and a line for the user saying which.
fn kept_tables(path: Option<&Path>) -> (LobeTables, String) {
    match path {
        Some(path) if !path.exists() => {
            (LobeTables::new(), format!("lobe tables: none kept at {} yet; built", path.display()))
        }
        Some(path) => match LobeTables::load(path) {
            Ok(t) => {
                let note = format!("lobe tables: {} nodes read from {}", t.len(), path.display());
                (t, note)
            }
            Err(e) => (LobeTables::new(), format!("lobe tables: {} not used ({e}); built", path.display())),
        },
        None => (LobeTables::new(), "lobe tables: built".to_string()),
    }
}

/// Where `lightrig fit lls` and the demo keep the lobe tables: `$LIGHTRIG_CACHE_DIR`, else
/// `$XDG_CACHE_HOME/lightrig`, else `$HOME/.cache/lightrig`; file `lobe-tables.bin`.
pub fn default_tables_file() -> Option<PathBuf> {
    let var = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    let dir = var("LIGHTRIG_CACHE_DIR")
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("lightrig")))
        .or_else(|| var("HOME").map(|d| d.join(".cache").join("lightrig")))?;
    Some(dir.join("lobe-tables.bin"))
}

/// The default resident trace budget: 32 MiB.
pub const BLOCK_BYTES: usize = 32 << 20;

/// Reads a session and fits it, with the camera calibration file `calibration` if given (else
/// the rig file's `[plan.fit].camera`), streaming the passes through scratch files in
/// `scratch` ([`fit_session_with`] with [`BLOCK_BYTES`]). `progress(done, total)` is called
/// as pixels finish.
pub fn fit_session(
    dir: &Path,
    calibration: Option<&Path>,
    scratch: &Path,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<LlsMaps, FitError> {
    let tables = default_tables_file();
    let streaming = Streaming { scratch, block_bytes: BLOCK_BYTES, tables: tables.as_deref() };
    fit_session_with(dir, calibration, streaming, None, progress)
}

/// [`fit_session`] with the streaming's scratch directory and block budget given. Every
/// image is decoded once; the passes whose traces the fit needs (reflectance, diagonal,
/// stripe) are written block-major to scratch files and fitted one block of pixels at a time,
/// so that the traces resident at once take at most `block_bytes` (or one pixel's traces,
/// if more) whatever the number of frames. The maps do not depend on the block size.
/// `models`, where given, overrides the rig file's [`FitSpec::models`].
pub fn fit_session_with(
    dir: &Path,
    calibration: Option<&Path>,
    streaming: Streaming,
    models: Option<Models>,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<LlsMaps, FitError> {
    let (session, _) = Session::read(dir).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let manifest = session.manifest().clone();
    let rig = crate::fit::session_rig(&manifest.rig, dir)?;
    let spec: FitSpec = crate::fit::plan_fit(&rig)
        .ok_or_else(|| {
            fail(format!("{}: the rig file has no [plan.fit] table (the fit's geometry)", dir.display()))
        })?
        .map_err(|e| fail(e.to_string()))?;
    let gantry = rig
        .stepper_named("gantry")
        .or_else(|| rig.steppers.first())
        .ok_or_else(|| fail("the rig file has no gantry stepper"))?;
    let tick_hz = f64::from(manifest.device.tick_hz);
    let triggers = trigger_events(dir).map_err(|e| fail(e.to_string()))?;
    // Passes by name and, for the reflectance passes, mount angle (the first of each).
    // One camera's frames (a rig may fire several together): the lowest-numbered.
    let camera = session.pipeline_camera(None).map_err(fail)?;
    let response = crate::response::for_session(&rig, dir, camera).map_err(fail)?;
    let mount_of = |s: &crate::session::PlanStep| s.extra["meta"]["mount_deg"].as_i64().unwrap_or(0);
    let pass_of = |name: &str, mount: Option<i64>| {
        manifest
            .plan
            .steps
            .iter()
            .find(|s| {
                s.extra["meta"]["pass"].as_str() == Some(name) && mount.is_none_or(|m| mount_of(s) == m)
            })
            .map(|s| s.id)
    };
    let positions_mount = |name: &str, mount: Option<i64>| -> Result<Vec<Position>, FitError> {
        match pass_of(name, mount) {
            Some(id) => positions_of(&session, dir, (id, camera), &triggers, gantry, tick_hz),
            None => Ok(Vec::new()),
        }
    };
    let positions = |name: &str| positions_mount(name, None);
    let board = first_frame(&positions("board")?, gantry, &response)?;
    let reflect_pos = positions_mount("reflectance", Some(0))?;
    let mut mounts: Vec<i64> = manifest
        .plan
        .steps
        .iter()
        .filter(|s| s.extra["meta"]["pass"].as_str() == Some("reflectance"))
        .map(mount_of)
        .filter(|&m| m != 0)
        .collect();
    mounts.sort_unstable();
    mounts.dedup();
    let diagonal_pos: Vec<(i64, Vec<Position>)> =
        if mounts.iter().any(|&m| m > 0) && mounts.iter().any(|&m| m < 0) {
            mounts
                .iter()
                .map(|&m| Ok((m, positions_mount("reflectance", Some(m))?)))
                .collect::<Result<_, FitError>>()?
        } else {
            Vec::new()
        };
    let stripe_pos = positions("stripe")?;
    let backlit = first_frame(&positions("backlit")?, gantry, &response)?;
    let lightbox = first_frame(&positions("light-box")?, gantry, &response)?;
    // A pass short of frames because the run lost them: said so, with the command that takes
    // them again.
    let short = |what: String| match session.missing_report() {
        Some(report) => fail(format!("{}: {what}: the session has {report}", dir.display())),
        None => fail(format!("{}: {what}", dir.display())),
    };
    let first =
        board.ok_or_else(|| short("the session has no board frame: the camera's pose needs one".into()))?;
    if reflect_pos.len() < 5 {
        return Err(short(format!(
            "the reflectance pass has {} positions; the fit needs a sweep",
            reflect_pos.len()
        )));
    }
    let (w, h) = (first.size.0 as usize, first.size.1 as usize);
    for (name, f) in [("backlit", &backlit), ("light-box", &lightbox)] {
        if let Some(f) = f.as_ref().filter(|f| f.size != first.size) {
            return Err(fail(format!(
                "the {name} pass's frames are {}×{} but the board frame is {w}×{h}: one camera, one size",
                f.size.0, f.size.1
            )));
        }
    }
    let setup = spec.setup(intrinsics(&spec, calibration, first.size)?);
    // Stream the passes with traces: one block partition for all (the same pixels in every
    // pass' block b), sized so that a block of every streamed pass together fits the budget.
    std::fs::create_dir_all(streaming.scratch)
        .map_err(|e| fail(format!("{}: {e}: the fit's scratch directory", streaming.scratch.display())))?;
    let streamed_positions =
        reflect_pos.len() + stripe_pos.len() + diagonal_pos.iter().map(|(_, p)| p.len()).sum::<usize>();
    let bp = block_pixels(streaming.block_bytes, streamed_positions);
    let stream = |pos: &[Position], name: &str, keep: Option<usize>| {
        stream_pass(pos, (gantry, &response), first.size, name, streaming.scratch, bp, keep)
    };
    let t_read = std::time::Instant::now();
    let mut reflect = stream(&reflect_pos, "reflectance", Some(reflect_pos.len() / 2))?;
    let mut diagonal: Vec<(i64, StreamedPass)> = diagonal_pos
        .iter()
        .map(|(m, pos)| Ok((*m, stream(pos, &format!("reflectance{m:+}"), None)?)))
        .collect::<Result<_, FitError>>()?;
    let mut stripe = stream(&stripe_pos, "stripe", None)?;
    let read_s = t_read.elapsed().as_secs_f64();
    let read_frames: usize = reflect_pos
        .iter()
        .chain(&stripe_pos)
        .chain(diagonal_pos.iter().flat_map(|(_, p)| p))
        .map(|p| p.images.len())
        .sum();
    let t_fit = std::time::Instant::now();
    // The kept lobe tables (25 MB for the demo's session, some 40 ms to read and check) are
    // read while the registration and the surface points take the fit's first stages.
    let tables_file = streaming.tables.map(Path::to_path_buf);
    let loading_tables = std::thread::spawn(move || kept_tables(tables_file.as_deref()));
    let blocks = reflect.stack.blocks();
    let resident = std::cell::Cell::new(0usize);
    let read = |s: &mut StreamedPass, b: usize, out: &mut Block| {
        s.stack.read_block(b, out).map_err(|e| {
            fail(format!("{}: {e}: reading the fit's scratch file back", s.stack.path().display()))
        })?;
        resident.set(resident.get().max(out.resident_bytes()));
        Ok::<(), FitError>(())
    };

    let board_img = Image {
        width: w as u32,
        height: h as u32,
        channels: 3,
        data: first.rate.iter().map(|v| if v.is_nan() { 1.0 } else { *v }).collect(),
        encoding: Encoding::Linear,
    };
    let reg: Registration = register(&setup, &board_img).map_err(|e| fail(e.to_string()))?;

    // Surface points: the stripe's crossing, or the reference plane where no stripe shows.
    let stripe_max = stripe.stack.peak[0].max(0.0);
    let mut points: Vec<Option<V3>> = vec![None; w * h];
    let mut height_measured = vec![false; w * h];
    let mut block = Block::default();
    for b in 0..blocks {
        read(&mut stripe, b, &mut block)?;
        let blk = &block;
        let stripe_pos = &stripe.gantry;
        let got: Vec<(Option<V3>, bool)> = blk
            .pixels
            .clone()
            .into_par_iter()
            .map(|i| {
                let (o, d) = reg.rays[i];
                // The red channel sees the laser best; where it clipped, the green one (which
                // passes a little of it).
                let channel = |c: usize| -> Vec<f64> {
                    (0..blk.positions()).map(|k| f64::from(blk.rate(i, k, c))).collect()
                };
                let red = channel(0);
                let trace: Vec<f64> = if red.iter().any(|v| v.is_nan()) { channel(1) } else { red }
                    .into_iter()
                    .map(|v| v.max(0.0))
                    .collect();
                let on_sheet = if stripe_pos.len() >= 3 {
                    stripe_peak(&trace, stripe_pos, f64::from(stripe_max) * 0.002)
                        .and_then(|g| point_on_sheet(o, d, g, &setup.sheet))
                } else {
                    None
                };
                let plane = || {
                    let t = -o[2] / d[2];
                    (t > 0.0).then(|| [o[0] + t * d[0], o[1] + t * d[1], 0.0])
                };
                (on_sheet.or_else(plane), on_sheet.is_some())
            })
            .collect();
        for ((p, m), (point, measured)) in
            points[blk.pixels.clone()].iter_mut().zip(&mut height_measured[blk.pixels.clone()]).zip(got)
        {
            (*p, *m) = (point, measured);
        }
    }
    drop(stripe);
    let in_strip = |i: usize| {
        points[i]
            .is_some_and(|p| setup.diffuse_strip.contains(p, -0.5) || setup.specular_strip.contains(p, -0.5))
    };
    let mut normals = normals_from_points(&points, w, h, 2, |j| !in_strip(j));
    for (i, n) in normals.iter_mut().enumerate() {
        if in_strip(i) {
            *n = Some([0.0, 0.0, 1.0]);
        }
    }
    // The passes' tubes at every frame, as every pixel's models take them (`Sweep`: what they
    // share, once).
    let sweep = Sweep::new(&reflect.gantry.iter().map(|&g| setup.light.at(g)).collect::<Vec<_>>());
    let diagonal_sweeps: Vec<Sweep> = diagonal
        .iter()
        .map(|(m, pass)| {
            let mount = (*m as f64).to_radians();
            Sweep::new(&pass.gantry.iter().map(|&g| setup.light.mounted(g, mount)).collect::<Vec<_>>())
        })
        .collect();
    // Pixel `i`'s observations from `pass` (the pixels gathered out of a block, a few at a
    // time: `Block::gather`) under the tubes of `sweep`.
    let trace_in = |pass: &Gathered, sweep: &Sweep, i: usize, p: V3, v: V3, scale: [f64; 3]| {
        let n = sweep.tubes().len();
        // Written in place (pushes cost a capacity check each: a third of this).
        let mut obs: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; n]);
        let mut valid: [Vec<bool>; 3] = std::array::from_fn(|_| vec![false; n]);
        // Leave a millimetre's margin around the tube's silhouette.
        let hidden = sweep.hidden(p, v, 1.0);
        for c in 0..3 {
            let frames = pass.trace(i).chunks_exact(3).zip(&hidden);
            for ((o, ok), (rgb, &hidden)) in obs[c].iter_mut().zip(valid[c].iter_mut()).zip(frames) {
                let r = f64::from(rgb[c]);
                *ok = !hidden && r.is_finite();
                *o = if r.is_finite() { r / scale[c] } else { 0.0 };
            }
        }
        (obs, valid)
    };
    // The light's scale from the diffuse strip (its inner part).
    let mut strip_ratios = Vec::new();
    let on_strip = |i: usize| points[i].is_some_and(|p| setup.diffuse_strip.contains(p, 1.0));
    for b in 0..blocks {
        // Only the blocks the strip crosses (it spans a few rows).
        if !reflect.stack.block_range(b).any(on_strip) {
            continue;
        }
        read(&mut reflect, b, &mut block)?;
        let blk = &block;
        let got: Vec<[Option<f64>; 3]> = blk
            .pixels
            .clone()
            .into_par_iter()
            .filter(|&i| on_strip(i))
            .map(|i| {
                let p = points[i].unwrap_or([0.0; 3]);
                let v = normalize(sub(reg.rays[i].0, p));
                let (obs, valid) = trace_in(&blk.gather(i..i + 1), &sweep, i, p, v, [1.0; 3]);
                let d = TraceModel::of(p, v, &sweep).diffuse([0.0, 0.0, 1.0]);
                strip_ratio(&(obs, valid, d), setup.diffuse_strip.albedo)
            })
            .collect();
        strip_ratios.extend(got);
    }
    let scale = strip_scale_of(&strip_ratios)
        .ok_or_else(|| fail("no pixel sees the diffuse calibration strip: check [plan.fit.diffuse_strip]"))?;
    // Progress: the first fit, then (with diagonal passes) the normals and the refit.
    let models = models.or(spec.models).unwrap_or_default();
    let rounds = if diagonal.is_empty() { 1 } else { 3 } + usize::from(models == Models::Both);
    let total = (w * h * rounds) as u64;
    let done = AtomicU64::new(0);
    let tick = || {
        let k = done.fetch_add(1, Ordering::Relaxed) + 1;
        if k.is_multiple_of(256) || k == total {
            progress(k, total);
        }
    };
    let fitted: Vec<bool> =
        (0..w * h).map(|i| points[i].is_some() && normals[i].is_some() && !in_strip(i)).collect();
    // The specular lobe's tables, shared by every pixel and pass of this session (built as
    // the pixels need them).
    let (tables, mut tables_note) =
        loading_tables.join().map_err(|_| fail("reading the kept lobe tables failed unexpectedly"))?;
    let kept = (tables.len(), tables.cuts());
    let want_fit = |i: usize| fitted[i] || points[i].is_some_and(|p| setup.specular_strip.contains(p, 1.0));
    // The check frame: a frame near the middle of the pass as captured and as the maps
    // predict it, from the last fit's model of each pixel (one lookup; the tube integrated
    // with a preview rule had taken 5 % of the command's time).
    let k_check = reflect_pos.len() / 2;
    let predict = |traces: &mut TabledTraces, f: &TraceFit| -> [f32; 3] {
        let (d, s) = traces.frame(k_check, f.alpha).unwrap_or((0.0, 0.0));
        std::array::from_fn(|c| ((f.diffuse[c] * d + f.specular[c] * s) * scale[c]) as f32)
    };
    let mut predicted = vec![[0f32; 3]; w * h];
    let mut fit: Vec<TraceFit> = vec![TraceFit::default(); w * h];
    for b in 0..blocks {
        read(&mut reflect, b, &mut block)?;
        let blk = &block;
        // Each row of the block in order: a pixel's search starts from its left neighbour's
        // fit where that found a lobe (`fit_trace`'s `prior`: two or three trials where the
        // material is the same, against six from the moments), the row's first pixel and
        // one after a pixel without a lobe from the moments. A fit depends on its trace and
        // its left neighbour's fit alone: the same maps whatever the blocks.
        let got: Vec<Vec<(TraceFit, [f32; 3])>> = rows_of(blk.pixels.clone(), w)
            .into_par_iter()
            .map(|row| {
                // At the block's start the neighbour is the last block's (fitted already).
                let mut left = (row.start % w != 0).then(|| fit[row.start - 1]);
                let mut gathered = blk.gather(row.start..row.start);
                let end = row.end;
                row.map(|i| {
                    if !gathered.holds(i) {
                        gathered = blk.gather(i..(i + GATHER).min(end));
                    }
                    let out = match (want_fit(i), points[i], normals[i]) {
                        (true, Some(p), Some(n)) => {
                            let v = normalize(sub(reg.rays[i].0, p));
                            let (obs, valid) = trace_in(&gathered, &sweep, i, p, v, scale);
                            let model = TraceModel::of(p, v, &sweep);
                            let mut traces = model.tabled(n, &tables);
                            let prior = left.filter(TraceFit::leads);
                            let f = fit_tabled_traces(&obs, &valid, &mut traces, prior.as_ref());
                            // The final fit when there is no refit.
                            let seen = if fitted[i] && diagonal.is_empty() {
                                predict(&mut traces, &f)
                            } else {
                                [0.0; 3]
                            };
                            (f, seen)
                        }
                        _ => (TraceFit::default(), [0.0; 3]),
                    };
                    left = Some(out.0);
                    tick();
                    out
                })
                .collect()
            })
            .collect();
        for ((f, seen), (fi, pi)) in got
            .into_iter()
            .flatten()
            .zip(fit[blk.pixels.clone()].iter_mut().zip(&mut predicted[blk.pixels.clone()]))
        {
            (*fi, *pi) = (f, seen);
        }
    }
    let geometric_normals = normals.clone();
    let mut photometric_normals = vec![None; w * h];
    let (mut split_normals, mut gloss_normals) = (vec![None; w * h], vec![None; w * h]);
    let normal_blend = spec.normal_blend.unwrap_or_default();
    if !diagonal.is_empty() {
        let mut diag_blocks: Vec<Block> = diagonal.iter().map(|_| Block::default()).collect();
        for b in 0..blocks {
            for ((_, pass), blk) in diagonal.iter_mut().zip(&mut diag_blocks) {
                read(pass, b, blk)?;
            }
            // With the straight pass' buffer, still allocated.
            let held = block.resident_bytes() + diag_blocks.iter().map(Block::resident_bytes).sum::<usize>();
            resident.set(resident.get().max(held));
            let range = diag_blocks[0].pixels.clone();
            // Each row of the block in order, as the first fit: a pixel's search starts from
            // its left neighbour's normal where that is within one step of the search (0.05
            // in slope) of the pixel's own from the displacement map (across an edge it is
            // not), else from that. 1.46 evaluations a pixel against 1.65 on the
            // `--step-mm 0.6` demo session; the same normals whatever the blocks.
            let photometric = &photometric_normals;
            let got: Vec<Vec<Option<V3>>> = rows_of(range.clone(), w)
                .into_par_iter()
                .map(|row| {
                    let mut left = if row.start % w != 0 { photometric[row.start - 1] } else { None };
                    let mut gathered: Vec<Gathered> = Vec::new();
                    let end = row.end;
                    row.map(|i| {
                        if !gathered.first().is_some_and(|g| g.holds(i)) {
                            gathered =
                                diag_blocks.iter().map(|b| b.gather(i..(i + GATHER).min(end))).collect();
                        }
                        let out = match (fitted[i], points[i], normals[i]) {
                            (true, Some(p), Some(n)) => {
                                let v = normalize(sub(reg.rays[i].0, p));
                                let traces: Vec<_> = gathered
                                    .iter()
                                    .zip(&diagonal_sweeps)
                                    .map(|(g, t)| trace_in(g, t, i, p, v, scale))
                                    .collect();
                                let models: Vec<TraceModel> =
                                    diagonal_sweeps.iter().map(|t| TraceModel::of(p, v, t)).collect();
                                let passes: Vec<PassTrace> = traces
                                    .iter()
                                    .zip(&models)
                                    .map(|((obs, valid), model)| PassTrace { obs, valid, model })
                                    .collect();
                                let start = left.filter(|&l| slope_distance(l, n) < 0.05).unwrap_or(n);
                                fit_normal(&passes, start, fit[i].alpha, Some(&tables))
                            }
                            _ => None,
                        };
                        left = out;
                        tick();
                        out
                    })
                    .collect()
                })
                .collect();
            let got: Vec<Option<V3>> = got.into_iter().flatten().collect();
            photometric_normals[range].copy_from_slice(&got);
        }
        drop(diag_blocks);
        // The geometric normals' low frequencies, the photometric ones' detail (σ 2 px); or
        // by each pixel's gloss ρs/α from the first fit (§7.2).
        split_normals = blend_normals(&photometric_normals, &geometric_normals, w, h, 2.0);
        let gloss: Vec<f64> = fit
            .iter()
            .map(|f| (f.specular.iter().sum::<f64>() / 3.0) / f.alpha)
            .map(|r| if r.is_finite() { r } else { f64::NAN })
            .collect();
        gloss_normals = blend_normals_by_gloss(&photometric_normals, &geometric_normals, &gloss);
        let blended = match normal_blend {
            NormalBlend::Split => &split_normals,
            NormalBlend::Gloss => &gloss_normals,
        };
        for i in 0..w * h {
            if fitted[i] {
                normals[i] = blended[i];
            }
        }
        for b in 0..blocks {
            read(&mut reflect, b, &mut block)?;
            let blk = &block;
            let refit: Vec<Option<(TraceFit, [f32; 3])>> = gathers_of(blk.pixels.clone())
                .into_par_iter()
                .flat_map_iter(|batch| {
                    let gathered = blk.gather(batch.clone());
                    let out: Vec<_> = batch
                        .map(|i| {
                            let out = match (fitted[i], points[i], normals[i]) {
                                (true, Some(p), Some(n)) => {
                                    let v = normalize(sub(reg.rays[i].0, p));
                                    let (obs, valid) = trace_in(&gathered, &sweep, i, p, v, scale);
                                    let model = TraceModel::of(p, v, &sweep);
                                    let mut traces = model.tabled(n, &tables);
                                    let f = fit_tabled_traces(&obs, &valid, &mut traces, Some(&fit[i]));
                                    Some((f, predict(&mut traces, &f)))
                                }
                                _ => None,
                            };
                            tick();
                            out
                        })
                        .collect();
                    out
                })
                .collect();
            let range = blk.pixels.clone();
            for (r, (f, seen)) in
                refit.into_iter().zip(fit[range.clone()].iter_mut().zip(&mut predicted[range]))
            {
                if let Some(r) = r {
                    (*f, *seen) = r;
                }
            }
        }
    }
    // GGX on the straight pass' traces with the final normals, its search started from the
    // Ward fit's α (the two α agree to tens of per cent on these lobes).
    let ggx = if models == Models::Both {
        let mut ggx = vec![TraceFit::default(); w * h];
        for b in 0..blocks {
            read(&mut reflect, b, &mut block)?;
            let blk = &block;
            let got: Vec<TraceFit> = gathers_of(blk.pixels.clone())
                .into_par_iter()
                .flat_map_iter(|batch| {
                    let gathered = blk.gather(batch.clone());
                    let out: Vec<_> = batch
                        .map(|i| {
                            let out = match (fitted[i], points[i], normals[i]) {
                                (true, Some(p), Some(n)) => {
                                    let v = normalize(sub(reg.rays[i].0, p));
                                    let (obs, valid) = trace_in(&gathered, &sweep, i, p, v, scale);
                                    let model = TraceModel::of(p, v, &sweep);
                                    fit_trace_ggx(&obs, &valid, &model, n, Some(&fit[i]))
                                }
                                _ => TraceFit::default(),
                            };
                            tick();
                            out
                        })
                        .collect();
                    out
                })
                .collect();
            ggx[blk.pixels.clone()].copy_from_slice(&got);
        }
        Some(ggx)
    } else {
        None
    };
    drop(block);
    // Keep what was built for the next fit (a failure to write costs the next fit the time
    // to build them again, nothing else: said, not fatal).
    if let Some(path) = streaming.tables.filter(|_| (tables.len(), tables.cuts()) != kept) {
        let saved = path.parent().map_or(Ok(()), std::fs::create_dir_all).and_then(|()| tables.save(path));
        tables_note += &match saved {
            Ok(()) => format!(", {} nodes now kept in {}", tables.len(), path.display()),
            Err(e) => format!(", could not be kept in {}: {e}", path.display()),
        };
    }
    let mut spec_strip: Vec<f64> = (0..w * h)
        .filter(|&i| points[i].is_some_and(|p| setup.specular_strip.contains(p, 1.0)))
        .map(|i| (fit[i].specular[0] + fit[i].specular[1] + fit[i].specular[2]) / 3.0)
        .collect();
    spec_strip.sort_by(f64::total_cmp);
    let specular_strip =
        (spec_strip.get(spec_strip.len() / 2).copied().unwrap_or(f64::NAN), setup.specular_strip.albedo);

    let translucency: Vec<f32> = (0..w * h)
        .map(|i| match (&backlit, &lightbox) {
            (Some(b), Some(l)) => {
                let (num, den): (f32, f32) = (0..3)
                    .map(|c| (b.rate[i * 3 + c], l.rate[i * 3 + c]))
                    .fold((0.0, 0.0), |a, x| (a.0 + x.0, a.1 + x.1));
                if den > 0.0 && num.is_finite() {
                    num / den
                } else {
                    f32::NAN
                }
            }
            _ => 0.0,
        })
        .collect();

    let predicted: Vec<f32> = predicted.into_iter().flatten().collect();
    let captured: Vec<f32> = reflect
        .kept
        .take()
        .unwrap_or_default()
        .iter()
        .map(|v| if v.is_finite() { *v } else { 0.0 })
        .collect();
    let check_gantry = reflect.gantry[k_check];
    drop(reflect);
    drop(diagonal);
    Ok(LlsMaps {
        width: w as u32,
        height: h as u32,
        fitted,
        fit,
        ggx,
        points,
        measured: Measured {
            // A stripe pass that crossed no pixel measured nothing.
            height: height_measured.iter().any(|&m| m),
            normals: height_measured.iter().any(|&m| m) || !diagonal_pos.is_empty(),
            translucency: backlit.is_some() && lightbox.is_some(),
        },
        height_measured,
        normals,
        geometric_normals,
        photometric_normals,
        split_normals,
        gloss_normals,
        normal_blend,
        diagonal_mounts: diagonal_pos.iter().map(|(m, _)| *m).collect(),
        translucency,
        registration_rms: reg.rms,
        intrinsics: setup.intrinsics,
        pose: reg.pose,
        scale,
        specular_strip,
        check_frame: (check_gantry, captured, predicted),
        resident_trace_bytes: resident.get(),
        tables_note,
        timing: FitTiming {
            frames: read_frames,
            read_s,
            fit_s: t_fit.elapsed().as_secs_f64(),
            threads: rayon::current_num_threads(),
        },
    })
}

/// Writes `maps.exr` (layers diffuse, specular, roughness, height, normal, translucency,
/// residual, and `valid.<mask>`: the [`quality::Validity`] masks, 1 where true), PNG previews, `quality.json`
/// ([`quality::Quality`]), and `relit.png`: a captured frame, the same frame predicted from
/// the maps, and the maps relit by a point light above the sample. A map the session's
/// passes did not measure ([`Measured`]) is not written. Returns the files written.
pub fn write_outputs(m: &LlsMaps, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    std::fs::create_dir_all(out).map_err(|e| fail(format!("{}: {e}", out.display())))?;
    let (w, h) = (m.width, m.height);
    let n = (w * h) as usize;
    let pick = |f: &dyn Fn(usize) -> Vec<f32>| -> Vec<f32> { (0..n).flat_map(f).collect() };
    let on = |i: usize| m.fitted[i];
    let diffuse = pick(&|i| m.fit[i].diffuse.map(|v| v as f32).to_vec());
    let specular = pick(&|i| m.fit[i].specular.map(|v| v as f32).to_vec());
    let rough = pick(&|i| vec![if on(i) { m.fit[i].alpha as f32 } else { 0.0 }]);
    let height = pick(&|i| vec![m.points[i].map_or(0.0, |p| p[2] as f32)]);
    let normal = pick(&|i| m.normals[i].unwrap_or([0.0, 0.0, 1.0]).map(|v| v as f32).to_vec());
    let resid = pick(&|i| vec![m.fit[i].residual as f32]);
    let valid = quality::validity(m);
    let q = quality::assess(m, &valid);
    let masks: [(&str, &[bool]); 5] = [
        ("valid.reflectance", &valid.reflectance),
        ("valid.roughness", &valid.roughness),
        ("valid.height", &valid.height),
        ("valid.translucency", &valid.translucency),
        ("valid.physical", &valid.physical),
    ];
    let mut layers = vec![
        Layer::linear("diffuse", &["R", "G", "B"], w, h, diffuse.clone()),
        Layer::linear("specular", &["R", "G", "B"], w, h, specular.clone()),
        Layer::linear("roughness", &["Y"], w, h, rough.clone()),
    ];
    if m.measured.height {
        layers.push(Layer::linear("height", &["Y"], w, h, height.clone()));
    }
    if m.measured.normals {
        layers.push(Layer::linear("normal", &["X", "Y", "Z"], w, h, normal.clone()));
    }
    if m.measured.translucency {
        layers.push(Layer::linear("translucency", &["Y"], w, h, m.translucency.clone()));
    }
    layers.push(Layer::linear("residual", &["Y"], w, h, resid));
    for (name, mask) in masks {
        let ones = mask.iter().map(|&v| f32::from(u8::from(v))).collect();
        layers.push(Layer::linear(name, &["Y"], w, h, ones));
    }
    if let Some(ggx) = &m.ggx {
        let pick = |f: &dyn Fn(&TraceFit) -> Vec<f32>, ch: usize| -> Vec<f32> {
            (0..n).flat_map(|i| if on(i) { f(&ggx[i]) } else { vec![0.0; ch] }).collect()
        };
        layers.extend([
            Layer::linear(
                "ggx.diffuse",
                &["R", "G", "B"],
                w,
                h,
                pick(&|f| f.diffuse.map(|v| v as f32).to_vec(), 3),
            ),
            Layer::linear(
                "ggx.specular",
                &["R", "G", "B"],
                w,
                h,
                pick(&|f| f.specular.map(|v| v as f32).to_vec(), 3),
            ),
            Layer::linear("ggx.alpha", &["Y"], w, h, pick(&|f| vec![f.alpha as f32], 1)),
            Layer::linear("ggx.residual", &["Y"], w, h, pick(&|f| vec![f.residual as f32], 1)),
        ]);
    }
    let exr = out.join("maps.exr");
    write_exr_layers(&exr, &layers, ExrPrecision::Float).map_err(|e| fail(e.to_string()))?;
    let mut files = vec![exr];
    let quality_file = out.join("quality.json");
    let text = serde_json::to_string_pretty(&q).expect("the quality record serialises");
    std::fs::write(&quality_file, text + "\n")
        .map_err(|e| fail(format!("{}: {e}", quality_file.display())))?;
    files.push(quality_file);
    let png = |name: &str, ch: u8, data: Vec<f32>, files: &mut Vec<PathBuf>| -> Result<(), FitError> {
        let img = Image { width: w, height: h, channels: ch, data, encoding: Encoding::Linear };
        let p = out.join(name);
        write_png(&p, &img.to_srgb(), BitDepth::Eight).map_err(|e| fail(e.to_string()))?;
        files.push(p);
        Ok(())
    };
    let (hmin, hmax) = height.iter().fold((f32::MAX, f32::MIN), |a, &v| (a.0.min(v), a.1.max(v)));
    png("diffuse.png", 3, diffuse.iter().map(|v| v.clamp(0.0, 1.0)).collect(), &mut files)?;
    png("specular.png", 3, specular.iter().map(|v| (v * 5.0).clamp(0.0, 1.0)).collect(), &mut files)?;
    png("roughness.png", 1, rough.iter().map(|v| (v / 0.4).clamp(0.0, 1.0)).collect(), &mut files)?;
    if m.measured.height {
        let scaled = height.iter().map(|v| (v - hmin) / (hmax - hmin).max(1e-6)).collect();
        png("height.png", 1, scaled, &mut files)?;
    }
    if m.measured.normals {
        png("normal.png", 3, normal.iter().map(|v| ((v + 1.0) / 2.0).clamp(0.0, 1.0)).collect(), &mut files)?;
    }
    if m.measured.translucency {
        let t = m.translucency.iter().map(|v| if v.is_finite() { v.clamp(0.0, 1.0) } else { 0.0 }).collect();
        png("translucency.png", 1, t, &mut files)?;
    }
    // relit.png: captured | predicted | point light.
    let (_, cap, pred) = &m.check_frame;
    let peak = cap.iter().fold(0f32, |a, &v| a.max(v)).max(1e-12);
    let light = [0.0, 0.0, 150.0];
    let eye = m.pose.camera_centre();
    let mut relit = vec![0f32; n * 3];
    for i in 0..n {
        if let (true, Some(p), Some(nn)) = (m.fitted[i], m.points[i], m.normals[i]) {
            let wi = normalize(sub(light, p));
            let wo = normalize(sub(eye, p));
            let f = Ward {
                diffuse: m.fit[i].diffuse,
                specular: m.fit[i].specular,
                alpha: m.fit[i].alpha.max(1e-3),
            }
            .eval(nn, wi, wo);
            let ci = lightrig_pipelines::vec3::dot(nn, wi).max(0.0);
            for c in 0..3 {
                relit[i * 3 + c] = (f[c] * ci * 2.0) as f32;
            }
        }
    }
    let mut strip = vec![0f32; n * 9];
    for y in 0..h as usize {
        for x in 0..w as usize {
            let i = y * w as usize + x;
            for c in 0..3 {
                strip[(y * 3 * w as usize + x) * 3 + c] = cap[i * 3 + c] / peak;
                strip[(y * 3 * w as usize + w as usize + x) * 3 + c] = pred[i * 3 + c] / peak;
                strip[(y * 3 * w as usize + 2 * w as usize + x) * 3 + c] = relit[i * 3 + c].min(1.0);
            }
        }
    }
    let img = Image {
        width: w * 3,
        height: h,
        channels: 3,
        data: strip.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        encoding: Encoding::Linear,
    };
    let p = out.join("relit.png");
    write_png(&p, &img.to_srgb(), BitDepth::Eight).map_err(|e| fail(e.to_string()))?;
    files.push(p);
    // The check light's images from the maps (`export::check_light`), Ward's and GGX's, and
    // the Mitsuba scene of the GGX fit under the same light.
    let light = export::check_light(m);
    let mut relit_layers = Vec::new();
    for (name, model) in [("ward", export::Model::Ward), ("ggx", export::Model::Ggx)] {
        if let Some(img) = export::relit(m, model, &light) {
            relit_layers.push(Layer::linear(name, &["R", "G", "B"], w, h, img));
        }
    }
    let p = out.join("relit-point.exr");
    write_exr_layers(&p, &relit_layers, ExrPrecision::Float).map_err(|e| fail(e.to_string()))?;
    files.push(p);
    if m.ggx.is_some() {
        files.extend(export::write_mitsuba(m, &out.join("mitsuba"), &light)?);
        files.extend(gltf::write_gltf(m, &out.join("gltf"), &light)?);
    }
    Ok(files)
}
