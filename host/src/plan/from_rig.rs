//! Plans from a rig file: reads the method's `[plan]` table (human units) and the rig's
//! peripherals, converts to device units for the connected device's tick rate, and calls the
//! method's planner. Mistakes are reported with the rig file's line.
//!
//! `[plan]` keys of every method: `lost_frame_retries` (2: how often a step that lost frames is
//! acquired again at once, [`Plan::lost_retries`]).
//!
//! `[plan]` keys per method (see `docs/rigs/README.md` for the full reference):
//! - linear-light-source: `pass_mm = [from, to]`, `step_mm` (1.0), `exposures_us` (the
//!   camera's pulse), `settle_ms` (20), `readout_us` (1000), `passes` (every pass the rig has
//!   lights for: the lasers whose `role` is `tube`, `stripe`, `backlight`), `frame_bytes`.
//! - disco: `views` (turntable positions over a full turn), `spot_grid = [nx, ny]` over
//!   `spot_window_deg = [[x0, x1], [y0, y1]]` (optical degrees from the zero codes; the galvo's
//!   range without it), `lasers` (names, in order), `frames_per_spot` (1), `camera_positions`
//!   (see [`crate::disco`]), `white_balance` (default: whether `[plan.fit] white_target` is
//!   given), `registration` (name of a spotlight output), `exposure_us`, `readout_us`,
//!   `frame_bytes`.
//!
//! - fluorescent-immersion: `views` (turntable positions over a full turn), `sheet_positions`
//!   (spread over `sweep_codes = [first, last]`, by default the galvo's X range; Y at its zero
//!   code), `laser` (name; the first laser),
//!   `exposure_us`, `readout_us`, `calibration` (true), `frame_bytes`, `calibration_targets`
//!   (the target's positions, `[{ z_mm = … }, …]`, front to back: a board frame and a sweep at each).
//! - brdf-display: `patterns.NAME = { frequencies_hz = […], amplitudes = […] }` (amplitudes as
//!   fractions of full scale, the same on every voice coil), `captures` (3), `ramp_ms` (200),
//!   `settle_ms` (2000), `exposure_us`, `readout_us`, `frame_bytes`.
//!
//! - bispectral: `gonio.sample_angles` and `gonio.light_angles` (degrees, on the rotary axes
//!   named `sample` and `light-arm`), `tunable_filter.range_nm = [from, to]` and `step_nm` (the
//!   camera's emission grid), excitation from the filter wheel's `led-NNN` slots and, with
//!   `tunable_filter.excitation_range_nm`, the light filter through the `white` slot on the same
//!   grid; every pair with excitation ≤ emission (full mode), or `pairs = [[ex, em], …]` (sparse
//!   mode); with `sample = "spectralon"` (the spectral calibration) each excitation's pairs
//!   within two steps of its diagonal, either side;
//!   `exposures_us` (the camera's pulse), `readout_us`, `frame_bytes`. The host sets the tunable
//!   filter from each step's `meta.host` before running it.

use lightrig_protocol::config::{AxisKind, Xy};
use lightrig_protocol::session::DeviceInfo;

use super::{disco, display, firs, lls, Plan, LOST_RETRIES};
use crate::rigfile::{ticks_from_ms, ticks_from_us, Camera, LaserRole, Method, RigError, RigFile};

/// Default bytes per frame for the data-volume estimate: a 5 MP 16-bit frame.
const DEFAULT_FRAME_BYTES: u64 = 2448 * 2048 * 2;

/// The plan for `rig` on the device described by `info`.
pub fn plan(rig: &RigFile, info: &DeviceInfo) -> Result<Plan, RigError> {
    plan_at(rig, info.tick_hz)
}

/// The tick rate [`check`] plans at before a device says its own: the boards' and the virtual
/// rig's 1 MHz.
pub const NOMINAL_TICK_HZ: u32 = 1_000_000;

/// Everything about `rig`'s plan that needs no device, checked before one is connected (and
/// homed): its keys ([`check_keys`]) and the plan made at [`NOMINAL_TICK_HZ`] (every value, its
/// range, the positions against the steppers' limits). Each error names the key the rig file
/// has, with its line. The fit's `[plan.fit]` is [`crate::fit::check_rig`]'s.
pub fn check(rig: &RigFile) -> Result<Plan, RigError> {
    check_keys(rig)?;
    plan_at(rig, NOMINAL_TICK_HZ)
}

/// The plan for `rig` on a device counting `hz` ticks per second (the planners need nothing
/// else of it).
fn plan_at(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
    let mut plan = match rig.method {
        Method::LinearLightSource => lls_plan(rig, hz),
        Method::Disco => disco_plan(rig, hz),
        Method::FluorescentImmersion => immersion_plan(rig, hz),
        Method::BrdfDisplay => display_plan(rig, hz),
        Method::Bispectral => bispectral_plan(rig, hz),
    }?;
    plan.lost_retries = lost_retries(rig)?;
    Ok(plan)
}

/// `[plan]` keys every planner reads.
const COMMON_KEYS: &[&str] =
    &["cameras", "frame_bytes", "lost_frame_retries", "readout_us", "tunable_filter"];

/// `[plan]` keys the planner and fit of `method` read, besides [`COMMON_KEYS`].
fn method_keys(method: Method) -> &'static [&'static str] {
    match method {
        Method::LinearLightSource => &["exposures_us", "fit", "pass_mm", "passes", "settle_ms", "step_mm"],
        Method::Disco => &[
            "camera_positions",
            "exposure_us",
            "fit",
            "frames_per_spot",
            "lasers",
            "registration",
            "spot_grid",
            "spot_window_deg",
            "views",
            "white_balance",
        ],
        // `camera_filter` and `immersion_liquid`: the lab's notes of what the tank holds, kept
        // with the session (the shipped rig file documents them so).
        Method::FluorescentImmersion => &[
            "calibration",
            "calibration_targets",
            "camera_filter",
            "exposure_us",
            "fit",
            "immersion_liquid",
            "laser",
            "sheet_positions",
            "sweep_codes",
            "views",
        ],
        Method::BrdfDisplay => &[
            "alphas",
            "calibrate",
            "calibration",
            "captures",
            "coils",
            "exposure_us",
            "liquid",
            "max_slope_deg",
            "patterns",
            "ramp_ms",
            "screen",
            "settle_ms",
        ],
        Method::Bispectral => &["exposures_us", "fit", "gonio", "pairs", "sample", "steer"],
    }
}

/// Keys of the `[plan]` sub-tables read key by key (the fits' `[plan.fit]` tables that are
/// read whole are checked by the fit, with every field named): `(method or all, table, keys)`.
const TABLE_KEYS: &[(Option<Method>, &str, &[&str])] = &[
    (
        None,
        "tunable_filter",
        &[
            "baud",
            "camera_port",
            "camera_range_nm",
            "decimals",
            "error",
            "excitation_range_nm",
            "light_port",
            "light_range_nm",
            // The filter's make and model: a note for the session.
            "model",
            "ok",
            "range_nm",
            "settle_ms",
            "step_nm",
            "timeout_ms",
            "tune",
        ],
    ),
    (Some(Method::Bispectral), "gonio", &["light_angles", "sample_angles"]),
    (Some(Method::Bispectral), "steer", &["dense_angles", "select"]),
    (
        Some(Method::Bispectral),
        "fit",
        &["bins", "detection", "pca_angles", "select", "spectralon", "specular_deg"],
    ),
    (Some(Method::BrdfDisplay), "calibrate", &["drive"]),
    (
        Some(Method::BrdfDisplay),
        "screen",
        &["centre_px", "distance_mm", "incidence_deg", "pitch_mm", "tilt_deg"],
    ),
];

/// Refuses a key of `[plan]` (or of a sub-table read key by key) that nothing reads, with the
/// closest valid key: a misspelt key is otherwise silently ignored and the run goes on with
/// its default. Needs no device: `acquire` checks before connecting.
pub fn check_keys(rig: &RigFile) -> Result<(), RigError> {
    let mut valid: Vec<&str> = COMMON_KEYS.iter().chain(method_keys(rig.method)).copied().collect();
    valid.sort_unstable();
    for key in rig.plan.keys() {
        if !valid.contains(&key.as_str()) {
            return Err(rig.unknown_key(&format!("plan.{key}"), &valid));
        }
    }
    for (method, table, keys) in TABLE_KEYS {
        if method.is_some_and(|m| m != rig.method) {
            continue;
        }
        let Some(t) = rig.plan.get(*table).and_then(|v| v.as_table()) else { continue };
        for key in t.keys() {
            if !keys.contains(&key.as_str()) {
                return Err(rig.unknown_key(&format!("plan.{table}.{key}"), keys));
            }
        }
    }
    Ok(())
}

/// `[plan] lost_frame_retries`: a whole number of retries, [`LOST_RETRIES`] without it.
fn lost_retries(rig: &RigFile) -> Result<u32, RigError> {
    let n = num(rig, "lost_frame_retries", Some(f64::from(LOST_RETRIES)))?;
    if n.fract() != 0.0 || !(0.0..=100.0).contains(&n) {
        return Err(rig.error(
            "plan.lost_frame_retries",
            format!("{n} is not a whole number from 0 to 100 (how often a step that lost frames is acquired again)"),
        ));
    }
    Ok(n as u32)
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
    ticks_from_us(v, hz).ok_or_else(|| {
        let max = f64::from(u32::MAX) / f64::from(hz) * 1e6;
        rig.error(
            &format!("plan.{key}"),
            format!("{v} µs is out of range: give a duration from 0 to {max:.0} µs (32-bit device ticks at {hz} Hz)"),
        )
    })
}

fn laser_named(rig: &RigFile, key: &str, name: &str) -> Result<u8, RigError> {
    rig.lasers.iter().find(|l| l.name.as_deref() == Some(name)).map(|l| l.channel).ok_or_else(|| {
        let known: Vec<_> = rig.lasers.iter().filter_map(|l| l.name.clone()).collect();
        rig.error(key, format!("no laser named `{name}` (the rig has: {})", known.join(", ")))
    })
}

/// Trigger-to-trigger time: the exposure plus `readout_us` (1000), and at least every fired
/// camera's `min_interval_us`.
fn frame_gap(rig: &RigFile, cameras: &[&Camera], exposure: u32, hz: u32) -> Result<u32, RigError> {
    let readout = us(rig, "readout_us", num(rig, "readout_us", Some(1000.0))?, hz)?;
    Ok(exposure.saturating_add(readout).max(min_interval(rig, cameras, hz)?))
}

/// The longest `min_interval_us` of the fired cameras, ticks.
fn min_interval(rig: &RigFile, cameras: &[&Camera], hz: u32) -> Result<u32, RigError> {
    cameras.iter().try_fold(0, |m, c| Ok(m.max(us(rig, "camera.min_interval_us", c.min_interval_us, hz)?)))
}

/// The longest trigger pulse of the fired cameras, ticks: the default exposure.
fn pulse(rig: &RigFile, cameras: &[&Camera], hz: u32) -> Result<u32, RigError> {
    cameras.iter().try_fold(0, |m, c| Ok(m.max(us(rig, "camera.pulse_us", c.pulse_us, hz)?)))
}

/// `exposure_us` from `[plan]`, or the longest pulse of the fired cameras.
fn exposure(rig: &RigFile, cameras: &[&Camera], hz: u32) -> Result<u32, RigError> {
    match rig.plan.get("exposure_us") {
        Some(_) => us(rig, "exposure_us", num(rig, "exposure_us", None)?, hz),
        None => pulse(rig, cameras, hz),
    }
}

fn frame_bytes(rig: &RigFile) -> Result<u64, RigError> {
    Ok(num(rig, "frame_bytes", Some(DEFAULT_FRAME_BYTES as f64))? as u64)
}

/// The cameras the plan fires, all together at every trigger point: `[plan] cameras` (names
/// or device indices, in that order), or every `[[camera]]` of the rig.
fn plan_cameras(rig: &RigFile) -> Result<Vec<&Camera>, RigError> {
    if rig.cameras.is_empty() {
        return Err(rig.error("camera", "the plan needs a [[camera]]"));
    }
    let Some(v) = rig.plan.get("cameras") else { return Ok(rig.cameras.iter().collect()) };
    let bad = || rig.error("plan.cameras", "must be a list of camera names or device indices");
    let list = v.as_array().ok_or_else(bad)?;
    if list.is_empty() {
        return Err(rig.error("plan.cameras", "is empty: name at least one camera to trigger"));
    }
    let mut out: Vec<&Camera> = Vec::new();
    for x in list {
        let shown = match (x.as_str(), x.as_integer()) {
            (Some(n), _) => format!("`{n}`"),
            (None, Some(i)) => i.to_string(),
            _ => return Err(bad()),
        };
        let found = match (x.as_str(), x.as_integer()) {
            (Some(name), _) => rig.cameras.iter().find(|c| c.name.as_deref() == Some(name)),
            (None, Some(i)) => rig.cameras.iter().find(|c| i64::from(c.camera) == i),
            _ => return Err(bad()),
        };
        let camera = found.ok_or_else(|| {
            let known: Vec<String> = rig
                .cameras
                .iter()
                .map(|c| c.name.clone().map_or(c.camera.to_string(), |n| format!("{n} ({})", c.camera)))
                .collect();
            rig.error("plan.cameras", format!("no camera {shown} (the rig has: {})", known.join(", ")))
        })?;
        if out.iter().any(|c| c.camera == camera.camera) {
            return Err(rig.error("plan.cameras", format!("camera {shown} is listed twice")));
        }
        out.push(camera);
    }
    Ok(out)
}

fn indices(cameras: &[&Camera]) -> Vec<u8> {
    cameras.iter().map(|c| c.camera).collect()
}

fn lls_plan(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
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
    // Both ends within the gantry's soft limits: the error names `pass_mm`, the key to fix,
    // and the limits.
    let on_gantry = |mm: f64| {
        rig.stepper_steps(axis.axis, mm).map_err(|e| {
            rig.error("plan.pass_mm", format!("{} (the gantry's [[stepper]] limits)", e.message))
        })
    };
    let start = on_gantry(from)?;
    on_gantry(to)?;
    let second = on_gantry(from + step_mm.copysign(to - from))?;
    let cameras = plan_cameras(rig)?;
    let exposures: Vec<u32> = match nums(rig, "exposures_us")? {
        Some(v) => v.iter().map(|&e| us(rig, "exposures_us", e, hz)).collect::<Result<_, _>>()?,
        None => vec![pulse(rig, &cameras, hz)?],
    };
    let longest = exposures.iter().copied().max().unwrap_or(0);
    let settle_ms = num(rig, "settle_ms", Some(20.0))?;
    let settle = ticks_from_ms(settle_ms, hz).ok_or_else(|| rig.error("plan.settle_ms", "out of range"))?;
    let with_role = |r: LaserRole| rig.laser_with_role(r).map(|l| l.channel);
    let passes = match names(rig, "passes")? {
        Some(list) => list
            .iter()
            .map(|p| {
                lls::Pass::parse(p).ok_or_else(|| {
                    rig.error(
                        "plan.passes",
                        format!(
                            "`{p}`: expected board, light-box, reflectance (or reflectance+15, \
                             reflectance-15: the mount turned by whole degrees, at most 45), stripe or backlit"
                        ),
                    )
                })
            })
            .collect::<Result<Vec<_>, _>>()?,
        None => [
            (LaserRole::Tube, lls::Pass::REFLECTANCE),
            (LaserRole::Stripe, lls::Pass::Stripe),
            (LaserRole::Backlight, lls::Pass::Backlit),
        ]
        .into_iter()
        .filter(|(r, _)| with_role(*r).is_some())
        .map(|(_, p)| p)
        .collect(),
    };
    // Each light is the laser of its role; a pass whose light has no laser is refused (a
    // renamed tube once left the reflectance passes on laser 0, the stripe, unseen).
    for pass in &passes {
        let (role, needs) = match pass {
            lls::Pass::Reflectance { .. } => (LaserRole::Tube, "a reflectance pass"),
            lls::Pass::Stripe => (LaserRole::Stripe, "the stripe pass"),
            lls::Pass::Backlit => (LaserRole::Backlight, "the backlit pass"),
            lls::Pass::Board | lls::Pass::LightBox => continue,
        };
        if with_role(role).is_none() {
            let known: Vec<_> = rig
                .lasers
                .iter()
                .map(|l| {
                    let name = l.name.as_deref().map_or(String::new(), |n| format!(" `{n}`"));
                    let role = l.role.map_or("no role".to_string(), |r| format!("role {}", r.key()));
                    format!("channel {}{name} ({role})", l.channel)
                })
                .collect();
            return Err(rig.error(
                "plan.passes",
                format!(
                    "{needs} needs the [[laser]] with `role = \"{}\"`; the rig's lasers: {} (add the key \
                     to the laser that does it, or leave the pass out of plan.passes)",
                    role.key(),
                    if known.is_empty() { "none".to_string() } else { known.join(", ") }
                ),
            ));
        }
    }
    let light = with_role(LaserRole::Tube).unwrap_or(0);
    let stripe = with_role(LaserRole::Stripe).unwrap_or(0);
    let backlight = with_role(LaserRole::Backlight);
    let p = lls::LlsParams {
        axis: axis.axis,
        start,
        step: second - start,
        count,
        cameras: indices(&cameras),
        exposures,
        settle,
        frame_gap: frame_gap(rig, &cameras, longest, hz)?,
        light,
        stripe,
        backlight,
        passes,
        timeout: hz.saturating_mul(60),
        frame_bytes: frame_bytes(rig)?,
        tick_hz: hz,
    };
    lls::plan(&p).map_err(|e| rig.error("plan", e.0))
}

fn disco_plan(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
    let (turntable, view_steps) = turntable_views(rig)?;
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
    // `spot_window_deg = [[x0, x1], [y0, y1]]`: the grid's span in optical degrees from the
    // zero codes (the object's extent as the projector sees it), else the galvo's whole range.
    let window = match rig.plan.get("spot_window_deg") {
        None => None,
        Some(v) => {
            let w: [[f64; 2]; 2] = v.clone().try_into().map_err(|_| {
                rig.error(
                    "plan.spot_window_deg",
                    "must be [[x_from, x_to], [y_from, y_to]] in optical degrees",
                )
            })?;
            Some(w)
        }
    };
    let range =
        |axis: &crate::rigfile::GalvoAxisSpec, k: usize, name: &str| -> Result<(u16, u16), RigError> {
            let Some(w) = window else { return Ok((axis.min_code, axis.max_code)) };
            let code = |deg: f64| f64::from(axis.zero_code) + deg.to_radians() * 1e6 / axis.urad_per_code;
            let (a, b) = (code(w[k][0]), code(w[k][1]));
            let (lo, hi) = (a.min(b).round(), a.max(b).round());
            if lo < f64::from(axis.min_code) || hi > f64::from(axis.max_code) {
                return Err(rig.error(
                    "plan.spot_window_deg",
                    format!(
                        "the {name} span reaches codes {lo}..{hi}, outside the galvo's {}..{}",
                        axis.min_code, axis.max_code
                    ),
                ));
            }
            Ok((lo as u16, hi as u16))
        };
    let (x_lo, x_hi) = range(&galvo.x, 0, "x")?;
    let (y_lo, y_hi) = range(&galvo.y, 1, "y")?;
    let mut points = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            points.push(Xy { x: spread(x_lo, x_hi, nx, i), y: spread(y_lo, y_hi, ny, j) });
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
    let cameras = plan_cameras(rig)?;
    let exposure = exposure(rig, &cameras, hz)?;
    let positions = crate::disco::camera_positions(rig)?.into_iter().map(|p| p.name).collect();
    let frames_per_spot = num(rig, "frames_per_spot", Some(1.0))?;
    if !(1.0..=1000.0).contains(&frames_per_spot) || frames_per_spot.fract() != 0.0 {
        return Err(rig.error("plan.frames_per_spot", "must be a whole number from 1 to 1000"));
    }
    let has_white = rig.plan.get("fit").and_then(|f| f.get("white_target")).is_some();
    let white = match rig.plan.get("white_balance") {
        None => has_white,
        Some(v) => v.as_bool().ok_or_else(|| rig.error("plan.white_balance", "must be true or false"))?,
    }
    .then_some(Xy { x: galvo.x.zero_code, y: galvo.y.zero_code });
    let p = disco::DiscoParams {
        turntable,
        views: view_steps,
        lasers,
        positions,
        frames_per_spot: frames_per_spot as u32,
        white,
        galvo: galvo.galvo,
        grid: points,
        cameras: indices(&cameras),
        exposure,
        settle: us(rig, "galvo.settle_us", galvo.settle_us, hz)?,
        frame_gap: frame_gap(rig, &cameras, exposure, hz)?,
        spotlight,
        timeout: hz.saturating_mul(60),
        frame_bytes: frame_bytes(rig)?,
        tick_hz: hz,
    };
    disco::plan(&p).map_err(|e| rig.error("plan", e.0))
}

fn turntable_views(rig: &RigFile) -> Result<(u8, Vec<i32>), RigError> {
    let table = rig
        .stepper_named("turntable")
        .or_else(|| rig.steppers.iter().find(|s| s.kind == AxisKind::Rotary))
        .ok_or_else(|| rig.error("stepper", "the plan needs a rotary stepper (named `turntable`)"))?;
    let views = num(rig, "views", None)? as u32;
    if views == 0 {
        return Err(rig.error("plan.views", "must be at least 1"));
    }
    let steps = (0..views)
        .map(|v| rig.stepper_steps(table.axis, 360.0 * f64::from(v) / f64::from(views)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((table.axis, steps))
}

fn immersion_plan(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
    let (turntable, orientations) = turntable_views(rig)?;
    let galvo = rig.galvos.first().ok_or_else(|| rig.error("galvo", "the sheet needs a [[galvo]]"))?;
    let sheets = num(rig, "sheet_positions", None)? as u32;
    if sheets < 2 {
        return Err(rig.error("plan.sheet_positions", "must be at least 2"));
    }
    let laser = match rig.plan.get("laser").and_then(|v| v.as_str()) {
        Some(n) => laser_named(rig, "plan.laser", n)?,
        None => rig
            .lasers
            .first()
            .map(|l| l.channel)
            .ok_or_else(|| rig.error("laser", "the sheet needs a [[laser]]"))?,
    };
    let cameras = plan_cameras(rig)?;
    let exposure = exposure(rig, &cameras, hz)?;
    let calibration = match rig.plan.get("calibration") {
        None => true,
        Some(v) => v.as_bool().ok_or_else(|| rig.error("plan.calibration", "must be true or false"))?,
    };
    let sweep = match nums(rig, "sweep_codes")? {
        None => (galvo.x.min_code, galvo.x.max_code),
        Some(c) => {
            let (lo, hi) = (galvo.x.min_code, galvo.x.max_code);
            match c[..] {
                [a, b]
                    if a.fract() == 0.0
                        && b.fract() == 0.0
                        && a >= f64::from(lo)
                        && b <= f64::from(hi)
                        && a < b =>
                {
                    (a as u16, b as u16)
                }
                _ => {
                    return Err(rig.error(
                        "plan.sweep_codes",
                        format!(
                            "must be [first, last], whole galvo codes with first < last inside galvo[0].x's \
                             range {lo}..={hi}"
                        ),
                    ))
                }
            }
        }
    };
    let p = firs::ImmersionParams {
        turntable,
        orientations,
        laser,
        galvo: galvo.galvo,
        sweep: (sweep.0, sweep.1, sheets),
        sheet_y: galvo.y.zero_code,
        cameras: indices(&cameras),
        exposure,
        settle: us(rig, "galvo.settle_us", galvo.settle_us, hz)?,
        frame_gap: frame_gap(rig, &cameras, exposure, hz)?,
        calibration,
        timeout: hz.saturating_mul(60),
        frame_bytes: frame_bytes(rig)?,
        tick_hz: hz,
    };
    firs::plan_with_targets(&p, &targets(rig)?).map_err(|e| rig.error("plan", e.0))
}

/// `[plan] calibration_targets`: the calibration target's positions, front to back, each a
/// table the operator fills in (`{ z_mm = -12.0 }`: the target plane's depth in the tank's
/// frame); carried into the calibration steps' `meta.pose` for the fit and the virtual camera.
fn targets(rig: &RigFile) -> Result<Vec<serde_json::Value>, RigError> {
    let Some(v) = rig.plan.get("calibration_targets") else { return Ok(Vec::new()) };
    let key = "plan.calibration_targets";
    let list =
        v.as_array().ok_or_else(|| rig.error(key, "must be a list of tables, e.g. [{ z_mm = -12.0 }]"))?;
    if list.len() < 2 {
        return Err(rig.error(key, "per-pixel rays need at least 2 target positions (front and back)"));
    }
    list.iter()
        .map(|t| {
            let z = t.get("z_mm").and_then(|z| z.as_float().or_else(|| z.as_integer().map(|i| i as f64)));
            if !t.is_table() || !z.is_some_and(f64::is_finite) {
                return Err(rig.error(key, "each position needs z_mm, the target plane's depth in mm"));
            }
            serde_json::to_value(t).map_err(|e| rig.error(key, e.to_string()))
        })
        .collect()
}

fn display_plan(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
    use lightrig_pipelines::display::mapping::{X_SWEEP, Y_SWEEP};
    use lightrig_pipelines::display::Liquid;
    if rig.voice_coils.is_empty() {
        return Err(rig.error("voice_coil", "a BRDF display needs at least one [[voice_coil]]"));
    }
    let modes = ["patterns", "calibrate", "alphas"].into_iter().filter(|k| rig.plan.contains_key(*k));
    let modes: Vec<&str> = modes.collect();
    if modes.len() != 1 {
        return Err(rig.error(
            "plan",
            "give exactly one of `[plan.calibrate]` (measure the coils' responses), `alphas = [[αx, αy], …]` \
             with `calibration = \"FILE\"` (show Ward roughnesses), or `[plan.patterns]` (raw partials)",
        ));
    }
    let liquid_name = rig.plan.get("liquid").and_then(|v| v.as_str()).unwrap_or("water");
    if Liquid::preset(liquid_name).is_none() {
        return Err(rig.error("plan.liquid", format!("`{liquid_name}`: known liquids are water, galinstan")));
    }
    let screen = display_screen(rig)?;
    let max_slope = display_max_slope(rig)?;
    let meta = serde_json::json!({
        "liquid": liquid_name,
        "screen": screen,
        "max_slope_rad": max_slope,
    });
    let targets = match modes[0] {
        "patterns" => pattern_targets(rig)?,
        "calibrate" => {
            let cal = rig.plan.get("calibrate").and_then(|v| v.as_table());
            let field = |k: &str| cal.and_then(|c| c.get(k));
            let drive = match field("drive") {
                None => 0.03,
                Some(v) => v.as_float().filter(|d| (0.0..=1.0).contains(d) && *d > 0.0).ok_or_else(|| {
                    rig.error("plan.calibrate.drive", "must be a fraction of full scale, 0 < drive ≤ 1")
                })?,
            };
            let coils = display_coils(rig)?;
            for c in &coils {
                if drive > c.max_amplitude {
                    return Err(rig.error(
                        "plan.calibrate.drive",
                        format!("{drive} is above coil {}'s max_amplitude {}", coil_name(c), c.max_amplitude),
                    ));
                }
            }
            let axes = [(coils[0].channel, X_SWEEP.to_vec()), (coils[1].channel, Y_SWEEP.to_vec())];
            display::calibration_targets(&axes, drive)
        }
        _ => {
            let cal = display_calibration(rig)?;
            let bad = || rig.error("plan.alphas", "must be a list of [αx, αy] pairs, e.g. [[0.08, 0.04]]");
            let list = rig.plan.get("alphas").and_then(|v| v.as_array()).ok_or_else(bad)?;
            let mut alphas = Vec::new();
            for pair in list {
                let pair = pair.as_array().filter(|p| p.len() == 2).ok_or_else(bad)?;
                let v = |x: &toml::Value| {
                    x.as_float().or_else(|| x.as_integer().map(|i| i as f64)).ok_or_else(bad)
                };
                alphas.push([v(&pair[0])?, v(&pair[1])?]);
            }
            display::alpha_targets(&cal, &alphas, max_slope)
                .map_err(|e| rig.error("plan.alphas", e.to_string()))?
        }
    };
    let cameras = plan_cameras(rig)?;
    let exposure = exposure(rig, &cameras, hz)?;
    let ms = |key: &str, default: f64| -> Result<u32, RigError> {
        let v = num(rig, key, Some(default))?;
        ticks_from_ms(v, hz)
            .ok_or_else(|| rig.error(&format!("plan.{key}"), format!("{v} ms is out of range")))
    };
    let p = display::DisplayParams {
        targets,
        ramp: ms("ramp_ms", 200.0)?,
        settle: ms("settle_ms", 2000.0)?,
        cameras: indices(&cameras),
        captures: num(rig, "captures", Some(3.0))? as u32,
        exposure,
        frame_gap: frame_gap(rig, &cameras, exposure, hz)?,
        frame_bytes: frame_bytes(rig)?,
        tick_hz: hz,
        meta,
    };
    display::plan(&p).map_err(|e| rig.error("plan", e.0))
}

/// Where the display's screen stands: `[plan.screen]`, `distance_mm` from the spot along the
/// mirror direction, `pitch_mm` of screen per camera pixel, the beam's `incidence_deg`, the
/// screen's `tilt_deg` from facing the mirror direction (0 by default) and `centre_px = [x, y]`,
/// where the mirror direction meets the picture (its centre by default: `None`).
pub fn display_screen(rig: &RigFile) -> Result<DisplayScreen, RigError> {
    let t = rig.plan.get("screen").and_then(|v| v.as_table()).ok_or_else(|| {
        rig.error(
            "plan.screen",
            "a BRDF display needs its screen: `[plan.screen]` with distance_mm, pitch_mm and incidence_deg \
             (docs/rigs/README.md)",
        )
    })?;
    let get =
        |key: &str, default: Option<f64>, ok: &dyn Fn(f64) -> bool, range: &str| -> Result<f64, RigError> {
            let field = format!("plan.screen.{key}");
            let v = match t.get(key) {
                None => {
                    return default
                        .ok_or_else(|| rig.error("plan.screen", format!("`{key}` is required ({range})")))
                }
                Some(v) => v.as_float().or_else(|| v.as_integer().map(|i| i as f64)),
            };
            v.filter(|v| ok(*v)).ok_or_else(|| rig.error(&field, format!("must be a number, {range}")))
        };
    let centre_px = match t.get("centre_px") {
        None => None,
        Some(v) => {
            let xy: Option<Vec<f64>> = v.as_array().filter(|a| a.len() == 2).and_then(|a| {
                a.iter().map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64))).collect()
            });
            Some(
                xy.map(|xy| [xy[0], xy[1]])
                    .ok_or_else(|| rig.error("plan.screen.centre_px", "must be [x, y], pixels"))?,
            )
        }
    };
    Ok(DisplayScreen {
        distance_m: get("distance_mm", None, &|v| v > 0.0, "mm, above 0")? / 1000.0,
        pitch_m: get("pitch_mm", None, &|v| v > 0.0, "mm of screen per camera pixel, above 0")? / 1000.0,
        incidence_rad: get("incidence_deg", None, &|v| (0.0..80.0).contains(&v), "degrees, 0 to 80")?
            .to_radians(),
        tilt_rad: get("tilt_deg", Some(0.0), &|v| v.abs() < 80.0, "degrees, −80 to 80")?.to_radians(),
        centre_px,
    })
}

/// The display's screen as the rig file gives it ([`display_screen`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DisplayScreen {
    /// From the spot along the mirror direction, m.
    pub distance_m: f64,
    /// Screen per camera pixel, m.
    pub pitch_m: f64,
    /// The beam's incidence, rad.
    pub incidence_rad: f64,
    /// The screen's turn from facing the mirror direction, rad.
    pub tilt_rad: f64,
    /// Where the mirror direction meets the picture, pixels; `None`: its centre.
    pub centre_px: Option<[f64; 2]>,
}

impl DisplayScreen {
    /// The pipeline's screen for a `width × height` picture.
    pub fn screen(&self, width: u32, height: u32) -> lightrig_pipelines::display::Screen {
        lightrig_pipelines::display::Screen {
            distance_m: self.distance_m,
            pitch_m: self.pitch_m,
            incidence_rad: self.incidence_rad,
            tilt_rad: self.tilt_rad,
            centre_px: self.centre_px.unwrap_or([f64::from(width) / 2.0, f64::from(height) / 2.0]),
        }
    }
}

/// `[plan] max_slope_deg`: the bound on the total slope's standard deviation per axis, rad
/// (`mapping::LINEAR_LIMIT`, Eq. 5.1's 5°, without it).
pub fn display_max_slope(rig: &RigFile) -> Result<f64, RigError> {
    let deg =
        num(rig, "max_slope_deg", Some(lightrig_pipelines::display::mapping::LINEAR_LIMIT.to_degrees()))?;
    if !(deg > 0.0 && deg <= 30.0) {
        return Err(rig.error("plan.max_slope_deg", format!("{deg}: give degrees, above 0 and at most 30")));
    }
    Ok(deg.to_radians())
}

/// The x and y axes' coils: `[plan] coils = ["NAME", "NAME"]`, else the first two
/// `[[voice_coil]]`s.
pub fn display_coils(rig: &RigFile) -> Result<[&crate::rigfile::VoiceCoil; 2], RigError> {
    let coils: Vec<&crate::rigfile::VoiceCoil> = match names(rig, "coils")? {
        Some(n) => {
            n.iter()
                .map(|name| {
                    rig.voice_coils.iter().find(|c| c.name.as_deref() == Some(name.as_str())).ok_or_else(
                        || rig.error("plan.coils", format!("no [[voice_coil]] is named `{name}`")),
                    )
                })
                .collect::<Result<_, _>>()?
        }
        None => rig.voice_coils.iter().take(2).collect(),
    };
    match coils[..] {
        [x, y] => Ok([x, y]),
        _ => Err(rig.error(
            "plan.coils",
            "a display driven by Ward roughness needs two coils, one per axis (x then y)",
        )),
    }
}

fn coil_name(c: &crate::rigfile::VoiceCoil) -> String {
    c.name.as_ref().map_or_else(|| format!("channel {}", c.channel), |n| format!("`{n}`"))
}

/// The calibration file `[plan] calibration` names (relative to the rig file), checked against
/// the rig's coils.
pub fn display_calibration(rig: &RigFile) -> Result<lightrig_pipelines::display::Calibration, RigError> {
    let name = rig.plan.get("calibration").and_then(|v| v.as_str()).ok_or_else(|| {
        rig.error(
            "plan.calibration",
            "`alphas` needs `calibration = \"FILE\"`: the file `lightrig fit display` writes from a \
             calibration session (a rig file with `[plan.calibrate]`)",
        )
    })?;
    let path = rig.path.parent().unwrap_or(std::path::Path::new(".")).join(name);
    display_calibration_at(rig, &path)
}

/// The display calibration at `path`, checked against the rig's coils.
pub fn display_calibration_at(
    rig: &RigFile,
    path: &std::path::Path,
) -> Result<lightrig_pipelines::display::Calibration, RigError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| rig.error("plan.calibration", format!("{}: {e}", path.display())))?;
    let cal = lightrig_pipelines::display::Calibration::from_json(&text)
        .map_err(|e| rig.error("plan.calibration", format!("{}: {e}", path.display())))?;
    let coils = display_coils(rig)?;
    for (k, c) in coils.iter().enumerate() {
        if cal.axes[k].channel != c.channel {
            return Err(rig.error(
                "plan.calibration",
                format!(
                    "{}: axis {} was calibrated on channel {}, the rig drives it with {} on channel {}: calibrate again",
                    path.display(),
                    ["x", "y"][k],
                    cal.axes[k].channel,
                    coil_name(c),
                    c.channel
                ),
            ));
        }
    }
    Ok(cal)
}

fn pattern_targets(rig: &RigFile) -> Result<Vec<display::Target>, RigError> {
    use lightrig_protocol::sequence::Partial;
    let patterns = rig.plan.get("patterns").and_then(|v| v.as_table()).ok_or_else(|| {
        rig.error(
            "plan",
            "`[plan.patterns]` is required: NAME = { frequencies_hz = [...], amplitudes = [...] }",
        )
    })?;
    let mut targets = Vec::new();
    for (name, v) in patterns {
        let key = format!("plan.patterns.{name}");
        let list = |field: &str| -> Result<Vec<f64>, RigError> {
            let bad = || rig.error(&key, format!("`{field}` must be a list of numbers"));
            let arr = v.get(field).and_then(|a| a.as_array()).ok_or_else(bad)?;
            arr.iter()
                .map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64)).ok_or_else(bad))
                .collect()
        };
        let (freqs, amps) = (list("frequencies_hz")?, list("amplitudes")?);
        if freqs.len() != amps.len() || freqs.is_empty() {
            return Err(
                rig.error(&key, "frequencies_hz and amplitudes must be non-empty lists of the same length")
            );
        }
        let partials: Vec<Partial> = freqs
            .iter()
            .zip(&amps)
            .enumerate()
            .map(|(i, (&f, &a))| {
                display::partial(f, a, lightrig_pipelines::display::mapping::golden_phase(i))
            })
            .collect();
        let channels = rig.voice_coils.iter().map(|c| (c.channel, partials.clone())).collect();
        targets.push(display::Target { name: name.clone(), channels, meta: serde_json::Value::Null });
    }
    Ok(targets)
}

fn bispectral_plan(rig: &RigFile, hz: u32) -> Result<Plan, RigError> {
    use super::brrdf::{self, Pair};
    let axis = |name: &str| {
        rig.stepper_named(name).ok_or_else(|| {
            rig.error("stepper", format!("a bispectral rig needs a rotary stepper named `{name}`"))
        })
    };
    let (sample, light) = (axis("sample")?, axis("light-arm")?);
    let gonio = rig.plan.get("gonio").and_then(|v| v.as_table());
    let angles = |key: &str| -> Result<Vec<f64>, RigError> {
        let full = format!("plan.gonio.{key}");
        let bad = || rig.error(&full, "must be a list of angles in degrees");
        let arr = gonio.and_then(|g| g.get(key)).and_then(|a| a.as_array()).ok_or_else(bad)?;
        arr.iter()
            .map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64)).ok_or_else(bad))
            .collect()
    };
    // An angle beyond its stepper's limits is the plan key's mistake: named so, with the limits.
    let on = |axis: &crate::rigfile::Stepper, key: &str, deg: f64| {
        rig.stepper_steps(axis.axis, deg).map_err(|e| {
            let name = axis.name.as_deref().unwrap_or("its");
            rig.error(&format!("plan.gonio.{key}"), format!("{} (stepper `{name}`'s limits)", e.message))
        })
    };
    let mut geometries = Vec::new();
    for s_deg in angles("sample_angles")? {
        for l_deg in angles("light_angles")? {
            geometries.push((on(sample, "sample_angles", s_deg)?, on(light, "light_angles", l_deg)?));
        }
    }
    let wheel = rig
        .filter_wheels
        .first()
        .ok_or_else(|| rig.error("filter_wheel", "the excitation needs a [[filter_wheel]]"))?;
    // Excitation wavelengths: the wheel's `led-NNN` slots, and the light filter's band through
    // the `white` slot over `tunable_filter.excitation_range_nm` (an LED wins where both reach).
    let leds: Vec<(u16, u8)> = wheel
        .filters
        .iter()
        .enumerate()
        .filter_map(|(slot, n)| n.strip_prefix("led-").and_then(|w| w.parse().ok()).map(|w| (w, slot as u8)))
        .collect();
    let white = wheel.filters.iter().position(|n| n == "white").map(|s| s as u8);
    let filter = rig.plan.get("tunable_filter").and_then(|v| v.as_table());
    let range = |key: &str| -> Result<Option<(i64, i64)>, RigError> {
        let full = format!("plan.tunable_filter.{key}");
        let bad = || rig.error(&full, "must be [from_nm, to_nm], e.g. [400, 720]");
        match filter.and_then(|f| f.get(key)) {
            None => Ok(None),
            Some(v) => match v.as_array().map(|a| a.as_slice()) {
                Some([a, b]) => Ok(Some((a.as_integer().ok_or_else(bad)?, b.as_integer().ok_or_else(bad)?))),
                _ => Err(bad()),
            },
        }
    };
    let step = filter.and_then(|f| f.get("step_nm")).and_then(|v| v.as_integer()).filter(|s| *s > 0);
    let xenon = range("excitation_range_nm")?;
    if xenon.is_some() && white.is_none() {
        return Err(rig.error(
            "plan.tunable_filter.excitation_range_nm",
            "excitation through the light filter needs a `white` slot on the filter wheel",
        ));
    }
    if leds.is_empty() && xenon.is_none() {
        return Err(rig.error("filter_wheel", "no `led-NNN` filters on the wheel: nothing to excite with"));
    }
    let slot_of = |ex: u16| {
        leds.iter()
            .find(|(w, _)| *w == ex)
            .map(|(_, s)| *s)
            .or_else(|| xenon.filter(|(a, b)| (*a..=*b).contains(&i64::from(ex))).and(white))
    };
    let mut excitations: Vec<(u16, u8)> = leds.clone();
    if let (Some((from, to)), Some(white), Some(step)) = (xenon, white, step) {
        let mut ex = from;
        while ex <= to {
            if !leds.iter().any(|(w, _)| i64::from(*w) == ex) {
                excitations.push((ex as u16, white));
            }
            ex += step;
        }
    }
    excitations.sort_unstable();
    // The Spectralon session measures each excitation's row around its diagonal (two bands
    // either side, below the diagonal too): the spectral scaling sums those rows.
    let spectralon = rig.plan.get("sample").and_then(|v| v.as_str()) == Some("spectralon");
    let pairs: Vec<Pair> = match rig.plan.get("pairs").and_then(|v| v.as_array()) {
        Some(list) => list
            .iter()
            .map(|p| {
                let bad = || {
                    rig.error(
                        "plan.pairs",
                        "each pair is [excitation_nm, emission_nm] with an led-NNN slot (or the light \
                         filter's excitation_range_nm) for the excitation",
                    )
                };
                let a = p.as_array().ok_or_else(bad)?;
                let (ex, em) = match a.as_slice() {
                    [x, y] => {
                        (x.as_integer().ok_or_else(bad)? as u16, y.as_integer().ok_or_else(bad)? as u16)
                    }
                    _ => return Err(bad()),
                };
                // The camera filter must reach the emission.
                if let Some((from, to)) = range("range_nm")? {
                    if !(from..=to).contains(&i64::from(em)) {
                        return Err(rig.error(
                            "plan.pairs",
                            format!(
                                "[{ex}, {em}]: the camera filter reaches {from}-{to} nm \
                                 ([plan.tunable_filter] range_nm), not {em} nm"
                            ),
                        ));
                    }
                }
                let slot = slot_of(ex).ok_or_else(|| {
                    rig.error(
                        "plan.pairs",
                        format!(
                            "[{ex}, {em}]: no `led-{ex}` slot on the wheel and {ex} nm is outside the light \
                             filter's excitation_range_nm: nothing excites at {ex} nm"
                        ),
                    )
                })?;
                Ok(Pair { excitation: ex, emission: em, slot })
            })
            .collect::<Result<_, _>>()?,
        None => {
            let bad = || rig.error("plan.tunable_filter", "needs range_nm = [from, to] and step_nm");
            let (from, to) = range("range_nm")?.ok_or_else(bad)?;
            let step = step.ok_or_else(bad)?;
            let mut out = Vec::new();
            for &(ex, slot) in &excitations {
                let mut em = from;
                while em <= to {
                    let take =
                        if spectralon { (em - i64::from(ex)).abs() <= 2 * step } else { em >= i64::from(ex) };
                    if take {
                        out.push(Pair { excitation: ex, emission: em as u16, slot });
                    }
                    em += step;
                }
            }
            out
        }
    };
    let cameras = plan_cameras(rig)?;
    let exposures: Vec<u32> = match nums(rig, "exposures_us")? {
        Some(v) => v.iter().map(|&e| us(rig, "exposures_us", e, hz)).collect::<Result<_, _>>()?,
        None => vec![pulse(rig, &cameras, hz)?],
    };
    let readout = us(rig, "readout_us", num(rig, "readout_us", Some(1000.0))?, hz)?;
    // The PCA-steered plan (`[plan.steer]`): light angles taken with every pair, and how many
    // pairs the others get.
    let steer = match rig.plan.get("steer").and_then(|v| v.as_table()) {
        None => None,
        Some(t) => {
            let bad = |k: &str, what: &str| rig.error(&format!("plan.steer.{k}"), what);
            let dense: Vec<f64> = t
                .get("dense_angles")
                .and_then(|v| v.as_array())
                .and_then(|a| {
                    a.iter().map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64))).collect()
                })
                .ok_or_else(|| bad("dense_angles", "must be a list of light-arm angles, degrees"))?;
            let select = t
                .get("select")
                .and_then(|v| v.as_integer())
                .filter(|n| (1..=64).contains(n))
                .ok_or_else(|| bad("select", "must be the number of pairs per other angle, 1 to 64"))?
                as usize;
            let mut idx = Vec::new();
            for a in &dense {
                let steps = rig.stepper_steps(light.axis, *a)?;
                let found: Vec<usize> =
                    geometries.iter().enumerate().filter(|(_, g)| g.1 == steps).map(|(i, _)| i).collect();
                if found.is_empty() {
                    return Err(bad("dense_angles", &format!("{a}° is not among [plan.gonio] light_angles")));
                }
                idx.extend(found);
            }
            Some(brrdf::Steer {
                dense: idx,
                select,
                choose: crate::steer::chooser(rig.clone(), pairs.clone(), select),
            })
        }
    };
    let p = brrdf::BispectralParams {
        sample_axis: sample.axis,
        light_axis: light.axis,
        geometries,
        wheel: wheel.wheel,
        pairs,
        cameras: indices(&cameras),
        exposures,
        readout,
        min_interval: min_interval(rig, &cameras, hz)?,
        timeout: hz.saturating_mul(60),
        frame_bytes: frame_bytes(rig)?,
        tick_hz: hz,
    };
    brrdf::plan_steered(&p, steer).map_err(|e| rig.error("plan", e.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped(name: &str) -> String {
        std::fs::read_to_string(format!("{}/../docs/rigs/{name}", env!("CARGO_MANIFEST_DIR"))).unwrap()
    }

    #[test]
    fn every_shipped_rigs_plan_keys_are_known() {
        for name in [
            "lls-gantry.toml",
            "disco.toml",
            "fluorescent-immersion.toml",
            "bispectral.toml",
            "brdf-display.toml",
        ] {
            let rig = RigFile::parse(&shipped(name), std::path::Path::new(name)).unwrap();
            assert_eq!(check_keys(&rig), Ok(()), "{name}");
        }
    }

    /// A pass takes the laser of its role whatever the lasers are called: the tube renamed
    /// `led-tube` still lights the reflectance pass, and swapped roles swap the channels.
    #[test]
    fn lls_passes_take_their_lights_by_role_not_by_name() {
        let lasers_of = |text: &str| -> Vec<(String, u8)> {
            let rig = RigFile::parse(text, std::path::Path::new("lls-gantry.toml")).unwrap();
            let plan = lls_plan(&rig, 1_000_000).unwrap();
            plan.steps.iter().map(|s| (s.meta["pass"].as_str().unwrap_or("").to_string(), s.lasers)).collect()
        };
        let lls = shipped("lls-gantry.toml");
        let expected: Vec<(String, u8)> =
            vec![("board".into(), 0), ("reflectance".into(), 0b10), ("stripe".into(), 0b01)];
        assert_eq!(lasers_of(&lls), expected);
        assert_eq!(lasers_of(&lls.replace("name = \"light-tube\"", "name = \"led-tube\"")), expected);
        let swapped = lls
            .replace("role = \"stripe\"", "role = \"@\"")
            .replace("role = \"tube\"", "role = \"stripe\"")
            .replace("role = \"@\"", "role = \"tube\"");
        assert_eq!(
            lasers_of(&swapped),
            vec![("board".into(), 0), ("reflectance".into(), 0b01), ("stripe".into(), 0b10)]
        );
        // A role twice, or in a rig whose planner takes lasers by name, is refused at its key.
        let twice = lls.replace("role = \"tube\"", "role = \"stripe\"");
        let e = RigFile::parse(&twice, std::path::Path::new("lls-gantry.toml")).unwrap_err();
        assert_eq!(e.key, "laser[1].role");
        assert_eq!(e.message, "role \"stripe\" is already laser[0]'s; each role is one laser's");
        let disco = shipped("disco.toml").replacen("[[laser]]\n", "[[laser]]\nrole = \"tube\"\n", 1);
        let e = RigFile::parse(&disco, std::path::Path::new("disco.toml")).unwrap_err();
        assert_eq!(e.key, "laser[0].role");
    }

    #[test]
    fn a_misspelt_plan_key_is_refused_at_its_line_with_the_key_meant() {
        let text = shipped("lls-gantry.toml").replace("step_mm = 0.5", "step_m = 4");
        let line = text.lines().position(|l| l.starts_with("step_m =")).unwrap() + 1;
        let rig = RigFile::parse(&text, std::path::Path::new("lls-gantry.toml")).unwrap();
        let e = check_keys(&rig).unwrap_err();
        assert_eq!((e.line, e.key.as_str()), (Some(line), "plan.step_m"));
        assert!(e.message.starts_with("unknown key; did you mean \"step_mm\"? Valid keys here: "), "{e}");
        // A key of another method's planner: LLS takes a bracket of exposures, not one.
        let text = shipped("lls-gantry.toml").replace("step_mm = 0.5", "step_mm = 0.5\nexposure_us = 500");
        let rig = RigFile::parse(&text, std::path::Path::new("lls-gantry.toml")).unwrap();
        let e = check_keys(&rig).unwrap_err();
        assert!(e.message.contains("did you mean \"exposures_us\"?"), "{e}");
        // Inside a sub-table read key by key.
        let text = shipped("bispectral.toml").replace("\nrange_nm = ", "\nrang_nm = ");
        let rig = RigFile::parse(&text, std::path::Path::new("bispectral.toml")).unwrap();
        let e = check_keys(&rig).unwrap_err();
        assert_eq!(e.key, "plan.tunable_filter.rang_nm", "{e}");
        assert!(e.message.contains("did you mean \"range_nm\"?"), "{e}");
    }

    fn rig_with(targets: &str) -> RigFile {
        RigFile::parse(&rig_text(targets), std::path::Path::new("rig.toml")).unwrap()
    }

    fn rig_text(targets: &str) -> String {
        std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../docs/rigs/fluorescent-immersion.toml"
        ))
        .unwrap()
        .replace("views = 36 ", "views = 2 ")
        .replace("sheet_positions = 365 ", "sheet_positions = 5 ")
        .replace("calibration_targets = [{ z_mm = -12.0 }, { z_mm = 8.0 }]", targets)
    }

    #[test]
    fn calibration_targets_become_board_and_sweep_steps() {
        let info = lightrig_firmware::sim::virtual_device_info();
        let plan =
            super::plan(&rig_with("calibration_targets = [{ z_mm = -12.0 }, { z_mm = 8 }]"), &info).unwrap();
        // Two positions × (board, sweep), then 2 views.
        assert_eq!(plan.steps.len(), 6);
        assert_eq!(plan.steps[0].meta["pose"]["z_mm"], -12.0);
        assert_eq!(plan.steps[3].meta["pose"]["z_mm"], 8);
        assert_eq!(plan.summary().triggers, 2 * (1 + 1 + 5) + 2 * 5);
        // The sweep's codes must lie inside the galvo's range.
        for bad in ["[30000, 50000]", "[33749, 31578]", "[31578.5, 33000]", "[1]"] {
            let text = rig_text("calibration_targets = [{ z_mm = -12.0 }, { z_mm = 8 }]")
                .replace("sweep_codes = [31578, 33749]", &format!("sweep_codes = {bad}"));
            let rig = RigFile::parse(&text, std::path::Path::new("rig.toml")).unwrap();
            let e = super::plan(&rig, &info).unwrap_err().to_string();
            assert!(e.contains("plan.sweep_codes") && e.contains("range 19661..=45875"), "{bad}: {e}");
        }
        for bad in [
            "calibration_targets = [{ z_mm = -12.0 }]",
            "calibration_targets = [{ z = 1.0 }, { z_mm = 2.0 }]",
        ] {
            let e = super::plan(&rig_with(bad), &info).unwrap_err().to_string();
            assert!(e.contains("plan.calibration_targets"), "{bad}: {e}");
        }
    }
}
