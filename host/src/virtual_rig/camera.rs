//! The virtual camera: renders the scene at every trigger from the rig's state in the trigger
//! record, passes it through the sensor model, and writes it as the next numbered file into a
//! watched directory, which a [`DirectoryInput`] then picks up exactly as it would a real
//! camera's files.

use std::io;
use std::path::{Path, PathBuf};

use lightrig_imaging::io::{write_exr, write_png, BitDepth, Encoding, ExrPrecision, Image};
use lightrig_protocol::event::TriggerEvent;
use rayon::prelude::*;

use super::sensor::{mix, Depth, Sensor};
use crate::acquire::{Captured, DirectoryInput, FrameInput};
use crate::plan::Step;
use crate::rigfile::RigFile;

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
}

/// Something the virtual camera can look at.
pub trait Scene: Sync {
    /// Image size, pixels.
    fn size(&self) -> (u32, u32);
    /// Linear RGB radiance of pixel `(x, y)` in `state`.
    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3];
}

/// The virtual camera.
pub struct VirtualCamera<S: Scene> {
    camera: u8,
    scene: S,
    sensor: Sensor,
    tick_hz: f64,
    dir: PathBuf,
    next_file: u64,
    axis_units: Vec<Option<crate::rigfile::Stepper>>,
    pass: Option<String>,
    mount_deg: f64,
    meta: serde_json::Value,
    input: DirectoryInput,
    on_frame: Option<Box<dyn FnMut(u64)>>,
}

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
        let ext = if sensor.depth == Depth::Float { "exr" } else { "png" };
        let input = DirectoryInput::new(camera, dir, &format!("{PATTERN}.{ext}"))
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        let max_axis = rig.steppers.iter().map(|s| usize::from(s.axis) + 1).max().unwrap_or(0);
        let axis_units = (0..max_axis).map(|a| rig.stepper(a as u8).cloned()).collect();
        Ok(Self {
            camera,
            scene,
            sensor,
            tick_hz: f64::from(tick_hz),
            dir: dir.to_path_buf(),
            next_file: 0,
            axis_units,
            pass: None,
            mount_deg: 0.0,
            meta: serde_json::Value::Null,
            input,
            on_frame: None,
        })
    }

    /// Calls `f` with the count of frames rendered after each one (for a progress bar).
    pub fn on_frame(&mut self, f: impl FnMut(u64) + 'static) {
        self.on_frame = Some(Box::new(f));
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
            exposure_s: f64::from(t.width) / self.tick_hz,
            galvos: t.snapshot.galvos.iter().map(|g| [g.x, g.y]).collect(),
            meta: self.meta.clone(),
        }
    }

    /// Renders one frame of `state` with noise draw `frame_key`.
    pub fn render(&self, state: &RigState, frame_key: u64) -> Image {
        let (w, h) = self.scene.size();
        let mut img = Image::new(w, h, 3);
        let (sensor, scene) = (self.sensor, &self.scene);
        img.data.par_chunks_mut(w as usize * 3).enumerate().for_each(|(y, row)| {
            for x in 0..w {
                let l = scene.radiance(x, y as u32, state);
                for c in 0..3 {
                    let i = (y * w as usize + x as usize) * 3 + c;
                    let key = mix(frame_key).wrapping_add(i as u64);
                    row[x as usize * 3 + c] = sensor.expose(l[c], state.exposure_s, key);
                }
            }
        });
        img.with_encoding(Encoding::Linear)
    }

    fn write(&self, img: &Image, n: u64) -> io::Result<()> {
        let name = PATTERN.replace("{frame:06}", &format!("{n:06}"));
        let res = match self.sensor.depth {
            Depth::Float => write_exr(self.dir.join(format!("{name}.exr")), img, ExrPrecision::Float),
            Depth::U8 => write_png(self.dir.join(format!("{name}.png")), &img.to_srgb(), BitDepth::Eight),
            Depth::U12 | Depth::U16 => {
                write_png(self.dir.join(format!("{name}.png")), img, BitDepth::Sixteen)
            }
        };
        res.map_err(|e| io::Error::other(e.to_string()))
    }
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
        let n = self.next_file;
        let img = self.render(&state, n);
        self.write(&img, n)?;
        self.next_file += 1;
        if let Some(f) = self.on_frame.as_mut() {
            f(self.next_file);
        }
        Ok(())
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        self.input.poll(now_us)
    }
}
