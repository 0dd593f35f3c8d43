//! `lightrig fit disco`: a DISCO session → the object's throughput factor matrix `F`.
//!
//! The glue between a session on disk and [`lightrig_pipelines::disco`]:
//!
//! 1. **White balance** (section 4.4): the `white` step's frames, one per laser, each summed
//!    over the white target's area, give the camera's gain times each laser's flux
//!    ([`flux_scale`]) — absolute, so `F` comes out in mm⁻². Read after the projector is
//!    fitted (step 2): the spot on the target is where its beam meets it.
//! 2. **Registration** (section 4.4): where the plan took a registration frame per view (the
//!    spotlights alone on), the scanned mesh is placed on the turntable by its silhouettes
//!    ([`register`]); without them, the mesh is taken to be in the turntable's frame already.
//!    **Per view, once** (section 5): the object turned to the view's turntable angle (from the
//!    trigger snapshots) and seen from its camera position ([`ViewMap`]): visible vertices,
//!    their pixels, Fresnel terms and confidences.
//!    **Projector** (section 4.4): the spots of up to 12 views' frames (green), found near where
//!    the rig file's projector puts them and cast from the camera onto the placed mesh, fix the
//!    scanner's pivot and aim ([`fit_projector`]); the galvo's own calibration is kept.
//! 3. **Per frame** (section 6.1): the beam's entry point from the fitted projector and the
//!    galvo code in the trigger's snapshot ([`incidence`]); whether the camera sees the spot
//!    and where its sub-pixel peak lies (a check of the calibration, reported); the frame
//!    resampled at the visible vertices into the entry triangle's three columns by barycentric
//!    weight ([`Accumulator`]), lasers into R, G, B by wavelength, views combined by
//!    confidence. Frames are streamed a chunk at a time: memory is `F` plus one chunk, and
//!    the data of one view step's kept kernel spots (their rates pooled at the step's end).
//! 4. **Interpolation** (section 6.2, [`interpolate`]): missing entries and never-lit columns
//!    filled on the mesh, `F` made symmetric. The local term (section 7) and the detail texture
//!    `T_ρ` (section 6.3, [`frame_ratios`]) are gathered from the same frames in step 3.
//! 5. **Held out**: with `[plan.fit] held_out = N`, every N-th spot of the grid is left out of
//!    1–4 and its frames predicted from `F` afterwards ([`HeldOut`]).

use std::collections::HashMap;
use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};

use lightrig_pipelines::disco::atlas::Atlas;
use lightrig_pipelines::disco::detail::{
    frame_ratios, vertex_detail, DetailAccumulator, DetailParams, DetailTexture, DetailView,
};
use lightrig_pipelines::disco::falloff;
use lightrig_pipelines::disco::interpolate::{interpolate, FillParams, FillReport, Matrix};
use lightrig_pipelines::disco::kernel::{self, Sample};
use lightrig_pipelines::disco::local::{
    pool, spot_samples, spot_sigma, Blurs, LocalAccumulator, LocalParams, LocalTextures, PoolSpot, SpotKernel,
};
use lightrig_pipelines::disco::mesh::SurfaceMesh;
use lightrig_pipelines::disco::optics::{Hit, Pinhole, Projector};
use lightrig_pipelines::disco::projector_pose::{entry_shift, fit_projector, HitPoint, ProjectorFit};
use lightrig_pipelines::disco::register::{
    agreement, register_global, render, silhouette, Pose, SilhouetteView, ViewAgreement,
};
use lightrig_pipelines::disco::relight;
use lightrig_pipelines::disco::resample::{
    background_sigma, beam_sigma, flux_scale, spot_peak, Accumulator, Incidence, ViewLimits, ViewMap,
};
use lightrig_pipelines::disco::scan::{check as check_scan, drop_unused, orient, Orientation, ScanCheck};
use lightrig_pipelines::firs::mesh::{write_ply, Mesh};
use lightrig_pipelines::vec3::{dot, norm, normalize, sub, V3};
use lightrig_protocol::event::TriggerEvent;
use rayon::prelude::*;
use serde_json::{json, Value};

use super::{fail, FitError};
use crate::disco::DiscoSetup;
use crate::mesh_file::{read_mesh, MeshFormat};
use crate::rigfile::RigFile;
use crate::session::{FrameRecord, SessionIndex, StepId, StepRecords};

/// A frame is noise below this many background σ.
pub const FLOOR_SIGMAS: f32 = 5.0;

/// The held-out spots' frames predicted from the fitted `F`.
#[derive(Debug, Clone, Default)]
pub struct HeldOut {
    /// Frames predicted (of the frames held out, at most [`MAX_HELD_SCORED`], every k-th in the
    /// session's order).
    pub frames: usize,
    /// Pixels compared (on the object, above the noise floor, beyond `near_mm` of the spot, on
    /// triangles clear of the entry triangle's vertices and their rings).
    pub pixels: usize,
    /// Relative RMS error of the prediction over those pixels, `√(Σ(p−m)²/Σm²)`, median over
    /// frames.
    pub median_rel_rms: f64,
    /// The near field left out, mm from the entry point (the local term's domain).
    pub near_mm: f64,
    /// The near field predicted by the local term instead (the kernel at the held-out spot's
    /// texel — filled from its neighbours, since the spot was left out — through the beam's
    /// blur, times the correction texture): frames (those entering within the local fit's
    /// incidence limit), pixels (within its data radius of the spot, above 4× the noise
    /// floor), median relative RMS.
    pub near_frames: usize,
    pub near_pixels: usize,
    pub near_rel_rms: f64,
}

/// What the fit made.
#[derive(Debug, Clone)]
pub struct DiscoFit {
    pub mesh: SurfaceMesh,
    /// `F`, filled and symmetric (mm⁻²).
    pub matrix: Matrix,
    /// Entries measured (before the fill), `k·n + r`.
    pub observed: Vec<bool>,
    pub fill: FillReport,
    /// Gain × flux per colour channel (R, G, B lasers), from the white balance.
    pub flux: [f64; 3],
    /// The beam's σ, mm, from its spot on the white target.
    pub beam_sigma_mm: f64,
    /// Views (turntable angle × camera position).
    pub views: usize,
    /// Laser frames read; of them, resampled into `F`; whose beam missed the object or entered
    /// too grazing; held out.
    pub frames: usize,
    pub used: usize,
    pub missed: usize,
    pub held_out_frames: usize,
    /// Frames whose spot the camera saw, and the median distance between the spot's sub-pixel
    /// peak on the mesh and the projector's entry point, mm.
    pub spots_seen: usize,
    pub peak_offset_mm: f64,
    /// Columns whose incident vertex was lit.
    pub lit_columns: usize,
    pub held_out: HeldOut,
    /// The first camera position's camera (the relit picture's), and η.
    pub camera: Pinhole,
    pub eta: f64,
    /// The fall-off taken out for the interpolation, per channel (none: too few entries).
    pub falloff: Option<[falloff::Falloff; 3]>,
    /// The local term (section 7): the atlas, each spot's fitted `m(d)`, the filled textures,
    /// the spots the camera did not see (no data within δ2 of the entry point: hidden, or lit in
    /// one or two lasers only), and those whose fit failed (too few data farther out: at the
    /// object's silhouette).
    pub atlas: Atlas,
    pub spots: Vec<SpotKernel>,
    pub local: LocalTextures,
    /// The detail texture `T_ρ` on the atlas (section 6.3).
    pub detail: DetailTexture,
    /// Each vertex's skin relative to its ring ([`vertex_detail`]): the local term's light
    /// leaves through it.
    pub detail_vertices: Vec<[f32; 3]>,
    pub local_hidden: usize,
    pub local_failed: usize,
    /// Frames whose spot the camera saw near its beam's mirror direction: their pixels near
    /// the spot left out of `F` and the spot out of the local fit ([`ViewLimits::glint_deg`]).
    pub glint_frames: usize,
    /// Spots fitted but not kept ([`LocalParams::accepts`]: misfit, or no fast term), with
    /// their fits (in `fit.json` beside the kept ones, for a look at why).
    pub local_rejected: Vec<SpotKernel>,
    pub local_params: LocalParams,
    /// The scanned mesh as read and checked.
    pub scan: ScanReport,
    /// The mesh's pose on the turntable from the registration frames (none: the plan took
    /// none, and the mesh is used as placed).
    pub registration: Option<RegistrationReport>,
    /// The projector's pose fitted to the spots seen (section 4.4).
    pub projector: ProjectorReport,
    /// Each phase in order: its name, its wall time in s and the process's peak resident
    /// memory at its end (MiB; where the system says).
    pub phases: Vec<Phase>,
}

/// One phase of the fit, for the benchmark's break-down.
#[derive(Clone, Debug)]
pub struct Phase {
    pub name: &'static str,
    pub seconds: f64,
    pub peak_mib: Option<f64>,
}

/// This process's peak resident memory so far (VmHWM), MiB; Linux only.
pub fn peak_resident_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse::<f64>().ok().map(|kib| kib / 1024.0)
}

/// One laser frame to resample.
struct Job {
    view: usize,
    channel: usize,
    code: [u16; 2],
    file: PathBuf,
    held_out: bool,
}

/// A frame's result, computed in parallel.
struct Done {
    inc: Option<Incidence>,
    img: Vec<f32>,
    floor: f32,
    peak_offset: Option<f64>,
    /// The frame's data near its spot, for the local term.
    local: Vec<(u32, Sample)>,
    /// The detail texture's ratios ([`frame_ratios`]).
    ratios: Vec<(u32, f32, f32)>,
}

/// A spot's local data while its three lasers' frames come in.
struct Pending {
    samples: Vec<(u32, Sample)>,
    channels: u8,
    point: V3,
    angle_deg: f64,
    sigma_mm: f64,
}

/// A kept spot awaiting its view step's pooling: the spot, its data as sampled (for the
/// correction texture) and divided by the detail texture (for the rates).
type KeptSpot = (SpotKernel, Vec<(u32, Sample)>, Vec<Sample>);

/// A held-out frame: what its prediction needs (the image is read again then).
struct Held {
    view: usize,
    channel: usize,
    inc: Incidence,
    file: PathBuf,
    floor: f32,
}

/// Colour channel of each of the plan's three lasers: by wavelength, longest red.
pub fn colour_channels(rig: &RigFile, lasers: &[u8]) -> Result<HashMap<u8, usize>, FitError> {
    let mut l: Vec<(u16, u8)> = lasers
        .iter()
        .map(|&c| rig.lasers.iter().find(|x| x.channel == c).map(|x| (x.wavelength_nm, c)))
        .collect::<Option<_>>()
        .ok_or_else(|| fail("the plan names a laser the rig file lacks"))?;
    if l.len() != 3 {
        return Err(fail(format!(
            "[plan] lasers: a DISCO fit needs three lasers (red, green, blue), the plan has {}",
            l.len()
        )));
    }
    l.sort_by_key(|x| std::cmp::Reverse(x.0));
    Ok(l.iter().enumerate().map(|(k, &(_, c))| (c, k)).collect())
}

/// A whole frame, its first channel (see [`read_band`]).
fn read_plane(path: &Path, w: u32, h: u32) -> Result<Vec<f32>, FitError> {
    read_band(path, w, h, 0..h as usize).map(|(plane, _)| plane)
}

/// Rows `rows` of a one-channel frame (of an EXR, only the blocks that hold them decoded): the
/// plane at full size, zero outside the rows read, and those rows (a superset of `rows`).
fn read_band(path: &Path, w: u32, h: u32, rows: Range<usize>) -> Result<(Vec<f32>, Range<usize>), FitError> {
    let (img, read) = lightrig_imaging::io::read_rows(path, rows.start as u32..rows.end as u32)
        .map_err(|e| fail(format!("{}: {e}", path.display())))?;
    if img.width != w || img.height != h {
        return Err(fail(format!(
            "{}: the frame is {} × {}, the rig file's [plan.fit] image is {w} × {h}; fix image (or the camera's ROI)",
            path.display(),
            img.width,
            img.height
        )));
    }
    let c = usize::from(img.channels.max(1));
    let plane = if c == 1 { img.data } else { img.data.iter().step_by(c).copied().collect() };
    Ok((plane, read.start as usize..read.end as usize))
}

/// The rows of a view's frames that show the object, `margin` rows either side (a bilinear
/// look-up at a vertex on the outline reaches a row past it): all the frame pass reads.
fn object_rows(map: &ViewMap, w: usize, h: usize, margin: usize) -> Range<usize> {
    let first = map.surface.iter().position(Option::is_some);
    let last = map.surface.iter().rposition(Option::is_some);
    match (first, last) {
        (Some(a), Some(b)) => (a / w).saturating_sub(margin)..(b / w + 1 + margin).min(h),
        _ => 0..0,
    }
}

/// The background's noise in the rows of a frame that were read (see [`background_sigma`]).
fn band_sigma(img: &[f32], surface: &[Option<Hit>], w: usize, rows: &Range<usize>) -> f32 {
    let r = rows.start * w..rows.end * w;
    background_sigma(&img[r.clone()], &surface[r], 7)
}

/// Reads and fits the DISCO session in `dir`; `mesh` overrides `[plan.fit] mesh`. `progress`
/// gets (frames done, frames in all).
pub fn fit_session(
    dir: &Path,
    mesh: Option<&Path>,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<DiscoFit, FitError> {
    // The journal indexed, each step's records read back when it is processed: memory does
    // not grow with the session's frames.
    let s = SessionIndex::read(dir).map_err(|e| fail(e.to_string()))?;
    let m = s.manifest();
    let method = m.plan.extra.get("method").and_then(Value::as_str).unwrap_or("");
    if method != "disco" {
        return Err(fail(format!(
            "{}: a `{method}` session; `lightrig fit disco` reads DISCO sessions",
            dir.display()
        )));
    }
    if !s.is_done() {
        return Err(fail(format!("{}: not complete; `lightrig resume` it first", dir.display())));
    }
    let rig = crate::fit::session_rig(&m.rig, dir)?;
    let mut setup = DiscoSetup::from_rig(&rig).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let mesh_path = match (mesh, &setup.mesh) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some(p)) => dir.join(p),
        (None, None) => {
            return Err(fail(format!(
            "{}: no mesh: give `--mesh FILE.ply` or `[plan.fit] mesh` (relative to the session directory)",
            dir.display()
        )))
        }
    };
    let (scan, scan_report) = read_scan(&mesh_path, setup.mesh_unit_mm)?;
    let camera = s.pipeline_camera(None).map_err(fail)?;
    let table = rig
        .stepper_named("turntable")
        .or_else(|| rig.steppers.iter().find(|x| x.kind == lightrig_protocol::config::AxisKind::Rotary))
        .ok_or_else(|| fail("the rig file has no turntable (a rotary [[stepper]])"))?;
    let limits = ViewLimits { eta: setup.eta, ..ViewLimits::default() };
    let (w, h) = (setup.cameras[0].1.width, setup.cameras[0].1.height);
    let plan_meta = m.plan.extra.get("meta").cloned().unwrap_or(Value::Null);
    let grid: Vec<[u16; 2]> = plan_meta
        .get("grid")
        .and_then(Value::as_array)
        .map(|a| {
            a.iter().filter_map(|p| Some([p.get(0)?.as_u64()? as u16, p.get(1)?.as_u64()? as u16])).collect()
        })
        .unwrap_or_default();
    let records = |id: StepId| s.step(id).map_err(|e| fail(e.to_string()));

    // 1. White balance, from the `white` step wherever the plan has it (read once the
    // projector is fitted, below).
    let mut flux = [f64::NAN; 3];
    let mut beam_sigma_mm = 0.0;
    let lasers_of_plan: Vec<u8> = m
        .plan
        .steps
        .iter()
        .find_map(|p| {
            let a = p.extra.get("meta")?.get("lasers")?.as_array()?;
            Some(a.iter().filter_map(|x| x.as_u64().map(|v| v as u8)).collect())
        })
        .unwrap_or_default();
    let channels = colour_channels(&rig, &lasers_of_plan)?;
    let kind_of = |p: &crate::session::PlanStep| -> String {
        p.extra.get("meta").and_then(|m| m.get("kind")).and_then(Value::as_str).unwrap_or("view").to_string()
    };
    let channel_of = |t: &TriggerEvent| {
        channels.iter().find(|(l, _)| t.snapshot.lasers & (1 << **l) != 0).map(|(_, &c)| c)
    };
    let clock = std::time::Instant::now();
    let mut phases: Vec<Phase> = Vec::new();
    let mut lap = |name: &'static str| {
        let t = clock.elapsed().as_secs_f64();
        let before: f64 = phases.iter().map(|p| p.seconds).sum();
        phases.push(Phase { name, seconds: t - before, peak_mib: peak_resident_mib() });
    };
    // 2a. The object's pose on the turntable.
    let spotlights = match rig.plan.get("registration").and_then(|v| v.as_str()) {
        None => None,
        Some(name) => {
            Some(rig.lasers.iter().find(|l| l.name.as_deref() == Some(name)).map(|l| l.channel).ok_or_else(
                || {
                    fail(format!(
                        "[plan] registration = \"{name}\": the rig file has no [[laser]] of that name"
                    ))
                },
            )?)
        }
    };
    let registration = match spotlights {
        None => None,
        Some(c) => {
            let frames = registration_frames(&s, &m.plan.steps, camera, c, table, dir)?;
            Some(register_mesh(&scan, &mesh_path, &setup, &frames, (w, h))?)
        }
    };
    let mesh = SurfaceMesh::new(&match &registration {
        Some(r) => r.pose.place(&scan),
        None => scan,
    });
    lap("registration");
    // 2b. The projector's pose from the spots on the placed mesh (section 4.4).
    let distinct = |k: usize| {
        let mut v: Vec<u16> = grid.iter().map(|g| g[k]).collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    let (grid_xs, grid_ys) = (distinct(0), distinct(1));
    let view_steps: Vec<&crate::session::PlanStep> =
        m.plan.steps.iter().filter(|p| kind_of(p) != "white").collect();
    let mut spot_frames: Vec<SpotFrame> = Vec::new();
    let stride = view_steps.len().div_ceil(PROJECTOR_VIEWS).max(1);
    for p in view_steps.iter().step_by(stride) {
        let pos =
            p.extra.get("meta").and_then(|m| m.get("camera_position")).and_then(Value::as_u64).unwrap_or(0)
                as usize;
        if pos >= setup.cameras.len() {
            continue; // refused, with the step named, below
        }
        // The green laser's spots (the brightest in the camera); where a view has too few,
        // every laser's (a spot's peak is where its beam enters, whatever its colour).
        let step = records(p.id)?;
        let laser: Vec<(&FrameRecord, &TriggerEvent, usize)> = step
            .camera_frames(camera)
            .filter_map(|f| {
                let t = step.trigger_of(f)?;
                let c = channel_of(t)?;
                Some((f, t, c))
            })
            .collect();
        let green = laser.iter().filter(|x| x.2 == 1).count();
        let lit: Vec<(&FrameRecord, &TriggerEvent)> = laser
            .into_iter()
            .filter(|x| green < PROJECTOR_SPOTS_PER_VIEW || x.2 == 1)
            .map(|(f, t, _)| (f, t))
            .collect();
        // Every k-th spot along the grid's diagonals: all its rows and columns.
        let every = lit.len().div_ceil(PROJECTOR_SPOTS_PER_VIEW).max(1);
        for (f, t) in lit {
            let steps = t.snapshot.axes.get(usize::from(table.axis)).copied().unwrap_or(0);
            let code = t.snapshot.galvos.first().map_or([0, 0], |g| [g.x, g.y]);
            let rank = |v: &[u16], c: u16| v.partition_point(|&x| x < c);
            if (rank(&grid_xs, code[0]) + rank(&grid_ys, code[1])) % every != 0 {
                continue;
            }
            spot_frames.push(SpotFrame {
                pos,
                deg: table.units(i64::from(steps)).unwrap_or(0.0),
                code: code.map(f64::from),
                file: dir.join(&f.file),
            });
        }
    }
    let projector = calibrate_projector(&mesh, &setup, &limits, &spot_frames, (w, h))?;
    setup.projector = projector.projector;
    lap("projector");
    // 1. White balance (after the projector: the spot on the target is where its beam meets it).
    let mut white_seen = false;
    for p in m.plan.steps.iter().filter(|p| kind_of(p) == "white") {
        white_seen = true;
        let (_, cam) = setup.cameras[0];
        let mut sums = [(0.0, 0usize); 3];
        let mut widths = Vec::new();
        let step = records(p.id)?;
        for f in step.camera_frames(camera) {
            let t = trigger(&step, f, dir)?;
            let Some(c) = channel_of(t) else { continue };
            let img = read_plane(&dir.join(&f.file), w, h)?;
            let code = t.snapshot.galvos.first().map_or([0.0; 2], |g| [f64::from(g.x), f64::from(g.y)]);
            let centre = beam_on_plane(&setup, code);
            sums[c].0 += flux_scale(&img, &cam, &setup.white, centre, 25.0);
            sums[c].1 += 1;
            widths.extend(beam_sigma(&img, &cam, &setup.white, setup.projector.ray(code), centre, 10.0));
        }
        for c in 0..3 {
            if sums[c].1 > 0 {
                flux[c] = sums[c].0 / sums[c].1 as f64;
            }
        }
        if !widths.is_empty() {
            beam_sigma_mm = widths.iter().sum::<f64>() / widths.len() as f64;
        }
    }
    if !white_seen || flux.iter().any(|f| !f.is_finite() || *f <= 0.0) {
        return Err(fail(format!(
            "{}: no usable white balance (a `white` step with one frame per laser on the white target); acquire with `white_balance = true` and [plan.fit] white_target",
            dir.display()
        )));
    }

    // 2–3. Step by step: each new view mapped once, the step's frames streamed a chunk at a
    // time (memory: `F`'s sums, the views, one chunk of frames, the step's job list).
    let grid_index: HashMap<[u16; 2], usize> = grid.iter().enumerate().map(|(i, &g)| (g, i)).collect();
    let total: u64 = view_steps.iter().map(|p| u64::from(s.frame_count(p.id, camera))).sum();
    let mut views: Vec<(usize, f64)> = Vec::new();
    let mut maps: Vec<ViewMap> = Vec::new();
    // Per view, the rows of its frames that show the object.
    let mut bands: Vec<Range<usize>> = Vec::new();
    let n = mesh.vertices.len();
    let mut acc = Accumulator::new(&mesh);
    let (mut frames, mut used, mut missed, mut seen, mut offsets) =
        (0usize, 0usize, 0usize, 0usize, Vec::new());
    let mut held: Vec<Held> = Vec::new();
    let near_mm = 2.0 * mesh.mean_edge();
    let local_params = LocalParams::default();
    let atlas = Atlas::build(&mesh, local_params.texel_mm, 3);
    let blurs = Blurs::new(local_params.radius_mm + 1.0);
    let mut local = LocalAccumulator::new(&atlas);
    let detail_params = DetailParams { eta: setup.eta, ..DetailParams::default() };
    let mut detail_views: Vec<DetailView> = Vec::new();
    let mut detail_acc = DetailAccumulator::new(&atlas);
    let mut pending: HashMap<(usize, [u16; 2]), Pending> = HashMap::new();
    let mut spots: Vec<SpotKernel> = Vec::new();
    let (mut local_hidden, mut local_failed, mut glint_frames) = (0usize, 0usize, 0usize);
    let mut local_rejected: Vec<SpotKernel> = Vec::new();
    // A view step's kept spots (their raw and detail-divided data), pooled at its end.
    let mut step_kept: Vec<KeptSpot> = Vec::new();
    let mut done_count = 0u64;
    for p in view_steps {
        let meta = p.extra.get("meta").cloned().unwrap_or(Value::Null);
        let pos = meta.get("camera_position").and_then(Value::as_u64).unwrap_or(0) as usize;
        if pos >= setup.cameras.len() {
            return Err(fail(format!(
                "step {} ({}): camera position {pos}, but [plan] camera_positions has {}",
                p.id,
                p.name,
                setup.cameras.len()
            )));
        }
        let step = records(p.id)?;
        let mut jobs: Vec<Job> = Vec::new();
        for f in step.camera_frames(camera) {
            let t = trigger(&step, f, dir)?;
            let Some(c) = channel_of(t) else {
                done_count += 1;
                continue; // the registration frame
            };
            let steps = t.snapshot.axes.get(usize::from(table.axis)).copied().unwrap_or(0);
            let deg = table.units(i64::from(steps)).unwrap_or(0.0);
            let view = match views.iter().position(|&(q, d)| q == pos && (d - deg).abs() < 1e-6) {
                Some(v) => v,
                None => {
                    views.push((pos, deg));
                    let map = ViewMap::new(&mesh, &setup.cameras[pos].1, deg, &limits);
                    detail_views.push(DetailView::new(&mesh, &atlas, &map, &detail_params));
                    bands.push(object_rows(&map, w as usize, h as usize, 4));
                    maps.push(map);
                    views.len() - 1
                }
            };
            let code = t.snapshot.galvos.first().map_or([0, 0], |g| [g.x, g.y]);
            let index = grid_index.get(&code).copied().unwrap_or(0);
            let held_out = setup.held_out > 1 && index % setup.held_out == setup.held_out / 2;
            jobs.push(Job { view, channel: c, code, file: dir.join(&f.file), held_out });
        }
        frames += jobs.len();
        // A chunk decoded while the one before is summed into `F` (in order, on one thread):
        // the sums do not wait for the decoding nor leave a core idle (two chunks of 32 frames
        // held at a time).
        let decode = |chunk: &[Job]| -> Vec<Result<Done, FitError>> {
            chunk
                .par_iter()
                .map(|j| {
                    let map = &maps[j.view];
                    let (img, rows) = read_band(&j.file, w, h, bands[j.view].clone())?;
                    let origin = setup.projector.eye;
                    let dir_ = setup.projector.ray([f64::from(j.code[0]), f64::from(j.code[1])]);
                    let inc = map.incidence(&mesh, origin, dir_, &limits);
                    let floor = FLOOR_SIGMAS * band_sigma(&img, &map.surface, w as usize, &rows);
                    let peak_offset = inc.as_ref().and_then(|inc| spot_offset(&mesh, map, inc, &img, floor));
                    let local = match &inc {
                        // A glint would be the fast term: such a spot is not fitted.
                        Some(inc)
                            if !j.held_out
                                && inc.angle_deg <= local_params.max_incidence_deg
                                && inc.glint_mm == 0.0 =>
                        {
                            spot_samples(
                                &mesh,
                                &atlas,
                                map,
                                inc,
                                &img,
                                j.channel as u8,
                                flux[j.channel],
                                floor,
                                setup.eta,
                                &local_params,
                            )
                        }
                        _ => Vec::new(),
                    };
                    let ratios = match &inc {
                        Some(inc) if !j.held_out => frame_ratios(
                            &atlas,
                            &detail_views[j.view],
                            map,
                            &img,
                            inc.object,
                            floor,
                            &detail_params,
                        ),
                        _ => Vec::new(),
                    };
                    Ok(Done { inc, img, floor, peak_offset, local, ratios })
                })
                .collect()
        };
        // Sums a decoded chunk into `F`, the detail texture and the spots, in the frames' order.
        let mut sum = |chunk: &[Job], results: Vec<Result<Done, FitError>>| -> Result<(), FitError> {
            for (j, r) in chunk.iter().zip(results) {
                let d = r?;
                done_count += 1;
                if let Some(o) = d.peak_offset {
                    seen += 1;
                    offsets.push(o);
                }
                let Some(inc) = d.inc else {
                    missed += 1;
                    continue;
                };
                if j.held_out {
                    // The frame is read again for the comparison after the fit.
                    held.push(Held {
                        view: j.view,
                        channel: j.channel,
                        inc,
                        file: j.file.clone(),
                        floor: d.floor,
                    });
                    continue;
                }
                acc.add(&mesh, &maps[j.view], &inc, &d.img, j.channel, flux[j.channel], d.floor);
                detail_acc.add(j.channel, &d.ratios);
                used += 1;
                if inc.glint_mm > 0.0 {
                    glint_frames += 1;
                    continue;
                }
                if inc.angle_deg > local_params.max_incidence_deg {
                    continue;
                }
                let e = pending.entry((j.view, j.code)).or_insert_with(|| Pending {
                    samples: Vec::new(),
                    channels: 0,
                    point: inc.object,
                    angle_deg: inc.angle_deg,
                    sigma_mm: spot_sigma(beam_sigma_mm, &mesh, &maps[j.view], &inc),
                });
                e.samples.extend(d.local);
                e.channels |= 1 << j.channel;
            }
            // Spots with all three lasers in: fitted in parallel, recorded, dropped; in the
            // order of their keys, not the map's, so that a fit gives the same spots in the same
            // order (and the same textures to the bit) every time.
            let ready: Vec<((usize, [u16; 2]), Pending)> = {
                let mut keys: Vec<(usize, [u16; 2])> =
                    pending.iter().filter(|(_, p)| p.channels == 7).map(|(k, _)| *k).collect();
                keys.sort_unstable();
                keys.into_iter().filter_map(|k| pending.remove(&k).map(|p| (k, p))).collect()
            };
            // The data divided by the detail texture as the frames so far show it (by a spot's
            // last laser, its view's earlier lasers have shown most texels near it from afar):
            // a line of the skin's through a spot's data bends its fall-off.
            let fitted: Vec<(Vec<Sample>, Option<kernel::Profile>)> = ready
                .par_iter()
                .map(|(_, p)| {
                    let data: Vec<Sample> = p
                        .samples
                        .iter()
                        .map(|&(t, s)| {
                            let skin = detail_acc.current(t, usize::from(s.channel)).filter(|&v| v > 0.05);
                            Sample { value: s.value / skin.unwrap_or(1.0), ..s }
                        })
                        .collect();
                    let f = kernel::fit(&data, &blurs.at(p.sigma_mm), &local_params.stages);
                    (data, f)
                })
                .collect();
            for (((view, code), p), (data, f)) in ready.into_iter().zip(fitted) {
                let spot = |profile| SpotKernel {
                    view,
                    code,
                    point: p.point,
                    angle_deg: p.angle_deg,
                    sigma_mm: p.sigma_mm,
                    profile,
                    samples: p.samples.len(),
                    pooled: 1,
                };
                match f {
                    Some(f) if local_params.accepts(&f) => step_kept.push((spot(f), p.samples, data)),
                    Some(f) => local_rejected.push(spot(f)),
                    None if p.samples.iter().any(|s| s.1.d < local_params.stages.delta2) => local_failed += 1,
                    None => local_hidden += 1,
                }
            }
            progress(done_count, total);
            Ok(())
        };
        let chunks: Vec<&[Job]> = jobs.chunks(32).collect();
        let mut current = chunks.first().map(|c| decode(c));
        for (k, chunk) in chunks.iter().enumerate() {
            let results = current.take().unwrap_or_default();
            let (next, summed) = rayon::join(|| chunks.get(k + 1).map(|c| decode(c)), || sum(chunk, results));
            summed?;
            current = next;
        }
        // The view's kept spots: rates fitted with their neighbours', then recorded.
        let blur_of: Vec<std::sync::Arc<kernel::Blur>> =
            step_kept.iter().map(|(k, _, _)| blurs.at(k.sigma_mm)).collect();
        let pool_in: Vec<PoolSpot> = step_kept
            .iter()
            .zip(&blur_of)
            .map(|((k, _, data), b)| PoolSpot { point: k.point, samples: data, blur: b, own: k.profile })
            .collect();
        let pooled = pool(&pool_in, &local_params);
        drop(pool_in);
        for (((mut k, samples, _), (profile, n)), b) in step_kept.drain(..).zip(pooled).zip(&blur_of) {
            k.profile = profile;
            k.pooled = n;
            local.record(&atlas, b, &samples, k.point, &profile);
            spots.push(k);
        }
    }
    lap("frames: read, resampled, local data fitted");
    // Twice: the gradients the neighbouring columns show give a first `F` and its fall-off;
    // the fall-off's own gradient then moves each mean to its vertex (far less noisy than a
    // plane through a few neighbours' means).
    // One `F`-sized result at a time beside the sums (the fit's peak of memory).
    let (values, weights) = acc.nodal(&mesh, beam_sigma_mm, None);
    let first = Matrix { n, values, weight: weights };
    let (values, weights) = match falloff::fit(&mesh, &first, 2.0 * mesh.mean_edge()) {
        Some(f) => {
            drop(first);
            acc.nodal(&mesh, beam_sigma_mm, Some(f.map(|x| x.s)))
        }
        None => (first.values, first.weight),
    };
    drop(acc);
    let detail = detail_acc.finish();
    drop(detail_acc);
    drop(detail_views);
    local_hidden += pending.len();
    let local_textures = local.finish(&atlas);
    let observed: Vec<bool> = weights.iter().map(|&w| w > 0.0).collect();
    let lit_columns = (0..n).filter(|&k| observed[k * n + k]).count();
    let mut matrix =
        Matrix { n, values, weight: observed.iter().map(|&o| if o { 1.0 } else { 0.0 }).collect() };
    lap("F at the vertices, the local textures filled");
    // 4. On `F` without its overall fall-off (see `falloff`'s docs), so that what the camera's
    // dynamic range cannot reach continues the measured decay.
    let d_min = 0.5 * mesh.mean_edge();
    let rates = falloff::fit(&mesh, &matrix, 2.0 * mesh.mean_edge());
    // Before `F` is made symmetric: its rows are the light leaving at each vertex.
    let detail_vertices = match rates {
        Some(f) => vertex_detail(&mesh, &matrix.values, &observed, &f, detail_params.min_distance_mm),
        None => vec![[1.0; 3]; n],
    };
    if let Some(s) = rates {
        falloff::apply(&mesh, &mut matrix, s, d_min, true);
    }
    let fill = interpolate(&mut matrix, &mesh.rings, &FillParams::default());
    if let Some(s) = rates {
        falloff::apply(&mesh, &mut matrix, s, d_min, false);
    }
    lap("F interpolated on the mesh");
    // 5.
    let model = HeldModel {
        mesh: &mesh,
        f: &matrix,
        atlas: &atlas,
        detail: &detail,
        local: &local_textures,
        blurs: &blurs,
        params: &local_params,
        flux,
        near_mm,
        beam_sigma_mm,
        eta: setup.eta,
    };
    let held_out = predict_held_out(&model, (&maps, &bands), &held, (w, h))?;
    lap("held-out frames predicted");
    offsets.sort_by(f64::total_cmp);
    Ok(DiscoFit {
        observed,
        fill,
        flux,
        views: views.len(),
        frames,
        used,
        missed,
        held_out_frames: held.len(),
        spots_seen: seen,
        peak_offset_mm: offsets.get(offsets.len() / 2).copied().unwrap_or(f64::NAN),
        lit_columns,
        held_out,
        falloff: rates,
        atlas,
        spots,
        local: local_textures,
        detail,
        detail_vertices,
        local_hidden,
        local_failed,
        glint_frames,
        local_rejected,
        local_params,
        scan: scan_report,
        registration,
        projector,
        phases,
        beam_sigma_mm,
        camera: setup.cameras[0].1,
        eta: setup.eta,
        mesh,
        matrix,
    })
}

/// The scanned mesh as the fit read it: what reading and orienting changed, and the measures
/// it was checked by ([`lightrig_pipelines::disco::scan`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ScanReport {
    pub file: PathBuf,
    pub format: MeshFormat,
    /// The file's unit, mm.
    pub unit_mm: f64,
    pub polygons_split: usize,
    pub vertices_merged: usize,
    pub degenerate_dropped: usize,
    /// Vertices no triangle used, dropped.
    pub unused_dropped: usize,
    pub orientation: Orientation,
    pub check: ScanCheck,
}

/// Reads a lab's mesh file (any PLY or OBJ, [`read_mesh`]), scales it to mm, orients it and
/// checks it; a mesh the fit cannot use is an error naming the file, the measure and what
/// to do.
pub fn read_scan(path: &Path, unit_mm: f64) -> Result<(Mesh, ScanReport), FitError> {
    let file = read_mesh(path)
        .map_err(|e| fail(format!("{e}; give the object's scanned mesh with --mesh or [plan.fit] mesh")))?;
    let mut mesh = file.mesh;
    if unit_mm != 1.0 {
        for v in &mut mesh.vertices {
            *v = v.map(|c| c * unit_mm);
        }
    }
    let unused_dropped = drop_unused(&mut mesh);
    let orientation = orient(&mut mesh);
    let check = check_scan(&mesh);
    if let Some(why) = check.refusal() {
        return Err(fail(format!("{}: the DISCO fit cannot use this mesh: {why}", path.display())));
    }
    let report = ScanReport {
        file: path.to_path_buf(),
        format: file.format,
        unit_mm,
        polygons_split: file.polygons_split,
        vertices_merged: file.vertices_merged,
        degenerate_dropped: file.degenerate_dropped,
        unused_dropped,
        orientation,
        check,
    };
    Ok((mesh, report))
}

/// The registration's outcome, in the fit's summary.
#[derive(Debug, Clone)]
pub struct RegistrationReport {
    /// The scanned mesh's frame → the turntable's.
    pub pose: Pose,
    /// Views registered on (spread over all), and all views' agreement at the pose.
    pub views_used: usize,
    pub agreement: Vec<ViewAgreement>,
    pub evaluations: usize,
    /// The scan's own frame was too far from how the object stands: the search started from
    /// the views' visual hull ([`lightrig_pipelines::disco::hull`]).
    pub from_hull: bool,
}

impl RegistrationReport {
    /// The worst view's intersection over union.
    pub fn min_iou(&self) -> f64 {
        self.agreement.iter().map(|a| a.iou).fold(f64::INFINITY, f64::min)
    }
}

/// The views' silhouettes agree with the mesh at least this well, or the fit is refused.
pub const MIN_REGISTRATION_IOU: f64 = 0.95;
/// A registration from the scan's own frame whose worst view agrees less than this is
/// searched again from the visual hull: a wrong local optimum can pass the refusal's 95 %
/// (an egg turned 119° settled at 95.5 %), a right one agrees to 99.5 % and more.
const SETTLED_IOU: f64 = 0.99;
/// The registration runs on at most this many views, spread over the session's.
const REGISTRATION_VIEWS: usize = 12;

/// A registration frame: its step, camera position, turntable angle and file.
struct RegistrationFrame {
    step: String,
    position: usize,
    turntable_deg: f64,
    file: PathBuf,
}

/// The trigger event `f` was paired with, or an error naming the frame.
fn trigger<'a>(step: &'a StepRecords, f: &FrameRecord, dir: &Path) -> Result<&'a TriggerEvent, FitError> {
    step.trigger_of(f).ok_or_else(|| {
        fail(format!("{}: frame {} has no trigger record in the journal", dir.display(), f.file))
    })
}

/// Each view step's registration frame (the spotlights on channel `spot` alone); a view without
/// one is refused.
fn registration_frames(
    s: &SessionIndex,
    steps: &[crate::session::PlanStep],
    camera: u8,
    spot: u8,
    table: &crate::rigfile::Stepper,
    dir: &Path,
) -> Result<Vec<RegistrationFrame>, FitError> {
    let mut out = Vec::new();
    for p in steps {
        let meta = p.extra.get("meta").cloned().unwrap_or(Value::Null);
        if meta.get("kind").and_then(Value::as_str).unwrap_or("view") == "white" {
            continue;
        }
        let mut found = None;
        let step = s.step(p.id).map_err(|e| fail(e.to_string()))?;
        for f in step.camera_frames(camera) {
            let t = trigger(&step, f, dir)?;
            if t.snapshot.lasers == 1 << spot {
                let steps = t.snapshot.axes.get(usize::from(table.axis)).copied().unwrap_or(0);
                found = Some((f.file.clone(), table.units(i64::from(steps)).unwrap_or(0.0)));
                break;
            }
        }
        let Some((file, deg)) = found else {
            return Err(fail(format!(
                "{}: step {} ({}) has no registration frame (the spotlights, output {spot}, alone on), though the rig file's [plan] registration asks for one per view; re-acquire the session, or remove `registration` from the rig file in the session's manifest to fit with the mesh as placed",
                dir.display(),
                p.id,
                p.name
            )));
        };
        out.push(RegistrationFrame {
            step: format!("step {} ({})", p.id, p.name),
            position: meta.get("camera_position").and_then(Value::as_u64).unwrap_or(0) as usize,
            turntable_deg: deg,
            file: dir.join(file),
        });
    }
    Ok(out)
}

/// Places the scanned mesh on the turntable by the registration frames' silhouettes, from the
/// mesh's own frame as the first guess; refused where no pose makes them agree.
fn register_mesh(
    scan: &lightrig_pipelines::firs::mesh::Mesh,
    mesh_path: &Path,
    setup: &DiscoSetup,
    frames: &[RegistrationFrame],
    (w, h): (u32, u32),
) -> Result<RegistrationReport, FitError> {
    // A view searched on holds its silhouette and its outline distance (5 bytes a pixel): only
    // those views are held together; every other view is checked after by its silhouette
    // alone, one per thread at a time (the shipped plan has 144).
    let frame_mask = |f: &RegistrationFrame| -> Result<(Pinhole, Vec<bool>), FitError> {
        let img = read_plane(&f.file, w, h)?;
        let mask = silhouette(&img, w as usize, 8, 10.0).ok_or_else(|| {
            fail(format!(
                "{}: {}'s registration frame shows no object against a dark border; check the spotlights and that the object stands clear of the frame's edges",
                f.file.display(),
                f.step
            ))
        })?;
        let cam = setup.cameras.get(f.position).map(|c| c.1).ok_or_else(|| {
            fail(format!(
                "{}: camera position {}, but [plan] camera_positions has {}",
                f.step,
                f.position,
                setup.cameras.len()
            ))
        })?;
        Ok((cam, mask))
    };
    if frames.is_empty() {
        return Err(fail("the session has no views to register the mesh on"));
    }
    let stride = frames.len().div_ceil(REGISTRATION_VIEWS);
    let picked: Vec<&RegistrationFrame> = frames.iter().step_by(stride).collect();
    let used: Vec<SilhouetteView> = picked
        .par_iter()
        .map(|f| frame_mask(f).map(|(cam, mask)| SilhouetteView::new(cam, f.turntable_deg, mask)))
        .collect::<Result<_, FitError>>()?;
    let (r, from_hull) = register_global(scan, &used, Pose::IDENTITY, SETTLED_IOU);
    drop(used);
    // The views searched on were checked at the pose by the search.
    let checked: Vec<ViewAgreement> = frames
        .par_iter()
        .enumerate()
        .map(|(i, f)| {
            if i % stride == 0 {
                return Ok(r.views[i / stride]);
            }
            let (cam, mask) = frame_mask(f)?;
            let mut buf = Vec::new();
            render(scan, &r.pose, &cam, f.turntable_deg, &mut buf);
            Ok(agreement(&mask, &buf))
        })
        .collect::<Result<_, FitError>>()?;
    let report = RegistrationReport {
        pose: r.pose,
        views_used: picked.len(),
        agreement: checked,
        evaluations: r.evaluations,
        from_hull,
    };
    let (worst, a) = report
        .agreement
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.iou.total_cmp(&b.1.iou))
        .map(|(i, a)| (i, *a))
        .unwrap_or((0, ViewAgreement { mismatched: 0, iou: 0.0 }));
    if a.iou < MIN_REGISTRATION_IOU {
        return Err(fail(format!(
            "{}: the mesh's silhouette does not match the object's at any pose, searched from the mesh's own frame and from the views' visual hull: {} agrees to {:.1} % (intersection over union; {} pixels differ). Check that it is this object's scan, in mm, and that the registration frames show the whole object clear of their edges",
            mesh_path.display(),
            frames[worst].step,
            100.0 * a.iou,
            a.mismatched
        )));
    }
    Ok(report)
}

/// Views whose spots fix the projector's pose (spread over the session), and spots per view.
const PROJECTOR_VIEWS: usize = 12;
const PROJECTOR_SPOTS_PER_VIEW: usize = 256;
/// Spots are dropped as outliers beyond 3 × the median distance from their fitted beams, but
/// never nearer than this, mm.
const PROJECTOR_FLOOR_MM: f64 = 0.1;
/// Spots used: the rig file's beam enters within this angle of the normal, and the camera
/// sees the entry point (and the spot's peak) with at least this cosine.
const PROJECTOR_MAX_ANGLE_DEG: f64 = 45.0;
const PROJECTOR_MIN_FACING: f64 = 0.5;
/// How far from the rig file's entry point a spot is looked for, mm.
pub const PROJECTOR_SEARCH_MM: f64 = 12.0;
/// A projector fit whose points scatter more than this about their beams (RMS, mm) is refused.
pub const PROJECTOR_MAX_RMS_MM: f64 = 0.5;

/// A laser frame whose spot places the projector.
struct SpotFrame {
    pos: usize,
    deg: f64,
    code: [f64; 2],
    file: PathBuf,
}

/// The projector's pose, fitted to the spots seen, in the fit's summary.
#[derive(Debug, Clone)]
pub struct ProjectorReport {
    /// The fitted projector (used for every entry point).
    pub projector: Projector,
    /// How far the rig file's pivot moved (mm) and its axes turned (degrees).
    pub moved_mm: f64,
    pub turned_deg: f64,
    /// How far the entry points moved on the object, the farthest over the mesh at the views'
    /// turntable angles, mm ([`entry_shift`]).
    pub shift_mm: f64,
    /// Frames looked at; spots used and dropped (outliers); the used spots' RMS and largest
    /// distance from their beams, mm.
    pub frames: usize,
    pub used: usize,
    pub dropped: usize,
    pub rms_mm: f64,
    pub max_mm: f64,
}

/// Each frame's spot: the rig file's projector says roughly where it entered; its sub-pixel
/// peak within [`PROJECTOR_SEARCH_MM`] of that, cast from the camera onto the mesh, is where it
/// did. The projector is fitted to those points, then the spots are chosen again with the
/// fitted projector and the fit repeated from it: which spots pass the incidence, facing and
/// glint checks follows the projector they are judged by, and judged by the hand-measured one
/// the choice (and so the result) depended on how far off it was. The frames are read once:
/// the peaks are found by the rig file's projector, only the choice is made twice.
fn calibrate_projector(
    mesh: &SurfaceMesh,
    setup: &DiscoSetup,
    limits: &ViewLimits,
    frames: &[SpotFrame],
    (w, h): (u32, u32),
) -> Result<ProjectorReport, FitError> {
    let start = setup.projector;
    let seen = projector_spots(mesh, setup, limits, frames, (w, h))?;
    let first =
        fit_projector_checked(&start, &judge_spots(mesh, setup, &start, limits, &seen), frames.len())?;
    let hits = judge_spots(mesh, setup, &first.projector, limits, &seen);
    let fit = fit_projector_checked(&first.projector, &hits, frames.len())?;
    let mut angles: Vec<f64> = frames.iter().map(|f| f.deg).collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup();
    // The two fits' corrections together: the pivot's move and the axes' turn (from the trace
    // of the rotation taking the rig file's axes to the fitted ones).
    let trace: f64 = (0..3).map(|i| dot(start.axes[i], fit.projector.axes[i])).sum();
    Ok(ProjectorReport {
        projector: fit.projector,
        moved_mm: norm(sub(fit.projector.eye, start.eye)),
        turned_deg: ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees(),
        shift_mm: entry_shift(&start, &fit.projector, mesh, &angles),
        frames: frames.len(),
        used: fit.used,
        dropped: fit.dropped,
        rms_mm: fit.rms_mm,
        max_mm: fit.max_mm,
    })
}

/// [`fit_projector`], refused when too few spots were seen or its beams miss them.
fn fit_projector_checked(
    start: &Projector,
    hits: &[HitPoint],
    frames: usize,
) -> Result<ProjectorFit, FitError> {
    let fit = fit_projector(start, hits, PROJECTOR_FLOOR_MM).ok_or_else(|| {
        fail(format!(
            "the laser projector's pose: {} spots seen near where [plan.fit] projector puts them, in {} frames looked at; too few to fit it (at least 12). Check [plan.fit] projector (the scanner's pivot and aim, within some 10 mm and 3°) and the galvo's calibration; a plan with more spots per view gives more",
            hits.len(),
            frames
        ))
    })?;
    if fit.rms_mm > PROJECTOR_MAX_RMS_MM {
        return Err(fail(format!(
            "the laser projector's pose: its beams miss the {} spots seen by {:.2} mm RMS (at most {PROJECTOR_MAX_RMS_MM} mm); check the galvo's calibration ([[galvo]] urad_per_code, zero_code) and [plan.fit] projector",
            fit.used, fit.rms_mm
        )));
    }
    Ok(fit)
}

/// A frame's spot as the camera shows it: its galvo code, and its sub-pixel peak cast onto
/// the mesh (object frame) with how squarely the surface there faces the camera.
struct SeenSpot {
    code: [f64; 2],
    point: V3,
    facing: f64,
}

/// The spots of a view (camera position, turntable angle) as the camera showed them.
struct ViewSpots {
    pos: usize,
    deg: f64,
    spots: Vec<SeenSpot>,
}

/// Every frame's spot, each frame read once: the sub-pixel peak within
/// [`PROJECTOR_SEARCH_MM`] of where the rig file's projector puts its beam, cast onto the
/// placed mesh. Frames whose beam misses the mesh or whose peak is not found are left out.
fn projector_spots(
    mesh: &SurfaceMesh,
    setup: &DiscoSetup,
    limits: &ViewLimits,
    frames: &[SpotFrame],
    (w, h): (u32, u32),
) -> Result<Vec<ViewSpots>, FitError> {
    let p = &setup.projector;
    let mut out = Vec::new();
    let mut keys: Vec<(usize, i64)> = frames.iter().map(|f| (f.pos, (f.deg * 1e6).round() as i64)).collect();
    keys.sort_unstable();
    keys.dedup();
    for key in keys {
        let fr: Vec<&SpotFrame> =
            frames.iter().filter(|f| (f.pos, (f.deg * 1e6).round() as i64) == key).collect();
        let map = ViewMap::new(mesh, &setup.cameras[key.0].1, fr[0].deg, limits);
        let cam = &map.camera;
        let found: Vec<Result<Option<SeenSpot>, FitError>> = fr
            .par_iter()
            .map(|f| {
                let Some(inc) = map.incidence(mesh, p.eye, p.ray(f.code), limits) else { return Ok(None) };
                let Some((px, _)) = cam.project(inc.point) else { return Ok(None) };
                let pixel_mm = norm(sub(inc.point, cam.eye)) / cam.focal_px;
                let radius = (PROJECTOR_SEARCH_MM / pixel_mm).ceil() as usize;
                // Only the rows the search window covers are decoded, the noise measured
                // on the background beside the object in them.
                // (The whole frame where the object fills those rows from edge to edge.)
                let y = px[1].floor().max(0.0) as usize;
                let (mut img, rows) = read_band(&f.file, w, h, y.saturating_sub(radius + 1)..y + radius + 2)?;
                let mut sigma = band_sigma(&img, &map.surface, w as usize, &rows);
                if sigma == 0.0 {
                    let (whole, all) = read_band(&f.file, w, h, 0..h as usize)?;
                    sigma = band_sigma(&whole, &map.surface, w as usize, &all);
                    img = whole;
                }
                let floor = FLOOR_SIGMAS * sigma;
                let Some(peak) = spot_peak(&img, w as usize, h as usize, px, radius, floor) else {
                    return Ok(None);
                };
                let Some(on) = lightrig_pipelines::disco::optics::cast(
                    mesh,
                    &map.world,
                    cam.eye,
                    cam.ray(peak[0], peak[1]),
                ) else {
                    return Ok(None);
                };
                let (point, n) = map.point(mesh, &on);
                Ok(Some(SeenSpot { code: f.code, point, facing: dot(n, normalize(sub(cam.eye, point))) }))
            })
            .collect();
        let mut spots = Vec::new();
        for r in found {
            spots.extend(r?);
        }
        out.push(ViewSpots { pos: key.0, deg: fr[0].deg, spots });
    }
    Ok(out)
}

/// The spots `projector` accepts: its beam enters clear of a glint, within
/// [`PROJECTOR_MAX_ANGLE_DEG`] and where the surface faces the camera, and the spot seen lies
/// within [`PROJECTOR_SEARCH_MM`] of that entry on a surface facing the camera too.
fn judge_spots(
    mesh: &SurfaceMesh,
    setup: &DiscoSetup,
    projector: &Projector,
    limits: &ViewLimits,
    views: &[ViewSpots],
) -> Vec<HitPoint> {
    let mut hits = Vec::new();
    for v in views {
        let map = ViewMap::new(mesh, &setup.cameras[v.pos].1, v.deg, limits);
        let cam = &map.camera;
        hits.par_extend(v.spots.par_iter().filter_map(|s| {
            // A glint (the camera near the beam's mirror direction) puts the peak on the
            // surface's reflection, not on the glow the other spots' peaks sit on: left out.
            let inc = map
                .incidence(mesh, projector.eye, projector.ray(s.code), limits)
                .filter(|i| i.glint_mm == 0.0)?;
            // Only spots well inside the object's outline, for beam and camera alike: near it
            // the spot may be hidden and glow taken for it, and a grazing camera ray turns a
            // pixel's error into millimetres on the surface.
            let (_, n) = map.point(mesh, &inc.hit);
            let facing = dot(n, normalize(sub(cam.eye, inc.point)));
            (inc.angle_deg <= PROJECTOR_MAX_ANGLE_DEG
                && facing >= PROJECTOR_MIN_FACING
                && s.facing >= PROJECTOR_MIN_FACING
                && norm(sub(s.point, inc.point)) <= PROJECTOR_SEARCH_MM)
                .then_some(HitPoint { code: s.code, point: s.point })
        }));
    }
    hits
}

/// Every spot's local fit as `fit.json` lists it, the kept ones first ([`spot_json`]).
pub fn spots_json(fit: &DiscoFit) -> Vec<serde_json::Value> {
    let kept = fit.spots.iter().map(|k| spot_json(k, true));
    kept.chain(fit.local_rejected.iter().map(|k| spot_json(k, false))).collect()
}

/// A spot's local fit in `fit.json`: where and how its beam entered, the blur taken out, `m(d)`
/// and its misfit, and whether it went into the kernel textures.
fn spot_json(k: &SpotKernel, kept: bool) -> serde_json::Value {
    let p = &k.profile;
    serde_json::json!({
        "view": k.view, "code": k.code, "point_mm": k.point, "incidence_deg": k.angle_deg,
        "blur_sigma_mm": k.sigma_mm, "sigma_per_mm": p.sigma, "c1": p.c1, "c2": p.c2,
        "misfit": p.misfit, "samples": k.samples, "pooled": k.pooled, "kept": kept,
    })
}

/// Where the beam at `code` meets the white target's plane.
fn beam_on_plane(setup: &DiscoSetup, code: [f64; 2]) -> V3 {
    let d = setup.projector.ray(code);
    let t = &setup.white;
    let o = setup.projector.eye;
    let dn = dot(d, t.normal);
    let s = if dn.abs() < 1e-12 { 0.0 } else { dot(sub(t.point, o), t.normal) / dn };
    lightrig_pipelines::vec3::add(o, lightrig_pipelines::vec3::scale(d, s))
}

/// If the camera sees the entry point, the distance from it to the spot's sub-pixel peak on
/// the mesh, mm.
fn spot_offset(mesh: &SurfaceMesh, map: &ViewMap, inc: &Incidence, img: &[f32], floor: f32) -> Option<f64> {
    let cam: &Pinhole = &map.camera;
    let (px, _) = cam.project(inc.point)?;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (x, y) = (px[0].floor(), px[1].floor());
    if x < 0.0 || y < 0.0 || x as usize >= w || y as usize >= h {
        return None;
    }
    // Hidden: the pixel sees another part of the surface.
    let hit = map.surface[y as usize * w + x as usize]?;
    let (p, _) = map.point(mesh, &hit);
    if norm(sub(p, inc.point)) > mesh.mean_edge() {
        return None;
    }
    let peak = spot_peak(img, w, h, px, 4, floor)?;
    let d = cam.ray(peak[0], peak[1]);
    let on = lightrig_pipelines::disco::optics::cast(mesh, &map.world, cam.eye, d)?;
    let (q, _) = map.point(mesh, &on);
    Some(norm(sub(q, inc.point)))
}

/// The fitted model the held-out frames are predicted from.
struct HeldModel<'a> {
    mesh: &'a SurfaceMesh,
    f: &'a Matrix,
    atlas: &'a Atlas,
    detail: &'a DetailTexture,
    local: &'a LocalTextures,
    blurs: &'a Blurs,
    params: &'a LocalParams,
    flux: [f64; 3],
    near_mm: f64,
    beam_sigma_mm: f64,
    eta: f64,
}

/// Held-out frames scored at most: a median over this many is settled, and reading every
/// held-out frame again would add an eighth to the reading of a real session (110 592 frames
/// of the shipped plan's 884 736).
pub const MAX_HELD_SCORED: usize = 512;

/// Held-out frames (at most [`MAX_HELD_SCORED`], every k-th in the session's order) each read
/// once (its object rows) and predicted twice: away from the spot by `F` ([`far_error`]), near
/// it by the local term ([`near_error`]).
fn predict_held_out(
    model: &HeldModel,
    (maps, bands): (&[ViewMap], &[Range<usize>]),
    held: &[Held],
    (w, h): (u32, u32),
) -> Result<HeldOut, FitError> {
    type Score = Option<(f64, usize)>;
    let scored = spread(held, MAX_HELD_SCORED);
    let per_frame: Vec<(Score, Score)> = scored
        .par_iter()
        .map(|d| {
            let map = &maps[d.view];
            let (img, rows) = read_band(&d.file, w, h, bands[d.view].clone())?;
            // Only the rows read show the object (the rest of `img` is zero).
            let px = rows.start * w as usize..rows.end * w as usize;
            Ok((far_error(model, map, d, &img, px.clone()), near_error(model, map, d, &img, px)))
        })
        .collect::<Result<_, FitError>>()?;
    let (far, near): (Vec<Score>, Vec<Score>) = per_frame.into_iter().unzip();
    let (frames, pixels, median_rel_rms) = summarise(far);
    let (near_frames, near_pixels, near_rel_rms) = summarise(near);
    Ok(HeldOut {
        frames,
        pixels,
        median_rel_rms,
        near_mm: model.near_mm,
        near_frames,
        near_pixels,
        near_rel_rms,
    })
}

/// At most `most` of `items`, every k-th from the first (k as small as allows).
fn spread<T>(items: &[T], most: usize) -> Vec<&T> {
    if most == 0 {
        return Vec::new();
    }
    items.iter().step_by(items.len().div_ceil(most).max(1)).collect()
}

/// A held-out frame predicted from `F`: at every object pixel (of the pixels `px` read), the
/// vertices' predicted `Σk βk F(r, k)` interpolated by the pixel's barycentric weights in log,
/// times `Ft_o·Ft_i·Φ/π`, against the frame: (relative RMS, pixels).
fn far_error(m: &HeldModel, map: &ViewMap, d: &Held, img: &[f32], px: Range<usize>) -> Option<(f64, usize)> {
    let (mesh, f) = (m.mesh, m.f);
    let n = mesh.vertices.len();
    let inc = &d.inc;
    let tri = mesh.triangles[inc.hit.triangle as usize];
    // Predicted exitant Rd per vertex (column mix), then radiance at each vertex.
    let mut vertex_rd = vec![f64::NAN; n];
    for vv in &map.vertices {
        let r = vv.vertex as usize;
        let mut s = 0.0;
        for (k, &col) in tri.iter().enumerate() {
            s += f64::from(inc.hit.bary[k]) * f64::from(f.values[col as usize * n + r][d.channel]);
        }
        vertex_rd[r] = s;
    }
    let cam = &map.camera;
    // The near field (the entry triangle's vertices and their rings) is the local kernels'
    // domain: its triangles are left out, as are pixels within `near_mm` (and within a
    // glint's radius, where the surface may reflect the beam).
    let mut near = vec![false; n];
    for &v in &tri {
        near[v as usize] = true;
        for &(j, _) in &mesh.rings[v as usize] {
            near[j as usize] = true;
        }
    }
    let (mut se, mut sm, mut count) = (0.0, 0.0, 0usize);
    for i in px {
        let Some(hit) = &map.surface[i] else { continue };
        let t = mesh.triangles[hit.triangle as usize];
        if t.iter().any(|&v| vertex_rd[v as usize].is_nan() || near[v as usize]) {
            continue;
        }
        let measured = f64::from(img[i]);
        if measured <= f64::from(d.floor) {
            continue;
        }
        let (p, nrm) = map.point(mesh, hit);
        if norm(sub(p, inc.point)) < m.near_mm.max(inc.glint_mm) {
            continue;
        }
        // Between vertices in log: the fall-off is exponential (linear Gouraud would
        // overshoot mid-triangle by the edge's fall-off).
        if t.iter().any(|&v| vertex_rd[v as usize] <= 0.0) {
            continue;
        }
        let rd: f64 =
            (0..3).map(|k| f64::from(hit.bary[k]) * vertex_rd[t[k] as usize].ln()).sum::<f64>().exp();
        let cos_o = dot(nrm, normalize(sub(cam.eye, p)));
        let ft_o = lightrig_pipelines::disco::dipole::fresnel_transmittance(m.eta, cos_o);
        // The model's detail between the vertices (section 6.3).
        let skin = m.detail.at(m.atlas, mesh, hit.triangle, hit.bary.map(f64::from))[d.channel];
        let predicted = skin * rd * ft_o * inc.fresnel * m.flux[d.channel] / std::f64::consts::PI;
        se += (predicted - measured).powi(2);
        sm += measured * measured;
        count += 1;
    }
    (count > 0).then(|| ((se / sm).sqrt(), count))
}

/// Per-frame `(relative RMS, pixels)` → (frames, pixels, median relative RMS).
fn summarise(per_frame: Vec<Option<(f64, usize)>>) -> (usize, usize, f64) {
    let per_frame: Vec<(f64, usize)> = per_frame.into_iter().flatten().collect();
    let mut errs: Vec<f64> = per_frame.iter().map(|p| p.0).collect();
    errs.sort_by(f64::total_cmp);
    (
        per_frame.len(),
        per_frame.iter().map(|p| p.1).sum(),
        errs.get(errs.len() / 2).copied().unwrap_or(f64::NAN),
    )
}

/// A held-out frame's near field predicted by the local term (see [`HeldOut::near_rel_rms`]):
/// (relative RMS, pixels); `None` for a spot outside the local fit's incidence limit, on a
/// glint, or with nothing to compare.
fn near_error(m: &HeldModel, map: &ViewMap, d: &Held, img: &[f32], px: Range<usize>) -> Option<(f64, usize)> {
    let (mesh, params) = (m.mesh, m.params);
    let inc = &d.inc;
    if inc.angle_deg > params.max_incidence_deg || inc.glint_mm != 0.0 {
        return None;
    }
    let profile = m.atlas.nearest(inc.object).and_then(|t| m.local.profile(t))?;
    let blur = m.blurs.at(spot_sigma(m.beam_sigma_mm, mesh, map, inc));
    let cam = &map.camera;
    let (mut se, mut sm, mut count) = (0.0, 0.0, 0usize);
    for i in px {
        let Some(hit) = &map.surface[i] else { continue };
        let measured = f64::from(img[i]);
        if measured <= f64::from(lightrig_pipelines::disco::resample::MIN_FLOOR_RATIO * d.floor) {
            continue;
        }
        let (p, nrm) = map.point(mesh, hit);
        let dist = norm(sub(p, inc.point));
        if dist > params.radius_mm {
            continue;
        }
        let cos_o = dot(nrm, normalize(sub(cam.eye, p)));
        if cos_o < params.max_view_deg.to_radians().cos() {
            continue;
        }
        let object = lightrig_pipelines::disco::optics::at_hit(mesh, &mesh.vertices, hit);
        let corr = m
            .atlas
            .nearest(object)
            .and_then(|t| m.local.correction[t as usize])
            .map_or(1.0, |c| f64::from(c[d.channel]));
        let ft_o = lightrig_pipelines::disco::dipole::fresnel_transmittance(m.eta, cos_o);
        let predicted =
            profile.eval_blurred(&blur, d.channel, dist) * corr * ft_o * inc.fresnel * m.flux[d.channel]
                / std::f64::consts::PI;
        se += (predicted - measured).powi(2);
        sm += measured * measured;
        count += 1;
    }
    (count > 0).then(|| ((se / sm).sqrt(), count))
}

/// The object lit by [`relight::side_light`] (a light no frame used) as the first camera
/// position sees it with the turntable at 0°, rendered from `f` (`f(r, k)`; the fit's `F`, or a
/// truth to compare with): linear RGB, 3 per pixel.
pub fn relit(fit: &DiscoFit, f: &(dyn Fn(usize, usize) -> [f64; 3] + Sync)) -> Vec<f32> {
    let light = relight::side_light(&fit.camera, 0.0);
    let m = relight::exitance(&fit.mesh, f, &light, fit.eta);
    relight::render(&fit.mesh, &m, &fit.camera, 0.0, fit.eta)
}

/// The model — `F` beyond each vertex's one-ring, the local kernels within it
/// ([`relight::exitance_local`]), each pixel times the detail texture `T_ρ` — under
/// [`relight::side_light`], rendered as [`relit`] is.
pub fn relit_full(fit: &DiscoFit) -> Vec<f32> {
    relit_model(fit, true, true)
}

/// The model under [`relight::side_light`] with or without the local kernels (without: `F`'s
/// near entries) and the detail texture.
pub fn relit_model(fit: &DiscoFit, with_local: bool, with_detail: bool) -> Vec<f32> {
    let n = fit.matrix.n;
    let light = relight::side_light(&fit.camera, 0.0);
    let f = |r: usize, k: usize| fit.matrix.values[k * n + r].map(f64::from);
    let local = |r: usize| {
        if !with_local {
            return None;
        }
        let t = vertex_texel(fit, r)?;
        // The light the kernel brings leaves through the skin at the vertex, which `T_ρ` is
        // relative to (the correction `C` holds it only near kept spots).
        let corr = if with_detail {
            fit.detail_vertices[r].map(f64::from)
        } else {
            fit.local.correction[t as usize].map_or([1.0; 3], |c| c.map(f64::from))
        };
        Some((fit.local.profile(t)?, corr))
    };
    let m = relight::exitance_local(&fit.mesh, &f, &local, &light, fit.eta);
    let detail = |t: u32, b: [f64; 3]| {
        if with_detail {
            fit.detail.at(&fit.atlas, &fit.mesh, t, b)
        } else {
            [1.0; 3]
        }
    };
    relight::render_detailed(&fit.mesh, &m, &fit.camera, 0.0, fit.eta, &detail)
}

/// The atlas texel nearest vertex `r`.
pub fn vertex_texel(fit: &DiscoFit, r: usize) -> Option<u32> {
    fit.atlas.nearest(fit.mesh.vertices[r])
}

/// The exposure that puts `img`'s 99.5th percentile at 0.9.
pub fn exposure_of(img: &[f32]) -> f32 {
    let mut v: Vec<f32> = img.iter().copied().filter(|&x| x > 0.0).collect();
    if v.is_empty() {
        return 1.0;
    }
    let i = (v.len() * 995 / 1000).min(v.len() - 1);
    let (_, p, _) = v.select_nth_unstable_by(i, f32::total_cmp);
    0.9 / *p
}

/// Writes a relit picture as `name.exr` (linear) and `name.png` (× `exposure`, sRGB).
pub fn write_relit(
    img: &[f32],
    cam: &Pinhole,
    exposure: f32,
    out: &Path,
    name: &str,
) -> Result<Vec<PathBuf>, FitError> {
    use lightrig_imaging::io::{write_exr, write_png, BitDepth, Encoding, ExrPrecision, Image};
    let mut im = Image::new(cam.width, cam.height, 3);
    im.data.copy_from_slice(img);
    let im = im.with_encoding(Encoding::Linear);
    let (exr, png) = (out.join(format!("{name}.exr")), out.join(format!("{name}.png")));
    write_exr(&exr, &im, ExrPrecision::Float).map_err(|e| fail(format!("{}: {e}", exr.display())))?;
    let mut shown = im.clone();
    shown.data.iter_mut().for_each(|v| *v = (*v * exposure).clamp(0.0, 1.0));
    write_png(&png, &shown.to_srgb(), BitDepth::Eight)
        .map_err(|e| fail(format!("{}: {e}", png.display())))?;
    Ok(vec![exr, png])
}

/// The atlas file's format tag.
pub const ATLAS_FORMAT: &str = "lightrig-disco-atlas 1";

/// The local term's atlas textures (section 7), each `(name, image)`: linear, 3 channels, one
/// texel per pixel, zero off the charts. `kernel-rates` (R σ1, G σ2 in mm⁻¹, B 1 where a spot
/// gave the parameters, 0 where they were filled), `kernel-c1`, `kernel-c2` (the two terms'
/// weights per colour, mm⁻²), `kernel-correction` (the multiplicative correction `C` per
/// colour), and the detail texture `detail` (`T_ρ` per colour; 1 where no frame showed the
/// texel).
pub fn local_textures(fit: &DiscoFit) -> Vec<(&'static str, lightrig_imaging::io::Image)> {
    use lightrig_imaging::io::{Encoding, Image};
    let a = &fit.atlas;
    type Texel<'a> = &'a dyn Fn(usize) -> Option<[f32; 3]>;
    let textures: [(&str, Texel); 5] = [
        ("kernel-rates", &|i| {
            fit.local.params[i]
                .map(|p| [p[0].exp(), p[1].exp(), if fit.local.observed[i] { 1.0 } else { 0.0 }])
        }),
        ("kernel-c1", &|i| fit.local.profile(i as u32).map(|p| p.c1.map(|x| x as f32))),
        ("kernel-c2", &|i| fit.local.profile(i as u32).map(|p| p.c2.map(|x| x as f32))),
        ("kernel-correction", &|i| fit.local.correction[i]),
        ("detail", &|i| a.texels[i].and(fit.detail.values.get(i).copied())),
    ];
    textures
        .into_iter()
        .map(|(name, value)| {
            let mut im = Image::new(a.width.max(1), a.height.max(1), 3);
            for i in 0..a.texels.len() {
                if let Some(v) = value(i) {
                    im.data[3 * i..3 * i + 3].copy_from_slice(&v);
                }
            }
            (name, im.with_encoding(Encoding::Linear))
        })
        .collect()
}

/// `atlas.json`'s content: how a surface point finds its texel, and what the textures hold.
pub fn atlas_json(fit: &DiscoFit) -> Value {
    let a = &fit.atlas;
    let charts: Vec<Value> =
        a.charts.iter().map(|c| json!({ "axis": c.axis, "rect": c.rect, "shift": c.shift })).collect();
    json!({
        "format": ATLAS_FORMAT,
        "width": a.width, "height": a.height, "texel_mm": a.texel_mm, "border": a.border,
        "mapping": "triangle t of object.ply lies in chart triangle_chart[t] (4294967295: none); a point p (mm, object frame) of it is at atlas pixel (x, y) = (u / texel_mm + shift[0], v / texel_mm + shift[1]), texel centres at +0.5, where for axis a (0 +x, 1 -x, 2 +y, 3 -y, 4 +z, 5 -z) and k = a / 2: u = p[(k+1) % 3] (negated for odd a), v = p[(k+2) % 3]",
        "detail": "detail.exr holds T_rho (section 6.3): the global response interpolated over a triangle (in log between its vertices) is multiplied by the texel's value",
        "kernel": "m(d) = c1 e^(-sigma1 d) + c2 e^(-sigma2 d) per colour, d the 3D distance (mm) from the texel's point; a texel's 7x7 kernel is m at each neighbour's distance times that neighbour's correction times texel_mm^2",
        "charts": charts,
        "triangle_chart": a.triangle_chart,
    })
}

/// Writes the local term (section 7): `atlas.json` ([`atlas_json`]) and the atlas textures
/// ([`local_textures`]) as `<name>.exr`, float.
pub fn write_local(fit: &DiscoFit, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    use lightrig_imaging::io::{write_exr, ExrPrecision};
    let io = |p: &Path, e: std::io::Error| fail(format!("{}: {e}", p.display()));
    let mut files = Vec::new();
    for (name, im) in local_textures(fit) {
        let path = out.join(format!("{name}.exr"));
        write_exr(&path, &im, ExrPrecision::Float).map_err(|e| fail(format!("{}: {e}", path.display())))?;
        files.push(path);
    }
    let path = out.join("atlas.json");
    std::fs::write(&path, serde_json::to_string(&atlas_json(fit)).unwrap_or_default() + "\n")
        .map_err(|e| io(&path, e))?;
    files.push(path);
    Ok(files)
}

/// The scanned mesh's entry in `fit.json` (`scan`): the file, its format and unit, what
/// reading and orienting changed, and the measures it was checked by.
pub fn scan_json(r: &ScanReport) -> Value {
    let c = &r.check;
    json!({
        "file": r.file, "format": r.format.to_string(), "unit_mm": r.unit_mm,
        "vertices": c.vertices, "triangles": c.triangles,
        "polygons_split": r.polygons_split, "vertices_merged": r.vertices_merged,
        "degenerate_faces_dropped": r.degenerate_dropped, "unused_vertices_dropped": r.unused_dropped,
        "triangles_flipped": r.orientation.flipped, "pieces": r.orientation.pieces,
        "pieces_turned_outward": r.orientation.turned_outward,
        "boundary_edges": c.defects.boundary,
        "diagonal_mm": c.diagonal, "area_mm2": c.area,
        "area_spread_p95_over_p5": c.area_spread, "area_spread_limit": lightrig_pipelines::disco::scan::AREA_SPREAD_LIMIT,
    })
}

/// `F`'s file format tag.
pub const F_FORMAT: &str = "lightrig-disco-F 1";

/// Writes the fit's outputs into `out`: `object.ply` (the mesh the columns index), `F.f32` and
/// `F.json` (the matrix: see [`write_matrix`]), `F-observed.bits`, `relit.exr` and `relit.png`
/// (the model under a light no frame used, [`relit_full`]; `relit-global.*` the global term
/// alone, [`relit`]), the local term ([`write_local`]),
/// `fit.json` (the numbers).
pub fn write_outputs(fit: &DiscoFit, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    std::fs::create_dir_all(out).map_err(|e| fail(format!("{}: {e}", out.display())))?;
    let io = |p: &Path, e: std::io::Error| fail(format!("{}: {e}", p.display()));
    let ply = out.join("object.ply");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&ply).map_err(|e| io(&ply, e))?);
    write_ply(&fit.mesh.mesh(), &mut f).and_then(|_| f.flush()).map_err(|e| io(&ply, e))?;
    let mut files = vec![ply];
    files.extend(write_matrix(&fit.matrix, &fit.observed, out)?);
    let n = fit.matrix.n;
    let global = relit(fit, &|r, k| fit.matrix.values[k * n + r].map(f64::from));
    let img = relit_full(fit);
    files.extend(write_relit(&img, &fit.camera, exposure_of(&img), out, "relit")?);
    files.extend(write_relit(&global, &fit.camera, exposure_of(&img), out, "relit-global")?);
    files.extend(write_local(fit, out)?);
    let summary = out.join("fit.json");
    let j = json!({
        "vertices": fit.mesh.vertices.len(),
        "views": fit.views,
        "frames": fit.frames, "resampled": fit.used, "beam_missed_or_grazing": fit.missed,
        "held_out_frames": fit.held_out_frames,
        "spots_seen": fit.spots_seen, "peak_offset_mm_median": fit.peak_offset_mm,
        "lit_columns": fit.lit_columns,
        "observed_entries": fit.observed.iter().filter(|&&o| o).count(),
        "white_balance_gain_flux_rgb": fit.flux,
        "scan": scan_json(&fit.scan),
        "registration": fit.registration.as_ref().map(|r| json!({
            "rotation_vector_rad": r.pose.rotation, "translation_mm": r.pose.translation,
            "views_used": r.views_used, "views": r.agreement.len(), "evaluations": r.evaluations,
            "from_visual_hull": r.from_hull,
            "min_iou": r.min_iou(),
            "max_mismatched_pixels": r.agreement.iter().map(|a| a.mismatched).max().unwrap_or(0),
        })),
        "projector": {
            "eye_mm": fit.projector.projector.eye, "axes": fit.projector.projector.axes,
            "moved_mm": fit.projector.moved_mm, "turned_deg": fit.projector.turned_deg,
            "entry_points_moved_mm_max": fit.projector.shift_mm,
            "frames": fit.projector.frames, "spots_used": fit.projector.used, "spots_dropped": fit.projector.dropped,
            "rms_mm": fit.projector.rms_mm, "max_mm": fit.projector.max_mm,
        },
        "glint_frames": fit.glint_frames,
        "fill": format!("{:?}", fit.fill),
        "local": { "spots_fitted": fit.spots.len(), "spots_unseen": fit.local_hidden, "spots_failed": fit.local_failed, "spots_rejected": fit.local_rejected.len(),
                   "texel_mm": fit.atlas.texel_mm, "atlas": [fit.atlas.width, fit.atlas.height],
                   "observed_texels": fit.local.observed.iter().filter(|&&o| o).count(),
                   "spots": spots_json(fit) },
        "detail": { "observed_texels": fit.detail.observed.iter().filter(|&&o| o).count() },
        "held_out": { "frames": fit.held_out.frames, "pixels": fit.held_out.pixels,
                      "median_relative_rms": fit.held_out.median_rel_rms, "near_field_excluded_mm": fit.held_out.near_mm,
                      "near_field_by_local_term": { "frames": fit.held_out.near_frames, "pixels": fit.held_out.near_pixels,
                                                    "median_relative_rms": fit.held_out.near_rel_rms } },
    });
    std::fs::write(&summary, serde_json::to_string_pretty(&j).unwrap_or_default() + "\n")
        .map_err(|e| io(&summary, e))?;
    files.push(summary);
    Ok(files)
}

/// Writes `F` (symmetric) as its upper triangle: `F.f32` holds, for `k` from 0 to n−1 and `r`
/// from `k` to n−1, the entry `(r, k)` as three little-endian `f32` (R, G, B; mm⁻²);
/// `F-observed.bits` one bit per entry in the same order (LSB first; set: measured, clear:
/// interpolated); `F.json` says so.
pub fn write_matrix(f: &Matrix, observed: &[bool], out: &Path) -> Result<Vec<PathBuf>, FitError> {
    let n = f.n;
    let io = |p: &Path, e: std::io::Error| fail(format!("{}: {e}", p.display()));
    let (fp, bp, jp) = (out.join("F.f32"), out.join("F-observed.bits"), out.join("F.json"));
    let entries = n * (n + 1) / 2;
    let mut data = Vec::with_capacity(entries * 12);
    let mut bits = vec![0u8; entries.div_ceil(8)];
    let mut e = 0usize;
    for k in 0..n {
        for r in k..n {
            for c in 0..3 {
                data.extend_from_slice(&f.values[k * n + r][c].to_le_bytes());
            }
            if observed.get(k * n + r).copied().unwrap_or(false) {
                bits[e / 8] |= 1 << (e % 8);
            }
            e += 1;
        }
    }
    std::fs::write(&fp, &data).map_err(|e| io(&fp, e))?;
    std::fs::write(&bp, &bits).map_err(|e| io(&bp, e))?;
    let j = json!({
        "format": F_FORMAT, "vertices": n, "entries": entries,
        "layout": "upper triangle of the symmetric F: for k in 0..n, for r in k..n: F(r,k) as 3 little-endian f32 (R, G, B)",
        "units": "mm^-2 (diffuse subsurface reflectance Rd between vertices r and k)",
        "observed": "F-observed.bits: one bit per entry in the same order, LSB first; 1 = measured, 0 = interpolated",
        "mesh": "object.ply (vertex order = matrix index)",
    });
    std::fs::write(&jp, serde_json::to_string_pretty(&j).unwrap_or_default() + "\n")
        .map_err(|e| io(&jp, e))?;
    Ok(vec![fp, bp, jp])
}

/// Reads `F.f32` back (for tests and tools): the full symmetric matrix.
pub fn read_matrix(dir: &Path, n: usize) -> Result<Vec<[f32; 3]>, FitError> {
    let p = dir.join("F.f32");
    let data = std::fs::read(&p).map_err(|e| fail(format!("{}: {e}", p.display())))?;
    if data.len() != n * (n + 1) / 2 * 12 {
        return Err(fail(format!(
            "{}: {} bytes, not the {} of {n} vertices",
            p.display(),
            data.len(),
            n * (n + 1) / 2 * 12
        )));
    }
    let mut out = vec![[0.0f32; 3]; n * n];
    let mut i = 0;
    for k in 0..n {
        for r in k..n {
            let v = [0, 1, 2]
                .map(|c| f32::from_le_bytes(data[i + 4 * c..i + 4 * c + 4].try_into().unwrap_or([0; 4])));
            out[k * n + r] = v;
            out[r * n + k] = v;
            i += 12;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::spread;

    #[test]
    fn held_out_frames_are_scored_every_kth_up_to_the_cap() {
        let v: Vec<usize> = (0..1730).collect();
        let s = spread(&v, 1024);
        assert_eq!(s.len(), 865);
        assert_eq!((*s[0], *s[1], *s[864]), (0, 2, 1728));
        assert_eq!(spread(&v[..1024], 1024).len(), 1024);
        assert_eq!(spread(&v[..1025], 1024).len(), 513);
        assert_eq!(spread(&v[..10], 1024).len(), 10);
        assert!(spread(&v[..0], 1024).is_empty());
        assert!(spread(&v[..5], 0).is_empty());
    }
}
