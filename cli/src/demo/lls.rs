//! `lightrig demo lls` (the default): the linear-light-source gantry on the virtual rig, its
//! fit, and the fit against the ground truth the frames were rendered from.
//!
//! It writes, under the output directory:
//! `rig.toml` (the rig the demo runs, a valid rig file), `camera.toml` (the virtual camera's
//! intrinsics as a calibration file, standing in for `lightrig calibrate`), `truth/` (`scene.json` and `truth.exr`,
//! the ground truth per pixel), `camera/` (the frames as the virtual camera wrote them),
//! `session/` (the journaled session, as `lightrig acquire` writes it), `fit/` (the maps) and
//! `report.md` (the fit against the truth).

use std::path::{Path, PathBuf};
use std::time::Instant;

use lightrig_host::fit::lls::{export, fit_session, write_outputs, LlsMaps, NormalBlend};
use lightrig_imaging::io::{write_exr_layers, ExrPrecision, Layer};
use lightrig_pipelines::vec3::angle;
use lightrig_sim::scenes::lls::{LlsScene, LlsSceneSpec, Region};
use lightrig_sim::sensor::Sensor;

use super::{bar, write_scene_json, DemoRig, Report, Target};
use crate::error::{failure, io, CliError};

/// Demo size and where to write.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Small scene for tests (about 20 s).
    pub quick: bool,
    /// Output directory.
    pub out: PathBuf,
    /// Noise seed.
    pub seed: u64,
    /// Show progress bars.
    pub progress: bool,
    /// Pace the virtual rig in real time (as long as the real rig would take) instead of as
    /// fast as the rendering allows.
    pub real_time: bool,
    /// The gantry's step, mm; `None`: 1 mm (2 mm when `quick`).
    pub step_mm: Option<f64>,
    /// The virtual camera's display gamma; `None`: a linear camera. With a gamma the demo
    /// recovers the camera's response from an exposure series (`camera-response.json`,
    /// `lightrig hdr calibrate`'s output), and the rig file names it.
    pub camera_gamma: Option<f64>,
}

/// The fit against the truth: median errors over the sample's pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LlsAccuracy {
    /// Pixels compared.
    pub pixels: usize,
    /// Median |ρd − ρd*| over pixels and channels.
    pub diffuse_abs: f64,
    /// Median |ρs/ρs* − 1|.
    pub specular_rel: f64,
    /// Median |α/α* − 1|.
    pub roughness_rel: f64,
    /// Median normal angle error, degrees (the normals the fit used).
    pub normal_deg: f64,
    /// The same for the displacement map's normals alone.
    pub geometric_normal_deg: f64,
    /// The same for the diagonal passes' normals alone (NaN without diagonal passes).
    pub photometric_normal_deg: f64,
    /// The same for the two blends of the diagonal passes' normals with the displacement
    /// map's: the frequency split and the paper's `ρs/α` blend (NaN without diagonal passes).
    pub split_normal_deg: f64,
    pub gloss_normal_deg: f64,
    /// Median |h − h*|, mm.
    pub height_mm: f64,
    /// Median |τ − τ*|.
    pub translucency_abs: f64,
    /// The gantry step, mm (the height target is half of it).
    pub step_mm: f64,
}

impl LlsAccuracy {
    /// The issue's targets, each `(name, value, limit, met)`.
    pub fn targets(&self) -> [Target; 5] {
        let t = |n, v: f64, l: f64| (n, v, l, v <= l);
        [
            t("diffuse albedo, median abs", self.diffuse_abs, 0.01),
            t("specular albedo, median rel", self.specular_rel, 0.03),
            t("roughness, median rel", self.roughness_rel, 0.05),
            t("normal, median deg", self.normal_deg, 1.0),
            t("height, median mm", self.height_mm, self.step_mm / 2.0),
        ]
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The demo's rig file for `spec`: a valid rig file whose `[plan.fit]` holds the geometry the
/// fit needs (what a lab measures once for its rig).
pub fn lls_rig_text(spec: &LlsSceneSpec, pass: [f64; 2], step_mm: f64) -> String {
    lls_rig_text_with(spec, pass, step_mm, None)
}

/// [`lls_rig_text`] for a virtual camera with display gamma `gamma` (`Some`) whose response
/// is `camera-response.json` beside the rig file.
pub fn lls_rig_text_with(spec: &LlsSceneSpec, pass: [f64; 2], step_mm: f64, gamma: Option<f64>) -> String {
    let source = match gamma {
        None => "source = { kind = \"virtual\" }".to_string(),
        Some(g) => format!(
            "source = {{ kind = \"virtual\", gamma = {g} }}\n# From `lightrig hdr calibrate` on an exposure series of this camera.\nresponse = \"{RESPONSE_FILE}\""
        ),
    };
    let l = &spec.light;
    let s = &spec.stripe;
    let b = &spec.board;
    let (d, sp) = (&spec.diffuse_strip, &spec.specular_strip);
    format!(
        r#"# The linear-light-source rig `lightrig demo` runs on the virtual rig (written by the demo).
[rig]
name = "lls-demo"
method = "linear-light-source"
description = "Virtual LLS gantry: light tube and laser stripe over a flat sample on a light box"

[device]
connect = "virtual"

[safety]
heartbeat_timeout_ms = 500

[[stepper]]
axis = {axis}
name = "gantry"
kind = "linear"
steps_per_unit = "80"
max_speed = 100
accel = 500
limits = [-200.0, 200.0]
homing = {{ mode = "min", speed = 20, backoff = 2, position = -200 }}
limit_min = "low"
limit_max = "low"
enable = "low"

[[laser]]
channel = {stripe_ch}
name = "stripe"
role = "stripe"
wavelength_nm = 650
warmup_ms = 2
max_on_s = 900
enable = "high"
interlock = "unused"

[[laser]]
channel = {tube_ch}
name = "light-tube"
role = "tube"
wavelength_nm = 550
warmup_ms = 50
max_on_s = 900
enable = "high"
interlock = "unused"

[[laser]]
channel = {back_ch}
name = "backlight"
role = "backlight"
wavelength_nm = 550
warmup_ms = 20
max_on_s = 900
enable = "high"
interlock = "unused"

[[camera]]
camera = 0
name = "overhead"
pulse_us = 4000
polarity = "high"
exposure_input = "high"
min_interval_us = 5000
{source}

[plan]
pass_mm = [{p0}, {p1}]
step_mm = {step_mm}
exposures_us = [4000]
settle_ms = 5
passes = ["board", "light-box", "reflectance", "reflectance+15", "reflectance-15", "stripe", "backlit"]

# The fit's geometry; the camera's intrinsics come from camera.toml (`lightrig calibrate`).
[plan.fit]
light = {{ diameter_mm = {ld}, length_mm = {ll}, height_mm = {lh}, offset_mm = {lo} }}
stripe = {{ offset_mm = {so}, angle_deg = {sa} }}
board = {{ cols = {bc}, rows = {br}, square_mm = {bs}, origin_mm = [{bx}, {by}] }}
diffuse_strip = {{ x_mm = [{dx0}, {dx1}], y_mm = [{dy0}, {dy1}], albedo = {da} }}
specular_strip = {{ x_mm = [{sx0}, {sx1}], y_mm = [{sy0}, {sy1}], albedo = {sa2} }}
"#,
        axis = spec.gantry_axis,
        stripe_ch = spec.stripe_channel,
        tube_ch = spec.tube_channel,
        back_ch = spec.backlight_channel,
        p0 = pass[0],
        p1 = pass[1],
        ld = l.diameter_mm,
        ll = l.length_mm,
        lh = l.height_mm,
        lo = l.offset_mm,
        so = s.offset_mm,
        sa = s.angle_deg,
        bc = b.cols,
        br = b.rows,
        bs = b.square_mm,
        bx = b.origin_mm[0],
        by = b.origin_mm[1],
        dx0 = d.x_mm[0],
        dx1 = d.x_mm[1],
        dy0 = d.y_mm[0],
        dy1 = d.y_mm[1],
        da = d.diffuse,
        sx0 = sp.x_mm[0],
        sx1 = sp.x_mm[1],
        sy0 = sp.y_mm[0],
        sy1 = sp.y_mm[1],
        sa2 = sp.specular,
    )
}

/// The demo's camera response file (beside `rig.toml`).
pub const RESPONSE_FILE: &str = "camera-response.json";

/// Recovers the virtual camera's response as a lab would: an exposure series of a still scene
/// (the tube over the sample's specular side, 0.125–32 ms a stop apart) written as the camera
/// writes frames into `out/response-series/`, then `lightrig hdr calibrate` (Debevec) into
/// `out/camera-response.json`. Returns the images in the series.
fn calibrate_response(scene: &LlsScene, sensor: &Sensor, out: &Path) -> Result<usize, CliError> {
    use crate::cmd::hdr::{calibrate, Exposure, Method};
    use lightrig_imaging::io::{write_png, BitDepth};
    let dir = out.join("response-series");
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let s = &scene.spec;
    let gantry = (s.sample_x[0] + s.sample_x[1]) / 2.0 - 20.0;
    let mut exposures = Vec::new();
    for k in 0..9 {
        let t = 0.000125 * f64::from(1u32 << k);
        let state = lightrig_sim::camera::RigState {
            pass: Some("reflectance".into()),
            axes: vec![gantry; usize::from(s.gantry_axis) + 1],
            lasers: 1 << s.tube_channel,
            exposure_s: t,
            ..Default::default()
        };
        let img = lightrig_sim::camera::render_exposure(scene, sensor, &[(1.0, state)], 1_000_000 + k as u64);
        let path = dir.join(format!("exposure_{k:02}.png"));
        write_png(&path, &img, BitDepth::Sixteen).map_err(failure)?;
        exposures.push(Exposure { path, seconds: t as f32 });
    }
    calibrate(&exposures, Method::Debevec, &out.join(RESPONSE_FILE))
        .map_err(|e| crate::error::err(crate::error::FAILURE, e))?;
    Ok(exposures.len())
}

fn write_truth(scene: &LlsScene, dir: &Path) -> Result<(), CliError> {
    write_scene_json(dir, &scene.spec)?;
    let (w, h) = (scene.spec.camera.width, scene.spec.camera.height);
    let layer = |name: &str, ch: &[&str], f: &dyn Fn(usize) -> Vec<f32>| {
        Layer::linear(name, ch, w, h, (0..scene.truth.len()).flat_map(f).collect())
    };
    let t = &scene.truth;
    let layers = vec![
        layer("diffuse", &["R", "G", "B"], &|i| t[i].material.diffuse.map(|v| v as f32).to_vec()),
        layer("specular", &["R", "G", "B"], &|i| t[i].material.specular.map(|v| v as f32).to_vec()),
        layer("roughness", &["Y"], &|i| vec![t[i].material.alpha as f32]),
        layer("height", &["Y"], &|i| vec![t[i].point[2] as f32]),
        layer("normal", &["X", "Y", "Z"], &|i| t[i].normal.map(|v| v as f32).to_vec()),
        layer("translucency", &["Y"], &|i| vec![t[i].translucency as f32]),
        layer("region", &["Y"], &|i| vec![t[i].region as u8 as f32]),
    ];
    let p = dir.join("truth.exr");
    write_exr_layers(&p, &layers, ExrPrecision::Float).map_err(failure)
}

/// Writes the virtual camera's intrinsics as a calibration file: on a real rig this file comes
/// from `lightrig calibrate`.
fn write_calibration(spec: &LlsSceneSpec, path: &Path) -> Result<(), CliError> {
    let (k, _) = spec.camera.model();
    let file = lightrig_imaging::calib_file::CalibrationFile {
        tool: format!("lightrig {} demo (the virtual camera's model)", env!("CARGO_PKG_VERSION")),
        image_size: (spec.camera.width, spec.camera.height),
        intrinsics: k,
        board: lightrig_imaging::calib_file::BoardSpec {
            cols: spec.board.cols,
            rows: spec.board.rows,
            square: spec.board.square_mm,
            unit: "mm".into(),
        },
        rms: 0.0,
        views: Vec::new(),
        skipped: Vec::new(),
        reference: None,
    };
    lightrig_imaging::calib_file::write(path, &file).map_err(failure)
}

/// Compares the maps with the scene's truth.
pub fn lls_accuracy(scene: &LlsScene, m: &LlsMaps, step_mm: f64) -> LlsAccuracy {
    let (mut d, mut s, mut r, mut n, mut hgt, mut tr) = (vec![], vec![], vec![], vec![], vec![], vec![]);
    let (mut ng, mut np, mut ns, mut nb) = (vec![], vec![], vec![], vec![]);
    for (i, t) in scene.truth.iter().enumerate() {
        if t.region != Region::Sample || !m.fitted[i] {
            continue;
        }
        let f = &m.fit[i];
        for c in 0..3 {
            d.push((f.diffuse[c] - t.material.diffuse[c]).abs());
            s.push((f.specular[c] / t.material.specular[c] - 1.0).abs());
        }
        r.push((f.alpha / t.material.alpha - 1.0).abs());
        for (normals, errs) in [
            (&m.normals, &mut n),
            (&m.geometric_normals, &mut ng),
            (&m.photometric_normals, &mut np),
            (&m.split_normals, &mut ns),
            (&m.gloss_normals, &mut nb),
        ] {
            if let Some(nn) = normals[i] {
                errs.push(angle(nn, t.normal).to_degrees());
            }
        }
        if let Some(p) = m.points[i] {
            hgt.push((p[2] - t.point[2]).abs());
        }
        if m.translucency[i].is_finite() {
            tr.push((f64::from(m.translucency[i]) - t.translucency).abs());
        }
    }
    LlsAccuracy {
        pixels: r.len(),
        diffuse_abs: median(d),
        specular_rel: median(s),
        roughness_rel: median(r),
        normal_deg: median(n),
        geometric_normal_deg: median(ng),
        photometric_normal_deg: median(np),
        split_normal_deg: median(ns),
        gloss_normal_deg: median(nb),
        height_mm: median(hgt),
        translucency_abs: median(tr),
        step_mm,
    }
}

/// Roughness error per material of the scene: `(α*, pixels, median |α/α* − 1|)`.
pub fn roughness_by_material(scene: &LlsScene, m: &LlsMaps) -> Vec<(f64, usize, f64)> {
    scene
        .spec
        .tiles
        .iter()
        .map(|tile| {
            let errs: Vec<f64> = scene
                .truth
                .iter()
                .enumerate()
                .filter(|(i, t)| t.region == Region::Sample && m.fitted[*i] && t.material.alpha == tile.alpha)
                .map(|(i, t)| (m.fit[i].alpha / t.material.alpha - 1.0).abs())
                .collect();
            (tile.alpha, errs.len(), median(errs))
        })
        .collect()
}

/// One material of the scene under the two models fitted to the same traces (medians).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelRow {
    /// The true Ward α (the material's key).
    pub alpha: f64,
    pub pixels: usize,
    pub ward_residual: f64,
    pub ggx_residual: f64,
    pub ggx_alpha: f64,
}

/// [`ModelRow`] per material of the scene; `None` without a GGX fit.
pub fn models_by_material(scene: &LlsScene, m: &LlsMaps) -> Option<Vec<ModelRow>> {
    let ggx = m.ggx.as_ref()?;
    let rows = scene
        .spec
        .tiles
        .iter()
        .map(|tile| {
            let px: Vec<usize> = (0..scene.truth.len())
                .filter(|&i| {
                    let t = &scene.truth[i];
                    t.region == Region::Sample && m.fitted[i] && t.material.alpha == tile.alpha
                })
                .collect();
            let of = |f: &dyn Fn(usize) -> f64| median(px.iter().map(|&i| f(i)).collect());
            ModelRow {
                alpha: tile.alpha,
                pixels: px.len(),
                ward_residual: of(&|i| m.fit[i].residual),
                ggx_residual: of(&|i| ggx[i].residual),
                ggx_alpha: of(&|i| ggx[i].alpha),
            }
        })
        .collect();
    Some(rows)
}

/// The fit's images under the check light ([`export::check_light`]) against the true sample's:
/// over the fitted sample pixels, the median and 95th percentile of the relative error of the
/// pixel's RGB sum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelitError {
    pub pixels: usize,
    pub median: f64,
    pub p95: f64,
}

/// [`RelitError`] of `image` (interleaved RGB) against `truth`.
pub fn relit_error(scene: &LlsScene, m: &LlsMaps, image: &[f32], truth: &[[f64; 3]]) -> RelitError {
    let mut e: Vec<f64> = (0..truth.len())
        .filter(|&i| scene.truth[i].region == Region::Sample && m.fitted[i])
        .filter_map(|i| {
            let want: f64 = truth[i].iter().sum();
            let got: f64 = (0..3).map(|c| f64::from(image[i * 3 + c])).sum();
            (want > 0.0).then(|| (got / want - 1.0).abs())
        })
        .collect();
    e.sort_by(f64::total_cmp);
    let at = |q: f64| e.get(((e.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(f64::NAN);
    RelitError { pixels: e.len(), median: at(0.5), p95: at(0.95) }
}

/// What [`relight_check`] found and wrote.
struct RelightCheck {
    ward: Option<RelitError>,
    ggx: Option<RelitError>,
    png: Option<PathBuf>,
}

/// Writes `truth/point-light.exr` (the true sample under the check light) and `fit/relight.png`
/// (truth | GGX fit | ten times the absolute error, one exposure for all three); returns the
/// Ward and GGX errors.
fn relight_check(scene: &LlsScene, m: &LlsMaps, out: &Path) -> Result<RelightCheck, CliError> {
    let light = export::check_light(m);
    let truth = scene.point_lit(light.position, light.intensity);
    let (w, h) = (m.width, m.height);
    let flat: Vec<f32> = truth.iter().flat_map(|v| v.map(|x| x as f32)).collect();
    let p = out.join("truth").join("point-light.exr");
    write_exr_layers(&p, &[Layer::linear("", &["R", "G", "B"], w, h, flat.clone())], ExrPrecision::Float)
        .map_err(failure)?;
    let ward = export::relit(m, export::Model::Ward, &light);
    let ggx = export::relit(m, export::Model::Ggx, &light);
    let err = |img: &Option<Vec<f32>>| img.as_ref().map(|i| relit_error(scene, m, i, &truth));
    let (ew, eg) = (err(&ward), err(&ggx));
    let Some(g) = &ggx else { return Ok(RelightCheck { ward: ew, ggx: eg, png: None }) };
    // One exposure: the truth's 99th percentile to white.
    let mut lum: Vec<f32> = flat.clone();
    lum.sort_by(f32::total_cmp);
    let white = lum[((lum.len() - 1) as f64 * 0.99) as usize].max(1e-12);
    let (wu, hu) = (w as usize, h as usize);
    let mut strip = vec![0f32; wu * hu * 9];
    for y in 0..hu {
        for x in 0..wu {
            let i = y * wu + x;
            for c in 0..3 {
                let (t, f) = (flat[i * 3 + c], g[i * 3 + c]);
                let row = y * 3 * wu;
                strip[(row + x) * 3 + c] = t / white;
                strip[(row + wu + x) * 3 + c] = f / white;
                strip[(row + 2 * wu + x) * 3 + c] = 10.0 * (f - t).abs() / white;
            }
        }
    }
    let img = lightrig_imaging::io::Image {
        width: w * 3,
        height: h,
        channels: 3,
        data: strip.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        encoding: lightrig_imaging::io::Encoding::Linear,
    };
    let png = out.join("fit").join("relight.png");
    lightrig_imaging::io::write_png(&png, &img.to_srgb(), lightrig_imaging::io::BitDepth::Eight)
        .map_err(failure)?;
    Ok(RelightCheck { ward: ew, ggx: eg, png: Some(png) })
}

/// Runs the linear-light-source demo; returns the accuracy and the report's path.
pub fn run_lls(opts: &DemoOptions) -> Result<(LlsAccuracy, PathBuf), CliError> {
    let t0 = Instant::now();
    let (w, h, step) = if opts.quick { (80, 60, 2.0) } else { (128, 96, 1.0) };
    let step = opts.step_mm.unwrap_or(step);
    let out = &opts.out;
    std::fs::create_dir_all(out).map_err(io(out))?;
    let spec = LlsSceneSpec::new(w, h);
    // The pass covers every pixel's diffuse peak (tube overhead), its mirror position (about
    // 29 mm towards the camera) and the stripe's crossing, with the lobes' tails.
    let pass = [spec.sample_x[0] - 100.0, spec.sample_x[1] + 60.0];
    let demo = DemoRig::write(out, lls_rig_text_with(&spec, pass, step, opts.camera_gamma))?;
    let calibration = out.join("camera.toml");
    write_calibration(&spec, &calibration)?;
    let scene = LlsScene::new(spec);
    write_truth(&scene, &out.join("truth"))?;
    let sensor = Sensor {
        gain: 30_000.0 / (0.16 * 0.004),
        seed: opts.seed,
        response: lightrig_sim::sensor::Response::of_gamma(opts.camera_gamma.unwrap_or(1.0)),
        ..Sensor::default()
    };
    let series = match opts.camera_gamma {
        Some(_) => Some(calibrate_response(&scene, &sensor, out)?),
        None => None,
    };
    let summary = demo.plan.summary();
    println!(
        "lightrig demo lls: {}×{} px, {} frames ({} mm steps), output in {}",
        w,
        h,
        summary.triggers,
        step,
        out.display()
    );

    // Acquire, exactly as `lightrig acquire` does, on the virtual rig.
    let acq = bar(opts.progress, summary.triggers as u64, "acquire");
    let camera = demo.acquire(out, scene, sensor, opts.real_time, &acq)?;
    acq.finish();
    let t_acq = t0.elapsed();

    // Fit.
    let fitbar = bar(opts.progress, u64::from(w * h), "fit");
    let fb = fitbar.clone();
    let fb_len = fitbar.clone();
    let session_dir = out.join("session");
    let fit_dir = out.join("fit");
    let maps = fit_session(&session_dir, Some(&calibration), &fit_dir, &move |done, total| {
        fb_len.set_length(total);
        fb.set_position(done)
    })
    .map_err(failure)?;
    fitbar.finish();
    let files = write_outputs(&maps, &fit_dir).map_err(failure)?;
    let t_all = t0.elapsed();

    let scene = camera.scene();
    let acc = lls_accuracy(scene, &maps, step);
    let mut r = Report::default();
    r.line("# lightrig demo: linear light source\n");
    r.line(format_args!(
        "Virtual rig, {w}×{h} px, {} frames, gantry step {step} mm, seed {}. Acquisition {:.1} s, total {:.1} s.\n",
        summary.triggers,
        opts.seed,
        t_acq.as_secs_f64(),
        t_all.as_secs_f64()
    ));
    let t = maps.timing;
    r.line(format_args!(
        "Fit: {} frames of the streamed passes read (decoded, brackets merged, written block-major; one \
         thread) in {:.2} s, then fitted in {:.2} s on {} threads, {:.1}× the read ({}). The \
         per-thread comparison is in docs/benchmarks.md.\n",
        t.frames,
        t.read_s,
        t.fit_s,
        t.threads,
        t.fit_s / t.read_s.max(1e-9),
        maps.tables_note
    ));
    match (opts.camera_gamma, series) {
        (Some(g), Some(n)) => r.line(format_args!(
            "Camera: virtual, display gamma {g}; its response recovered by `lightrig hdr calibrate` \
             (Debevec) from {n} exposures ({RESPONSE_FILE}), named in rig.toml, every bracket merged \
             through it.\n"
        )),
        _ => r.line("Camera: virtual, linear.\n"),
    }
    r.line(format_args!(
        "Camera pose from the board image: reprojection RMS {:.3} px.",
        maps.registration_rms
    ));
    r.line(format_args!(
        "Specular calibration strip: fitted ρs {:.4} (known {:.4}).\n",
        maps.specular_strip.0, maps.specular_strip.1
    ));
    let valid = lightrig_host::fit::lls::quality::validity(&maps);
    r.line("The fit's own checks (`fit/quality.json`; per pixel, `maps.exr` layers `valid.*`):\n");
    for line in
        lightrig_host::fit::lls::quality::lines(&lightrig_host::fit::lls::quality::assess(&maps, &valid))
    {
        r.line(format_args!("- {line}"));
    }
    r.line("");
    r.line(format_args!("Fit against the ground truth over {} sample pixels (medians):\n", acc.pixels));
    r.targets(["quantity", "error", "target"], "≤ ", &acc.targets());
    r.line(format_args!("| translucency, median abs | {:.4} | | |", acc.translucency_abs));
    if !maps.diagonal_mounts.is_empty() {
        r.line(format_args!(
            "| normal from the displacement map alone, median deg | {:.4} | | |",
            acc.geometric_normal_deg
        ));
        r.line(format_args!(
            "| normal from the diagonal passes ({}°) alone, median deg | {:.4} | | |",
            maps.diagonal_mounts.iter().map(|m| format!("{m:+}")).collect::<Vec<_>>().join(", "),
            acc.photometric_normal_deg
        ));
        let used = |b| if maps.normal_blend == b { " (used)" } else { "" };
        r.line(format_args!(
            "| normal, frequency split of the two{}, median deg | {:.4} | | |",
            used(NormalBlend::Split),
            acc.split_normal_deg
        ));
        r.line(format_args!(
            "| normal, blended by ρs/α as the paper's §7.2{}, median deg | {:.4} | | |",
            used(NormalBlend::Gloss),
            acc.gloss_normal_deg
        ));
    }
    r.line("\nRoughness by material:\n\n| α | pixels | median rel error |\n|---|---|---|");
    for (a, n, e) in roughness_by_material(scene, &maps) {
        r.line(format_args!("| {a} | {n} | {e:.4} |"));
    }
    if let Some(rows) = models_by_material(scene, &maps) {
        r.line(
            "\nWard and GGX fitted to the same traces with the same normals (`maps.exr` layers `ggx.*`), \
             by material (residual: RMS relative to the trace's):\n\n\
             | true Ward α | pixels | Ward residual | GGX residual | GGX α |\n|---|---|---|---|---|",
        );
        for m in rows {
            r.line(format_args!(
                "| {} | {} | {:.4} | {:.4} | {:.4} |",
                m.alpha, m.pixels, m.ward_residual, m.ggx_residual, m.ggx_alpha
            ));
        }
    }
    let RelightCheck { ward: ew, ggx: eg, png } = relight_check(scene, &maps, out)?;
    let light = lightrig_host::fit::lls::export::check_light(&maps);
    r.line(format_args!(
        "\nUnder a light no frame used (a point at ({:.1}, {:.1}, {:.1}) mm, its highlight mid-sample; \
         `truth/point-light.exr` is the true sample's image, `fit/relit-point.exr` the maps', \
         `fit/mitsuba/scene.xml` the GGX fit for Mitsuba 3, `fit/gltf/sample.gltf` for glTF 2.0), relative error of each sample pixel:\n\n\
         | model | pixels | median | 95th percentile |\n|---|---|---|---|",
        light.position[0], light.position[1], light.position[2]
    ));
    for (name, e) in [("Ward", ew), ("GGX", eg)] {
        if let Some(e) = e {
            r.line(format_args!("| {name} | {} | {:.4} | {:.4} |", e.pixels, e.median, e.p95));
        }
    }
    if png.is_some() {
        r.line("\n![truth, GGX fit, 10 × |error| under the check light](fit/relight.png)\n");
    }
    let figures = super::lls_figures::write_map_figures(scene, &maps, out)?;
    r.line("\n## The maps: truth, fit, error\n");
    r.line(
        "Each figure: the scene's truth, the Ward fit and their error, over the fitted sample pixels \
         (grey: outside the sample or not fitted); a colour bar under each panel drawn through the \
         colour map, its range in the caption.\n",
    );
    for f in &figures {
        r.line(format_args!("![{}]({})\n\n*{}*\n", f.caption, f.file, f.caption));
    }
    r.outputs(&files);
    let report_path = out.join("report.md");
    r.write(&report_path)?;
    println!("{}", r.0);
    println!("report: {}", report_path.display());
    Ok((acc, report_path))
}
