//! `lightrig demo disco`: DISCO on the virtual rig with the shipped `docs/rigs/disco.toml`: the
//! white balance and a translucent pebble (marble with a skin-like vein, Jensen et al. 2001's
//! measured media) lit spot by spot from every turntable view at two camera positions, fitted as
//! `lightrig fit disco` does, and `F` compared with the scene's true throughput factors.

use std::path::PathBuf;

use lightrig_host::fit::disco::{self as fit, DiscoFit};
use lightrig_host::overrides::{apply, Override};
use lightrig_pipelines::disco::kernel::{self, Profile};
use lightrig_pipelines::disco::mesh::SurfaceMesh;
use lightrig_pipelines::disco::optics::Projector;
use lightrig_pipelines::disco::register::{max_displacement, Pose};
use lightrig_pipelines::disco::relight;
use lightrig_pipelines::firs::mesh::write_ply;
use lightrig_sim::camera::VirtualCamera;
use lightrig_sim::scenes::disco::DiscoScene;
use lightrig_sim::sensor::{Depth, Sensor};
use rayon::prelude::*;

use super::{bar, DemoRig, Report, Target};
use crate::error::{err, failure, io, CliError, INPUT};

/// How the demo runs.
#[derive(Debug, Clone)]
pub struct DiscoDemoOptions {
    /// A 642-vertex pebble at 288 × 186 pixels, 16 × 16 spots (else 2 562 vertices at 768 × 496,
    /// 24 × 24 spots); four turntable views at each of the two camera positions.
    pub quick: bool,
    /// Output directory (`object.ply`, `session/`, `camera/`, `fit/`, `report.md`).
    pub out: PathBuf,
    pub seed: u64,
    pub progress: bool,
    pub real_time: bool,
}

/// Measured entries of `F` against the truth: median relative error, per channel.
pub const OBSERVED_TOLERANCE: f64 = 0.05;
/// Interpolated entries: median relative error, per channel.
pub const INTERPOLATED_TOLERANCE: f64 = 0.20;

/// `F` against the truth.
#[derive(Debug, Clone, Copy, Default)]
pub struct Accuracy {
    /// Median relative error of the measured entries beyond the near field whose vertices'
    /// fans the skin's lines do not cross ([`DiscoScene::skin_clear`]), per channel.
    pub observed: [f64; 3],
    /// Of the measured entries a line crosses (reported: a vertex's `F` holds the skin as the
    /// few spots in its fan entered it, the truth its exact mean over the fan; `T_ρ` models the
    /// lines).
    pub observed_lines: [f64; 3],
    /// Of the interpolated ones whose true value the camera could measure (at least the
    /// dimmest measured entry's, in every channel).
    pub interpolated: [f64; 3],
    /// Of the rest, below the camera's floor: extrapolated by the fall-off (reported, no target).
    pub extrapolated: [f64; 3],
    /// The diagonal and one-ring entries, measured or not (reported, no target).
    pub near: [f64; 3],
    /// Entries compared (measured, interpolated, extrapolated, near field, measured on the
    /// lines).
    pub entries: [usize; 5],
    /// `F(r, k) == F(k, r)` bit for bit everywhere.
    pub symmetric: bool,
}

/// Local kernels' rates on homogeneous regions against the dipole's.
pub const KERNEL_TOLERANCE: f64 = 0.10;
/// The detail texture on the skin's lines against its truth: median relative error, per colour.
pub const DETAIL_TOLERANCE: f64 = 0.10;
/// The registration: the scanned mesh placed on the turntable, its farthest vertex from where
/// the object stands, mm (a tenth of the quick mesh's edge, a sixth of its pixels).
pub const REGISTRATION_TOLERANCE_MM: f64 = 0.1;
/// The projector fitted to its spots: the farthest its beams land on the object from the true
/// projector's, over beams aimed at every vertex, mm (a third of the quick camera's pixels).
pub const PROJECTOR_TOLERANCE_MM: f64 = 0.15;

/// The local kernels (section 7) against the scene's media.
#[derive(Debug, Clone, Copy)]
pub struct KernelCheck {
    /// The dipole's own `m(d)` per medium (body, vein): the same staged fit to its `Rd`
    /// at a spot's sample distances, no beam.
    pub reference: [Profile; 2],
    /// Spots fitted wholly inside each medium (every data point farther than the data radius
    /// plus 1 mm from the other), the body's also clear of the skin's lines (its skin at least
    /// 0.98 everywhere within the data radius plus 1 mm: a homogeneous region, surface included).
    pub spots: [usize; 2],
    /// Median σ1, σ2 of those spots' fits, per medium.
    pub sigma: [[f64; 2]; 2],
    /// The body's spots whose data a line crosses: how many, median σ1, σ2 (reported).
    pub lined: (usize, [f64; 2]),
    /// Of the body's spots: the fraction with both rates within the tolerance of the reference.
    pub within: f64,
    /// Of the body's spots: each rate's scatter, the median absolute deviation over the median.
    pub spread: [f64; 2],
    /// Of the body's spots: the median number of spots whose data fixed a spot's rates
    /// (`local::pool`).
    pub pooled: usize,
    /// Median relative error of the kernels' total (`2π∫m`, the medium's diffuse
    /// reflectance) against the reference's, body, per channel.
    pub total: [f64; 3],
}

impl KernelCheck {
    /// Worst relative error of the body's median rates.
    pub fn worst(&self) -> f64 {
        (0..2).map(|k| (self.sigma[0][k] / self.reference[0].sigma[k] - 1.0).abs()).fold(0.0, f64::max)
    }
}

/// The fitted projector against the scene's: the farthest an entry point moves (mm), over
/// beams aimed at every vertex with the object turned to 0°, 90°, 180° and 270°, from where the
/// true beam enters to the fitted beam at that point.
pub fn projector_error(truth: &Projector, mesh: &SurfaceMesh, fitted: &Projector) -> f64 {
    lightrig_pipelines::disco::projector_pose::entry_shift(truth, fitted, mesh, &[0.0, 90.0, 180.0, 270.0])
}

/// Fits the dipoles' own profiles and compares the homogeneous spots' fits with them.
pub fn kernel_check(scene: &DiscoScene, f: &DiscoFit) -> Option<KernelCheck> {
    let lp = &f.local_params;
    let ds = local_distances(lp.texel_mm, lp.radius_mm);
    let reference = [
        kernel::dipole_profile(&scene.media[0].dipoles(), &ds, &lp.stages)?,
        kernel::dipole_profile(&scene.media[1].dipoles(), &ds, &lp.stages)?,
    ];
    let v = scene.vein;
    let medium = |p: [f64; 3]| -> Option<usize> {
        let off = (lightrig_pipelines::vec3::dot(p, v.normal) - v.offset_mm).abs();
        if off > v.half_width_mm + lp.radius_mm + 1.0 {
            Some(0)
        } else if off < v.half_width_mm - lp.radius_mm - 1.0 {
            Some(1)
        } else {
            None
        }
    };
    let clear = |p: [f64; 3]| {
        f.atlas.texels_near(p, lp.radius_mm + 1.0).into_iter().all(|t| {
            f.atlas.texels[t as usize]
                .as_ref()
                .is_none_or(|x| scene.detail(x.point).iter().all(|&v| v >= 0.98))
        })
    };
    let mut sig: [Vec<[f64; 2]>; 2] = [Vec::new(), Vec::new()];
    let mut lined: Vec<[f64; 2]> = Vec::new();
    let mut totals: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    let mut pooled: Vec<f64> = Vec::new();
    for s in &f.spots {
        let Some(m) = medium(s.point) else { continue };
        if m == 0 && !clear(s.point) {
            lined.push(s.profile.sigma);
            continue;
        }
        sig[m].push(s.profile.sigma);
        if m == 0 {
            pooled.push(s.pooled as f64);
            for (c, t) in totals.iter_mut().enumerate() {
                t.push((kernel::total(&s.profile, c) / kernel::total(&reference[0], c) - 1.0).abs());
            }
        }
    }
    let med = |v: &[[f64; 2]], k: usize| median(v.iter().map(|x| x[k]).collect());
    let within = sig[0]
        .iter()
        .filter(|x| (0..2).all(|k| (x[k] / reference[0].sigma[k] - 1.0).abs() <= KERNEL_TOLERANCE))
        .count() as f64
        / sig[0].len().max(1) as f64;
    let spread = [0, 1].map(|k| {
        let m = med(&sig[0], k);
        median(sig[0].iter().map(|x| (x[k] - m).abs()).collect()) / m
    });
    Some(KernelCheck {
        reference,
        spread,
        pooled: median(pooled) as usize,
        spots: [sig[0].len(), sig[1].len()],
        sigma: [[med(&sig[0], 0), med(&sig[0], 1)], [med(&sig[1], 0), med(&sig[1], 1)]],
        lined: (lined.len(), [med(&lined, 0), med(&lined, 1)]),
        within,
        total: [0, 1, 2].map(|c| median(totals[c].clone())),
    })
}

/// The detail texture `T_ρ` (section 6.3) against the scene's skin.
#[derive(Debug, Clone, Copy, Default)]
pub struct DetailCheck {
    /// Texels compared: observed in every colour, on a triangle wholly in one medium (across the
    /// vein's boundary `T_ρ` also holds the change of medium, which the skin's truth does not).
    pub texels: usize,
    /// Of them, on the skin's dark lines (the truth below 0.9 in some colour).
    pub lines: usize,
    /// Median relative error of `T_ρ` against the truth, per colour: all compared texels.
    pub error: [f64; 3],
    /// The same on the lines.
    pub lines_error: [f64; 3],
    /// On the lines: median of `(1 − T_ρ)/(1 − truth)`, the share of the lines' depth recovered
    /// (the rest blurred away by the camera's pixels), per colour.
    pub depth: [f64; 3],
}

/// `T_ρ` against its truth: the skin's transmittance at the texel over its vertices' (in log,
/// as the fit interpolates them), `T(x) / Π T(v_i)^{b_i}`.
pub fn detail_check(scene: &DiscoScene, f: &DiscoFit) -> DetailCheck {
    let mesh = &f.mesh;
    let rows: Vec<([f64; 3], [f64; 3])> = f
        .atlas
        .texels
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            let t = (*t)?;
            if !f.detail.observed[i] {
                return None;
            }
            let tri = mesh.triangles[t.triangle as usize].map(|v| mesh.vertices[v as usize]);
            let m = scene.material_at(t.point);
            if tri.iter().any(|&v| scene.material_at(v) != m) {
                return None;
            }
            let at = scene.detail(t.point);
            let vs = tri.map(|v| scene.detail(v));
            let truth = [0, 1, 2]
                .map(|c| at[c] / (0..3).map(|k| f64::from(t.bary[k]) * vs[k][c].ln()).sum::<f64>().exp());
            Some((truth, f.detail.values[i].map(f64::from)))
        })
        .collect();
    let lines: Vec<&([f64; 3], [f64; 3])> = rows.iter().filter(|(t, _)| t.iter().any(|&x| x < 0.9)).collect();
    let err = |v: &[&([f64; 3], [f64; 3])], c: usize| {
        median(v.iter().map(|(t, g)| (g[c] / t[c] - 1.0).abs()).collect())
    };
    let all: Vec<&([f64; 3], [f64; 3])> = rows.iter().collect();
    DetailCheck {
        texels: rows.len(),
        lines: lines.len(),
        error: [0, 1, 2].map(|c| err(&all, c)),
        lines_error: [0, 1, 2].map(|c| err(&lines, c)),
        depth: [0, 1, 2].map(|c| {
            median(
                lines.iter().filter(|(t, _)| t[c] < 0.97).map(|(t, g)| (1.0 - g[c]) / (1.0 - t[c])).collect(),
            )
        }),
    }
}

/// The distances of a spot's data: texels of `texel` mm within `radius` mm of an entry point
/// off the texel grid.
fn local_distances(texel: f64, radius: f64) -> Vec<f64> {
    let n = (2.0 * radius / texel).ceil() as usize + 1;
    kernel::grid_distances(n, texel, [0.3, -0.2]).into_iter().filter(|&d| d <= radius).collect()
}

/// The relative error map's range: 0 (dark) to 20 % (yellow).
pub const RELIT_ERROR_RANGE: f32 = 0.2;

/// Writes the relit truth, the fit and their relative error side by side (`fit/relit-figure.png`):
/// the two pictures at the fit's exposure, the error `|fit − truth| / truth` of each pixel's
/// luminance from 0 to [`RELIT_ERROR_RANGE`] with its colour bar, grey off the object (and where
/// the truth is too dark to compare, below 1 % of the exposure's white).
pub fn write_relit_figure(
    truth: &[f32],
    model: &[f32],
    cam: &lightrig_pipelines::disco::optics::Pinhole,
    path: &std::path::Path,
) -> Result<PathBuf, CliError> {
    use lightrig_imaging::figure::{row, Panel};
    let (w, h) = (cam.width, cam.height);
    let gain = fit::exposure_of(model);
    let luminance = |p: &[f32]| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2];
    let on = |p: &[f32]| luminance(p) * gain > 0.01;
    let pictures = |img: &[f32]| -> Vec<Option<[f32; 3]>> {
        img.chunks_exact(3)
            .zip(truth.chunks_exact(3))
            .map(|(p, t)| on(t).then(|| [p[0], p[1], p[2]]))
            .collect()
    };
    let error: Vec<Option<f32>> = model
        .chunks_exact(3)
        .zip(truth.chunks_exact(3))
        .map(|(p, t)| on(t).then(|| (luminance(p) - luminance(t)).abs() / luminance(t)))
        .collect();
    let figure = row(
        &[
            Panel::colour(w, h, &pictures(truth), gain),
            Panel::colour(w, h, &pictures(model), gain),
            Panel::scalar(w, h, &error, (0.0, RELIT_ERROR_RANGE)),
        ],
        2,
    );
    lightrig_imaging::io::write_png(path, &figure, lightrig_imaging::io::BitDepth::Eight).map_err(failure)?;
    Ok(path.to_path_buf())
}

/// What the demo measured.
#[derive(Debug)]
pub struct DiscoDemoResult {
    pub fit: DiscoFit,
    pub accuracy: Accuracy,
    /// The relit picture (a light no frame used) from the fitted `F` against the object's
    /// physics under that light (the dipole integrated over the surface): relative RMS over the
    /// object's pixels.
    pub relit_error: f64,
    /// The same with the global term alone (`F`'s near entries in the near field).
    pub relit_global_error: f64,
    /// The full model without the detail texture.
    pub relit_plain_error: f64,
    /// The detail texture against the scene's skin.
    pub detail: DetailCheck,
    /// The local kernels against the media (none: no spot fitted).
    pub kernels: Option<KernelCheck>,
    /// The registered mesh's farthest vertex from the object's, mm (none: not registered).
    pub registration_error_mm: Option<f64>,
    /// The fitted projector's beams against the true projector's where they enter the object,
    /// farthest over beams aimed at every vertex, mm ([`projector_error`]).
    pub projector_error_mm: f64,
    pub frames: u64,
    pub report: PathBuf,
}

impl DiscoDemoResult {
    /// The accuracy targets: `(name, value, limit, met)`.
    pub fn targets(&self) -> Vec<Target> {
        let a = &self.accuracy;
        let worst = |v: [f64; 3]| v.iter().copied().fold(0.0, f64::max);
        let (o, i) = (worst(a.observed), worst(a.interpolated));
        vec![
            (
                "measured entries of F (beyond the one-ring, clear of the skin's lines) against the truth, median relative error (worst channel)",
                o,
                OBSERVED_TOLERANCE,
                o <= OBSERVED_TOLERANCE,
            ),
            (
                "interpolated entries of F (within the camera's range) against the truth, median relative error (worst channel)",
                i,
                INTERPOLATED_TOLERANCE,
                i <= INTERPOLATED_TOLERANCE,
            ),
            ("F exactly symmetric (1 = yes)", f64::from(u8::from(a.symmetric)), 1.0, a.symmetric),
            {
                let k = self.kernels.map_or(f64::INFINITY, |k| if k.spots[0] > 0 { k.worst() } else { f64::INFINITY });
                (
                    "local kernels' σ1, σ2 on homogeneous marble (clear of the skin's lines) against the dipole's, relative error of the median (worse rate)",
                    k,
                    KERNEL_TOLERANCE,
                    k <= KERNEL_TOLERANCE,
                )
            },
            {
                let e = self.registration_error_mm.unwrap_or(f64::INFINITY);
                (
                    "registration: the scanned mesh placed on the turntable by the spotlit silhouettes, farthest vertex from the object's, mm",
                    e,
                    REGISTRATION_TOLERANCE_MM,
                    e <= REGISTRATION_TOLERANCE_MM,
                )
            },
            (
                "projector: its pivot and aim fitted to the spots, its beams' entry points against the true projector's, farthest over beams aimed at every vertex, mm",
                self.projector_error_mm,
                PROJECTOR_TOLERANCE_MM,
                self.projector_error_mm <= PROJECTOR_TOLERANCE_MM,
            ),
            {
                let d = &self.detail;
                let e = if d.lines > 0 { worst(d.lines_error) } else { f64::INFINITY };
                (
                    "detail texture T_ρ on the skin's lines against its truth, median relative error (worst colour)",
                    e,
                    DETAIL_TOLERANCE,
                    e <= DETAIL_TOLERANCE,
                )
            },
        ]
    }

    /// The names of the targets missed.
    pub fn missed(&self) -> Vec<String> {
        self.targets().into_iter().filter(|t| !t.3).map(|t| t.0.to_string()).collect()
    }
}

/// The shipped rig file with `sets` applied.
fn rig_text(sets: &[String]) -> Result<String, CliError> {
    let shipped = include_str!("../../../docs/rigs/disco.toml");
    let sets: Vec<Override> =
        sets.iter().map(|s| s.parse()).collect::<Result<_, _>>().map_err(|e| err(INPUT, e))?;
    apply(shipped, &sets).map_err(|e| err(INPUT, e))
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// `F` against `scene`'s truth, over every `stride`-th entry of the upper triangle.
///
/// Entries fall in four classes: the near field (the diagonal and each vertex's one-ring, the
/// paper's "close points": there `Rd` changes by orders of magnitude within the beam and the
/// triangle, so the fit keeps the paper's mean over the hat function, compared with the same
/// mean of the truth; the local kernels' domain, reported, no target), measured, interpolated
/// within the camera's range (the true value at least the dimmest measured entry's, the 1st
/// percentile, in every channel), and below the camera's floor (extrapolated by the fall-off;
/// reported, no target). Beyond the near field the truth is [`DiscoScene::truth`]: `Rd` between
/// the two vertices, with the skin's detail as `F` holds it.
pub fn accuracy(scene: &DiscoScene, f: &DiscoFit, stride: usize) -> Accuracy {
    let n = f.matrix.n;
    let entries: Vec<(usize, usize)> =
        (0..n).flat_map(|k| (k..n).map(move |r| (r, k))).step_by(stride.max(1)).collect();
    let near = |r: usize, k: usize| r == k || f.mesh.rings[k].iter().any(|&(j, _)| j as usize == r);
    let rows: Vec<([f64; 3], [f64; 3])> = entries
        .par_iter()
        .map(|&(r, k)| {
            let t = if near(r, k) { scene.hat_truth(r, k) } else { scene.truth(r, k) };
            let v = f.matrix.values[k * n + r];
            (t, [0, 1, 2].map(|c| (f64::from(v[c]) / t[c] - 1.0).abs()))
        })
        .collect();
    let measured = |&(r, k): &(usize, usize)| f.observed[k * n + r];
    // The camera's floor per channel: the 1st percentile of the measured entries.
    let floor: [f64; 3] = [0, 1, 2].map(|c| {
        let mut v: Vec<f64> = entries
            .iter()
            .filter(|e| measured(e))
            .map(|&(r, k)| f64::from(f.matrix.values[k * n + r][c]))
            .collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 100).copied().unwrap_or(0.0)
    });
    let class = |e: &(usize, usize), t: &[f64; 3]| -> usize {
        if near(e.0, e.1) {
            3
        } else if measured(e) {
            if scene.skin_clear(e.0) && scene.skin_clear(e.1) {
                0
            } else {
                4
            }
        } else if (0..3).all(|c| t[c] >= floor[c]) {
            1
        } else {
            2
        }
    };
    let classes: Vec<usize> = entries.iter().zip(&rows).map(|(e, (t, _))| class(e, t)).collect();
    let mut acc = Accuracy::default();
    for slot in 0..5 {
        let sel: Vec<&[f64; 3]> =
            rows.iter().zip(&classes).filter(|(_, &c)| c == slot).map(|(e, _)| &e.1).collect();
        acc.entries[slot] = sel.len();
        let m = [0, 1, 2].map(|c| median(sel.iter().map(|e| e[c]).collect()));
        match slot {
            0 => acc.observed = m,
            1 => acc.interpolated = m,
            2 => acc.extrapolated = m,
            3 => acc.near = m,
            _ => acc.observed_lines = m,
        }
    }
    acc.symmetric = (0..n).all(|k| (k..n).all(|r| f.matrix.values[k * n + r] == f.matrix.values[r * n + k]));
    acc
}

/// The demo's overrides of the shipped rig file and the pebble's subdivision level.
fn demo_sets(quick: bool) -> (u32, Vec<String>) {
    if quick {
        (
            3,
            vec![
                "plan.views=4".into(),
                "plan.spot_grid=[16, 16]".into(),
                "plan.spot_window_deg=[[-4.6, 4.6], [-5.6, 5.6]]".into(),
                "plan.fit.image=[288, 186]".into(),
                "plan.fit.focal_px=675".into(),
                "plan.fit.held_out=7".into(),
            ],
        )
    } else {
        (
            4,
            vec![
                "plan.views=4".into(),
                "plan.spot_grid=[24, 24]".into(),
                "plan.spot_window_deg=[[-4.6, 4.6], [-5.6, 5.6]]".into(),
                "plan.fit.held_out=11".into(),
            ],
        )
    }
}

/// Acquires the demo's session on the virtual rig into `opts.out` (`object.ply`, `rig.toml`,
/// `session/`, `camera/`), the rig file with the demo's overrides and then `extra` applied
/// (e.g. `plan.spot_grid=[8, 8]`). Returns the camera (holding the scene) and the frames.
pub fn acquire_disco(
    opts: &DiscoDemoOptions,
    extra: &[String],
) -> Result<(VirtualCamera<DiscoScene>, u64), CliError> {
    let out = &opts.out;
    std::fs::create_dir_all(out).map_err(io(out))?;
    let (level, mut sets) = demo_sets(opts.quick);
    sets.extend(extra.iter().cloned());
    let text = rig_text(&sets)?;
    let rig = DemoRig::write(out, text)?;
    let scene = DiscoScene::new(&rig.rig, level).map_err(|e| err(INPUT, e))?;
    // The "scanned" mesh the fit reads: the scene's own in the scanner's frame (the paper's came
    // from a laser scanner); the fit registers it by the spotlit silhouettes.
    let ply = out.join("object.ply");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&ply).map_err(io(&ply))?);
    write_ply(&scene.scanned_mesh(), &mut f).map_err(io(&ply))?;
    drop(f);
    let pulse_s = rig.rig.cameras.first().map_or(1e-4, |c| c.pulse_us * 1e-6);
    let sensor = Sensor {
        gain: 1e8 / (0.1 * pulse_s),
        depth: Depth::Half,
        grey: true,
        seed: opts.seed,
        ..Sensor::default()
    };
    let frames = rig.plan.summary().triggers as u64;
    let (w, h) = lightrig_sim::camera::Scene::size(&scene);
    if opts.progress {
        println!(
            "lightrig demo disco: {} vertices, {w}×{h} px, {frames} frames, output in {}",
            scene.mesh.vertices.len(),
            out.display()
        );
    }
    let b = bar(opts.progress, frames, "acquire");
    let camera = rig.acquire(out, scene, sensor, opts.real_time, &b)?;
    b.finish_and_clear();
    Ok((camera, frames))
}

/// Runs the demo.
pub fn run_disco(opts: &DiscoDemoOptions) -> Result<DiscoDemoResult, CliError> {
    let out = &opts.out;
    let (camera, frames) = acquire_disco(opts, &[])?;
    let b = bar(opts.progress, 0, "fit");
    let bb = b.clone();
    let fitted = fit::fit_session(&out.join("session"), None, &move |d, t| {
        bb.set_length(t);
        bb.set_position(d);
    })
    .map_err(failure)?;
    b.finish_and_clear();
    let files = fit::write_outputs(&fitted, &out.join("fit")).map_err(failure)?;
    let scene = camera.scene();
    let accuracy = accuracy(scene, &fitted, if opts.quick { 1 } else { 7 });
    // The relit picture from the object's physics (the dipole integrated over the surface,
    // no F involved), at the fitted picture's exposure.
    let n = fitted.matrix.n;
    let global = fit::relit(&fitted, &|r, k| fitted.matrix.values[k * n + r].map(f64::from));
    let mine = fit::relit_full(&fitted);
    let plain = fit::relit_model(&fitted, true, false);
    let light = relight::side_light(&fitted.camera, 0.0);
    // The exitance under the skin is smooth under a broad light: interpolated between the
    // vertices, times the skin's transmittance at each pixel's surface point.
    let mesh = &fitted.mesh;
    let skin = |t: u32, b: [f64; 3]| {
        let tri = mesh.triangles[t as usize];
        scene.detail((0..3).fold([0.0; 3], |p, k| {
            lightrig_pipelines::vec3::add(
                p,
                lightrig_pipelines::vec3::scale(mesh.vertices[tri[k] as usize], b[k]),
            )
        }))
    };
    let truth = relight::render_detailed(
        mesh,
        &scene.exitance_below_skin(&light),
        &fitted.camera,
        0.0,
        fitted.eta,
        &skin,
    );
    let mut files = files;
    files.extend(
        fit::write_relit(&truth, &fitted.camera, fit::exposure_of(&mine), &out.join("fit"), "relit-truth")
            .map_err(failure)?,
    );
    files.push(write_relit_figure(&truth, &mine, &fitted.camera, &out.join("fit/relit-figure.png"))?);
    let (se, st) = mine
        .iter()
        .zip(&truth)
        .fold((0.0, 0.0), |(se, st), (&a, &b)| (se + f64::from(a - b).powi(2), st + f64::from(b).powi(2)));
    let relit_error = if st > 0.0 { (se / st).sqrt() } else { f64::NAN };
    let sg: f64 = global.iter().zip(&truth).map(|(&a, &b)| f64::from(a - b).powi(2)).sum();
    let relit_global_error = if st > 0.0 { (sg / st).sqrt() } else { f64::NAN };
    let sp: f64 = plain.iter().zip(&truth).map(|(&a, &b)| f64::from(a - b).powi(2)).sum();
    let relit_plain_error = if st > 0.0 { (sp / st).sqrt() } else { f64::NAN };
    let detail = detail_check(scene, &fitted);
    let kernels = kernel_check(scene, &fitted);
    let registration_error_mm = fitted
        .registration
        .as_ref()
        .map(|r| max_displacement(&scene.scan_pose.then(&r.pose), &Pose::IDENTITY, &scene.mesh.vertices));
    let projector_error_mm =
        projector_error(&scene.setup.projector, &scene.mesh, &fitted.projector.projector);
    let result = DiscoDemoResult {
        fit: fitted,
        accuracy,
        relit_error,
        relit_global_error,
        relit_plain_error,
        detail,
        kernels,
        registration_error_mm,
        projector_error_mm,
        frames,
        report: out.join("report.md"),
    };
    write_report(&result, scene, &files, opts)?;
    Ok(result)
}

fn write_report(
    r: &DiscoDemoResult,
    scene: &DiscoScene,
    files: &[PathBuf],
    opts: &DiscoDemoOptions,
) -> Result<(), CliError> {
    let f = &r.fit;
    let n = f.mesh.vertices.len();
    let mut rep = Report::default();
    rep.line("# DISCO on the virtual rig");
    rep.line("");
    rep.line(format!(
        "The shipped `docs/rigs/disco.toml`{} on the virtual controller and the translucent pebble \
         (`sim/src/scenes/disco.rs`: {} with a vein of {}, Jensen et al. 2001's measured σs′, σa; η = 1.3; \
         dipole `Rd` made symmetric; dark lines in its skin finer than the mesh, the surface detail; a 2 mm beam): \
         {} frames, {} views (turntable × camera position), fitted as `lightrig fit disco` does. Truth: each entry \
         is `Rd` between its two vertices times the skin where the light leaves (the vertex) and enters (the hat \
         function's mean), made symmetric.",
        if opts.quick {
            " (quick: 4 turntable views, 16 × 16 spots, 288 × 186 px, 642 vertices)"
        } else {
            " (4 turntable views, 24 × 24 spots, 768 × 496 px, 2 562 vertices)"
        },
        scene.media[0].name,
        scene.media[1].name,
        r.frames,
        f.views
    ));
    rep.line("");
    rep.targets(["target", "value", "limit"], "", &r.targets());
    rep.line("");
    let a = &r.accuracy;
    rep.line("| entries | compared | median relative error R / G / B |");
    rep.line("|---|---|---|");
    rep.line(format!(
        "| measured, beyond the one-ring, clear of the skin's lines | {} | {:.2} % / {:.2} % / {:.2} % |",
        a.entries[0],
        100.0 * a.observed[0],
        100.0 * a.observed[1],
        100.0 * a.observed[2]
    ));
    rep.line(format!(
        "| measured, beyond the one-ring, a vertex's fan crossed by a line | {} | {:.2} % / {:.2} % / {:.2} % |",
        a.entries[4],
        100.0 * a.observed_lines[0],
        100.0 * a.observed_lines[1],
        100.0 * a.observed_lines[2]
    ));
    rep.line(format!(
        "| interpolated, within the camera's range | {} | {:.2} % / {:.2} % / {:.2} % |",
        a.entries[1],
        100.0 * a.interpolated[0],
        100.0 * a.interpolated[1],
        100.0 * a.interpolated[2]
    ));
    rep.line(format!(
        "| below the camera's floor, extrapolated by the fall-off | {} | {:.2} % / {:.2} % / {:.2} % |",
        a.entries[2],
        100.0 * a.extrapolated[0],
        100.0 * a.extrapolated[1],
        100.0 * a.extrapolated[2]
    ));
    rep.line(format!(
        "| near field: the diagonal and one-ring | {} | {:.2} % / {:.2} % / {:.2} % |",
        a.entries[3],
        100.0 * a.near[0],
        100.0 * a.near[1],
        100.0 * a.near[2]
    ));
    rep.line("");
    rep.line(
        "Near field: within a vertex's one-ring `Rd` changes by orders of magnitude across the 2 mm beam and the \
         triangle; there F keeps the paper's barycentric mean (what carries the right energy under a broad light), \
         compared with the truth's mean over the incident vertex's hat function; the local kernels' domain (section 7). \
         The camera's range: an entry is within it when its true value is at least the dimmest measured entry's \
         (1st percentile) in every channel; beyond it (far through the object) nothing was measured and the \
         fill continues the measured fall-off.",
    );
    rep.line("");
    rep.line(format!(
        "Frames: {} laser frames, {} resampled into F, {} whose beam missed the object or entered beyond 60°, {} held out; \
         in {} the camera saw the spot within {:.0}° of its beam's mirror direction, where the surface's glint may show: \
         their pixels within {:.0} mm of the spot left out, the spot not fitted by the local term. \
         F: {n} vertices, {} of {n} columns lit, {} of {} entries measured.",
        f.frames,
        f.used,
        f.missed,
        f.held_out_frames,
        f.glint_frames,
        lightrig_pipelines::disco::resample::ViewLimits::default().glint_deg,
        lightrig_pipelines::disco::resample::ViewLimits::default().glint_radius_mm,
        f.lit_columns,
        f.observed.iter().filter(|&&o| o).count(),
        n * n
    ));
    rep.line("");
    if let Some(g) = &f.registration {
        rep.line(format!(
            "Registration (section 4.4): `object.ply` is the mesh in the scanner's frame, {:.1}° and {:.1} mm from \
             where the object stands; from the spotlit frame of {} of the {} views, the mesh's silhouettes matched \
             to the frames' ({} evaluations) place every vertex within {:.3} mm of the object's; every view's \
             silhouettes then agree to {:.2} % (intersection over union, the worst view; {} pixels differ at most).",
            scene.scan_pose.angle_deg(),
            lightrig_pipelines::vec3::norm(scene.scan_pose.translation),
            g.views_used,
            g.agreement.len(),
            g.evaluations,
            r.registration_error_mm.unwrap_or(f64::NAN),
            100.0 * g.min_iou(),
            g.agreement.iter().map(|a| a.mismatched).max().unwrap_or(0)
        ));
        rep.line("");
    }
    let pr = &f.projector;
    rep.line(format!(
        "Projector (section 4.4): fitted to the spots of {} frames ({} used, {} dropped as outliers; its beams miss \
         them by {:.3} mm RMS), moved {:.2} mm and turned {:.2}° from the rig file's pose; its entry points are within \
         {:.3} mm of the true projector's (beams aimed at every vertex, 4 turntable angles).",
        pr.frames, pr.used, pr.dropped, pr.rms_mm, pr.moved_mm, pr.turned_deg, r.projector_error_mm
    ));
    rep.line("");
    rep.line(format!(
        "The spot was seen in {} frames; its sub-pixel peak lies {:.2} mm (median) from the projector's entry point \
         (translucency moves the peak, Godin et al. 2001).",
        f.spots_seen, f.peak_offset_mm
    ));
    if f.held_out.frames > 0 {
        rep.line("");
        rep.line(format!(
            "Held out: {} of the {} frames of spots left out of the fit (every k-th, at most {}), predicted from F (Gouraud over the mesh, as the global term \
             renders, times the detail texture) against the frames themselves: relative RMS error {:.1} % (median over frames, {} pixels, beyond \
             {:.1} mm of the spot: nearer is the local kernels' domain). Their near field (within {:.1} mm) predicted by \
             the local term — the kernel of the spot's texel, filled from its neighbours as the spot was left out, \
             through the beam's blur, times the correction: {:.1} % ({} frames entering within {:.0}°, {} pixels).",
            f.held_out.frames,
            f.held_out_frames,
            fit::MAX_HELD_SCORED,
            100.0 * f.held_out.median_rel_rms,
            f.held_out.pixels,
            f.held_out.near_mm,
            f.local_params.radius_mm,
            100.0 * f.held_out.near_rel_rms,
            f.held_out.near_frames,
            f.local_params.max_incidence_deg,
            f.held_out.near_pixels
        ));
    }
    rep.line("");
    rep.line(format!(
        "Relit (`fit/relit.png`: a distant light from the side and above, which no frame used) against the \
         object's physics under that light (`fit/relit-truth.png`: the dipole integrated over the surface, no F \
         involved), both rendered alike from the vertices: relative RMS error {:.1} % over the object's pixels \
         with the local kernels carrying each vertex's one-ring and the detail texture; {:.1} % without the detail \
         texture; {:.1} % from F alone (`fit/relit-global.png`). The truth is the exitance under the skin interpolated \
         between the vertices (smooth under a broad light) times the skin's transmittance at each pixel.",
        100.0 * r.relit_error,
        100.0 * r.relit_plain_error,
        100.0 * r.relit_global_error
    ));
    rep.line("");
    rep.line(format!(
        "![relit truth, fit, relative error](fit/relit-figure.png)\n\nLeft to right: the truth, the fit \
         (with the local kernels and the detail texture) at the same exposure, and |fit − truth| / truth of each \
         pixel's luminance from 0 (dark) to {:.0} % (yellow); grey off the object.",
        100.0 * RELIT_ERROR_RANGE
    ));
    let d = &r.detail;
    rep.line("");
    rep.line(format!(
        "Detail texture (section 6.3, `fit/detail.exr`): {} texels observed in every colour on triangles within one \
         medium, against the skin's transmittance at the texel over its vertices' (`T(x)/Π T(v_i)^b_i`): median \
         relative error {:.1} / {:.1} / {:.1} % (R / G / B); on the dark lines ({} texels) {:.1} / {:.1} / {:.1} %, \
         their depth recovered {:.0} / {:.0} / {:.0} % (median; the camera's pixels blur the rest).",
        d.texels,
        100.0 * d.error[0],
        100.0 * d.error[1],
        100.0 * d.error[2],
        d.lines,
        100.0 * d.lines_error[0],
        100.0 * d.lines_error[1],
        100.0 * d.lines_error[2],
        100.0 * d.depth[0],
        100.0 * d.depth[1],
        100.0 * d.depth[2]
    ));
    rep.line("");
    rep.line(format!(
        "White balance: the camera's gain × each laser's flux {:.4e} / {:.4e} / {:.4e} (R / G / B), the beam's σ {:.2} mm \
         (from its spot on the white target). Fall-off taken out for the interpolation: {}.",
        f.flux[0],
        f.flux[1],
        f.flux[2],
        f.beam_sigma_mm,
        f.falloff.map_or("none (too few entries)".to_string(), |x| format!(
            "e^(−s·d)/d² with s = {:.3} / {:.3} / {:.3} mm⁻¹",
            x[0].s, x[1].s, x[2].s
        ))
    ));
    rep.line("");
    if let Some(k) = &r.kernels {
        rep.line(format!(
            "Local kernels (section 7; `m(d) = c1·e^(−σ1·d) + c2·e^(−σ2·d)` per spot in the paper's stages, through \
             the beam's blur, from the texels within {:.1} mm of the entry point, {:.2} mm texels on a {} × {} atlas; \
             each kept spot's rates then fitted together with those of its view's kept spots within {:.0} mm, {} a spot in the median): \
             {} spots kept, {} not seen by the camera, {} with too few data (at the silhouette), {} fitted but rejected (misfit over {:.0} %, or no fast term: near the vein's boundary or the skin's lines, or noisy). On homogeneous {} clear of the skin's lines ({} spots): median σ1 {:.3}, σ2 {:.3} mm⁻¹ \
             against the dipole's {:.3}, {:.3} (the same fit to its `Rd`, misfit {:.1} %), scattered by {:.1} / {:.1} % (median absolute deviation); {:.0} % of those spots \
             within {:.0} % on both rates; the kernels' total (2π∫m) within {:.1} / {:.1} / {:.1} % (median, R / G / B). \
             Spots whose data a line crosses ({}; the data divided by the detail texture as gathered so far): σ1 {:.3}, σ2 {:.3}. {}",
            f.local_params.radius_mm,
            f.atlas.texel_mm,
            f.atlas.width,
            f.atlas.height,
            f.local_params.pool_mm,
            k.pooled,
            f.spots.len(),
            f.local_hidden,
            f.local_failed,
            f.local_rejected.len(),
            100.0 * f.local_params.max_misfit,
            scene.media[0].name,
            k.spots[0],
            k.sigma[0][0],
            k.sigma[0][1],
            k.reference[0].sigma[0],
            k.reference[0].sigma[1],
            100.0 * k.reference[0].misfit,
            100.0 * k.spread[0],
            100.0 * k.spread[1],
            100.0 * k.within,
            100.0 * KERNEL_TOLERANCE,
            100.0 * k.total[0],
            100.0 * k.total[1],
            100.0 * k.total[2],
            k.lined.0,
            k.lined.1[0],
            k.lined.1[1],
            if k.spots[1] > 0 {
                format!(
                    "Inside the {} vein ({} spots): σ1 {:.3}, σ2 {:.3} against {:.3}, {:.3}.",
                    scene.media[1].name,
                    k.spots[1],
                    k.sigma[1][0],
                    k.sigma[1][1],
                    k.reference[1].sigma[0],
                    k.reference[1].sigma[1]
                )
            } else {
                format!(
                    "The {} vein ({:.0} mm wide) is narrower than a spot's data reach: no spot inside it is homogeneous.",
                    scene.media[1].name,
                    2.0 * scene.vein.half_width_mm
                )
            },
        ));
        rep.line("");
    }
    rep.line(format!("Interpolation: {:?}.", f.fill));
    rep.outputs(files);
    rep.write(&r.report)?;
    Ok(())
}
