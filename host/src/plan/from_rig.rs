//! Plans from a rig file: reads the method's `[plan]` table (human units) and the rig's
//! peripherals, converts to device units for the connected device's tick rate, and calls the
//! method's planner. Mistakes are reported with the rig file's line.
//!
//! `[plan]` keys per method (see `docs/rigs/README.md` for the full reference):
//! - linear-light-source: `pass_mm = [from, to]`, `step_mm` (1.0), `exposures_us` (the
//!   camera's pulse), `settle_ms` (20), `readout_us` (1000), `passes` (every pass the rig has
//!   lights for: lasers named `light-tube`, `stripe`, `backlight`), `frame_bytes`.
//! - disco: `views` (turntable positions over a full turn), `spot_grid = [nx, ny]` over the
//!   galvo range, `lasers` (names, in order), `registration` (name of a spotlight output),
//!   `exposure_us`, `readout_us`, `frame_bytes`.
//!
//! The other methods are planned through the library API for now (`lightrig_host::plan::*`).

use lightrig_protocol::config::{AxisKind, Xy};
use lightrig_protocol::session::DeviceInfo;

use super::{disco, lls, Plan};
use crate::rigfile::{ticks_from_ms, ticks_from_us, Method, RigError, RigFile};

/// Default bytes per frame for the data-volume estimate: a 5 MP 16-bit frame.
const DEFAULT_FRAME_BYTES: u64 = 2448 * 2048 * 2;

/// The plan for `rig` on the device described by `info`.
pub fn plan(rig: &RigFile, info: &DeviceInfo) -> Result<Plan, RigError> {
    match rig.method {
        Method::LinearLightSource => lls_plan(rig, info),
        Method::Disco => disco_plan(rig, info),
        other => Err(rig.error(
            "rig.method",
            format!(
                "planning `{}` from a rig file is not available yet; build the plan with the library \
                 (lightrig_host::plan) instead",
                other.as_str()
            ),
        )),
    }
}

fn num(rig: &RigFile, key: &str, default: Option<f64>) -> Result<f64, RigError> {
    match rig.plan.get(key) {
        None => default
            .ok_or_else(|| rig.error("plan", format!("`{key}` is required for {}", rig.method.as_str()))),
        Some(v) => v
            .as_float()
            .or_else(|| v.as_integer().map(|i| i as f64))
            .ok_or_else(|| rig.error(&format!("plan.{key}"), "must be a number")),
    }
}

fn nums(rig: &RigFile, key: &str) -> Result<Option<Vec<f64>>, RigError> {
    let Some(v) = rig.plan.get(key) else { return Ok(None) };
    let bad = || rig.error(&format!("plan.{key}"), "must be a list of numbers");
    let arr = v.as_array().ok_or_else(bad)?;
    arr.iter()
        .map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64)).ok_or_else(bad))
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

fn names(rig: &RigFile, key: &str) -> Result<Option<Vec<String>>, RigError> {
    let Some(v) = rig.plan.get(key) else { return Ok(None) };
    let bad = || rig.error(&format!("plan.{key}"), "must be a list of names");
    let arr = v.as_array().ok_or_else(bad)?;
    arr.iter()
        .map(|x| x.as_str().map(str::to_string).ok_or_else(bad))
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

fn us(rig: &RigFile, key: &str, v: f64, hz: u32) -> Result<u32, RigError> {
    ticks_from_us(v, hz).ok_or_else(|| rig.error(&format!("plan.{key}"), format!("{v} µs is out of range")))
}

fn laser_named(rig: &RigFile, key: &str, name: &str) -> Result<u8, RigError> {
    rig.lasers.iter().find(|l| l.name.as_deref() == Some(name)).map(|l| l.channel).ok_or_else(|| {
        let known: Vec<_> = rig.lasers.iter().filter_map(|l| l.name.clone()).collect();
        rig.error(key, format!("no laser named `{name}` (the rig has: {})", known.join(", ")))
    })
}

fn first_camera(rig: &RigFile) -> Result<&crate::rigfile::Camera, RigError> {
    rig.cameras.first().ok_or_else(|| rig.error("camera", "the plan needs a [[camera]]"))
}

fn lls_plan(rig: &RigFile, info: &DeviceInfo) -> Result<Plan, RigError> {
    let hz = info.tick_hz;
    let axis = rig
        .stepper_named("gantry")
        .or_else(|| rig.steppers.iter().find(|s| s.kind == AxisKind::Linear))
        .ok_or_else(|| {
            rig.error("stepper", "a linear-light-source rig needs a linear stepper (named `gantry`)")
        })?;
    let pass =
        nums(rig, "pass_mm")?.ok_or_else(|| rig.error("plan", "`pass_mm = [from, to]` is required"))?;
    let [from, to] = pass[..] else { return Err(rig.error("plan.pass_mm", "must be [from, to] in mm")) };
    let step_mm = num(rig, "step_mm", Some(1.0))?;
    if step_mm <= 0.0 {
        return Err(rig.error("plan.step_mm", "must be positive"));
    }
    let count = ((to - from).abs() / step_mm).floor() as u32 + 1;
    let start = rig.stepper_steps(axis.axis, from)?;
    // The far end must lie within the soft limits too (the error names them).
    rig.stepper_steps(axis.axis, to).map_err(|e| rig.error("plan.pass_mm", e.message))?;
    let second = rig.stepper_steps(axis.axis, from + step_mm.copysign(to - from))?;
    let camera = first_camera(rig)?;
    let exposures: Vec<u32> = match nums(rig, "exposures_us")? {
        Some(v) => v.iter().map(|&e| us(rig, "exposures_us", e, hz)).collect::<Result<_, _>>()?,
        None => vec![us(rig, "camera.pulse_us", camera.pulse_us, hz)?],
    };
    let readout = us(rig, "readout_us", num(rig, "readout_us", Some(1000.0))?, hz)?;
    let min_interval = us(rig, "camera.min_interval_us", camera.min_interval_us, hz)?;
    let longest = exposures.iter().copied().max().unwrap_or(0);
    let settle_ms = num(rig, "settle_ms", Some(20.0))?;
    let settle = ticks_from_ms(settle_ms, hz).ok_or_else(|| rig.error("plan.settle_ms", "out of range"))?;
    let has = |n: &str| rig.lasers.iter().any(|l| l.name.as_deref() == Some(n));
    let passes = match names(rig, "passes")? {
        Some(list) => {
            list.iter()
                .map(|p| match p.as_str() {
                    "reflectance" => Ok(lls::Pass::Reflectance),
                    "stripe" => Ok(lls::Pass::Stripe),
                    "backlit" => Ok(lls::Pass::Backlit),
                    other => Err(rig
                        .error("plan.passes", format!("`{other}`: expected reflectance, stripe or backlit"))),
                })
                .collect::<Result<Vec<_>, _>>()?
        }
        None => [
            ("light-tube", lls::Pass::Reflectance),
            ("stripe", lls::Pass::Stripe),
            ("backlight", lls::Pass::Backlit),
        ]
        .into_iter()
        .filter(|(n, _)| has(n))
        .map(|(_, p)| p)
        .collect(),
    };
    let light = if has("light-tube") { laser_named(rig, "laser", "light-tube")? } else { 0 };
    let stripe = if has("stripe") { laser_named(rig, "laser", "stripe")? } else { 0 };
    let backlight = if has("backlight") { Some(laser_named(rig, "laser", "backlight")?) } else { None };
    let p = lls::LlsParams {
        axis: axis.axis,
        start,
        step: second - start,
        count,
        camera: camera.camera,
        exposures,
        settle,
        frame_gap: longest.saturating_add(readout).max(min_interval),
        light,
        stripe,
        backlight,
        passes,
        timeout: hz.saturating_mul(60),
        frame_bytes: num(rig, "frame_bytes", Some(DEFAULT_FRAME_BYTES as f64))? as u64,
        tick_hz: hz,
    };
    lls::plan(&p).map_err(|e| rig.error("plan", e.0))
}

fn disco_plan(rig: &RigFile, info: &DeviceInfo) -> Result<Plan, RigError> {
    let hz = info.tick_hz;
    let table = rig
        .stepper_named("turntable")
        .or_else(|| rig.steppers.iter().find(|s| s.kind == AxisKind::Rotary))
        .ok_or_else(|| rig.error("stepper", "a DISCO rig needs a rotary stepper (named `turntable`)"))?;
    let views = num(rig, "views", None)? as u32;
    if views == 0 {
        return Err(rig.error("plan.views", "must be at least 1"));
    }
    let view_steps = (0..views)
        .map(|v| rig.stepper_steps(table.axis, 360.0 * f64::from(v) / f64::from(views)))
        .collect::<Result<Vec<_>, _>>()?;
    let galvo = rig.galvos.first().ok_or_else(|| rig.error("galvo", "a DISCO rig needs a [[galvo]]"))?;
    let grid =
        nums(rig, "spot_grid")?.ok_or_else(|| rig.error("plan", "`spot_grid = [nx, ny]` is required"))?;
    let [nx, ny] = grid[..] else { return Err(rig.error("plan.spot_grid", "must be [nx, ny]")) };
    let (nx, ny) = (nx.max(1.0) as u32, ny.max(1.0) as u32);
    let spread = |lo: u16, hi: u16, n: u32, k: u32| -> u16 {
        if n == 1 {
            return ((u32::from(lo) + u32::from(hi)) / 2) as u16;
        }
        (u32::from(lo) + (u32::from(hi) - u32::from(lo)) * k / (n - 1)) as u16
    };
    let mut points = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            points.push(Xy {
                x: spread(galvo.x.min_code, galvo.x.max_code, nx, i),
                y: spread(galvo.y.min_code, galvo.y.max_code, ny, j),
            });
        }
    }
    let lasers = match names(rig, "lasers")? {
        Some(list) => {
            list.iter().map(|n| laser_named(rig, "plan.lasers", n)).collect::<Result<Vec<_>, _>>()?
        }
        None => rig.lasers.iter().map(|l| l.channel).collect(),
    };
    let spotlight = match rig.plan.get("registration").and_then(|v| v.as_str()) {
        Some(n) => Some(laser_named(rig, "plan.registration", n)?),
        None => None,
    };
    let camera = first_camera(rig)?;
    let exposure = us(rig, "exposure_us", num(rig, "exposure_us", Some(camera.pulse_us))?, hz)?;
    let readout = us(rig, "readout_us", num(rig, "readout_us", Some(1000.0))?, hz)?;
    let min_interval = us(rig, "camera.min_interval_us", camera.min_interval_us, hz)?;
    let p = disco::DiscoParams {
        turntable: table.axis,
        views: view_steps,
        lasers,
        galvo: galvo.galvo,
        grid: points,
        camera: camera.camera,
        exposure,
        settle: us(rig, "galvo.settle_us", galvo.settle_us, hz)?,
        frame_gap: exposure.saturating_add(readout).max(min_interval),
        spotlight,
        timeout: hz.saturating_mul(60),
        frame_bytes: num(rig, "frame_bytes", Some(DEFAULT_FRAME_BYTES as f64))? as u64,
        tick_hz: hz,
    };
    disco::plan(&p).map_err(|e| rig.error("plan", e.0))
}
