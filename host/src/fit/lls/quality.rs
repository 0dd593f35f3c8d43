//! What an LLS fit can be trusted for: per-pixel validity and the session's own checks.
//!
//! A fit always produces numbers; these say which of them were measured and which only
//! look so. Per pixel ([`Validity`]): whether the reflectance was fitted, whether the trace
//! determined α (a lobe found inside the searched range: a matte pixel's α is a guess),
//! whether the stripe gave the height (else the reference plane), whether the backlit pass
//! gave the translucency, and whether the values are physical (albedo ≤ 1). For the session
//! ([`Quality`]): the board's reprojection RMS, the specular strip's fitted value against the
//! one the rig file gives, the residuals, the counts behind each mask, the maps the session's
//! passes could not measure, and warnings where a check fails.

use lightrig_pipelines::lls::TraceFit;
use serde::Serialize;

use super::LlsMaps;

/// A board reprojection RMS above this (pixels) leaves the camera's pose in doubt.
pub const BOARD_RMS_WARN_PX: f64 = 1.0;
/// The specular strip fitted this far from the rig file's value (relative) says that the
/// scale, the strip's geometry or its stated ρs is wrong.
pub const STRIP_WARN: f64 = 0.25;
/// Fewer of the frame's pixels fitted than this says the geometry misses the sample.
pub const FITTED_WARN: f64 = 0.25;

/// Per-pixel masks, row-major like the maps (`maps.exr` layers `valid.<field>`, 1 where true).
#[derive(Debug, Clone, PartialEq)]
pub struct Validity {
    /// The reflectance was fitted (a surface point and normal, off the calibration strips).
    pub reflectance: Vec<bool>,
    /// The trace determined α: a specular lobe inside the searched range, the residual
    /// curved about it. False where α sits at a bound or no lobe was seen.
    pub roughness: Vec<bool>,
    /// The stripe's crossing gave the height (else it is the reference plane's).
    pub height: Vec<bool>,
    /// The backlit and light-box passes gave the translucency.
    pub translucency: Vec<bool>,
    /// Every fitted albedo within physics: ρd ≤ 1 and ρs ≤ 1 in each channel.
    pub physical: Vec<bool>,
}

/// Counts of a mask.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Count {
    /// Pixels where the mask holds.
    pub pixels: usize,
    /// Of the pixels it is counted among.
    pub of: usize,
}

/// The fit's own checks, as `quality.json` holds them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Quality {
    /// The frame's pixels.
    pub pixels: usize,
    /// Reflectance fitted, of the frame's pixels.
    pub fitted: Count,
    /// α determined, of the fitted pixels.
    pub roughness_determined: Count,
    /// Height from the stripe, of the fitted pixels.
    pub height_measured: Count,
    /// Fitted pixels with ρd > 1 in a channel.
    pub diffuse_over_one: usize,
    /// Fitted pixels with ρs > 1 in a channel.
    pub specular_over_one: usize,
    /// The residual (RMS relative to the trace's) over the fitted pixels: median, 95th
    /// percentile.
    pub residual: [f64; 2],
    /// The pose board's reprojection RMS, pixels.
    pub board_rms_px: f64,
    /// The specular strip: fitted ρs (median), the rig file's.
    pub specular_strip: [f64; 2],
    /// The camera the maps' pixels are: the intrinsics the fit used and the pose the board
    /// frame gave.
    pub camera: CameraUsed,
    /// Maps the session's passes did not measure (not written), with why.
    pub unmeasured: Vec<String>,
    /// Checks that failed, each with what to look at.
    pub warnings: Vec<String>,
}

/// The camera of a fit's pixel grid (`quality.json` `camera`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CameraUsed {
    /// Frame size, pixels.
    pub width: u32,
    pub height: u32,
    /// Pinhole intrinsics, pixels; pixel centres at whole coordinates, (0, 0) the top-left
    /// pixel's centre.
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Brown–Conrady distortion, OpenCV's order (k1, k2, p1, p2, k3).
    pub distortion: [f64; 5],
    /// World (mm; the sample plane z = 0, x along the gantry) to camera: Rodrigues rotation
    /// vector and translation, mm; a point X is seen at R·X + t.
    pub rvec: [f64; 3],
    pub tvec: [f64; 3],
}

/// The masks of `m`.
pub fn validity(m: &LlsMaps) -> Validity {
    let n = m.fitted.len();
    let fitted = |i: usize| m.fitted[i] && m.fit[i].residual.is_finite();
    Validity {
        reflectance: (0..n).map(fitted).collect(),
        roughness: (0..n).map(|i| fitted(i) && m.fit[i].leads()).collect(),
        height: m.height_measured.clone(),
        translucency: (0..n).map(|i| m.measured.translucency && m.translucency[i].is_finite()).collect(),
        physical: (0..n)
            .map(|i| !fitted(i) || m.fit[i].diffuse.iter().chain(&m.fit[i].specular).all(|&v| v <= 1.0))
            .collect(),
    }
}

/// `m`'s checks, from its masks `v` ([`validity`]).
pub fn assess(m: &LlsMaps, v: &Validity) -> Quality {
    let n = m.fitted.len();
    let fitted: Vec<usize> = (0..n).filter(|&i| v.reflectance[i]).collect();
    let among =
        |mask: &[bool]| Count { pixels: fitted.iter().filter(|&&i| mask[i]).count(), of: fitted.len() };
    let over = |f: &dyn Fn(&TraceFit) -> [f64; 3]| {
        fitted.iter().filter(|&&i| f(&m.fit[i]).iter().any(|&x| x > 1.0)).count()
    };
    let mut residuals: Vec<f64> = fitted.iter().map(|&i| m.fit[i].residual).collect();
    residuals.sort_by(f64::total_cmp);
    let quantile = |q: f64| {
        if residuals.is_empty() {
            f64::NAN
        } else {
            residuals[((residuals.len() - 1) as f64 * q).round() as usize]
        }
    };
    let mut q = Quality {
        pixels: n,
        fitted: Count { pixels: fitted.len(), of: n },
        roughness_determined: among(&v.roughness),
        height_measured: among(&v.height),
        diffuse_over_one: over(&|f| f.diffuse),
        specular_over_one: over(&|f| f.specular),
        residual: [quantile(0.5), quantile(0.95)],
        board_rms_px: m.registration_rms,
        specular_strip: [m.specular_strip.0, m.specular_strip.1],
        camera: CameraUsed {
            width: m.width,
            height: m.height,
            fx: m.intrinsics.fx,
            fy: m.intrinsics.fy,
            cx: m.intrinsics.cx,
            cy: m.intrinsics.cy,
            distortion: [m.intrinsics.k1, m.intrinsics.k2, m.intrinsics.p1, m.intrinsics.p2, m.intrinsics.k3],
            rvec: m.pose.rvec,
            tvec: m.pose.tvec,
        },
        unmeasured: Vec::new(),
        warnings: Vec::new(),
    };
    if !m.measured.height {
        q.unmeasured.push(
            "height: the session has no stripe pass, or its stripe crossed no pixel (add \"stripe\" to \
             plan.passes and a [[laser]] with role = \"stripe\", check [plan.fit] stripe); the fit took \
             the sample as the plane z = 0"
                .into(),
        );
    }
    if !m.measured.normals {
        q.unmeasured.push(
            "normal: neither the stripe pass nor the diagonal reflectance passes (reflectance±N) were \
             acquired; the fit took the sample as flat"
                .into(),
        );
    }
    if !m.measured.translucency {
        q.unmeasured.push("translucency: the session needs both the backlit and the light-box passes".into());
    }
    let pct = |c: Count| 100.0 * c.pixels as f64 / c.of.max(1) as f64;
    if q.board_rms_px > BOARD_RMS_WARN_PX {
        q.warnings.push(format!(
            "the pose board reprojects with {:.2} px RMS (above {BOARD_RMS_WARN_PX} px): check \
             [plan.fit] board (cols, rows, square_mm, origin_mm) and the camera's intrinsics",
            q.board_rms_px
        ));
    }
    let [strip, nominal] = q.specular_strip;
    if !(strip.is_finite() && ((strip / nominal) - 1.0).abs() <= STRIP_WARN) {
        q.warnings.push(format!(
            "the specular strip fits ρs {strip:.4} where [plan.fit] specular_strip.albedo says {nominal:.4}: \
             check the strip's x_mm/y_mm, its albedo and the tube's geometry ([plan.fit] light)"
        ));
    }
    if pct(q.fitted) < 100.0 * FITTED_WARN {
        q.warnings.push(format!(
            "only {:.1} % of the frame's pixels were fitted: check the camera's intrinsics and the \
             board's pose against the frames",
            pct(q.fitted)
        ));
    }
    if q.specular_over_one + q.diffuse_over_one > 0 {
        q.warnings.push(format!(
            "{} fitted pixels have ρs > 1 and {} have ρd > 1, outside physics (`valid.physical` is 0 there): the \
             scale from the diffuse strip, the tube's geometry or the exposures are off there",
            q.specular_over_one, q.diffuse_over_one
        ));
    }
    q
}

/// The checks as lines for a terminal or a report.
pub fn lines(q: &Quality) -> Vec<String> {
    let pct = |c: Count| 100.0 * c.pixels as f64 / c.of.max(1) as f64;
    let mut out = vec![
        format!(
            "fitted {} of {} pixels ({:.1} %); α determined in {:.1} % of them, height from the stripe in {:.1} %",
            q.fitted.pixels,
            q.pixels,
            pct(q.fitted),
            pct(q.roughness_determined),
            pct(q.height_measured)
        ),
        format!(
            "residual {:.3} median, {:.3} 95th percentile; board {:.3} px RMS; specular strip ρs {:.4} (rig file {:.4}); \
             {} pixels ρs > 1, {} ρd > 1",
            q.residual[0],
            q.residual[1],
            q.board_rms_px,
            q.specular_strip[0],
            q.specular_strip[1],
            q.specular_over_one,
            q.diffuse_over_one
        ),
    ];
    out.extend(q.unmeasured.iter().map(|u| format!("not measured: {u}")));
    out.extend(q.warnings.iter().map(|w| format!("warning: {w}")));
    out
}
