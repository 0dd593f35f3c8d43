//! `lightrig fit display`: a BRDF display session's frames (the camera's pictures of the screen
//! the reflected beam lands on, through the rig file's `[plan.screen]`) → from a calibration
//! session, each step's spread of facet tilts and so each coil's response `|H(f)|` over the
//! calibration's sweep; from a display session, Ward's lobe fitted to each target's picture
//! (`lightrig_pipelines::display::lobe`): the α it showed and how far its shape is from
//! Ward's. The calibration keeps what each target showed for the next plan (the closed loop).

use std::path::Path;

use lightrig_pipelines::display::calibration::{AxisCalibration, Calibration, FORMAT};
use lightrig_pipelines::display::lobe::{
    fit_ward, pixel_spread, single_sine_roughness, spread, surface_variance, Spread,
};
use lightrig_pipelines::display::mapping::{X_FREQUENCIES, Y_FREQUENCIES};
use lightrig_pipelines::display::{Liquid, Screen};
use serde_json::Value;

use super::{fail, FitError};
use crate::plan::from_rig::{display_coils, display_screen};
use crate::rigfile::RigFile;
use crate::session::Session;

/// One step as the camera saw it.
#[derive(Debug, Clone)]
pub struct Seen {
    /// Step id.
    pub step: u32,
    /// Step name.
    pub name: String,
    /// The step's `meta` (`kind`: `still`, `sine`, `display`; what it showed).
    pub meta: Value,
    /// The mean of the step's captures (the first channel), row-major.
    pub picture: Vec<f32>,
    /// The facet tilts the picture holds ([`spread`]).
    pub spread: Spread,
}

/// A display session's steps as the camera saw them, with the plan's liquid and screen.
pub struct DisplaySession {
    /// The rig file the session was planned from.
    pub rig: RigFile,
    /// The liquid.
    pub liquid: Liquid,
    /// The screen, for the camera's pictures.
    pub screen: Screen,
    /// The pictures' size, pixels.
    pub size: (usize, usize),
    /// Each done step.
    pub steps: Vec<Seen>,
}

/// Reads a BRDF display session: every done step's frames from its pipeline camera.
pub fn read(dir: &Path) -> Result<DisplaySession, FitError> {
    let (s, _) = Session::read(dir).map_err(|e| fail(e.to_string()))?;
    let m = s.manifest();
    let method = m.plan.extra.get("method").and_then(Value::as_str).unwrap_or("");
    if method != "brdf-display" {
        return Err(fail(format!(
            "{}: a `{method}` session; `lightrig fit display` reads BRDF display sessions",
            dir.display()
        )));
    }
    if !s.is_done() {
        return Err(fail(format!("{}: not complete; `lightrig resume` it first", dir.display())));
    }
    let rig = crate::fit::session_rig(&m.rig, dir)?;
    let meta = m.plan.extra.get("meta").cloned().unwrap_or(Value::Null);
    let liquid_name = meta.get("liquid").and_then(Value::as_str).unwrap_or("water");
    let liquid = Liquid::preset(liquid_name)
        .ok_or_else(|| fail(format!("{}: liquid `{liquid_name}` is not a known preset", dir.display())))?;
    let screen_spec = display_screen(&rig).map_err(|e| fail(e.to_string()))?;
    let camera = s.pipeline_camera(None).map_err(fail)?;
    let mut size = None;
    let mut pictures = Vec::new();
    for p in &m.plan.steps {
        let frames = s.camera_frames_of(p.id, camera);
        if frames.is_empty() {
            return Err(fail(format!("{}: step {} ({}) has no frame", dir.display(), p.id, p.name)));
        }
        let mut sum: Vec<f32> = Vec::new();
        for f in &frames {
            let path = dir.join(&f.file);
            let img =
                lightrig_imaging::io::read(&path).map_err(|e| fail(format!("{}: {e}", path.display())))?;
            let wh = (img.width as usize, img.height as usize);
            if *size.get_or_insert(wh) != wh {
                return Err(fail(format!(
                    "{}: {}×{} where the session's other frames are {}×{}",
                    path.display(),
                    wh.0,
                    wh.1,
                    size.unwrap_or(wh).0,
                    size.unwrap_or(wh).1
                )));
            }
            let c = usize::from(img.channels.max(1));
            let px = img.data.iter().step_by(c);
            if sum.is_empty() {
                sum = px.map(|v| v / frames.len() as f32).collect();
            } else {
                sum.iter_mut().zip(px).for_each(|(a, v)| *a += v / frames.len() as f32);
            }
        }
        let meta = p.extra.get("meta").cloned().unwrap_or(Value::Null);
        pictures.push((p.id, p.name.clone(), meta, sum));
    }
    let size = size.unwrap_or((0, 0));
    let screen = screen_spec.screen(size.0 as u32, size.1 as u32);
    let steps = pictures
        .into_iter()
        .map(|(step, name, meta, picture)| {
            let spread = spread(&picture, size.0, size.1, &screen);
            Seen { step, name, meta, picture, spread }
        })
        .collect();
    Ok(DisplaySession { rig, liquid, screen, size, steps })
}

fn kind(s: &Seen) -> &str {
    s.meta.get("kind").and_then(Value::as_str).unwrap_or("")
}

/// A calibration session (`[plan.calibrate]`) → the display's calibration: the still step's
/// spread is the beam's own; step `i`'s spread on each axis is one sine's, `ρ²/2` in facet
/// tilt, so `|H(fᵢ)| = ρ / (k(fᵢ)·drive)` at the sweep's frequencies; the display's partials
/// (`mapping::X_FREQUENCIES`, `Y_FREQUENCIES`) are driven through `|H|` interpolated.
pub fn calibration(d: &DisplaySession) -> Result<Calibration, FitError> {
    let still = d
        .steps
        .iter()
        .find(|s| kind(s) == "still")
        .ok_or_else(|| fail("the session has no `still` step: it is not a calibration session"))?;
    let coils = display_coils(&d.rig).map_err(|e| fail(e.to_string()))?;
    let mut axes = coils.map(|c| AxisCalibration {
        coil: c.name.clone().unwrap_or_else(|| format!("channel {}", c.channel)),
        channel: c.channel,
        max_drive: c.max_amplitude,
        frequencies_hz: Vec::new(),
        response_m: Vec::new(),
        partials_hz: Vec::new(),
        seen: Vec::new(),
    });
    axes[0].partials_hz = X_FREQUENCIES.to_vec();
    axes[1].partials_hz = Y_FREQUENCIES.to_vec();
    let mut drive = 0.0;
    for s in d.steps.iter().filter(|s| kind(s) == "sine") {
        let f = s.meta.get("frequencies_hz").and_then(Value::as_array);
        let dr = s.meta.get("drive").and_then(Value::as_f64);
        let (Some(f), Some(dr)) = (f, dr) else {
            return Err(fail(format!(
                "step {} ({}): its meta lacks frequencies_hz or drive",
                s.step, s.name
            )));
        };
        drive = dr;
        let var = surface_variance(&s.spread, &still.spread);
        for (k, axis) in axes.iter_mut().enumerate() {
            let fk = f
                .get(k)
                .and_then(Value::as_f64)
                .ok_or_else(|| fail(format!("step {}: frequency {k}", s.step)))?;
            let rho = single_sine_roughness(var[k]);
            axis.frequencies_hz.push(fk);
            axis.response_m.push(rho / (d.liquid.wave_number(fk) * dr));
        }
    }
    if axes[0].frequencies_hz.is_empty() {
        return Err(fail("the calibration session has no `sine` step"));
    }
    Ok(Calibration {
        format: FORMAT,
        liquid: d.liquid.name.to_string(),
        drive,
        screen: d.screen,
        beam_var: still.spread.var,
        beam_px: pixel_spread(&still.picture, d.size.0, d.size.1).var.map(|v| v.max(0.0).sqrt()),
        axes,
    })
}

/// What one target showed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shown {
    /// Step id.
    pub step: u32,
    /// The α the plan aimed at, x and y.
    pub target: [f64; 2],
    /// The α it asked of the solver (the closed loop's correction included).
    pub asked: [f64; 2],
    /// The α the camera saw: Ward's lobe fitted to the step's picture.
    pub shown: [f64; 2],
    /// How far the displayed bell is from Ward's shape (`WardFit::shape_error`).
    pub shape_error: f64,
}

impl Shown {
    /// The relative error of each axis.
    pub fn error(&self) -> [f64; 2] {
        [self.shown[0] / self.target[0] - 1.0, self.shown[1] / self.target[1] - 1.0]
    }
}

/// A display session (`alphas`) → what each target showed: Ward's lobe fitted to its picture,
/// blurred by the still beam's spot (from `cal`). `cal` learns each `asked → shown` pair for
/// the next plan.
pub fn measure(d: &DisplaySession, cal: &mut Calibration) -> Result<Vec<Shown>, FitError> {
    let mut out = Vec::new();
    for s in d.steps.iter().filter(|s| kind(s) == "display") {
        let pair = |key: &str| -> Result<[f64; 2], FitError> {
            let v = s.meta.get(key).and_then(Value::as_array);
            let g = |i: usize| v.and_then(|v| v.get(i)).and_then(Value::as_f64);
            match (g(0), g(1)) {
                (Some(x), Some(y)) => Ok([x, y]),
                _ => Err(fail(format!("step {} ({}): its meta lacks `{key}`", s.step, s.name))),
            }
        };
        let (target, asked) = (pair("alpha")?, pair("asked")?);
        let fit = fit_ward(&s.picture, d.size.0, d.size.1, &d.screen, cal.beam_px);
        let shown = fit.alpha;
        for k in 0..2 {
            cal.axes[k].saw(asked[k], shown[k]);
        }
        out.push(Shown { step: s.step, target, asked, shown, shape_error: fit.shape_error });
    }
    if out.is_empty() {
        return Err(fail("the session shows no α target (`alphas` in the rig file's [plan])"));
    }
    Ok(out)
}

/// What `lightrig fit display` made of a session.
pub enum Fitted {
    /// A calibration session: the calibration.
    Calibration(Calibration),
    /// A display session: what each target showed, and the calibration that learnt it.
    Shown(Vec<Shown>, Calibration),
}

/// The file name of the calibration `lightrig fit display` writes.
pub const CALIBRATION_FILE: &str = "display-calibration.json";

/// Fits a display session: a calibration session gives the calibration; a display session
/// needs the calibration its plan was solved with (`calibration`) and gives what each target
/// showed. Writes `out/display-calibration.json` (for a display session, the given one with
/// the new `asked → shown` pairs: plan from it again to close the loop) and, for a display
/// session, `out/shown.json`. Returns the result and the files written.
pub fn fit_session(
    dir: &Path,
    calibration: Option<&Path>,
    out: &Path,
) -> Result<(Fitted, Vec<std::path::PathBuf>), FitError> {
    let d = read(dir)?;
    let is_calibration = d.steps.iter().any(|s| kind(s) == "still");
    std::fs::create_dir_all(out).map_err(|e| fail(format!("{}: {e}", out.display())))?;
    let write = |name: &str, json: String| -> Result<std::path::PathBuf, FitError> {
        let p = out.join(name);
        std::fs::write(&p, json + "\n").map_err(|e| fail(format!("{}: {e}", p.display())))?;
        Ok(p)
    };
    if is_calibration {
        let cal = self::calibration(&d)?;
        let p = write(CALIBRATION_FILE, serde_json::to_string_pretty(&cal).expect("serializes"))?;
        return Ok((Fitted::Calibration(cal), vec![p]));
    }
    let path = calibration.ok_or_else(|| {
        fail(format!(
            "{}: a display session is measured against the calibration its plan was solved with: \
             give it with --calibration FILE",
            dir.display()
        ))
    })?;
    let text = std::fs::read_to_string(path).map_err(|e| fail(format!("{}: {e}", path.display())))?;
    let mut cal = Calibration::from_json(&text).map_err(|e| fail(format!("{}: {e}", path.display())))?;
    let shown = measure(&d, &mut cal)?;
    let rows: Vec<Value> = shown
        .iter()
        .map(|s| {
            serde_json::json!({
                "step": s.step,
                "alpha": s.target,
                "asked": s.asked,
                "shown": s.shown,
                "shape_error": s.shape_error,
            })
        })
        .collect();
    let a = write("shown.json", serde_json::to_string_pretty(&rows).expect("serializes"))?;
    let b = write(CALIBRATION_FILE, serde_json::to_string_pretty(&cal).expect("serializes"))?;
    Ok((Fitted::Shown(shown, cal), vec![a, b]))
}
