//! Bispectral BRRDF (Hullin et al. 2010): a turntable gonioreflectometer measures reflected
//! radiance for pairs of (illumination, observation) wavelengths, with tunable filters on the
//! light and the camera and an LED filter wheel for the near-UV; each measurement is an HDR
//! exposure series.
//!
//! One step per (geometry, wavelength pair). The tunable filters are host instruments: the
//! engine sets them from the step's `meta` before running the step; the device sequence moves
//! the sample turntable and the light arm, turns the filter wheel to the pair's slot and takes
//! the exposure series. Full mode takes every pair of the grid with excitation ≤ emission (the
//! bispectral matrix is zero above the diagonal: no anti-Stokes emission); sparse mode takes
//! the pairs the PCA step of the pipeline chose.

use lightrig_protocol::sequence::{Action, AxisRef, WaitFor};
use serde_json::json;

use std::path::Path;
use std::sync::Arc;

use super::{Plan, PlanError, Step};

/// An (illumination, observation) wavelength pair, nm, and the filter-wheel slot that lights it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pair {
    /// Illumination wavelength, nm.
    pub excitation: u16,
    /// Observed wavelength, nm.
    pub emission: u16,
    /// Filter-wheel slot for the light path (an LED slot for the near-UV, "open" otherwise).
    pub slot: u8,
}

/// Everything the bispectral planner needs, in device units.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BispectralParams {
    /// Sample turntable axis.
    pub sample_axis: u8,
    /// Light arm axis.
    pub light_axis: u8,
    /// (sample, light) positions, steps.
    pub geometries: Vec<(i32, i32)>,
    /// Filter wheel.
    pub wheel: u8,
    /// Wavelength pairs, in capture order.
    pub pairs: Vec<Pair>,
    /// Cameras, all fired at every exposure (at least one).
    pub cameras: Vec<u8>,
    /// Exposure series, ticks, shortest first.
    pub exposures: Vec<u32>,
    /// Gap after each exposure (readout), ticks.
    pub readout: u32,
    /// Shortest trigger-to-trigger time the camera takes (its `min_interval_us`), ticks: a
    /// trigger sooner than that is refused by the device (`TriggerTooSoon`).
    pub min_interval: u32,
    /// Longest a move may take, ticks.
    pub timeout: u32,
    /// Bytes per frame.
    pub frame_bytes: u64,
    /// Device tick rate.
    pub tick_hz: u32,
}

/// All pairs of a wavelength grid with excitation ≤ emission (full mode), each lit through
/// `slot_for(excitation)`.
pub fn full_pairs(grid: &[u16], slot_for: impl Fn(u16) -> u8) -> Vec<Pair> {
    let mut out = Vec::new();
    for &ex in grid {
        for &em in grid.iter().filter(|&&em| em >= ex) {
            out.push(Pair { excitation: ex, emission: em, slot: slot_for(ex) });
        }
    }
    out
}

/// Chooses the steered plan's pairs for the session in a directory (see [`Steer::choose`]).
pub type Chooser = Arc<dyn Fn(&Path) -> Result<Vec<Pair>, String> + Send + Sync>;

/// The PCA-steered acquisition (thesis §4.5): the geometries in `dense` take every pair; the
/// others only `select` pairs, chosen by `choose` from what the session holds when the first
/// of them is reached (the dense geometries come first).
#[derive(Clone)]
pub struct Steer {
    /// Indices into [`BispectralParams::geometries`] taken with every pair.
    pub dense: Vec<usize>,
    /// Pairs taken at each other geometry.
    pub select: usize,
    /// The chosen pairs for the session in a directory (its dense steps done), at least `select`.
    pub choose: Chooser,
}

/// One geometry and pair's step: the axes and the wheel moved, the exposure series taken.
fn pair_step(p: &Arc<BispectralParams>, id: u32, g: usize, pair: Pair, extra: &serde_json::Value) -> Step {
    let (sample, light) = p.geometries[g];
    let mut meta = json!({
        "geometry": g, "sample": sample, "light": light,
        "excitation_nm": pair.excitation, "emission_nm": pair.emission, "slot": pair.slot,
        "exposures": p.exposures,
        "host": { "light_filter_nm": pair.excitation, "camera_filter_nm": pair.emission },
    });
    if let (Some(m), Some(e)) = (meta.as_object_mut(), extra.as_object()) {
        m.extend(e.clone());
    }
    let name = format!("geometry {g} {}→{} nm", pair.excitation, pair.emission);
    let p = Arc::clone(p);
    Step::new(id, name, meta, move |b| {
        for axis in
            [AxisRef::Stepper(p.sample_axis), AxisRef::Stepper(p.light_axis), AxisRef::FilterWheel(p.wheel)]
        {
            b.settle(axis, p.timeout);
        }
        // Both axes and the wheel move together; wait for all three.
        b.then(Action::StepperMove { axis: p.sample_axis, target: sample, profile: Default::default() });
        b.then(Action::StepperMove { axis: p.light_axis, target: light, profile: Default::default() });
        b.then(Action::FilterWheel { wheel: p.wheel, slot: pair.slot });
        b.until(WaitFor::MoveDone(AxisRef::Stepper(p.sample_axis)), p.timeout);
        b.until(WaitFor::MoveDone(AxisRef::Stepper(p.light_axis)), p.timeout);
        b.until(WaitFor::MoveDone(AxisRef::FilterWheel(p.wheel)), p.timeout);
        for (e, &exposure) in p.exposures.iter().enumerate() {
            b.shoot_all(&p.cameras, exposure, format!("exposure {e}"));
            b.wait(exposure.saturating_add(p.readout).max(p.min_interval));
        }
    })
}

/// The bispectral plan: one step per geometry and pair.
pub fn plan(p: &BispectralParams) -> Result<Plan, PlanError> {
    plan_steered(p, None)
}

/// The bispectral plan, PCA-steered with `steer`: the dense geometries' steps first, every
/// pair; then each other geometry's `select` steps, each deciding its pair when reached. The
/// plan's `meta` holds the optical exposure time against the dense plan's
/// (`optical_exposure_s`, `dense_optical_exposure_s`).
pub fn plan_steered(p: &BispectralParams, steer: Option<Steer>) -> Result<Plan, PlanError> {
    if p.geometries.is_empty() || p.pairs.is_empty() || p.exposures.is_empty() {
        return Err(PlanError("bispectral: geometries, pairs and exposures must not be empty".into()));
    }
    if p.cameras.is_empty() {
        return Err(PlanError("bispectral: no camera to trigger".into()));
    }
    if let Some(s) = &steer {
        if s.dense.is_empty() || s.select == 0 || s.select > p.pairs.len() {
            return Err(PlanError(format!(
                "bispectral: a steered plan needs dense geometries and 1 to {} chosen pairs",
                p.pairs.len()
            )));
        }
    }
    let shared = Arc::new(p.clone());
    let none = serde_json::Value::Null;
    let mut steps = Vec::new();
    let dense = |g: usize| steer.as_ref().is_none_or(|s| s.dense.contains(&g));
    for g in (0..p.geometries.len()).filter(|&g| dense(g)) {
        for &pair in &p.pairs {
            steps.push(pair_step(&shared, steps.len() as u32, g, pair, &none));
        }
    }
    if let Some(s) = &steer {
        for g in (0..p.geometries.len()).filter(|&g| !dense(g)) {
            for j in 0..s.select {
                let id = steps.len() as u32;
                let extra = json!({ "chosen": j });
                // Planned with the first pair (the same triggers whatever is chosen); decided
                // when the acquisition reaches it.
                let placeholder = pair_step(&shared, id, g, p.pairs[0], &extra);
                let (sample, light) = p.geometries[g];
                let meta = json!({
                    "geometry": g, "sample": sample, "light": light, "chosen": j, "exposures": p.exposures,
                });
                let step = Step { name: format!("geometry {g} chosen pair {j}"), meta, ..placeholder };
                let (choose, shared) = (Arc::clone(&s.choose), Arc::clone(&shared));
                steps.push(step.resolved_by(Arc::new(move |dir: &Path| {
                    let chosen = choose(dir)?;
                    let pair = *chosen.get(j).ok_or_else(|| {
                        format!("the PCA chose {} pairs where the plan takes {}", chosen.len(), j + 1)
                    })?;
                    Ok(pair_step(&shared, id, g, pair, &json!({ "chosen": j })))
                })));
            }
        }
    }
    let series_s = p.exposures.iter().map(|&e| f64::from(e)).sum::<f64>() / f64::from(p.tick_hz);
    let dense_steps = p.geometries.len() * p.pairs.len();
    let meta = json!({
            "optical_exposure_s": series_s * steps.len() as f64,
        "dense_optical_exposure_s": series_s * dense_steps as f64,
    });
    Ok(Plan {
        method: "bispectral".into(),
        tick_hz: p.tick_hz,
        steps,
        frame_bytes: p.frame_bytes,
        meta,
        lost_retries: super::LOST_RETRIES,
    })
}
