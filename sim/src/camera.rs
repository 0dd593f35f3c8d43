//! The virtual camera: renders the scene at every trigger from the rig's state in the trigger
//! record, passes it through the sensor model, and writes it as the next numbered file into a
//! watched directory, which a [`DirectoryInput`] then picks up exactly as it would a real
//! camera's files.

use std::collections::VecDeque;
use std::io;
use std::path::{Path, PathBuf};

use lightrig_imaging::io::{write_exr, write_png, BitDepth, Encoding, ExrPrecision, Image};
use lightrig_protocol::event::TriggerEvent;
use rayon::prelude::*;

use crate::sensor::{mix, Depth, Sensor};
use crate::timeline::{Motion, Timeline};
use lightrig_host::acquire::{Captured, DirectoryInput, FrameInput};
use lightrig_host::plan::Step;
use lightrig_host::rigfile::RigFile;

/// The rig at a trigger, in the rig file's units.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RigState {
    /// The step's `meta.pass` (or `meta.kind`), if it has one: tells a scene what is on the
    /// rig (the board, the bare light box, the sample).
    pub pass: Option<String>,
    /// The step's `meta.mount_deg`: how far the linear light's mount is turned from across the
    /// gantry's travel (the LLS diagonal passes), degrees; 0 when absent.
    pub mount_deg: f64,
    /// Each stepper axis' position, rig units (mm or degrees), by axis index.
    pub axes: Vec<f64>,
    /// Lasers emitting, one bit per channel.
    pub lasers: u8,
    /// Filter wheels' slots.
    pub filters: Vec<Option<u8>>,
    /// Exposure, seconds.
    pub exposure_s: f64,
    /// Each galvo pair's codes `[x, y]`, by index, from the trigger's snapshot.
    pub galvos: Vec<[u16; 2]>,
    /// The step's whole `meta` (e.g. the immersion calibration target's pose); `Null` if none.
    pub meta: serde_json::Value,
    /// Each voice coil's samples that play during the exposure, by channel (following a
    /// [`Timeline`] only; empty otherwise). The same in every state of one exposure.
    pub coils: Vec<Vec<i16>>,
    /// Each voice coil's samples that played in the [`COIL_LEAD_S`] before the exposure, by
    /// channel: what a scene whose response lasts (a liquid's waves) needs to start from.
    pub coils_before: Vec<Vec<i16>>,
}

/// How much of each voice coil's output before an exposure [`RigState::coils_before`] holds, s.
pub const COIL_LEAD_S: f64 = 0.1;

/// Something the virtual camera can look at (rendered on the camera's threads).
pub trait Scene: Send + Sync {
    /// Image size, pixels.
    fn size(&self) -> (u32, u32);
    /// Linear RGB radiance of pixel `(x, y)` in `state`.
    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3];
    /// Row `y`'s radiance in `state`, one entry per column of `out`: the camera renders by
    /// rows, so a scene with work shared by a frame's pixels (finding its view, its beam)
    /// does it once a row here instead of once a pixel.
    fn radiance_row(&self, y: u32, state: &RigState, out: &mut [[f64; 3]]) {
        for (x, o) in out.iter_mut().enumerate() {
            *o = self.radiance(x as u32, y, state);
        }
    }
}

impl<S: Scene + ?Sized> Scene for Box<S> {
    fn size(&self) -> (u32, u32) {
        (**self).size()
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        (**self).radiance(x, y, state)
    }

    fn radiance_row(&self, y: u32, state: &RigState, out: &mut [[f64; 3]]) {
        (**self).radiance_row(y, state, out)
    }
}

/// The virtual camera.
pub struct VirtualCamera<S: Scene> {
    camera: u8,
    scene: S,
    sensor: Sensor,
    tick_hz: u32,
    dir: PathBuf,
    next_file: u64,
    axis_units: Vec<Option<lightrig_host::rigfile::Stepper>>,
    wheels: Vec<Option<lightrig_host::rigfile::FilterWheel>>,
    /// Each voice coil's sample rate, by channel.
    coil_rates: Vec<Option<u32>>,
    pass: Option<String>,
    mount_deg: f64,
    meta: serde_json::Value,
    input: DirectoryInput,
    on_frame: Option<Box<dyn FnMut(u64) + Send>>,
    /// The board's changes: with it, frames integrate over their exposure.
    timeline: Option<(Timeline, usize)>,
    /// Triggers whose exposure has not ended yet, with the state at their tick.
    pending: VecDeque<(TriggerEvent, RigState)>,
}

/// Most distinct states rendered for one exposure; beyond, the exposure is sampled at this
/// many evenly spaced instants (stratified, as a renderer's motion blur).
pub const MAX_EXPOSURE_STATES: usize = 16;

const PATTERN: &str = "img_{frame:06}";

impl<S: Scene> VirtualCamera<S> {
    /// A camera `camera` of `rig` looking at `scene`, writing into `dir` (created if needed).
    pub fn new(
        rig: &RigFile,
        camera: u8,
        scene: S,
        sensor: Sensor,
        tick_hz: u32,
        dir: &Path,
    ) -> io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let ext = if matches!(sensor.depth, Depth::Float | Depth::Half) { "exr" } else { "png" };
        let input = DirectoryInput::new(camera, dir, &format!("{PATTERN}.{ext}"))
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        let max_axis = rig.steppers.iter().map(|s| usize::from(s.axis) + 1).max().unwrap_or(0);
        let axis_units = (0..max_axis).map(|a| rig.stepper(a as u8).cloned()).collect();
        let mut wheels = Vec::new();
        for w in &rig.filter_wheels {
            let i = usize::from(w.wheel);
            if wheels.len() <= i {
                wheels.resize(i + 1, None);
            }
            wheels[i] = Some(w.clone());
        }
        let mut coil_rates = Vec::new();
        for c in &rig.voice_coils {
            let i = usize::from(c.channel);
            if coil_rates.len() <= i {
                coil_rates.resize(i + 1, None);
            }
            coil_rates[i] = Some(c.sample_rate_hz);
        }
        Ok(Self {
            camera,
            scene,
            sensor,
            tick_hz,
            dir: dir.to_path_buf(),
            next_file: 0,
            axis_units,
            wheels,
            coil_rates,
            pass: None,
            mount_deg: 0.0,
            meta: serde_json::Value::Null,
            input,
            on_frame: None,
            timeline: None,
            pending: VecDeque::new(),
        })
    }

    /// Calls `f` with the count of frames rendered after each one (for a progress bar).
    pub fn on_frame(&mut self, f: impl FnMut(u64) + Send + 'static) {
        self.on_frame = Some(Box::new(f));
    }

    /// Follows the board's state at every tick
    /// ([`VirtualTransport::timeline`](crate::transport::VirtualTransport::timeline)): each
    /// frame then integrates the scene
    /// over its whole exposure, and is rendered once the exposure has ended. Without it, a
    /// frame shows the state at its trigger's tick.
    pub fn follow(&mut self, timeline: Timeline) {
        let reader = timeline.reader();
        self.timeline = Some((timeline, reader));
    }

    /// The rig's states over trigger `t`'s exposure, each with the fraction of the exposure
    /// it lasted, from the state at the trigger (`at_trigger`) and the timeline's changes.
    pub fn exposure_states(&self, t: &TriggerEvent, at_trigger: &RigState) -> Vec<(f64, RigState)> {
        let Some((tl, _)) = &self.timeline else { return vec![(1.0, at_trigger.clone())] };
        let (t0, t1) = (t.tick, t.tick + u64::from(t.width.max(1)));
        let mut state = at_trigger.clone();
        let samples = |from: u64, to: u64| -> Vec<Vec<i16>> {
            (0..self.coil_rates.len())
                .map(|c| match self.coil_rates[c] {
                    Some(rate) => tl.coil_samples(c as u8, rate, self.tick_hz, from, to),
                    None => Vec::new(),
                })
                .collect()
        };
        state.coils = samples(t0, t1);
        let lead = (COIL_LEAD_S * f64::from(self.tick_hz)) as u64;
        state.coils_before = samples(t0.saturating_sub(lead), t0);
        let changes = tl.between(t0, t1);
        if changes.is_empty() {
            return vec![(1.0, state)];
        }
        // Replay: integer steps per axis from the snapshot, converted to units per state; a
        // wheel's position from its slot's centre, when the snapshot knows the slot.
        let mut steps: Vec<i64> = t.snapshot.axes.iter().map(|&s| i64::from(s)).collect();
        let mut wheel_at: Vec<Option<i64>> = t
            .snapshot
            .filters
            .iter()
            .enumerate()
            .map(|(i, slot)| Some(slot_centre(self.wheels.get(i)?.as_ref()?, (*slot)?)))
            .collect();
        let last_wheel_step: Vec<Option<u64>> = (0..wheel_at.len())
            .map(|w| {
                changes
                    .iter()
                    .rev()
                    .find(|(_, m)| matches!(m, Motion::WheelStep { wheel, .. } if usize::from(*wheel) == w))
                    .map(|&(c, _)| c)
            })
            .collect();
        let apply = |state: &mut RigState,
                     steps: &mut Vec<i64>,
                     wheel_at: &mut Vec<Option<i64>>,
                     at: u64,
                     m: &Motion| match *m {
            Motion::WheelStep { wheel, physical } => {
                // Moving, a wheel has no slot (as the device reports); after its last step in
                // this exposure it has the slot whose centre it sits on, if any.
                let i = usize::from(wheel);
                let cfg = self.wheels.get(i).and_then(|w| w.as_ref());
                let logical = if cfg.is_some_and(|w| w.invert_dir) { -physical } else { physical };
                let pos = wheel_at.get_mut(i).and_then(|p| {
                    p.as_mut().map(|p| {
                        *p += i64::from(logical);
                        *p
                    })
                });
                let settled = last_wheel_step.get(i).copied().flatten() == Some(at);
                if let Some(f) = state.filters.get_mut(i) {
                    *f = match (settled, cfg, pos) {
                        (true, Some(cfg), Some(p)) => slot_at(cfg, p),
                        _ => None,
                    };
                }
            }
            Motion::Galvo { pair, to } => {
                if let Some(g) = state.galvos.get_mut(usize::from(pair)) {
                    *g = to;
                }
            }
            Motion::LaserToggled { channel } => {
                state.lasers ^= 1u8.checked_shl(u32::from(channel)).unwrap_or(0)
            }
            Motion::Step { axis, physical } => {
                let i = usize::from(axis);
                let unit = self.axis_units.get(i).and_then(|s| s.as_ref());
                let logical = if unit.is_some_and(|s| s.invert_dir) { -physical } else { physical };
                if let Some(s) = steps.get_mut(i) {
                    *s += i64::from(logical);
                    if let Some(a) = state.axes.get_mut(i) {
                        *a = unit.and_then(|u| u.units(*s)).unwrap_or(*s as f64);
                    }
                }
            }
        };
        let len = (t1 - t0) as f64;
        // Distinct instants at which the state changes.
        let mut instants: Vec<u64> = changes.iter().map(|&(c, _)| c).collect();
        instants.dedup();
        if instants.len() < MAX_EXPOSURE_STATES {
            let mut out = Vec::with_capacity(instants.len() + 1);
            let (mut from, mut next) = (t0, 0);
            for &at in &instants {
                out.push(((at - from) as f64 / len, state.clone()));
                while next < changes.len() && changes[next].0 == at {
                    apply(&mut state, &mut steps, &mut wheel_at, at, &changes[next].1);
                    next += 1;
                }
                from = at;
            }
            out.push(((t1 - from) as f64 / len, state));
            out.retain(|(w, _)| *w > 0.0);
            return out;
        }
        // Too many to render each: the state at the middle of each of N equal slices.
        let n = MAX_EXPOSURE_STATES as u64;
        let mut out = Vec::with_capacity(MAX_EXPOSURE_STATES);
        let mut next = 0;
        for k in 0..n {
            let at = t0 + ((t1 - t0) * (2 * k + 1)) / (2 * n);
            while next < changes.len() && changes[next].0 <= at {
                apply(&mut state, &mut steps, &mut wheel_at, changes[next].0, &changes[next].1);
                next += 1;
            }
            out.push((1.0 / n as f64, state.clone()));
        }
        out
    }

    /// The scene.
    pub fn scene(&self) -> &S {
        &self.scene
    }

    /// The rig's state at trigger `t`.
    pub fn state(&self, t: &TriggerEvent) -> RigState {
        let axes = t
            .snapshot
            .axes
            .iter()
            .enumerate()
            .map(|(i, &steps)| {
                self.axis_units
                    .get(i)
                    .and_then(|s| s.as_ref())
                    .and_then(|s| s.units(i64::from(steps)))
                    .unwrap_or(f64::from(steps))
            })
            .collect();
        RigState {
            pass: self.pass.clone(),
            mount_deg: self.mount_deg,
            axes,
            lasers: t.snapshot.lasers,
            filters: t.snapshot.filters.iter().copied().collect(),
            exposure_s: f64::from(t.width) / f64::from(self.tick_hz),
            galvos: t.snapshot.galvos.iter().map(|g| [g.x, g.y]).collect(),
            meta: self.meta.clone(),
            coils: Vec::new(),
            coils_before: Vec::new(),
        }
    }

    /// Renders one frame of `state` with noise draw `frame_key`.
    pub fn render(&self, state: &RigState, frame_key: u64) -> Image {
        self.render_exposure(&[(1.0, state.clone())], frame_key)
    }

    /// Renders one frame whose exposure saw each of `states` for its fraction of the time:
    /// the radiance is their weighted sum, then the sensor exposes it once.
    pub fn render_exposure(&self, states: &[(f64, RigState)], frame_key: u64) -> Image {
        render_exposure(&self.scene, &self.sensor, states, frame_key)
    }

    /// Renders and writes the pending frames whose exposure has ended (all of them without a
    /// timeline).
    fn render_ready(&mut self) -> io::Result<()> {
        while let Some((t, _)) = self.pending.front() {
            let end = t.tick + u64::from(t.width.max(1));
            if self.timeline.as_ref().is_some_and(|(tl, _)| tl.horizon() < end) {
                break;
            }
            let Some((t, state)) = self.pending.pop_front() else { break };
            let states = self.exposure_states(&t, &state);
            let n = self.next_file;
            let img = self.render_exposure(&states, n);
            self.write(&img, n)?;
            if let Some((tl, reader)) = &self.timeline {
                tl.forget_before(*reader, t.tick);
            }
            self.next_file += 1;
            if let Some(f) = self.on_frame.as_mut() {
                f(self.next_file);
            }
        }
        Ok(())
    }

    fn write(&self, img: &Image, n: u64) -> io::Result<()> {
        let name = PATTERN.replace("{frame:06}", &format!("{n:06}"));
        let res = match self.sensor.depth {
            Depth::Float => write_exr(self.dir.join(format!("{name}.exr")), img, ExrPrecision::Float),
            Depth::Half => write_exr(self.dir.join(format!("{name}.exr")), img, ExrPrecision::Half),
            Depth::U8 => write_png(self.dir.join(format!("{name}.png")), &img.to_srgb(), BitDepth::Eight),
            Depth::U12 | Depth::U16 => {
                write_png(self.dir.join(format!("{name}.png")), img, BitDepth::Sixteen)
            }
        };
        res.map_err(|e| io::Error::other(e.to_string()))
    }
}

/// One frame of `scene` through `sensor` whose exposure saw each of `states` for its fraction
/// of the time (the first state's exposure): the radiance is their weighted sum, then the
/// sensor exposes it once; `frame_key` selects the noise draw.
pub fn render_exposure<S: Scene + ?Sized>(
    scene: &S,
    sensor: &Sensor,
    states: &[(f64, RigState)],
    frame_key: u64,
) -> Image {
    let (w, h) = scene.size();
    let ch = if sensor.grey { 1 } else { 3 };
    let mut img = Image::new(w, h, ch as u8);
    let exposure_s = states.first().map_or(0.0, |(_, s)| s.exposure_s);
    img.data.par_chunks_mut(w as usize * ch).enumerate().for_each(|(y, row)| {
        let mut sum = vec![[0.0; 3]; w as usize];
        let mut one = vec![[0.0; 3]; w as usize];
        for (f, state) in states {
            scene.radiance_row(y as u32, state, &mut one);
            for (s, r) in sum.iter_mut().zip(&one) {
                for c in 0..3 {
                    s[c] += f * r[c];
                }
            }
        }
        for x in 0..w {
            let mut l = sum[x as usize];
            if sensor.grey {
                l[0] = (l[0] + l[1] + l[2]) / 3.0;
            }
            for c in 0..ch {
                let i = (y * w as usize + x as usize) * ch + c;
                let key = mix(frame_key).wrapping_add(i as u64);
                row[x as usize * ch + c] = sensor.expose(l[c], exposure_s, key);
            }
        }
    });
    img.with_encoding(Encoding::Linear)
}

impl<S: Scene> FrameInput for VirtualCamera<S> {
    fn begin_step(&mut self, step: &Step) -> io::Result<()> {
        self.pass = step
            .meta
            .get("pass")
            .or_else(|| step.meta.get("kind"))
            .and_then(|p| p.as_str())
            .map(str::to_string);
        self.mount_deg = step.meta.get("mount_deg").and_then(|m| m.as_f64()).unwrap_or(0.0);
        self.meta = step.meta.clone();
        self.input.begin_step(step)
    }

    fn on_trigger(&mut self, t: &TriggerEvent, _host_us: Option<f64>) -> io::Result<()> {
        if t.camera != self.camera {
            return Ok(());
        }
        let state = self.state(t);
        self.pending.push_back((t.clone(), state));
        self.render_ready()
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        self.render_ready()?;
        self.input.poll(now_us)
    }
}

/// A filter wheel's motor position (steps from slot 0's centre) at `slot`'s centre, as the
/// firmware places it.
fn slot_centre(w: &lightrig_host::rigfile::FilterWheel, slot: u8) -> i64 {
    i64::from(slot) * i64::from(w.steps_per_rev) / i64::from(w.slots.max(1))
}

/// The slot whose centre a wheel at `position` sits on, if any.
fn slot_at(w: &lightrig_host::rigfile::FilterWheel, position: i64) -> Option<u8> {
    let p = position.rem_euclid(i64::from(w.steps_per_rev.max(1)));
    (0..w.slots).find(|&k| slot_centre(w, k) == p)
}
