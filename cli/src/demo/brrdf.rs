//! `lightrig demo brrdf`: the bispectral gonioreflectometer on the virtual rig with the shipped
//! `docs/rigs/bispectral.toml`: a Spectralon session (the spectral calibration) and a session of
//! the two coated spheres (orange clear coat on top, fluorescent yellow below), fitted with
//! `lightrig fit brrdf`'s pipeline. The report holds the scaled samples against the scene's
//! band-limited truth (what an ideal instrument with these filter bands reports), the
//! components a same-angle PCA needs, and an angle left out of the PCA set reconstructed from
//! five wavelength pairs (thesis figure 4.12), standard and saturated PCA side by side.

use std::path::PathBuf;

use lightrig_host::fit::brrdf::{self as fit, BrrdfFit, Sample};
use lightrig_host::overrides::{apply, Override};
use lightrig_pipelines::brrdf::spectra::{ccd, led, xenon, Material};
use lightrig_pipelines::ward::Ward;
use lightrig_sim::scenes::bispectral::BispectralScene;
use lightrig_sim::scenes::scene_for;

use super::{bar, DemoRig, Report, Target};
use crate::error::{err, failure, io, CliError, INPUT};

/// How the demo runs.
#[derive(Debug, Clone)]
pub struct BrrdfDemoOptions {
    /// Fewer light angles.
    pub quick: bool,
    /// Output directory (`spectralon/`, `spheres/`, `fit/`, `report.md`).
    pub out: PathBuf,
    pub seed: u64,
    pub progress: bool,
    pub real_time: bool,
}

/// Scaled diagonal entries against the truth: median relative error.
pub const DIAGONAL_TOLERANCE: f64 = 0.03;
/// Scaled reradiation entries against the truth: median relative error.
pub const RERADIATION_TOLERANCE: f64 = 0.05;
/// Components a same-angle reconstruction of the fluorescent sphere may need for 1 % residual.
pub const MAX_COMPONENTS: usize = 10;
/// The held-out angle's non-specular PSNR with the saturated PCA, dB (thesis: 45.1).
pub const MIN_PSNR: f64 = 45.0;

/// The angles a PCA-steered session took with the chosen pairs only, reconstructed: their
/// non-specular PSNR against the truth, dB.
pub const SPARSE_MIN_PSNR: f64 = 40.0;

/// One sphere's samples against the truth.
#[derive(Debug, Clone, Copy, Default)]
pub struct TruthError {
    /// Median relative error of the diagonal entries (non-specular pixels).
    pub diagonal: f64,
    /// Median relative error of the reradiation entries two or more bands off the diagonal
    /// holding at least 1 % of their row's diagonal (NaN where the material has none).
    pub reradiation: f64,
    pub entries: [usize; 2],
}

/// What the demo measured.
#[derive(Debug)]
pub struct BrrdfDemoResult {
    pub fit: BrrdfFit,
    /// Per sphere (top: orange coat, bottom: fluorescent yellow).
    pub truth: Vec<TruthError>,
    /// Per sphere: the samples reconstructed from the chosen pairs against the truth,
    /// non-specular PSNR, dB.
    pub sparse_psnr: Vec<f64>,
    /// Frames acquired (Spectralon, spheres).
    pub frames: (u64, u64),
    /// The spheres' optical exposure time, s: as planned (PCA-steered) and a dense plan's.
    pub exposure_s: (f64, f64),
    pub report: PathBuf,
}

impl BrrdfDemoResult {
    /// The accuracy targets: `(name, value, limit, met)`.
    pub fn targets(&self) -> Vec<Target> {
        let diag = self.truth.iter().map(|t| t.diagonal).fold(0.0, f64::max);
        let rerad = self.truth.get(1).map_or(f64::NAN, |t| t.reradiation);
        let fl = self.fit.spheres.get(1);
        let comps = fl
            .and_then(|s| s.same_angle.iter().map(|a| a.components_1pc).max())
            .map_or(f64::INFINITY, |c| c as f64);
        let psnr = fl.and_then(|s| s.transfer.as_ref()).map_or(0.0, |t| t.psnr_saturated[0]);
        let sparse = self.sparse_psnr.iter().copied().fold(f64::INFINITY, f64::min);
        vec![
            (
                "diagonal entries against the truth, median relative error (worse sphere)",
                diag,
                DIAGONAL_TOLERANCE,
                diag <= DIAGONAL_TOLERANCE,
            ),
            (
                "reradiation entries against the truth, median relative error",
                rerad,
                RERADIATION_TOLERANCE,
                rerad <= RERADIATION_TOLERANCE,
            ),
            (
                "fluorescent sphere, same angle: components for 1 % residual energy, worst PCA angle",
                comps,
                MAX_COMPONENTS as f64,
                comps <= MAX_COMPONENTS as f64,
            ),
            (
                "fluorescent sphere: held-out angle, non-specular PSNR, saturated PCA (dB, at least)",
                psnr,
                MIN_PSNR,
                psnr >= MIN_PSNR,
            ),
            (
                "angles that took only the chosen pairs, reconstructed: non-specular PSNR against the truth (dB, at least, worse sphere)",
                sparse,
                SPARSE_MIN_PSNR,
                sparse >= SPARSE_MIN_PSNR,
            ),
        ]
    }

    /// The names of the targets missed.
    pub fn missed(&self) -> Vec<String> {
        self.targets().into_iter().filter(|t| !t.3).map(|t| t.0.to_string()).collect()
    }
}

/// The shipped rig file with `sets` applied.
fn rig_text(sets: &[&str]) -> Result<String, CliError> {
    let shipped = include_str!("../../../docs/rigs/bispectral.toml");
    let sets: Vec<Override> =
        sets.iter().map(|s| s.parse()).collect::<Result<_, _>>().map_err(|e| err(INPUT, e))?;
    apply(shipped, &sets).map_err(|e| err(INPUT, e))
}

/// Acquires `text` into `out/name/session` on the virtual rig; returns the frames taken.
fn session(
    out: &std::path::Path,
    name: &str,
    text: String,
    opts: &BrrdfDemoOptions,
) -> Result<(u64, f64, f64), CliError> {
    let dir = out.join(name);
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let rig = DemoRig::write(&dir, text)?;
    let (scene, sensor) = scene_for(&rig.rig, opts.seed);
    let frames = rig.plan.summary().triggers as u64;
    let b = bar(opts.progress, frames, name);
    rig.acquire(&dir, scene, sensor, opts.real_time, &b)?;
    b.finish_and_clear();
    let exposure = |k: &str| rig.plan.meta[k].as_f64().unwrap_or(0.0);
    Ok((frames, exposure("optical_exposure_s"), exposure("dense_optical_exposure_s")))
}

/// The band-limited truth of every entry of `s` (the scene's material and true normal).
fn truth_of(scene: &BispectralScene, fit: &BrrdfFit, material: &Material, s: &Sample) -> Option<Vec<f64>> {
    let (_, n) = scene.surface(s.x, s.y)?;
    let wi = lightrig_pipelines::brrdf::geometry::light_dir(s.light_deg);
    let wo = [0.0, 0.0, 1.0];
    let co = n[2];
    let leds: Vec<f64> =
        scene.slots.iter().filter_map(|n| n.strip_prefix("led-").and_then(|w| w.parse().ok())).collect();
    let specular = material
        .specular
        .map_or(0.0, |(rho, alpha)| Ward { diffuse: [0.0; 3], specular: [rho; 3], alpha }.eval(n, wi, wo)[0]);
    Some(
        fit.pairs
            .iter()
            .map(|&(ex, em)| {
                let (ex, em) = (f64::from(ex), f64::from(em));
                let is_led = leds.contains(&ex);
                let source = |nm: f64| {
                    if is_led {
                        led(ex, nm)
                    } else {
                        xenon(nm) * scene.light_filter.transmission(ex, nm)
                    }
                };
                let camera = |nm: f64| scene.camera_filter.transmission(em, nm) * ccd(nm);
                if ex == em {
                    material.band_diagonal(&source, &camera) + specular
                } else {
                    material.band_reradiation(&source, &camera, fit.spec.step_nm)
                        * Material::reradiation_angular(co)
                }
            })
            .collect(),
    )
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs the demo.
pub fn run_brrdf(opts: &BrrdfDemoOptions) -> Result<BrrdfDemoResult, CliError> {
    let out = &opts.out;
    std::fs::create_dir_all(out).map_err(io(out))?;
    // The PCA-steered plan: every pair at the PCA angles (0°, 70°, 140°) and at one more, held
    // out of the PCA to check its transfer; the chosen five at the others.
    let (angles, dense) = if opts.quick {
        ("[0, 35, 70, 100, 120, 140]", "[0, 35, 70, 140]")
    } else {
        ("[0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130, 140, 150]", "[0, 30, 70, 140]")
    };
    let (cal_frames, _, _) = session(
        out,
        "spectralon",
        rig_text(&["plan.sample=\"spectralon\"", "plan.gonio.light_angles=[0]"])?,
        opts,
    )?;
    let sets = [
        format!("plan.gonio.light_angles={angles}"),
        format!("plan.steer.dense_angles={dense}"),
        "plan.steer.select=5".to_string(),
        "plan.fit.spectralon=\"../../spectralon/session\"".to_string(),
    ];
    let sphere_text = rig_text(&sets.iter().map(String::as_str).collect::<Vec<_>>())?;
    let (frames, exposure_s, dense_s) = session(out, "spheres", sphere_text.clone(), opts)?;
    let b = bar(opts.progress, 0, "fit");
    let bb = b.clone();
    let fitted = fit::fit_session(
        &out.join("spheres/session"),
        Some(&out.join("spectralon/session")),
        &move |d, t| {
            bb.set_length(t);
            bb.set_position(d);
        },
    )
    .map_err(failure)?;
    b.finish_and_clear();
    let files = fit::write_outputs(&fitted, &out.join("fit")).map_err(failure)?;
    // The truth.
    let rig = lightrig_host::rigfile::RigFile::parse(&sphere_text, &out.join("spheres/rig.toml"))
        .map_err(|e| err(INPUT, e.to_string()))?;
    let (w, h) = scene_for(&rig, opts.seed).0.size();
    let scene = BispectralScene::new(&rig, w, h);
    let mut truth = Vec::new();
    let mut sparse = Vec::new();
    for (k, sphere) in fitted.spheres.iter().enumerate() {
        let material = &scene.materials[k];
        // The reconstructed samples (the angles that took only the chosen pairs) against the
        // truth: PSNR over their non-specular entries, the peak the truth's largest.
        let (mut se, mut n, mut peak) = (0.0, 0usize, 0.0f64);
        for s in sphere.samples.iter().filter(|s| s.reconstructed && s.half_deg > fitted.spec.specular_deg) {
            let Some(t) = truth_of(&scene, &fitted, material, s) else { continue };
            for (v, t) in s.values.iter().zip(&t) {
                se += (v - t) * (v - t);
                n += 1;
                peak = peak.max(t.abs());
            }
        }
        sparse.push(if n == 0 { f64::NAN } else { 10.0 * (peak * peak / (se / n as f64)).log10() });
        let (mut diag, mut rerad) = (Vec::new(), Vec::new());
        for s in sphere.samples.iter().filter(|s| !s.reconstructed && s.half_deg > fitted.spec.specular_deg) {
            let Some(t) = truth_of(&scene, &fitted, material, s) else { continue };
            for (j, &(ex, em)) in fitted.pairs.iter().enumerate() {
                let d = fitted.pairs.iter().position(|&p| p == (ex, ex)).map(|d| t[d]);
                if ex == em {
                    diag.push((s.values[j] / t[j] - 1.0).abs());
                } else if d.is_some_and(|d| em >= ex + 40 && t[j] >= 0.01 * d) {
                    rerad.push((s.values[j] / t[j] - 1.0).abs());
                }
            }
        }
        let entries = [diag.len(), rerad.len()];
        truth.push(TruthError { diagonal: median(diag), reradiation: median(rerad), entries });
    }
    let mut files = files;
    let mut figures = Vec::new();
    for (k, sphere) in fitted.spheres.iter().enumerate() {
        let path = out.join(format!("fit/compare-{}.png", sphere.name));
        if let Some(caption) = write_sphere_figure(&scene, &fitted, k, (w, h), &path)? {
            figures.push((format!("fit/compare-{}.png", sphere.name), caption));
            files.push(path);
        }
    }
    let result = BrrdfDemoResult {
        fit: fitted,
        truth,
        sparse_psnr: sparse,
        frames: (cal_frames, frames),
        exposure_s: (exposure_s, dense_s),
        report: out.join("report.md"),
    };
    write_report(&result, &files, &figures, opts)?;
    Ok(result)
}

/// The truth, the fit and their relative error side by side for sphere `k` at the light angle
/// that shows most of its body (the most samples outside the highlight), in the diagonal band
/// nearest 550 nm (`path`); the caption, or `None` where the sphere has no sample there.
fn write_sphere_figure(
    scene: &BispectralScene,
    fitted: &BrrdfFit,
    k: usize,
    (w, h): (u32, u32),
    path: &std::path::Path,
) -> Result<Option<String>, CliError> {
    use lightrig_imaging::figure::{row, Panel};
    let Some(j) = (0..fitted.pairs.len())
        .filter(|&j| fitted.pairs[j].0 == fitted.pairs[j].1)
        .min_by_key(|&j| (i64::from(fitted.pairs[j].0) - 550).abs())
    else {
        return Ok(None);
    };
    let sphere = &fitted.spheres[k];
    let material = &scene.materials[k];
    let n = (w * h) as usize;
    let (mut truth, mut fit, mut error) = (vec![None; n], vec![None; n], vec![None; n]);
    // The light angle that shows most of the body (least of the highlight).
    let body = |g: usize| {
        sphere
            .samples
            .iter()
            .filter(|s| s.geometry == g && !s.reconstructed && s.half_deg > fitted.spec.specular_deg)
            .count()
    };
    let mut geometries: Vec<usize> =
        sphere.samples.iter().filter(|s| !s.reconstructed).map(|s| s.geometry).collect();
    geometries.sort_unstable();
    geometries.dedup();
    let first = geometries.into_iter().max_by_key(|&g| (body(g), std::cmp::Reverse(g)));
    for s in sphere.samples.iter().filter(|s| Some(s.geometry) == first && !s.reconstructed) {
        let Some(t) = truth_of(scene, fitted, material, s) else { continue };
        let i = (s.y * w + s.x) as usize;
        if i >= n || t[j] <= 0.0 {
            continue;
        }
        truth[i] = Some(t[j] as f32);
        fit[i] = Some(s.values[j] as f32);
        error[i] = Some(((s.values[j] - t[j]) / t[j]).abs() as f32);
    }
    // The scale from the truth's 2nd to its 98th percentile: the highlight saturates it rather
    // than darken the rest.
    let mut shown: Vec<f64> = truth.iter().flatten().map(|&v| f64::from(v)).collect();
    if shown.is_empty() {
        return Ok(None);
    }
    shown.sort_by(f64::total_cmp);
    let at = |q: f64| shown[((shown.len() - 1) as f64 * q).round() as usize];
    let (low, peak) = (at(0.02), at(0.98).max(at(0.02) * 1.001 + 1e-9));
    let light = sphere.samples.iter().find(|s| Some(s.geometry) == first).map_or(0.0, |s| s.light_deg);
    let figure = row(
        &[
            Panel::scalar(w, h, &truth, (low as f32, peak as f32)),
            Panel::scalar(w, h, &fit, (low as f32, peak as f32)),
            Panel::scalar(w, h, &error, (0.0, SPHERE_ERROR_RANGE as f32)),
        ],
        SPHERE_FIGURE_ZOOM,
    );
    lightrig_imaging::io::write_png(path, &figure, lightrig_imaging::io::BitDepth::Eight).map_err(failure)?;
    Ok(Some(format!(
        "The {} sphere, light at {light}°, band {} nm → {} nm: left to right the truth and the scaled fit ({low:.3} to {peak:.3} sr⁻¹, \
         the truth's 2nd to 98th percentile, on the same scale) and |fit − truth| / truth from 0 (dark) to {:.0} % (yellow); grey where the sphere has no sample.",
        sphere.name,
        fitted.pairs[j].0,
        fitted.pairs[j].1,
        100.0 * SPHERE_ERROR_RANGE
    )))
}

/// The sphere figures' relative error range: 0 to 10 %.
pub const SPHERE_ERROR_RANGE: f64 = 0.1;

/// The sphere figures' enlargement: a sphere is some 30 px across in the frame.
pub const SPHERE_FIGURE_ZOOM: u32 = 3;

fn write_report(
    r: &BrrdfDemoResult,
    files: &[PathBuf],
    figures: &[(String, String)],
    opts: &BrrdfDemoOptions,
) -> Result<(), CliError> {
    let mut rep = Report::default();
    rep.line("# Bispectral BRRDF on the virtual rig");
    rep.line("");
    rep.line(format!(
        "The shipped `docs/rigs/bispectral.toml` on the virtual controller and the gonioreflectometer scene \
         (`sim/src/scenes/bispectral.rs`){}: a Spectralon session ({} frames) and the two spheres ({} frames), \
         {} wavelength pairs, fitted as `lightrig fit brrdf` does. Truth: the entries an ideal instrument with \
         the same filter bands reports (`Material::band_diagonal`, `band_reradiation`).",
        if opts.quick { ", quick: light at 0°, 35°, 70°, 140°" } else { "" },
        r.frames.0,
        r.frames.1,
        r.fit.pairs.len()
    ));
    rep.line("");
    rep.targets(["target", "value", "limit"], "", &r.targets());
    rep.line("");
    for (file, caption) in figures {
        rep.line(format!("![truth, fit, relative error]({file})\n\n{caption}\n"));
    }
    let choice = lightrig_host::steer::Choice::load(&opts.out.join("spheres/session")).ok().flatten();
    rep.line(format!(
        "PCA-steered: every pair at light angles {}, the chosen pairs ({}) at the others; optical exposure \
         {:.0} s against {:.0} s for every pair at every angle ({:.1} %).",
        r.fit
            .spheres
            .first()
            .map(|s| {
                let mut a: Vec<f64> =
                    s.samples.iter().filter(|x| !x.reconstructed).map(|x| x.light_deg).collect();
                a.dedup();
                a.sort_by(f64::total_cmp);
                a.dedup();
                a.iter().map(|d| format!("{d:.0}°")).collect::<Vec<_>>().join(", ")
            })
            .unwrap_or_default(),
        choice
            .map(|c| c.pairs.iter().map(|p| format!("{}→{} nm", p[0], p[1])).collect::<Vec<_>>().join(", "))
            .unwrap_or_else(|| "none".into()),
        r.exposure_s.0,
        r.exposure_s.1,
        100.0 * r.exposure_s.0 / r.exposure_s.1.max(1e-9)
    ));
    for n in &r.fit.notes {
        rep.line("");
        rep.line(format!("Note: {n}."));
    }
    rep.line("");
    rep.line("## Per sphere");
    rep.line("");
    rep.line("| sphere | samples (reconstructed) | bins observed | diagonal error (median) | reradiation error (median) | same angle: components 1 % / 0.1 % | held out | pairs chosen (saturated) | PSNR non-specular std / sat | PSNR specular std / sat | reconstructed angles: PSNR against the truth |");
    rep.line("|---|---|---|---|---|---|---|---|---|---|---|");
    for (k, s) in r.fit.spheres.iter().enumerate() {
        let t = r.truth.get(k).copied().unwrap_or_default();
        let (held, chosen, ns, sp) = match &s.transfer {
            Some(t) => (
                format!("{:.1}°", t.held_out_deg),
                t.chosen_saturated.iter().map(|p| format!("{}→{}", p.0, p.1)).collect::<Vec<_>>().join(", "),
                format!("{:.1} / {:.1} dB", t.psnr[0], t.psnr_saturated[0]),
                format!("{:.1} / {:.1} dB ({} px)", t.psnr[1], t.psnr_saturated[1], t.pixels[1]),
            ),
            None => ("–".into(), "–".into(), "–".into(), "–".into()),
        };
        rep.line(format!(
            "| {} ({}) | {} ({}) | {} of {} | {:.2} % | {} | {} | {held} | {chosen} | {ns} | {sp} | {:.1} dB |",
            s.name,
            ["orange coat", "fluorescent yellow"].get(k).unwrap_or(&""),
            s.samples.len(),
            s.reconstructed,
            s.binned.observed(),
            s.binned.n.pow(3),
            100.0 * t.diagonal,
            if t.reradiation.is_nan() {
                "none".to_string()
            } else {
                format!("{:.2} %", 100.0 * t.reradiation)
            },
            s.same_angle
                .iter()
                .map(|a| format!("{:.0}°: {} / {}", a.light_deg, a.components_1pc, a.components_01pc))
                .collect::<Vec<_>>()
                .join(", "),
            r.sparse_psnr.get(k).copied().unwrap_or(f64::NAN),
        ));
    }
    rep.outputs(files);
    rep.write(&r.report)?;
    Ok(())
}
