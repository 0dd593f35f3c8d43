//! `lightrig fit brrdf`: a bispectral session (coated spheres) and its Spectralon session
//! (the spectral calibration) through the thesis's processing (§4.4.2–4.5):
//!
//! 1. every step's exposure series merged through the camera's response ([`bracket`]);
//! 2. the spectral scaling `s(λo, λi)` from the Spectralon session's rows
//!    ([`Scaling`]: the rows sum to ρ/π with ρ = 0.99);
//! 3. the spheres found as discs in the frames lit nearest the camera; each pixel's normal,
//!    `(ωi, ωo)` from the light arm's angle β, its bispectral sample (every measured pair,
//!    divided by `cos θi`, scaled);
//! 4. the samples binned in `(θo, θi, φd)` (`[plan.fit] bins`, 32), empty bins diffused;
//! 5. the PCA-steered reconstruction measured: the components a same-angle reconstruction
//!    needs, and an angle left out of the PCA set reconstructed from the greedily chosen
//!    wavelength pairs, with standard and saturated PCA, PSNR in and out of the highlight.
//!
//! `[plan.fit]` keys (all optional): `spectralon` (the calibration session, relative to the
//! session directory; `--spectralon` on the command line wins), `detection = [[nm, W], …]`
//! (the camera filter × sensor's integral per band, from the manufacturers' curves; without
//! it every band counts as equally sensitive), `bins` (32), `pca_angles` (light-arm angles of
//! the dense PCA set; the first, middle and last by default), `select` (5 pairs),
//! `specular_deg` (20: pixels whose half vector lies within this of the normal form the
//! highlight region).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use lightrig_imaging::io::{linear_to_srgb, write_png, BispectralImage, BitDepth, Encoding, Image, Nm};
use lightrig_pipelines::brrdf::binning::{Binned, Binner};
use lightrig_pipelines::brrdf::colorimetry::{xyz_to_linear_srgb, Illuminant, Renderer};
use lightrig_pipelines::brrdf::geometry::{angles, find_discs, light_dir, Disc};
use lightrig_pipelines::brrdf::pca::{Pca, SaturatedPca};
use lightrig_pipelines::brrdf::scaling::{PairNm, Scaling};
use rayon::prelude::*;
use serde::Serialize;

use crate::fit::{bracket, fail, FitError};
use crate::rigfile::RigFile;
use crate::session::{trigger_events, Session};

/// Spectralon's reflectance (§4.4.2: "99 % quasi-Lambertian").
pub const SPECTRALON: f64 = 0.99;

/// Reconstructing an angle from the chosen pairs uses the components that leave less than this
/// share of the PCA set's energy (at most as many as pairs were chosen).
pub const KEEP_RESIDUAL: f64 = 1e-3;

/// Pixels seen or lit more grazing than this (`cos θ`, 81°) are left out: the rim mixes sphere
/// and background, and dividing by `cos θi` there multiplies the noise.
pub const MIN_COS: f64 = 0.15;

/// One plan step's merged exposure series.
#[derive(Debug, Clone)]
pub struct StepImage {
    pub step: u32,
    pub geometry: usize,
    /// The light arm's angle β, degrees.
    pub light_deg: f64,
    pub pair: PairNm,
    /// Camera value per second, NaN where every exposure clipped.
    pub rate: Vec<f32>,
}

/// A session's steps merged.
#[derive(Debug)]
pub struct Merged {
    pub dir: PathBuf,
    pub rig: RigFile,
    pub width: usize,
    pub height: usize,
    pub steps: Vec<StepImage>,
}

/// The fit's settings (`[plan.fit]`).
#[derive(Debug, Clone, PartialEq)]
pub struct FitSpec {
    pub spectralon: Option<PathBuf>,
    pub detection: Vec<(f64, f64)>,
    pub bins: usize,
    pub pca_angles: Option<Vec<f64>>,
    pub select: usize,
    pub specular_deg: f64,
    /// The emission grid's step, nm (`[plan.tunable_filter] step_nm`).
    pub step_nm: f64,
}

impl FitSpec {
    /// From `rig`'s `[plan.fit]` (every key optional).
    pub fn from_rig(rig: &RigFile) -> Result<FitSpec, FitError> {
        let fit = rig.plan.get("fit").and_then(|v| v.as_table());
        let get = |k: &str| fit.and_then(|f| f.get(k));
        let num = |v: &toml::Value| v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
        let bad = |k: &str, what: &str| fail(rig.error(&format!("plan.fit.{k}"), what).to_string());
        let detection = match get("detection") {
            None => Vec::new(),
            Some(v) => v
                .as_array()
                .ok_or_else(|| bad("detection", "must be a list of [nm, sensitivity] pairs"))?
                .iter()
                .map(|p| match p.as_array().map(|a| a.as_slice()) {
                    Some([a, b]) => num(a).zip(num(b)).filter(|(_, w)| *w > 0.0),
                    _ => None,
                })
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| bad("detection", "each entry is [nm, sensitivity > 0]"))?,
        };
        let bins = match get("bins") {
            None => 32,
            Some(v) => v.as_integer().filter(|b| [4, 8, 16, 32, 64, 128].contains(b)).ok_or_else(|| {
                bad("bins", "must be a power of two from 4 to 128 (32, or 64 for specular materials)")
            })? as usize,
        };
        let pca_angles = match get("pca_angles") {
            None => None,
            Some(v) => Some(
                v.as_array()
                    .and_then(|a| a.iter().map(num).collect::<Option<Vec<_>>>())
                    .filter(|a| !a.is_empty())
                    .ok_or_else(|| bad("pca_angles", "must be a list of light-arm angles, degrees"))?,
            ),
        };
        let select = match get("select") {
            None => 5,
            Some(v) => v
                .as_integer()
                .filter(|s| (1..=64).contains(s))
                .ok_or_else(|| bad("select", "must be 1 to 64"))? as usize,
        };
        let specular_deg = match get("specular_deg") {
            None => 20.0,
            Some(v) => num(v)
                .filter(|d| (0.0..90.0).contains(d))
                .ok_or_else(|| bad("specular_deg", "must be 0 to 90"))?,
        };
        let step_nm =
            rig.plan.get("tunable_filter").and_then(|t| t.get("step_nm")).and_then(num).unwrap_or(20.0);
        Ok(FitSpec {
            spectralon: get("spectralon").and_then(|v| v.as_str()).map(PathBuf::from),
            detection,
            bins,
            pca_angles,
            select,
            specular_deg,
            step_nm,
        })
    }

    /// The detection branch's band integral at `nm`: interpolated in the table, 1 without one.
    pub fn band_integral(&self, nm: f64) -> f64 {
        let t = &self.detection;
        match t.iter().position(|&(x, _)| x >= nm) {
            None => t.last().map_or(1.0, |p| p.1),
            Some(0) => t[0].1,
            Some(i) => {
                let ((a, wa), (b, wb)) = (t[i - 1], t[i]);
                wa + (nm - a) / (b - a) * (wb - wa)
            }
        }
    }
}

/// Reads session `dir` and merges every step's exposure series (on all cores), `progress`
/// told `(done, total)`.
pub fn read(dir: &Path, progress: &(dyn Fn(u64, u64) + Sync)) -> Result<Merged, FitError> {
    let (session, _) = Session::read(dir).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let manifest = session.manifest().clone();
    let rig = crate::fit::session_rig(&manifest.rig, dir)?;
    if rig.method != crate::rigfile::Method::Bispectral {
        return Err(fail(format!("{}: a {:?} session, not a bispectral one", dir.display(), rig.method)));
    }
    let arm = rig
        .stepper_named("light-arm")
        .ok_or_else(|| fail(format!("{}: the rig file has no stepper named `light-arm`", dir.display())))?;
    let camera = session.pipeline_camera(None).map_err(fail)?;
    let response = crate::response::for_session(&rig, dir, camera).map_err(fail)?;
    let triggers = trigger_events(dir).map_err(|e| fail(e.to_string()))?;
    let tick_hz = f64::from(manifest.device.tick_hz);
    let choice = crate::steer::Choice::load(dir).map_err(fail)?;
    let mut jobs = Vec::new();
    for s in &manifest.plan.steps {
        let meta = &s.extra["meta"];
        // A PCA-steered step's pair is the session's choice (made when it was reached); before
        // the choice, it has none and is left out.
        let pair =
            match (meta["excitation_nm"].as_u64(), meta["emission_nm"].as_u64(), meta["chosen"].as_u64()) {
                (Some(ex), Some(em), _) => (ex as u16, em as u16),
                (_, _, Some(j)) => match &choice {
                    Some(c) => {
                        let [ex, em] = *c.pairs.get(j as usize).ok_or_else(|| {
                            fail(format!(
                                "{}: step {} takes chosen pair {j} but {} holds {}",
                                dir.display(),
                                s.id,
                                crate::steer::CHOICE_FILE,
                                c.pairs.len()
                            ))
                        })?;
                        (ex, em)
                    }
                    None => continue,
                },
                _ => continue,
            };
        let frames = session.camera_frames_of(s.id, camera);
        if frames.is_empty() {
            return Err(fail(format!(
                "{}: step {} ({}) has no frames: finish the session with `lightrig resume`",
                dir.display(),
                s.id,
                s.name
            )));
        }
        let mut images = Vec::new();
        for f in &frames {
            let t = triggers.get(&(f.sequence, f.item)).ok_or_else(|| {
                fail(format!("{}: frame {} has no trigger record in the journal", dir.display(), f.file))
            })?;
            images.push((dir.join(&f.file), f64::from(t.width) / tick_hz));
        }
        let light = meta["light"].as_i64().unwrap_or(0);
        let light_deg = arm.units(light).unwrap_or(0.0);
        jobs.push((s.id, meta["geometry"].as_u64().unwrap_or(0) as usize, light_deg, pair, images));
    }
    if jobs.is_empty() {
        return Err(fail(format!(
            "{}: no bispectral steps (excitation_nm, emission_nm) in the plan",
            dir.display()
        )));
    }
    let total = jobs.len() as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let merged: Vec<((u32, u32), StepImage)> = jobs
        .into_par_iter()
        .map(|(step, geometry, light_deg, pair, images)| {
            let (size, rate) = bracket::merge(&images, None, 1, &response)?;
            // Pixels clipped in every exposure have no value: a few (a highlight's core) are
            // left out of the fit, more mean the series is too long.
            let clipped = rate.iter().filter(|v| v.is_nan()).count();
            if clipped * 100 > rate.len() {
                return Err(fail(format!(
                    "{}: step {step} ({}→{} nm): {clipped} of {} pixels clipped in every exposure of the \
                     series: add a shorter exposure to [plan] exposures_us",
                    dir.display(),
                    pair.0,
                    pair.1,
                    rate.len()
                )));
            }
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, total);
            Ok((size, StepImage { step, geometry, light_deg, pair, rate }))
        })
        .collect::<Result<_, FitError>>()?;
    let size = merged[0].0;
    if let Some((s, m)) = merged.iter().find(|(s, _)| *s != size) {
        return Err(fail(format!(
            "{}: step {} has {}×{} frames where the first has {}×{}",
            dir.display(),
            m.step,
            s.0,
            s.1,
            size.0,
            size.1
        )));
    }
    Ok(Merged {
        dir: dir.to_path_buf(),
        rig,
        width: size.0 as usize,
        height: size.1 as usize,
        steps: merged.into_iter().map(|m| m.1).collect(),
    })
}

/// Spectralon's value per pair: the mean rate over the middle quarter of the frame per unit
/// `cos θi`, averaged over the geometries with the light within 60° of the target's normal.
pub fn spectralon_rows(m: &Merged) -> Result<Vec<(PairNm, f64)>, FitError> {
    let (w, h) = (m.width, m.height);
    let mut acc: BTreeMap<PairNm, (f64, u32)> = BTreeMap::new();
    for s in m.steps.iter().filter(|s| s.light_deg.abs() < 60.0) {
        let (mut sum, mut n) = (0.0, 0u32);
        for y in h / 4..h - h / 4 {
            for x in w / 4..w - w / 4 {
                let v = s.rate[y * w + x];
                if !v.is_nan() {
                    sum += f64::from(v);
                    n += 1;
                }
            }
        }
        if n == 0 {
            return Err(fail(format!(
                "{}: step {} ({}→{} nm): every exposure of the series is clipped on the Spectralon \
                 target: add a shorter exposure to `exposures_us`",
                m.dir.display(),
                s.step,
                s.pair.0,
                s.pair.1
            )));
        }
        let e = acc.entry(s.pair).or_default();
        e.0 += sum / f64::from(n) / s.light_deg.to_radians().cos();
        e.1 += 1;
    }
    if acc.is_empty() {
        return Err(fail(format!(
            "{}: no geometry lights the Spectralon target within 60° of its normal",
            m.dir.display()
        )));
    }
    Ok(acc.into_iter().map(|(p, (s, n))| (p, s / f64::from(n))).collect())
}

/// One pixel's bispectral sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    pub geometry: usize,
    pub light_deg: f64,
    pub x: u32,
    pub y: u32,
    /// Unit normal.
    pub normal: [f64; 3],
    /// `(θo, θi, φd)`, radians.
    pub angles: (f64, f64, f64),
    /// Angle between the normal and the half vector, degrees.
    pub half_deg: f64,
    /// Scaled BRRDF per pair (the fit's `pairs`), sr⁻¹.
    pub values: Vec<f64>,
    /// Reconstructed through the PCA from the chosen pairs (a PCA-steered plan's other angles).
    pub reconstructed: bool,
}

/// The angle transfer (thesis figure 4.12): a geometry left out of the PCA set, its samples
/// reconstructed from their values at the chosen pairs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Transfer {
    /// The held-out geometry's light angle, degrees.
    pub held_out_deg: f64,
    /// Pairs chosen (standard PCA, saturated PCA).
    pub chosen: Vec<PairNm>,
    pub chosen_saturated: Vec<PairNm>,
    /// `cond(R)` of each choice.
    pub cond: f64,
    pub cond_saturated: f64,
    /// PSNR, dB: `[non-specular, specular]`, standard and saturated PCA.
    pub psnr: [f64; 2],
    pub psnr_saturated: [f64; 2],
    /// Samples in each region.
    pub pixels: [usize; 2],
}

/// A same-angle reconstruction's cost (thesis figure 4.7): how many components bring the
/// residual energy under 1 % and 0.1 %.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SameAngle {
    pub light_deg: f64,
    /// Observed bins at this angle (the samples of its PCA).
    pub bins: usize,
    pub components_1pc: usize,
    pub components_01pc: usize,
}

/// One sphere's fit.
#[derive(Debug, Clone)]
pub struct SphereFit {
    /// "top" or "bottom".
    pub name: String,
    pub disc: Disc,
    pub samples: Vec<Sample>,
    pub binned: Binned,
    /// Same-angle PCA, one per PCA angle: each angle's samples binned (the BRRDF as stored)
    /// and decomposed on their own.
    pub same_angle: Vec<SameAngle>,
    pub transfer: Option<Transfer>,
    /// Samples reconstructed from the chosen pairs.
    pub reconstructed: usize,
}

/// The whole fit.
#[derive(Debug, Clone)]
pub struct BrrdfFit {
    pub pairs: Vec<PairNm>,
    pub scaling: Scaling,
    pub spec: FitSpec,
    pub spheres: Vec<SphereFit>,
    /// The light angles of the PCA set, degrees.
    pub pca_angles: Vec<f64>,
    /// What the fit left out, and why.
    pub notes: Vec<String>,
    /// The frames' size, pixels.
    pub size: (u32, u32),
}

/// Fits session `dir` with the Spectralon session `spectralon` (else `[plan.fit] spectralon`).
pub fn fit_session(
    dir: &Path,
    spectralon: Option<&Path>,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<BrrdfFit, FitError> {
    let m = read(dir, progress)?;
    let spec = FitSpec::from_rig(&m.rig)?;
    let cal_dir = match (spectralon, &spec.spectralon) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some(p)) => dir.join(p),
        (None, None) => {
            return Err(fail(format!(
                "{}: no Spectralon session to scale by: give --spectralon DIR (a session of the same rig \
                 with `plan.sample=\"spectralon\"`) or [plan.fit] spectralon",
                dir.display()
            )))
        }
    };
    let (scaling, dropped) = scaling_from(&cal_dir, &spec)?;
    let mut m = m;
    let left_out = |ex: u16| m.steps.iter().filter(|s| s.pair.0 == ex).count();
    let counts: Vec<(u16, usize)> = dropped.iter().map(|&ex| (ex, left_out(ex))).collect();
    m.steps.retain(|s| !dropped.contains(&s.pair.0));
    let mut fit = fit_merged(&m, scaling, spec)?;
    for (ex, steps) in counts {
        fit.notes.push(format!(
            "excitation {ex} nm left out ({steps} steps): the Spectralon session has no {ex}→{ex} nm pair to scale \
             it by (its diagonal lies outside the camera filter's range)"
        ));
    }
    Ok(fit)
}

/// The spectral scaling from the Spectralon session in `cal_dir`, and the excitations it cannot
/// scale (their diagonal lies outside the camera filter's range: their pairs are left out).
pub fn scaling_from(cal_dir: &Path, spec: &FitSpec) -> Result<(Scaling, Vec<u16>), FitError> {
    if !cal_dir.join("manifest.json").exists() {
        return Err(fail(format!(
            "{}: the Spectralon session is missing (no manifest.json): acquire it with \
             `lightrig acquire RIG --set plan.sample='\"spectralon\"'`",
            cal_dir.display()
        )));
    }
    let cal = read(cal_dir, &|_, _| {})?;
    if cal.rig.plan.get("sample").and_then(|v| v.as_str()) != Some("spectralon") {
        return Err(fail(format!(
            "{}: not a Spectralon session (its rig file's [plan] sample is not \"spectralon\")",
            cal_dir.display()
        )));
    }
    let mut rows = spectralon_rows(&cal)?;
    let mut dropped = Vec::new();
    let excitations: std::collections::BTreeSet<u16> = rows.iter().map(|r| r.0 .0).collect();
    for ex in excitations {
        if !rows.iter().any(|r| r.0 == (ex, ex)) {
            dropped.push(ex);
        }
    }
    rows.retain(|r| !dropped.contains(&r.0 .0));
    let scaling = Scaling::new(&rows, |nm| spec.band_integral(f64::from(nm)), spec.step_nm, SPECTRALON)
        .map_err(|e| fail(format!("{}: {e}", cal_dir.display())))?;
    Ok((scaling, dropped))
}

/// The PCA-steered plan's choice for the session in `dir` (its dense steps done), scaled by the
/// Spectralon session in `cal_dir`: the saturated PCA of every full sample of both spheres,
/// `select` pairs chosen greedily (thesis §4.5).
pub fn choose(dir: &Path, cal_dir: &Path, select: usize) -> Result<crate::steer::Choice, FitError> {
    let mut m = read(dir, &|_, _| {})?;
    let mut spec = FitSpec::from_rig(&m.rig)?;
    let (scaling, dropped) = scaling_from(cal_dir, &spec)?;
    m.steps.retain(|s| !dropped.contains(&s.pair.0));
    spec.select = select;
    let fit = fit_merged(&m, scaling, spec)?;
    let set: Vec<Vec<f64>> = fit.spheres.iter().flat_map(|s| &s.samples).map(|s| s.values.clone()).collect();
    if set.len() < select {
        return Err(fail(format!(
            "{}: {} samples on the spheres, too few to choose {select} pairs",
            dir.display(),
            set.len()
        )));
    }
    let sat = SaturatedPca::new(&set, select, saturation_scale(&set));
    let chosen = sat.pca.select_pairs(select);
    let mut from: Vec<f64> = fit.spheres.iter().flat_map(|s| &s.samples).map(|s| s.light_deg).collect();
    from.sort_by(f64::total_cmp);
    from.dedup();
    Ok(crate::steer::Choice {
        pairs: chosen.iter().map(|&j| [fit.pairs[j].0, fit.pairs[j].1]).collect(),
        from_light_deg: from,
        cond: sat.pca.condition(&chosen),
    })
}

/// Where the saturation bends: the median of the samples' largest entries (their diffuse level).
fn saturation_scale(set: &[Vec<f64>]) -> f64 {
    let mut peaks: Vec<f64> = set.iter().map(|s| s.iter().copied().fold(0.0, f64::max)).collect();
    peaks.sort_by(f64::total_cmp);
    peaks.get(peaks.len() / 2).copied().unwrap_or(1.0).max(1e-9)
}

/// The fit of merged sphere steps with a spectral scaling.
pub fn fit_merged(m: &Merged, scaling: Scaling, spec: FitSpec) -> Result<BrrdfFit, FitError> {
    let mut pairs: Vec<PairNm> = m.steps.iter().map(|s| s.pair).collect();
    pairs.sort_unstable();
    pairs.dedup();
    for &(ex, _) in &pairs {
        if !scaling.diagonal.contains_key(&ex) {
            return Err(fail(format!(
                "{}: excitation {ex} nm was not measured in the Spectralon session: acquire it with the same \
                 excitations",
                m.dir.display()
            )));
        }
    }
    let mut geometries: Vec<(usize, f64)> = m.steps.iter().map(|s| (s.geometry, s.light_deg)).collect();
    geometries.sort_by_key(|g| g.0);
    geometries.dedup_by_key(|g| g.0);
    // The spheres: discs in the diagonal frames of the geometry lit nearest the camera.
    let (g0, _) = *geometries
        .iter()
        .min_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .ok_or_else(|| fail("no geometries"))?;
    let (w, h) = (m.width, m.height);
    let mut lit = vec![0.0f32; w * h];
    for s in m.steps.iter().filter(|s| s.geometry == g0 && s.pair.0 == s.pair.1) {
        for (l, v) in lit.iter_mut().zip(&s.rate) {
            if v.is_finite() {
                *l += v;
            }
        }
    }
    let mut sorted: Vec<f32> = lit.iter().copied().filter(|v| *v > 0.0).collect();
    sorted.sort_by(f32::total_cmp);
    let top = sorted.get(sorted.len() * 99 / 100).copied().unwrap_or(0.0);
    let discs = find_discs(&lit, w, h, 0.03 * top, 30);
    if discs.len() != 2 {
        return Err(fail(format!(
            "{}: {} bright disc(s) in the diagonal frames of geometry {g0} where two spheres were expected: \
             check the framing and that a geometry lights the spheres from near the camera",
            m.dir.display(),
            discs.len()
        )));
    }
    // Steps by (geometry, pair).
    let index: BTreeMap<(usize, PairNm), &StepImage> =
        m.steps.iter().map(|s| ((s.geometry, s.pair), s)).collect();
    let mut spheres = Vec::new();
    // The PCA set: each angle asked for, as the geometry acquired nearest it (the arm's
    // steps round the angle); one not acquired is an error naming it.
    let pca_angles = match &spec.pca_angles {
        Some(asked) => asked
            .iter()
            .map(|&a| {
                geometries.iter().map(|g| g.1).find(|g| (g - a).abs() < 0.05).ok_or_else(|| {
                    fail(format!(
                        "{}: [plan.fit] pca_angles: {a}° is not among the light angles acquired ({}): \
                         list angles of [plan.gonio] light_angles",
                        m.dir.display(),
                        geometries.iter().map(|g| format!("{:.1}°", g.1)).collect::<Vec<_>>().join(", ")
                    ))
                })
            })
            .collect::<Result<Vec<f64>, FitError>>()?,
        None => {
            let n = geometries.len();
            let mut v = vec![geometries[0].1, geometries[n / 2].1, geometries[n - 1].1];
            v.dedup();
            v
        }
    };
    for (d, disc) in discs.iter().enumerate() {
        let mut samples = Vec::new();
        let mut sparse = Vec::new();
        for &(g, light_deg) in &geometries {
            // The pairs this geometry took: all of them, or (a PCA-steered plan's other angles)
            // the chosen few, reconstructed below.
            let taken: Vec<usize> =
                (0..pairs.len()).filter(|&j| index.contains_key(&(g, pairs[j]))).collect();
            let steps: Vec<&StepImage> = taken.iter().map(|&j| index[&(g, pairs[j])]).collect();
            let got = pixel_samples(disc, (w, h), (g, light_deg), (&taken, &pairs), &steps, &scaling)?;
            if taken.len() == pairs.len() {
                samples.extend(got);
            } else {
                sparse.push((taken, got));
            }
        }
        // Sparse geometries: each sample whole again through the saturated PCA of the PCA set.
        let set: Vec<Vec<f64>> =
            samples.iter().filter(|s| pca_angles.contains(&s.light_deg)).map(|s| s.values.clone()).collect();
        let mut reconstructed = 0;
        if !sparse.is_empty() {
            let count = sparse.iter().map(|(t, _)| t.len()).max().unwrap_or(0);
            if set.len() < count {
                return Err(fail(format!(
                    "{}: the {} sphere has {} samples at the PCA angles, too few to reconstruct from",
                    m.dir.display(),
                    ["top", "bottom"][d],
                    set.len()
                )));
            }
            let mut sat = SaturatedPca::new(&set, count, saturation_scale(&set));
            // Only the components that hold energy: a sphere whose samples are nearly of rank one
            // (a non-fluorescent paint) would otherwise fit the chosen pairs' noise with the rest.
            let keep = (1..=count).find(|&n| sat.pca.residual(n) < KEEP_RESIDUAL).unwrap_or(count);
            sat.pca.basis.truncate(keep);
            for (taken, got) in sparse {
                for mut s in got {
                    s.values = sat.reconstruct(&taken, &s.values);
                    s.reconstructed = true;
                    samples.push(s);
                    reconstructed += 1;
                }
            }
        }
        let mut binner = Binner::new(spec.bins, pairs.len());
        for s in &samples {
            binner.add(s.angles.0, s.angles.1, s.angles.2, &s.values);
        }
        let binned = binner.finish(2 * spec.bins);
        let in_set = |s: &Sample| pca_angles.contains(&s.light_deg);
        // Same angle: each PCA angle's samples binned, decomposed on their own.
        let mut same_angle = Vec::new();
        for &a in &pca_angles {
            let mut b = Binner::new(spec.bins, pairs.len());
            for s in samples.iter().filter(|s| s.light_deg == a) {
                b.add(s.angles.0, s.angles.1, s.angles.2, &s.values);
            }
            let binned = b.finish(0);
            let k = pairs.len();
            let rows: Vec<Vec<f64>> = (0..binned.count.len())
                .filter(|&i| binned.count[i] > 0)
                .map(|i| binned.values[i * k..(i + 1) * k].iter().map(|&v| f64::from(v)).collect())
                .collect();
            if rows.len() < 2 {
                continue;
            }
            let pca = Pca::new(&rows, 0);
            let need = |limit: f64| (0..=k).find(|&n| pca.residual(n) < limit).unwrap_or(k);
            same_angle.push(SameAngle {
                light_deg: a,
                bins: rows.len(),
                components_1pc: need(0.01),
                components_01pc: need(0.001),
            });
        }
        let transfer = transfer(&samples, &pairs, &pca_angles, &spec, &in_set);
        spheres.push(SphereFit {
            name: ["top", "bottom"][d].to_string(),
            disc: *disc,
            samples,
            binned,
            same_angle,
            transfer,
            reconstructed,
        });
    }
    Ok(BrrdfFit {
        pairs,
        scaling,
        spec,
        spheres,
        pca_angles,
        notes: Vec::new(),
        size: (m.width as u32, m.height as u32),
    })
}

/// The samples of one sphere at one geometry: every pixel inside the disc lit and seen within
/// [`MIN_COS`], its values at the pairs `taken` (indices into `pairs`, read from `steps`) over
/// `cos θi`, scaled.
fn pixel_samples(
    disc: &Disc,
    (w, h): (usize, usize),
    (g, light_deg): (usize, f64),
    (taken, pairs): (&[usize], &[PairNm]),
    steps: &[&StepImage],
    scaling: &Scaling,
) -> Result<Vec<Sample>, FitError> {
    let wi = light_dir(light_deg);
    let wo = [0.0, 0.0, 1.0];
    let sub: Vec<PairNm> = taken.iter().map(|&j| pairs[j]).collect();
    let mut raw = vec![0.0; taken.len()];
    let mut out = Vec::new();
    for y in (disc.cy - disc.r).max(0.0) as usize..((disc.cy + disc.r).ceil() as usize).min(h) {
        for x in (disc.cx - disc.r).max(0.0) as usize..((disc.cx + disc.r).ceil() as usize).min(w) {
            let Some(n) = disc.normal(x, y, 0.95) else { continue };
            let Some(a) = angles(n, wi, wo) else { continue };
            let ci = a.1.cos();
            if ci < MIN_COS || a.0.cos() < MIN_COS {
                continue;
            }
            let mut ok = true;
            for (r, s) in raw.iter_mut().zip(steps) {
                let v = s.rate[y * w + x];
                ok &= v.is_finite();
                *r = f64::from(v) / ci;
            }
            if !ok {
                continue;
            }
            let mut values = vec![0.0; taken.len()];
            scaling.apply(&sub, &raw, &mut values).map_err(|e| fail(e.to_string()))?;
            let hv = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
            let hl = (hv[0] * hv[0] + hv[1] * hv[1] + hv[2] * hv[2]).sqrt();
            let half_deg =
                ((n[0] * hv[0] + n[1] * hv[1] + n[2] * hv[2]) / hl).clamp(-1.0, 1.0).acos().to_degrees();
            out.push(Sample {
                geometry: g,
                light_deg,
                x: x as u32,
                y: y as u32,
                normal: n,
                angles: a,
                half_deg,
                values,
                reconstructed: false,
            });
        }
    }
    Ok(out)
}

/// PSNR of `got` against `want` over samples, dB: the peak is `want`'s largest value.
fn psnr(want: &[&[f64]], got: &[Vec<f64>]) -> f64 {
    let (mut se, mut n, mut peak) = (0.0, 0usize, 0.0f64);
    for (w, g) in want.iter().zip(got) {
        for (a, b) in w.iter().zip(g) {
            se += (a - b) * (a - b);
            n += 1;
            peak = peak.max(a.abs());
        }
    }
    if n == 0 || se == 0.0 {
        return f64::INFINITY;
    }
    10.0 * (peak * peak / (se / n as f64)).log10()
}

fn transfer(
    samples: &[Sample],
    pairs: &[PairNm],
    pca_angles: &[f64],
    spec: &FitSpec,
    in_set: &dyn Fn(&Sample) -> bool,
) -> Option<Transfer> {
    let set: Vec<Vec<f64>> = samples.iter().filter(|s| in_set(s)).map(|s| s.values.clone()).collect();
    // Held out: the geometry outside the set nearest the middle of the first two PCA angles.
    let mid = match pca_angles {
        [a, b, ..] => (a + b) / 2.0,
        [a] => *a,
        [] => return None,
    };
    let held = samples
        .iter()
        .filter(|s| !in_set(s) && !s.reconstructed)
        .map(|s| s.light_deg)
        .min_by(|a, b| (a - mid).abs().total_cmp(&(b - mid).abs()))?;
    let out: Vec<&Sample> = samples.iter().filter(|s| s.light_deg == held && !s.reconstructed).collect();
    if set.is_empty() || out.is_empty() {
        return None;
    }
    let count = spec.select.min(pairs.len());
    let plain = Pca::new(&set, count);
    let chosen = plain.select_pairs(count);
    // The saturation bends at the samples' typical largest value (their diffuse level).
    let sat = SaturatedPca::new(&set, count, saturation_scale(&set));
    let chosen_sat = sat.pca.select_pairs(count);
    let mut result = Transfer {
        held_out_deg: held,
        chosen: chosen.iter().map(|&j| pairs[j]).collect(),
        chosen_saturated: chosen_sat.iter().map(|&j| pairs[j]).collect(),
        cond: plain.condition(&chosen),
        cond_saturated: sat.pca.condition(&chosen_sat),
        psnr: [0.0; 2],
        psnr_saturated: [0.0; 2],
        pixels: [0; 2],
    };
    for region in 0..2 {
        let members: Vec<&Sample> =
            out.iter().copied().filter(|s| (s.half_deg <= spec.specular_deg) == (region == 1)).collect();
        result.pixels[region] = members.len();
        let want: Vec<&[f64]> = members.iter().map(|s| s.values.as_slice()).collect();
        let rec = |pick: &[usize], f: &dyn Fn(&[f64]) -> Vec<f64>| -> Vec<Vec<f64>> {
            members.iter().map(|s| f(&pick.iter().map(|&j| s.values[j]).collect::<Vec<_>>())).collect()
        };
        result.psnr[region] = psnr(&want, &rec(&chosen, &|m| plain.reconstruct(&chosen, m)));
        result.psnr_saturated[region] = psnr(&want, &rec(&chosen_sat, &|m| sat.reconstruct(&chosen_sat, m)));
    }
    Some(result)
}

/// The binned BRRDF's header (`brrdf-<sphere>.json`); the values are in `brrdf-<sphere>.f32`.
#[derive(Debug, Serialize)]
struct BinnedHeader<'a> {
    format: &'static str,
    layout: &'static str,
    bins: usize,
    domain: [&'static str; 3],
    pairs: &'a [PairNm],
    observed_bins: usize,
    values: String,
}

/// The spheres at light angle `light_deg` as a bispectral image in the layout of Fichet et al.
/// (2021): each pixel's scaled entries times π (a reflectance factor: Spectralon's diagonal
/// reads 0.99), zero off the spheres.
pub fn spectral_image(fit: &BrrdfFit, light_deg: f64) -> BispectralImage {
    let (w, h) = fit.size;
    let n = w as usize * h as usize;
    let mut img = BispectralImage::new(w, h);
    let pi = std::f64::consts::PI;
    for (j, &(ex, em)) in fit.pairs.iter().enumerate() {
        let mut plane = vec![0.0f32; n];
        for s in fit.spheres.iter().flat_map(|s| &s.samples).filter(|s| s.light_deg == light_deg) {
            plane[s.y as usize * w as usize + s.x as usize] = (s.values[j] * pi) as f32;
        }
        if ex == em {
            img.diagonal.insert(Nm(f64::from(ex)), plane);
        } else {
            img.reradiation.insert((Nm(f64::from(ex)), Nm(f64::from(em))), plane);
        }
    }
    img
}

/// Sphere `sphere`'s reradiation matrix in the layout of Fichet et al. (2021), for spectral
/// renderers and colour-science: one pixel per PCA angle (column `k` at light angle
/// `pca_angles[k]`), each channel (`T.<λ>nm` on the diagonal, `T.<λi>nm.<λo>nm` off it) the
/// median over the sphere's samples at that angle of the entry times π, a reflectance factor
/// as in [`spectral_image`] (the median keeps the specular highlight's pixels out).
pub fn sphere_matrix(fit: &BrrdfFit, sphere: usize) -> BispectralImage {
    let angles = &fit.pca_angles;
    let mut img = BispectralImage::new(angles.len() as u32, 1);
    let Some(s) = fit.spheres.get(sphere) else { return img };
    let pi = std::f64::consts::PI;
    for (j, &(ex, em)) in fit.pairs.iter().enumerate() {
        let row: Vec<f32> = angles
            .iter()
            .map(|&a| {
                let mut v: Vec<f64> =
                    s.samples.iter().filter(|x| x.light_deg == a).map(|x| x.values[j]).collect();
                v.sort_by(f64::total_cmp);
                if v.is_empty() {
                    return 0.0;
                }
                let m = v.len() / 2;
                let median = if v.len() % 2 == 1 { v[m] } else { 0.5 * (v[m - 1] + v[m]) };
                (median * pi) as f32
            })
            .collect();
        if ex == em {
            img.diagonal.insert(Nm(f64::from(ex)), row);
        } else {
            img.reradiation.insert((Nm(f64::from(ex)), Nm(f64::from(em))), row);
        }
    }
    img
}

/// The spheres at light angle `light_deg` rendered under `light` with the CIE 1931 observer:
/// linear sRGB per pixel (each sample's reflected radiance at its `cos θi`), zero off the
/// spheres.
pub fn render(fit: &BrrdfFit, light_deg: f64, light: Illuminant) -> Vec<[f64; 3]> {
    let (w, h) = fit.size;
    let pairs: Vec<(f64, f64)> = fit.pairs.iter().map(|&(i, o)| (f64::from(i), f64::from(o))).collect();
    let r = Renderer::new(&pairs, light);
    let mut out = vec![[0.0; 3]; w as usize * h as usize];
    for s in fit.spheres.iter().flat_map(|s| &s.samples).filter(|s| s.light_deg == light_deg) {
        let xyz = r.xyz(&s.values).map(|v| v * s.angles.1.cos());
        out[s.y as usize * w as usize + s.x as usize] = xyz_to_linear_srgb(xyz);
    }
    out
}

/// The illuminants of the renderings: daylight, tungsten and the wheel's violet LED.
pub const RENDER_ILLUMINANTS: [Illuminant; 3] =
    [Illuminant::D65, Illuminant::A, Illuminant::Led { centre: 400.0, fwhm: 15.0 }];

/// Writes the fit's files into `out`: per sphere the binned BRRDF (`brrdf-<sphere>.json` and
/// `.f32`) and the PCA choice (`pca-<sphere>.json`), the spectral scaling (`scaling.json`),
/// per sphere its reradiation matrix (`reradiation-<sphere>.exr`, [`sphere_matrix`]), per PCA
/// angle the bispectral image (`spectral-<angle>deg.exr`), and the first PCA angle
/// rendered in sRGB under D65, illuminant A and a 400 nm LED (`render-<light>.png`).
pub fn write_outputs(fit: &BrrdfFit, out: &Path) -> Result<Vec<PathBuf>, FitError> {
    std::fs::create_dir_all(out).map_err(|e| fail(format!("{}: {e}", out.display())))?;
    let write = |p: PathBuf, bytes: Vec<u8>| -> Result<PathBuf, FitError> {
        std::fs::write(&p, bytes).map_err(|e| fail(format!("{}: {e}", p.display())))?;
        Ok(p)
    };
    let mut files = Vec::new();
    for s in &fit.spheres {
        let raw: Vec<u8> = s.binned.values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let values = format!("brrdf-{}.f32", s.name);
        files.push(write(out.join(&values), raw)?);
        let header = BinnedHeader {
            format: "lightrig-brrdf 1",
            layout:
                "f32 little-endian, [θo][θi][φd][pair], sr⁻¹; bin centres at (k + 0.5)/bins of the domain",
            bins: s.binned.n,
            domain: ["θo 0..π/2", "θi 0..π/2", "φd 0..π"],
            pairs: &fit.pairs,
            observed_bins: s.binned.observed(),
            values,
        };
        let json = serde_json::to_string_pretty(&header).map_err(|e| fail(e.to_string()))? + "\n";
        files.push(write(out.join(format!("brrdf-{}.json", s.name)), json.into_bytes())?);
        let pca = serde_json::json!({
            "sphere": s.name,
            "pca_angles_deg": fit.pca_angles,
            "same_angle": s.same_angle,
            "transfer": s.transfer,
        });
        let json = serde_json::to_string_pretty(&pca).map_err(|e| fail(e.to_string()))? + "\n";
        files.push(write(out.join(format!("pca-{}.json", s.name)), json.into_bytes())?);
    }
    let scaling = serde_json::json!({
        "reflectance": fit.scaling.reflectance,
        "diagonal": fit.scaling.diagonal,
        "row": fit.scaling.row,
        "detection": fit.scaling.detection,
        "leak": fit.scaling.leak.iter().map(|(k, v)| (format!("{}-{}", k.0, k.1), v)).collect::<BTreeMap<_, _>>(),
    });
    let json = serde_json::to_string_pretty(&scaling).map_err(|e| fail(e.to_string()))? + "\n";
    files.push(write(out.join("scaling.json"), json.into_bytes())?);
    for (k, s) in fit.spheres.iter().enumerate() {
        let p = out.join(format!("reradiation-{}.exr", s.name));
        sphere_matrix(fit, k).write(&p).map_err(|e| fail(e.to_string()))?;
        files.push(p);
    }
    for &a in &fit.pca_angles {
        let p = out.join(format!("spectral-{:.0}deg.exr", a));
        spectral_image(fit, a).write(&p).map_err(|e| fail(e.to_string()))?;
        files.push(p);
    }
    if let Some(&a) = fit.pca_angles.first() {
        for light in RENDER_ILLUMINANTS {
            let rgb = render(fit, a, light);
            let data: Vec<f32> =
                rgb.iter().flat_map(|p| p.map(|v| linear_to_srgb(v.clamp(0.0, 1.0) as f32))).collect();
            let img =
                Image { width: fit.size.0, height: fit.size.1, channels: 3, data, encoding: Encoding::Srgb };
            let p = out.join(format!("render-{}.png", light.name()));
            write_png(&p, &img, BitDepth::Eight).map_err(|e| fail(e.to_string()))?;
            files.push(p);
        }
    }
    Ok(files)
}
