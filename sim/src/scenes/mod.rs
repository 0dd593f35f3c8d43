//! What the virtual camera looks at: one scene per rig, each with its ground truth.
//!
//! - [`lls`]: the linear-light-source sample and its ground truth.
//! - [`firs`]: the fluorescent-immersion tank scene and its ground truth.
//! - [`display`]: the BRDF display's liquid surface, driven by the coils' samples.
//! - [`bispectral`]: the gonioreflectometer's coated spheres (or Spectralon), spectra in closed form.
//! - [`disco`]: the translucent pebble on the turntable under the laser spot, its `F` known.
//! - [`card`]: the test card, for a DISCO rig file without the `[plan.fit]` geometry.
//! - [`scene_for`]: a rig file's scene, for `lightrig acquire` with `source = { kind = "virtual" }`.

pub mod bispectral;
pub mod card;
pub mod disco;
pub mod display;
pub mod firs;
pub mod lls;

use lightrig_host::rigfile::{LaserRole, Method, RigFile};
use lightrig_protocol::config::AxisKind;

use crate::camera::Scene;
use crate::sensor::Sensor;

/// What `rig`'s `[plan.fit]` says that the scene [`scene_for`] renders for it does not: each
/// as `key = value (the virtual rig's: value)`. The scene is fixed per method (the LLS one is
/// the demo's sample at 128 × 96, its tube, stripe, strips and board); a fit told another
/// camera or geometry than the frames were rendered with gives numbers that mean nothing, so
/// `lightrig acquire` refuses such a file on a virtual camera. Empty when the file agrees, when
/// the method's scene reads nothing of `[plan.fit]`, or when the table does not parse (the
/// fit's own check says what is wrong with it).
pub fn unsimulated(rig: &RigFile) -> Vec<String> {
    use lightrig_host::fit::lls::FitSpec;
    if rig.method != Method::LinearLightSource {
        return Vec::new();
    }
    let Some(Ok(fit)) = rig.plan.get("fit").map(|t| t.clone().try_into::<FitSpec>()) else {
        return Vec::new();
    };
    let spec = lls::LlsSceneSpec::new(128, 96);
    let c = &spec.camera;
    let mut out = Vec::new();
    let mut check = |key: &str, given: f64, rendered: f64, tolerance: f64| {
        if (given - rendered).abs() > tolerance {
            out.push(format!("plan.fit.{key} = {given} (the virtual rig's: {rendered})"));
        }
    };
    if let Some(k) = fit.camera {
        let (cx, cy) = ((f64::from(c.width) - 1.0) / 2.0, (f64::from(c.height) - 1.0) / 2.0);
        for (key, given, rendered) in
            [("fx", k.fx, c.focal_px), ("fy", k.fy, c.focal_px), ("cx", k.cx, cx), ("cy", k.cy, cy)]
        {
            check(&format!("camera.{key}"), given, rendered, 1e-3);
        }
    }
    let (l, sl) = (&fit.light, &spec.light);
    check("light.diameter_mm", l.diameter_mm, sl.diameter_mm, 1e-3);
    check("light.length_mm", l.length_mm, sl.length_mm, 1e-3);
    check("light.height_mm", l.height_mm, sl.height_mm, 1e-3);
    check("light.offset_mm", l.offset_mm, sl.offset_mm, 1e-3);
    check("stripe.offset_mm", fit.stripe.offset_mm, spec.stripe.offset_mm, 1e-3);
    check("stripe.angle_deg", fit.stripe.angle_deg, spec.stripe.angle_deg, 1e-3);
    let (b, sb) = (&fit.board, &spec.board);
    check("board.cols", b.cols as f64, sb.cols as f64, 0.0);
    check("board.rows", b.rows as f64, sb.rows as f64, 0.0);
    check("board.square_mm", b.square_mm, sb.square_mm, 1e-3);
    for k in 0..2 {
        check(&format!("board.origin_mm[{k}]"), b.origin_mm[k], sb.origin_mm[k], 1e-3);
    }
    for (name, strip, rendered, albedo) in [
        ("diffuse_strip", &fit.diffuse_strip, &spec.diffuse_strip, spec.diffuse_strip.diffuse),
        ("specular_strip", &fit.specular_strip, &spec.specular_strip, spec.specular_strip.specular),
    ] {
        for k in 0..2 {
            check(&format!("{name}.x_mm[{k}]"), strip.x_mm[k], rendered.x_mm[k], 1e-3);
            check(&format!("{name}.y_mm[{k}]"), strip.y_mm[k], rendered.y_mm[k], 1e-3);
        }
        check(&format!("{name}.albedo"), strip.albedo, albedo, 1e-4);
    }
    out
}

/// What the virtual camera of `rig` looks at, and a sensor exposed for it (noise seed
/// `seed`):
///
/// - linear light source: the demo's sample ([`lls::LlsScene`], 128 × 96), its tube,
///   stripe and light box on the lasers of those roles (`[[laser]] role`: `tube`, `stripe`,
///   `backlight`), the gantry on the first linear axis;
/// - fluorescent immersion: the demo's tank and sphere ([`firs::FirsScene`], 208 × 160),
///   the sheet from `[plan] laser` (else the first laser) on the first galvo pair, the
///   turntable on the first rotary axis;
/// - BRDF display: the liquid ([`display_scene`]: every fault on, 192 × 192 float
///   frames), the coils at the rig file's sample rates, the screen where `[plan.screen]` puts
///   it (the demo's without one);
/// - bispectral: the coated spheres ([`bispectral::BispectralScene`], 160 × 100; Spectralon
///   with `[plan] sample = "spectralon"`), Spectralon at 550 nm through the white slot filling
///   half the well at the camera's pulse width;
/// - DISCO: the translucent pebble ([`disco::DiscoScene`], 642 vertices) at the size
///   `[plan.fit] image` gives, in float frames (an HDR camera); without `[plan.fit]`, the
///   [`card::CardScene`] test card (160 × 120).
pub fn scene_for(rig: &RigFile, seed: u64) -> (Box<dyn Scene + Send>, Sensor) {
    let laser = |role: LaserRole| rig.laser_with_role(role).map(|l| l.channel);
    let axis = |kind: AxisKind| rig.steppers.iter().find(|s| s.kind == kind).map(|s| s.axis);
    match rig.method {
        Method::LinearLightSource => {
            let mut spec = lls::LlsSceneSpec::new(128, 96);
            spec.tube_channel = laser(LaserRole::Tube).unwrap_or(spec.tube_channel);
            spec.stripe_channel = laser(LaserRole::Stripe).unwrap_or(spec.stripe_channel);
            spec.backlight_channel = laser(LaserRole::Backlight).unwrap_or(spec.backlight_channel);
            spec.gantry_axis = axis(AxisKind::Linear).unwrap_or(spec.gantry_axis);
            // As the demo's: a white tile under the tube fills about half the well in 4 ms.
            let sensor = Sensor { gain: 30_000.0 / (0.16 * 0.004), seed, ..Sensor::default() };
            (Box::new(lls::LlsScene::new(spec)), sensor)
        }
        Method::FluorescentImmersion => {
            let mut spec = firs::FirsSceneSpec::new(208, 160);
            let named = rig.plan.get("laser").and_then(|n| n.as_str());
            spec.sheet.laser = rig
                .lasers
                .iter()
                .find(|l| named.is_none_or(|n| l.name.as_deref() == Some(n)))
                .map_or(spec.sheet.laser, |l| l.channel);
            spec.sheet.galvo = rig.galvos.first().map_or(spec.sheet.galvo, |g| g.galvo);
            spec.turntable_axis = axis(AxisKind::Rotary).unwrap_or(spec.turntable_axis);
            let sensor = Sensor { gain: 20_000.0 / (1.3 * 0.02), seed, ..Sensor::default() };
            (Box::new(firs::FirsScene::new(spec)), sensor)
        }
        Method::BrdfDisplay => {
            let (scene, sensor) = display_scene(rig, seed);
            (Box::new(scene), sensor)
        }
        Method::Bispectral => {
            let scene = bispectral::BispectralScene::new(rig, 160, 100);
            let pulse_s = rig.cameras.first().map_or(1e-3, |c| c.pulse_us * 1e-6).max(1e-6);
            let sensor = Sensor { gain: 15_000.0 / pulse_s, seed, ..Sensor::default() };
            (Box::new(scene), sensor)
        }
        Method::Disco => {
            let pulse_s = rig.cameras.first().map_or(1e-3, |c| c.pulse_us * 1e-6).max(1e-6);
            if let Ok(scene) = disco::DiscoScene::new(rig, 3) {
                // A grey HDR camera: half-float frames; the spot's peak (radiance about 0.1) at 10⁸ e⁻,
                // so that the far field, 10⁻⁵ of it, still collects a thousand.
                let sensor = Sensor {
                    gain: 1e8 / (0.1 * pulse_s),
                    depth: crate::sensor::Depth::Half,
                    grey: true,
                    seed,
                    ..Sensor::default()
                };
                return (Box::new(scene), sensor);
            }
            let card = card::CardScene::new(rig, 160, 120);
            // A laser spot on white fills half the well at the camera's own pulse width.
            let sensor = Sensor { gain: 15_000.0 / (card.spot * pulse_s), seed, ..Sensor::default() };
            (Box::new(card), sensor)
        }
    }
}

/// The BRDF display's scene and sensor for `rig` as [`scene_for`] makes them: the liquid of
/// [`display::DisplayScene::small_water`] with every fault on ([`display::Faults::ALL`]), its
/// screen the rig file's `[plan.screen]`, each coil at its `sample_rate_hz`.
pub fn display_scene(rig: &RigFile, seed: u64) -> (display::DisplayScene, Sensor) {
    let mut scene = display::DisplayScene::small_water(display::SCREEN_PIXELS, display::SCREEN_PIXELS);
    scene.faults = display::Faults::ALL;
    if let Ok(s) = lightrig_host::plan::from_rig::display_screen(rig) {
        let side = f64::from(display::SCREEN_PIXELS);
        scene.screen = display::ScreenView {
            distance_m: s.distance_m,
            pitch_m: s.pitch_m,
            incidence_rad: s.incidence_rad,
            tilt_rad: s.tilt_rad,
            centre_px: s.centre_px.unwrap_or([side / 2.0; 2]),
        };
    }
    for c in &rig.voice_coils {
        if let Some(r) = scene.rates_hz.get_mut(usize::from(c.channel)) {
            *r = f64::from(c.sample_rate_hz);
        }
    }
    // Float frames: the lobe's tails carry its variance and must not be clipped.
    let sensor = Sensor { gain: 200_000.0, depth: crate::sensor::Depth::Float, seed, ..Sensor::default() };
    (scene, sensor)
}
