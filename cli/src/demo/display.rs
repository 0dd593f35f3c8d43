//! `lightrig demo display`: the BRDF display on the virtual rig, as a lab would run it with
//! the shipped `docs/rigs/brdf-display.toml`: a calibration session (a still surface, then one
//! sine per coil per step) fitted into the coils' responses; a display session showing a sweep
//! of Ward roughnesses solved through them, measured by the camera; the same targets planned
//! again from the calibration that learnt what the camera saw (the closed loop), measured again.
//! The scene has every fault a lab's tank and coils have (`Faults::ALL`); the same workflow
//! then runs with each fault alone and on the ideal display. The report compares the measured
//! responses with the scene's true ones, each shown α with its target, what each fault does,
//! and the simulated surface's slope statistics with Eq. 5.6 and a Gaussian.

use std::path::{Path, PathBuf};

use lightrig_firmware::synth::Synth;
use lightrig_host::fit::display::{self as fit, Shown, CALIBRATION_FILE};
use lightrig_host::plan::from_rig::display_screen;
use lightrig_imaging::figure::{histogram, row, Panel};
use lightrig_imaging::io::{write_png, BitDepth};
use lightrig_pipelines::display::calibration::Calibration;
use lightrig_pipelines::display::lobe::fit_ward;
use lightrig_pipelines::display::mapping::{
    bell_ratio, golden_phase, partial_roughness, slope_roughness, X_FREQUENCIES, Y_FREQUENCIES,
};
use lightrig_pipelines::display::slopes::{arcsine_cdf, ks_distance, ks_to_gaussian, moments, normal_cdf};
use lightrig_protocol::sequence::Partial;
use lightrig_sim::scenes::display::{DisplayScene, Faults};
use lightrig_sim::scenes::display_scene;

use super::{bar, DemoRig, Report, Target};
use crate::error::{failure, io, CliError};

/// How the demo runs.
#[derive(Debug, Clone)]
pub struct DisplayDemoOptions {
    /// A shorter sweep.
    pub quick: bool,
    /// Output directory (`calibration/`, `display/`, `corrected/`, `report.md`).
    pub out: PathBuf,
    /// Noise seed.
    pub seed: u64,
    /// Progress bars.
    pub progress: bool,
    /// The virtual rig in real time.
    pub real_time: bool,
}

/// The shown α's tolerance right after calibration (the target), relative.
pub const FIRST_TOLERANCE: f64 = 0.05;
/// The tolerance once the loop has closed, relative.
pub const CORRECTED_TOLERANCE: f64 = 0.01;
/// The largest |H| error the calibration may make against the scene's truth, relative.
pub const RESPONSE_TOLERANCE: f64 = 0.05;

/// What the demo measured.
#[derive(Debug, Clone)]
pub struct DisplayDemoResult {
    /// The calibration after the display session (with what the camera saw).
    pub calibration: Calibration,
    /// Largest relative error of the measured `|H|` against the truth, per axis.
    pub response_error: [f64; 2],
    /// The sweep, straight from the calibration.
    pub first: Vec<Shown>,
    /// The sweep again, planned from what the camera saw.
    pub corrected: Vec<Shown>,
    /// Kolmogorov–Smirnov distances measured on the simulated surface: one sine against
    /// Eq. 5.6, then 1, 3, 5 and 7 partials against a Gaussian.
    pub ks_one_sine: f64,
    /// `(partials, KS to a Gaussian)`.
    pub ks_gaussian: Vec<(usize, f64)>,
    /// Ward's lobe fitted to the screen's picture of `n` partials per axis for α = 0.08, on
    /// the ideal display and with every fault on.
    pub ward_shape: Vec<WardShape>,
    /// The rig file's bound on the total slope, rad (`[plan] max_slope_deg`).
    pub max_slope: f64,
    /// The slope histograms as pictures: `(file relative to the output directory, caption)`.
    pub histograms: Vec<(String, String)>,
    /// The highlights the camera saw after the correction, one panel per target: `(file,
    /// caption)`.
    pub lobes: (String, String),
    /// What each fault does alone (and the ideal display, `none`), on the quick sweep.
    pub faults: Vec<FaultEffect>,
    /// `report.md`.
    pub report: PathBuf,
}

/// Ward's lobe fitted to the picture of `partials` per axis planned for α = 0.08 through the
/// true small-signal response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WardShape {
    /// Partials per axis.
    pub partials: usize,
    /// On the ideal display: `(α the fit found on x and y, shape error)`.
    pub ideal: ([f64; 2], f64),
    /// With every fault on.
    pub faulted: ([f64; 2], f64),
}

/// What one of the scene's faults does alone to the lab's workflow.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultEffect {
    /// The fault ([`Faults::NAMES`]) or `none`.
    pub name: String,
    /// Largest relative error of the calibrated `|H|`, both axes.
    pub response_error: f64,
    /// Largest relative error of the shown α after calibration.
    pub first: f64,
    /// After one correction.
    pub corrected: f64,
}

/// The largest relative error of any axis of `v`.
fn worst(v: &[Shown]) -> f64 {
    v.iter().flat_map(|s| s.error()).map(f64::abs).fold(0.0, f64::max)
}

impl DisplayDemoResult {
    /// The accuracy targets: `(name, value, limit, met)`.
    pub fn targets(&self) -> Vec<Target> {
        let (h, a1, a2) =
            (self.response_error[0].max(self.response_error[1]), worst(&self.first), worst(&self.corrected));
        let bell = self.ks_gaussian.iter().find(|(n, _)| *n >= 5).map_or(1.0, |x| x.1);
        vec![
            ("calibrated |H| against the truth, worst", h, RESPONSE_TOLERANCE, h <= RESPONSE_TOLERANCE),
            ("shown α after calibration, worst error", a1, FIRST_TOLERANCE, a1 <= FIRST_TOLERANCE),
            ("shown α after one correction, worst error", a2, CORRECTED_TOLERANCE, a2 <= CORRECTED_TOLERANCE),
            ("one sine against Eq. 5.6 (KS)", self.ks_one_sine, 0.01, self.ks_one_sine <= 0.01),
            ("five or more partials against a Gaussian (KS)", bell, 0.03, bell <= 0.03),
        ]
    }

    /// The names of the targets missed.
    pub fn missed(&self) -> Vec<String> {
        self.targets().into_iter().filter(|t| !t.3).map(|t| t.0.to_string()).collect()
    }
}

/// The shipped rig file with its `[plan.calibrate]` (calibration) or the sweep `alphas` solved
/// through `calibration` (display).
fn rig_text(alphas: Option<(&[[f64; 2]], &str)>) -> String {
    let shipped = include_str!("../../../docs/rigs/brdf-display.toml");
    match alphas {
        None => shipped.to_string(),
        Some((alphas, cal)) => {
            let list: Vec<String> = alphas.iter().map(|a| format!("[{}, {}]", a[0], a[1])).collect();
            let plan = format!("alphas = [{}]\ncalibration = \"{cal}\"\n", list.join(", "));
            let calibrate = "[plan.calibrate]\ndrive = 0.03";
            assert!(shipped.contains(calibrate), "the shipped rig file calibrates");
            shipped.replacen(calibrate, &plan, 1)
        }
    }
}

/// One session of the demo in `out/name`: the rig written, acquired on the virtual rig, read.
fn session(
    out: &Path,
    name: &str,
    text: String,
    faults: Faults,
    opts: &DisplayDemoOptions,
) -> Result<fit::DisplaySession, CliError> {
    let dir = out.join(name);
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let rig = DemoRig::write(&dir, text)?;
    let (mut scene, sensor) = display_scene(&rig.rig, opts.seed);
    scene.faults = faults;
    let b = bar(
        opts.progress,
        rig.plan.summary().triggers as u64,
        &format!("{name} ({})", faults.names().join(", ")),
    );
    rig.acquire(&dir, Box::new(scene), sensor, opts.real_time, &b)?;
    b.finish_and_clear();
    fit::read(&dir.join("session")).map_err(failure)
}

/// What the controller's synthesiser plays for `partials` `(Hz, drive)`: 0.1 s, then 1 s.
fn played(partials: &[(f64, f64)]) -> (Vec<i16>, Vec<i16>) {
    let mut synth = Synth::new(48_000);
    let p: Vec<Partial> = partials
        .iter()
        .enumerate()
        .map(|(i, &(f, d))| Partial {
            freq_mhz: (f * 1000.0).round() as u32,
            amplitude: (d * f64::from(u16::MAX)).round() as u16,
            phase: (golden_phase(i) * 65536.0) as u16,
        })
        .collect();
    synth.set(&p, 0).expect("valid partials");
    let (mut before, mut now) = (vec![0i16; 4_800], vec![0i16; 48_000]);
    synth.fill(&mut before);
    synth.fill(&mut now);
    (before, now)
}

/// What one pass of the lab's workflow found.
struct Pass {
    /// The calibration session's fit.
    calibration: Calibration,
    /// The calibration after both display sessions (what the camera saw, learnt twice).
    learnt: Calibration,
    /// Largest relative error of the measured `|H|` against what a small sine shows of the
    /// scene's truth (its walls and film included), per axis.
    response_error: [f64; 2],
    first: Vec<Shown>,
    corrected: Vec<Shown>,
}

/// One pass of the lab's workflow on the scene with `faults`, in `out`: calibration, the
/// `sweep` solved through it, the sweep again planned from what the camera saw.
fn pass(out: &Path, faults: Faults, sweep: &[[f64; 2]], opts: &DisplayDemoOptions) -> Result<Pass, CliError> {
    std::fs::create_dir_all(out).map_err(io(out))?;
    // 1. Calibration.
    let cal_session = session(out, "calibration", rig_text(None), faults, opts)?;
    let cal = fit::calibration(&cal_session).map_err(failure)?;
    let cal_path = out.join("calibration").join(CALIBRATION_FILE);
    let json = serde_json::to_string_pretty(&cal).map_err(failure)? + "\n";
    std::fs::write(&cal_path, json).map_err(io(&cal_path))?;
    let mut truth = DisplayScene::small_water(16, 16);
    truth.faults = faults;
    let mut response_error = [0.0f64; 2];
    for (k, a) in cal.axes.iter().enumerate() {
        for (&f, &h) in a.frequencies_hz.iter().zip(&a.response_m) {
            let t = truth.effective_response(k, f);
            response_error[k] = response_error[k].max((h / t - 1.0).abs());
        }
    }
    // 2. The sweep through the calibration.
    let rel = format!("../calibration/{CALIBRATION_FILE}");
    let mut learnt = cal.clone();
    let display = session(out, "display", rig_text(Some((sweep, &rel))), faults, opts)?;
    let first = fit::measure(&display, &mut learnt).map_err(failure)?;
    // 3. The closed loop: plan again from the calibration that saw the sweep.
    let learnt_path = out.join("display").join(CALIBRATION_FILE);
    let json = serde_json::to_string_pretty(&learnt).map_err(failure)? + "\n";
    std::fs::write(&learnt_path, json).map_err(io(&learnt_path))?;
    let rel = format!("../display/{CALIBRATION_FILE}");
    let corrected_session = session(out, "corrected", rig_text(Some((sweep, &rel))), faults, opts)?;
    let corrected = fit::measure(&corrected_session, &mut learnt).map_err(failure)?;
    Ok(Pass { calibration: cal, learnt, response_error, first, corrected })
}

/// Runs the demo.
pub fn run_display(opts: &DisplayDemoOptions) -> Result<DisplayDemoResult, CliError> {
    let out = &opts.out;
    std::fs::create_dir_all(out).map_err(io(out))?;
    // The sweep: isotropic over the thesis's range, anisotropic up to 3:1 both ways.
    let quick_sweep = vec![[0.02, 0.02], [0.08, 0.08], [0.14, 0.14], [0.12, 0.04], [0.03, 0.09]];
    let sweep: Vec<[f64; 2]> = if opts.quick {
        quick_sweep.clone()
    } else {
        vec![
            [0.02, 0.02],
            [0.05, 0.05],
            [0.08, 0.08],
            [0.11, 0.11],
            [0.14, 0.14],
            [0.12, 0.04],
            [0.04, 0.12],
            [0.08, 0.04],
            [0.03, 0.09],
        ]
    };
    // The lab's display: every fault on.
    let Pass { calibration: cal, learnt: again, response_error, first, corrected } =
        pass(out, Faults::ALL, &sweep, opts)?;
    // What each fault does alone, and the ideal display, on the quick sweep.
    let mut faults = Vec::new();
    for name in std::iter::once("none").chain(Faults::NAMES) {
        let f = Faults::only(name).unwrap_or(Faults::NONE);
        let p = pass(&out.join("faults").join(name), f, &quick_sweep, opts)?;
        faults.push(FaultEffect {
            name: name.to_string(),
            response_error: p.response_error[0].max(p.response_error[1]),
            first: worst(&p.first),
            corrected: worst(&p.corrected),
        });
    }
    let lobes = write_lobes(&out.join("corrected").join("session"), &corrected, out)?;
    // 4. The simulated surface's slopes: one sine (Eq. 5.6), then 1, 3, 5, 7 partials.
    let side = lightrig_sim::scenes::display::SCREEN_PIXELS;
    let scene = DisplayScene::small_water(side, side);
    let mut faulted = DisplayScene::small_water(side, side);
    faulted.faults = Faults::ALL;
    let kh = |axis: usize, f: f64| {
        scene.liquid.wave_number(f) * scene.actuators[axis].response(&scene.liquid, f).norm()
    };
    let k = |f: f64| kh(0, f);
    let gradients = |axis: usize, partials: &[(f64, f64)]| -> Vec<f64> {
        let (before, now) = played(partials);
        scene.slopes(axis, 48_000.0, &before, &now)
    };
    // Reflection angles in the small-angle model of Eq. 5.6 and figure 5.8: δ = 2·slope.
    let slopes =
        |partials: &[(f64, f64)]| -> Vec<f64> { gradients(0, partials).iter().map(|s| 2.0 * s).collect() };
    let shipped = lightrig_host::rigfile::RigFile::parse(
        include_str!("../../../docs/rigs/brdf-display.toml"),
        Path::new("docs/rigs/brdf-display.toml"),
    )
    .map_err(failure)?;
    let screen = display_screen(&shipped).map_err(failure)?.screen(side, side);
    let f1 = X_FREQUENCIES[4];
    let one = slopes(&[(f1, 0.03)]);
    let rho = k(f1) * 0.03;
    let ks_one_sine = ks_distance(&one, |d| arcsine_cdf(d, rho, 0.0));
    // Each distribution as a histogram beside its model (40 bins, 6 px each, 160 px tall).
    let mut histograms = Vec::new();
    let mut picture =
        |name: &str, samples: &[f64], range: (f64, f64), cdf: &dyn Fn(f64) -> f64, caption: String| {
            let file = format!("{name}.png");
            let img = histogram(samples, range, 40, cdf, (6, 160));
            write_png(out.join(&file), &img, BitDepth::Eight).map_err(failure)?;
            histograms.push((file, caption));
            Ok::<(), CliError>(())
        };
    picture(
        "slopes-one-sine",
        &one,
        (-2.2 * rho, 2.2 * rho),
        &|d| arcsine_cdf(d, rho, 0.0),
        format!(
            "reflection angle δ of one sine at {f1} Hz, ±{:.3} rad: the surface's histogram (bars) and \
             Eq. 5.6's arcsine distribution (marks)",
            2.2 * rho
        ),
    )?;
    let mut ks_gaussian = Vec::new();
    let mut ward_shape = Vec::new();
    for n in [1usize, 3, 5, 7] {
        // Equal roughness per partial for α = 0.08 over n partials, as the solver plans it.
        let r = partial_roughness(slope_roughness(0.08), n) / bell_ratio(n);
        let p: Vec<(f64, f64)> = X_FREQUENCIES[..n].iter().map(|&f| (f, r / k(f))).collect();
        let d = slopes(&p);
        ks_gaussian.push((n, ks_to_gaussian(&d)));
        // The same on both axes, as the screen shows it, against Ward's lobe.
        let py: Vec<(f64, f64)> = Y_FREQUENCIES[..n].iter().map(|&f| (f, r / kh(1, f))).collect();
        let (gx, gy) = (gradients(0, &p), gradients(1, &py));
        let both: Vec<(f64, f64)> = gx.iter().copied().zip(gy.iter().copied()).collect();
        let pic: Vec<f32> = scene.picture_of(&both).iter().map(|&v| v as f32).collect();
        let fit = fit_ward(&pic, side as usize, side as usize, &screen, cal.beam_px);
        // And on the lab's display, every fault on, driven through its small-signal response.
        let lab = |axis: usize, freqs: &[f64]| -> (Vec<i16>, Vec<i16>) {
            let p: Vec<(f64, f64)> = freqs[..n]
                .iter()
                .map(|&f| (f, r / (faulted.liquid.wave_number(f) * faulted.effective_response(axis, f))))
                .collect();
            played(&p)
        };
        let ((bx, nx), (by, ny)) = (lab(0, &X_FREQUENCIES), lab(1, &Y_FREQUENCIES));
        let both = faulted.gradients_of([&bx, &by], [&nx, &ny]);
        let pic: Vec<f32> = faulted.picture_of(&both).iter().map(|&v| v as f32).collect();
        let lab_fit = fit_ward(&pic, side as usize, side as usize, &screen, cal.beam_px);
        ward_shape.push(WardShape {
            partials: n,
            ideal: (fit.alpha, fit.shape_error),
            faulted: (lab_fit.alpha, lab_fit.shape_error),
        });
        let (mean, var) = moments(&d);
        let sd = var.sqrt();
        picture(
            &format!("slopes-{n}-partials"),
            &d,
            (mean - 4.0 * sd, mean + 4.0 * sd),
            &|x| normal_cdf(x, mean, sd),
            format!(
                "δ of {n} partial(s) for α = 0.08, mean ± 4 sd ({:.3} rad): histogram (bars) and the Gaussian \
                 of the same mean and variance (marks)",
                4.0 * sd
            ),
        )?;
    }
    let result = DisplayDemoResult {
        calibration: again,
        response_error,
        first,
        corrected,
        ks_one_sine,
        ks_gaussian,
        ward_shape,
        max_slope: lightrig_host::plan::from_rig::display_max_slope(&shipped).map_err(failure)?,
        histograms,
        lobes,
        faults,
        report: out.join("report.md"),
    };
    write_report(&result, &cal, opts)?;
    Ok(result)
}

/// `out/lobes.png`: each target's first frame of the display session in `dir` (the screen as
/// the camera saw it), through the colour map from 0 to its own peak, in the order of `shown`.
fn write_lobes(dir: &Path, shown: &[Shown], out: &Path) -> Result<(String, String), CliError> {
    let (s, _) = lightrig_host::session::Session::read(dir).map_err(failure)?;
    let camera = s.pipeline_camera(None).map_err(failure)?;
    let mut panels = Vec::new();
    for sh in shown {
        let frames = s.camera_frames_of(sh.step, camera);
        let f = frames.first().ok_or_else(|| failure(format!("step {} has no frame", sh.step)))?;
        let img = lightrig_imaging::io::read(dir.join(&f.file)).map_err(failure)?;
        let c = usize::from(img.channels.max(1));
        let px: Vec<Option<f32>> = img.data.iter().step_by(c).map(|&v| Some(v)).collect();
        let peak = px.iter().flatten().copied().fold(0.0, f32::max).max(f32::MIN_POSITIVE);
        panels.push(Panel::scalar(img.width, img.height, &px, (0.0, peak)));
    }
    let file = "lobes.png".to_string();
    write_png(out.join(&file), &row(&panels, 1), BitDepth::Eight).map_err(failure)?;
    let each: Vec<String> = shown
        .iter()
        .map(|s| format!("[{}, {}] shown [{:.3}, {:.3}]", s.target[0], s.target[1], s.shown[0], s.shown[1]))
        .collect();
    let caption = format!(
        "the highlight on the screen after one correction, left to right for the targets αx, αy {} \
         (each from 0 to its own peak)",
        each.join(", ")
    );
    Ok((file, caption))
}

fn write_report(r: &DisplayDemoResult, cal: &Calibration, opts: &DisplayDemoOptions) -> Result<(), CliError> {
    let mut rep = Report::default();
    rep.line("# BRDF display on the virtual rig");
    rep.line("");
    rep.line(format!(
        "The shipped `docs/rigs/brdf-display.toml` on the virtual controller and the liquid scene \
         (`sim/src/scenes/display.rs`: water 5 mm deep in a 2 cm tank, paddle resonances 190 and \
         215 Hz) with every fault a lab's display has on: a surfactant film, reflections from the \
         wall and the paddles, the coils' saturation and harmonics, crosstalk between the coils{}. \
         Sessions: `calibration/`, `display/`, `corrected/`; each fault alone in `faults/`.",
        if opts.quick { "; quick sweep" } else { "" }
    ));
    rep.line("");
    rep.targets(["target", "value", "limit"], "≤ ", &r.targets());
    rep.line("");
    rep.line("## Calibration");
    rep.line("");
    rep.line("| axis | coil | f (Hz) | measured |H| (µm per full scale) | reachable α |");
    rep.line("|---|---|---|---|---|");
    let liquid = cal.liquid().map_err(failure)?;
    for (k, a) in cal.axes.iter().enumerate() {
        let (max, limit) = a.axis(["x", "y"][k], r.max_slope).reachable(&liquid).map_err(failure)?;
        for (i, (f, h)) in a.frequencies_hz.iter().zip(&a.response_m).enumerate() {
            let reach = if i == 0 { format!("≤ {max:.3} ({limit})") } else { String::new() };
            rep.line(format!("| {} | {} | {f} | {:.1} | {reach} |", ["x", "y"][k], a.coil, h * 1e6));
        }
    }
    for (name, v) in [("After calibration", &r.first), ("After one correction", &r.corrected)] {
        rep.line("");
        rep.line(format!("## {name}"));
        rep.line("");
        rep.line(
            "| target αx | target αy | asked αx | asked αy | shown αx | shown αy | error x | error y | lobe-shape error |",
        );
        rep.line("|---|---|---|---|---|---|---|---|---|");
        for s in v.iter() {
            let e = s.error();
            rep.line(format!(
                "| {} | {} | {:.4} | {:.4} | {:.4} | {:.4} | {:+.2} % | {:+.2} % | {:.4} |",
                s.target[0],
                s.target[1],
                s.asked[0],
                s.asked[1],
                s.shown[0],
                s.shown[1],
                100.0 * e[0],
                100.0 * e[1],
                s.shape_error
            ));
        }
    }
    rep.line("");
    rep.line("## What each fault does");
    rep.line("");
    rep.line(
        "The same workflow (calibration, the quick sweep, one correction) on the scene with one \
         fault on at a time, and on the ideal display (`none`): the worst error of the calibrated \
         |H| against what a small sine shows of the truth, and of the shown α against its target.",
    );
    rep.line("");
    rep.line("| fault | calibrated |H| | shown α after calibration | after one correction |");
    rep.line("|---|---|---|---|");
    for f in &r.faults {
        rep.line(format!(
            "| {} | {:.2} % | {:.2} % | {:.2} % |",
            f.name,
            100.0 * f.response_error,
            100.0 * f.first,
            100.0 * f.corrected
        ));
    }
    rep.line("");
    rep.line("## Slope statistics of the simulated surface (figure 5.8)");
    rep.line("");
    rep.line(format!("One sine at {} Hz against Eq. 5.6: KS {:.4}.", X_FREQUENCIES[4], r.ks_one_sine));
    rep.line("");
    rep.line(
        "Each row: `n` partials per axis planned for α = 0.08 (the first `n` of each coil's \
         frequencies, driven through the true response): the KS distance of the x slope from the \
         Gaussian of its own moments, and, on both coils as the screen shows it, Ward's lobe fitted \
         to the picture: the α it finds and the lobe-shape error (the total-variation distance \
         between the picture and the fitted lobe).",
    );
    rep.line("");
    rep.line(
        "| partials | KS to a Gaussian | Ward fit αx | Ward fit αy | lobe-shape error | with every fault: αx | αy | lobe-shape error |",
    );
    rep.line("|---|---|---|---|---|---|---|---|");
    for ((n, ks), w) in r.ks_gaussian.iter().zip(&r.ward_shape) {
        let ((a, shape), (b, lab)) = (w.ideal, w.faulted);
        rep.line(format!(
            "| {n} | {ks:.4} | {:.4} | {:.4} | {shape:.4} | {:.4} | {:.4} | {lab:.4} |",
            a[0], a[1], b[0], b[1]
        ));
    }
    rep.line("");
    let (file, caption) = &r.lobes;
    rep.line(format!("![{caption}]({file})\n\n*{caption}*\n"));
    for (file, caption) in &r.histograms {
        rep.line(format!("![{caption}]({file})\n\n*{caption}*\n"));
    }
    rep.write(&r.report)?;
    Ok(())
}
