//! Pairing a step's camera triggers with the frames a frame source delivered.
//!
//! A pure function: no I/O, no clock. Frames are matched to triggers by camera and frame number
//! (`TriggerEvent::frame`: the count of triggers on that camera since the sequence started).

use std::collections::HashMap;

use lightrig_protocol::event::TriggerEvent;
use serde::{Deserialize, Serialize};

use crate::client::EventRecord;
use lightrig_protocol::Event;

/// A camera trigger as the pairing needs it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Trigger {
    /// Sequence the trigger item belongs to.
    pub sequence: u32,
    /// Index of the trigger item within the sequence.
    pub item: u32,
    /// Camera output.
    pub camera: u8,
    /// Frame number on this camera, from 0 at the sequence start.
    pub frame: u32,
    /// Device tick of the leading edge.
    pub tick: u64,
    /// Host time of the tick (µs), if the clock was mapped.
    pub host_us: Option<f64>,
}

impl Trigger {
    /// From a trigger event and its host time.
    pub fn from_event(t: &TriggerEvent, host_us: Option<f64>) -> Self {
        Trigger {
            sequence: t.sequence,
            item: t.item,
            camera: t.camera,
            frame: t.frame,
            tick: t.tick,
            host_us,
        }
    }

    /// From an event as the client delivers it, if it is a trigger.
    pub fn from_record(e: &EventRecord) -> Option<Self> {
        match &e.event {
            Event::Trigger(t) => Some(Self::from_event(t, e.host_us)),
            _ => None,
        }
    }
}

/// A frame that arrived from a frame source.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// Camera it came from.
    pub camera: u8,
    /// Its frame number counted from the sequence start, when the source reports one; `None`:
    /// numbered by arrival order among this camera's arrivals (0, 1, …), which cannot tell a
    /// dropped frame from a late one.
    pub frame: Option<u32>,
    /// Host time it arrived (µs, on the same clock as [`Trigger::host_us`]).
    pub host_us: f64,
}

/// A trigger and its frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pair {
    /// The trigger.
    pub trigger: Trigger,
    /// Index of the frame in the arrivals.
    pub arrival: usize,
    /// When the frame arrived (µs).
    pub arrived_us: f64,
    /// Arrival minus the trigger's host time (µs), when the trigger has one.
    pub delay_us: Option<f64>,
    /// The frame arrived more than the tolerance after its trigger. It is still paired.
    pub late: bool,
}

/// Why a frame has no trigger.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ExtraReason {
    /// An earlier frame already answered this trigger.
    Duplicate,
    /// No trigger of this step has the frame's camera and number.
    NoTrigger,
    /// The camera made it before the step began: a straggler of an earlier attempt (its
    /// `frame` is the camera's own number). Never paired (format 3).
    BeforeStep,
}

/// A frame without a trigger.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extra {
    /// Index of the frame in the arrivals.
    pub arrival: usize,
    /// Its camera.
    pub camera: u8,
    /// Its frame number (reported, or from arrival order).
    pub frame: u32,
    /// When it arrived (µs).
    pub arrived_us: f64,
    /// Why it is extra.
    pub reason: ExtraReason,
}

/// The outcome of [`pair`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pairing {
    /// Triggers with their frame, in trigger order.
    pub pairs: Vec<Pair>,
    /// Triggers without a frame, in trigger order.
    pub missing: Vec<Trigger>,
    /// Frames without a trigger, in arrival order.
    pub extra: Vec<Extra>,
}

impl Pairing {
    /// The pairs whose frame came late.
    pub fn late(&self) -> impl Iterator<Item = &Pair> {
        self.pairs.iter().filter(|p| p.late)
    }
}

/// Pairs `triggers` with `arrivals` by (camera, frame number). The first arrival for a trigger
/// wins; a later one for the same trigger is a [`ExtraReason::Duplicate`], one matching no
/// trigger is [`ExtraReason::NoTrigger`]. A trigger matched by no arrival is missing. A pair is
/// late when the frame arrived more than `tolerance_us` after the trigger's host time (never
/// when the trigger has no host time). A trigger repeating an earlier one's camera and frame
/// number (the device never sends one) is ignored.
pub fn pair(triggers: &[Trigger], arrivals: &[Arrival], tolerance_us: f64) -> Pairing {
    // (camera, frame) -> first arrival index, and every arrival's resolved number.
    let mut first: HashMap<(u8, u32), usize> = HashMap::new();
    let mut order: HashMap<u8, u32> = HashMap::new();
    let mut numbers = Vec::with_capacity(arrivals.len());
    for (i, a) in arrivals.iter().enumerate() {
        let seen = order.entry(a.camera).or_insert(0);
        let n = a.frame.unwrap_or(*seen);
        *seen += 1;
        numbers.push(n);
        first.entry((a.camera, n)).or_insert(i);
    }
    let mut out = Pairing::default();
    let mut used: HashMap<(u8, u32), bool> = HashMap::new();
    for t in triggers {
        let key = (t.camera, t.frame);
        if used.contains_key(&key) {
            continue;
        }
        used.insert(key, first.contains_key(&key));
        match first.get(&key) {
            Some(&i) => {
                let arrived_us = arrivals[i].host_us;
                let delay_us = t.host_us.map(|h| arrived_us - h);
                let late = delay_us.is_some_and(|d| d > tolerance_us);
                out.pairs.push(Pair { trigger: *t, arrival: i, arrived_us, delay_us, late });
            }
            None => out.missing.push(*t),
        }
    }
    for (i, a) in arrivals.iter().enumerate() {
        let key = (a.camera, numbers[i]);
        let reason = match used.get(&key) {
            Some(true) if first[&key] == i => continue,
            Some(true) => ExtraReason::Duplicate,
            _ => ExtraReason::NoTrigger,
        };
        out.extra.push(Extra { arrival: i, camera: a.camera, frame: key.1, arrived_us: a.host_us, reason });
    }
    out
}

/// A camera's clock against the device's, from frames paired with their triggers: a least-
/// squares line `time_ns ≈ offset_ns + ns_per_tick · tick` and each frame's residual, ns.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraClock {
    pub offset_ns: f64,
    pub ns_per_tick: f64,
    /// Per input point, `time_ns − line(tick)`.
    pub residuals_ns: Vec<f64>,
}

/// Fits [`CameraClock`] to `(trigger tick, camera time ns)` pairs; `None` with fewer than 3
/// points or all at one tick. A frame paired with the wrong trigger sits a trigger spacing
/// off the line the others make: compare its residual with the spacing.
pub fn camera_clock(points: &[(u64, u64)]) -> Option<CameraClock> {
    if points.len() < 3 {
        return None;
    }
    // Relative to the first point: ticks and nanoseconds are large, their spread small.
    let (t0, c0) = (points[0].0 as f64, points[0].1 as f64);
    let xs: Vec<f64> = points.iter().map(|p| p.0 as f64 - t0).collect();
    let ys: Vec<f64> = points.iter().map(|p| p.1 as f64 - c0).collect();
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
    if sxx <= 0.0 {
        return None;
    }
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let slope = sxy / sxx;
    let icept = my - slope * mx;
    let residuals_ns = xs.iter().zip(&ys).map(|(x, y)| y - (icept + slope * x)).collect();
    Some(CameraClock { offset_ns: c0 + icept - slope * t0, ns_per_tick: slope, residuals_ns })
}

/// A camera's clock against the controller's, fitted robustly to `(trigger tick, camera time
/// ns)` points: the median of neighbouring slopes, then the median offset, so it follows the
/// majority of the frames however many sit a trigger spacing off.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobustClock {
    t0: f64,
    c0: f64,
    /// ns per tick.
    pub slope: f64,
    offset: f64,
    /// A frame further off than this (ns) was paired with the wrong trigger: a quarter of the
    /// median trigger spacing, at least 1 ms.
    pub limit_ns: f64,
}

impl RobustClock {
    /// From points in trigger order; `None` with fewer than 3 or no two at different ticks.
    pub fn fit(points: &[(u64, u64)]) -> Option<RobustClock> {
        if points.len() < 3 {
            return None;
        }
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied()
        };
        let (t0, c0) = (points[0].0 as f64, points[0].1 as f64);
        let xy: Vec<(f64, f64)> = points.iter().map(|p| (p.0 as f64 - t0, p.1 as f64 - c0)).collect();
        let slopes: Vec<f64> = xy
            .windows(2)
            .filter(|w| w[1].0 > w[0].0)
            .map(|w| (w[1].1 - w[0].1) / (w[1].0 - w[0].0))
            .collect();
        let slope = median(slopes)?;
        if slope <= 0.0 {
            return None;
        }
        let offset = median(xy.iter().map(|(x, y)| y - slope * x).collect())?;
        let gaps: Vec<f64> = xy.windows(2).map(|w| (w[1].0 - w[0].0) * slope).collect();
        let limit_ns = (0.25 * median(gaps).unwrap_or(0.0)).max(1e6);
        Some(RobustClock { t0, c0, slope, offset, limit_ns })
    }

    /// Camera time minus the clock's time for `tick`, ns.
    pub fn residual_ns(&self, tick: u64, time_ns: u64) -> f64 {
        (time_ns as f64 - self.c0) - (self.offset + self.slope * (tick as f64 - self.t0))
    }

    /// The controller's tick at camera time `time_ns`.
    pub fn tick_at(&self, time_ns: u64) -> f64 {
        self.t0 + ((time_ns as f64 - self.c0) - self.offset) / self.slope
    }
}

/// The points of `points` (`(trigger tick, camera time ns)`, in trigger order) that the
/// camera's clock ([`RobustClock`]) puts off their triggers. A camera that missed a trigger
/// numbers every later frame one early, and exactly those frames land a spacing off. Returns
/// `(index, residual ns)`; nothing with fewer than 3 points.
pub fn off_their_triggers(points: &[(u64, u64)]) -> Vec<(usize, f64)> {
    let Some(clock) = RobustClock::fit(points) else { return Vec::new() };
    points
        .iter()
        .enumerate()
        .map(|(k, &(t, c))| (k, clock.residual_ns(t, c)))
        .filter(|(_, r)| r.abs() > clock.limit_ns)
        .collect()
}

/// Pairs again, by the camera's clock, the frames a line-triggered camera's timestamps put off
/// their triggers (`stamps[arrival]`: each arrival's camera time, ns): each goes to the
/// trigger of its camera at the tick its stamp names (within [`RobustClock::limit_ns`]) if no
/// frame in agreement with the clock holds it, else it is extra; triggers left without a frame
/// are missing. Returns the triggers that had a frame by number and have none by the clock:
/// the ones the camera missed, `(camera, frame)`.
pub fn repair_by_stamps(pairing: &mut Pairing, stamps: &[Option<u64>]) -> Vec<(u8, u32)> {
    let mut cameras: Vec<u8> = pairing.pairs.iter().map(|p| p.trigger.camera).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let mut missed = Vec::new();
    for cam in cameras {
        let mut mine: Vec<Pair> = pairing.pairs.iter().filter(|p| p.trigger.camera == cam).copied().collect();
        mine.sort_by_key(|p| p.trigger.frame);
        let stamp = |p: &Pair| stamps.get(p.arrival).copied().flatten();
        let pts: Vec<(u64, u64)> =
            mine.iter().filter_map(|p| stamp(p).map(|s| (p.trigger.tick, s))).collect();
        let Some(clock) = RobustClock::fit(&pts) else { continue };
        let off =
            |p: &Pair| stamp(p).is_some_and(|s| clock.residual_ns(p.trigger.tick, s).abs() > clock.limit_ns);
        if !mine.iter().any(off) {
            continue;
        }
        // Every trigger of this camera, by number and by clock.
        let mut triggers: Vec<Trigger> = mine.iter().map(|p| p.trigger).collect();
        triggers.extend(pairing.missing.iter().filter(|t| t.camera == cam).copied());
        triggers.sort_by_key(|t| t.tick);
        let (keep, moved): (Vec<Pair>, Vec<Pair>) = mine.iter().partition(|p| !off(p));
        let mut taken: std::collections::BTreeSet<u32> = keep.iter().map(|p| p.trigger.frame).collect();
        let mut pairs = keep;
        for p in moved {
            let at = clock.tick_at(stamp(&p).expect("off needs a stamp"));
            let nearest = triggers
                .iter()
                .filter(|t| !taken.contains(&t.frame))
                .min_by(|a, b| (a.tick as f64 - at).abs().total_cmp(&(b.tick as f64 - at).abs()));
            match nearest {
                Some(t) if (t.tick as f64 - at).abs() * clock.slope <= clock.limit_ns => {
                    taken.insert(t.frame);
                    let delay_us = t.host_us.map(|h| p.arrived_us - h);
                    pairs.push(Pair { trigger: *t, delay_us, ..p });
                }
                _ => pairing.extra.push(Extra {
                    arrival: p.arrival,
                    camera: cam,
                    frame: p.trigger.frame,
                    arrived_us: p.arrived_us,
                    reason: ExtraReason::NoTrigger,
                }),
            }
        }
        for t in triggers.iter().filter(|t| !taken.contains(&t.frame)) {
            if mine.iter().any(|p| p.trigger.frame == t.frame) {
                missed.push((cam, t.frame));
            }
        }
        pairing.missing.retain(|t| t.camera != cam);
        pairing.missing.extend(triggers.iter().filter(|t| !taken.contains(&t.frame)).copied());
        pairing.pairs.retain(|p| p.trigger.camera != cam);
        pairing.pairs.extend(pairs);
    }
    pairing.pairs.sort_by_key(|p| (p.trigger.tick, p.trigger.camera));
    pairing.missing.sort_by_key(|t| (t.tick, t.camera));
    missed
}

#[cfg(test)]
mod camera_clock_tests {
    use super::*;

    #[test]
    fn a_steady_camera_clock_fits_exactly_and_a_shifted_frame_stands_out() {
        // 1 MHz ticks, a camera clock 20 ppm fast and 3 s ahead, triggers 50 ms apart.
        let ticks: Vec<u64> = (0..20).map(|k| 1_000_000 + k * 50_000).collect();
        let cam = |t: u64| (3e9 + t as f64 * 1000.0 * (1.0 + 20e-6)).round() as u64;
        let pts: Vec<(u64, u64)> = ticks.iter().map(|&t| (t, cam(t))).collect();
        let c = camera_clock(&pts).unwrap();
        assert!((c.ns_per_tick - 1000.02).abs() < 1e-6, "{}", c.ns_per_tick);
        assert!(c.residuals_ns.iter().all(|r| r.abs() < 1.0), "{:?}", c.residuals_ns);
        // Frame 7 paired with trigger 8's tick: 50 ms off the others' line.
        let mut shifted = pts.clone();
        shifted[7].1 = cam(ticks[8]);
        let c = camera_clock(&shifted).unwrap();
        let worst =
            (0..20).max_by(|&a, &b| c.residuals_ns[a].abs().total_cmp(&c.residuals_ns[b].abs())).unwrap();
        assert_eq!(worst, 7);
        assert!(c.residuals_ns[7] > 40e6, "{}", c.residuals_ns[7]);
        assert_eq!(off_their_triggers(&pts), []);
        assert_eq!(off_their_triggers(&shifted).iter().map(|p| p.0).collect::<Vec<_>>(), [7]);
        // A trigger the camera missed at frame 12: every later frame is numbered one early
        // (paired with the trigger before its own).
        let missed: Vec<(u64, u64)> =
            ticks.iter().enumerate().map(|(k, &t)| (t, cam(if k >= 12 { t + 50_000 } else { t }))).collect();
        let off = off_their_triggers(&missed);
        assert_eq!(off.iter().map(|p| p.0).collect::<Vec<_>>(), (12..20).collect::<Vec<_>>());
        assert!(off.iter().all(|p| (p.1 - 50e6).abs() < 1e5), "a spacing (50 ms) off: {off:?}");
        assert!(camera_clock(&pts[..2]).is_none());
        assert!(camera_clock(&[(5, 1), (5, 2), (5, 3)]).is_none());
    }
}
