//! `lightrig.Session`: a session directory opened read-only ([`SessionIndex`]: the journal
//! checked as `lightrig` opens it, one step's records in memory at a time), and its frames
//! streamed with their trigger records ([`Frames`]).

use std::path::PathBuf;
use std::sync::Arc;

use lightrig_host::session::{
    FrameRecord, Frames, Record, SessionError as RustSessionError, SessionIndex, StepId,
};
use lightrig_protocol::event::TriggerEvent;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::convert::{self, dict, object};
use crate::SessionError;

fn session_err(e: RustSessionError) -> PyErr {
    SessionError::new_err(e.to_string())
}

/// A session directory, read-only: its manifest, rig file and plan, each step's records and
/// frames. Nothing is written to it.
#[pyclass(frozen, module = "lightrig")]
pub struct Session {
    index: Arc<SessionIndex>,
}

#[pymethods]
impl Session {
    /// Opens `path` read-only: reads and checks its manifest and journal (a torn last line is
    /// ignored, as `lightrig` ignores it; damage before it raises `SessionError` naming the line).
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let index = py.detach(|| SessionIndex::read(&path)).map_err(session_err)?;
        Ok(Session { index: Arc::new(index) })
    }

    /// The session directory.
    #[getter]
    fn path(&self) -> PathBuf {
        self.index.dir().to_path_buf()
    }

    /// `manifest.json` as a dict.
    #[getter]
    fn manifest<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        object(py, self.index.manifest())
    }

    /// The rig file the session was taken with, verbatim.
    #[getter]
    fn rig_text(&self) -> String {
        self.index.manifest().rig.clone()
    }

    /// The rig file parsed (TOML tables as dicts).
    #[getter]
    fn rig<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let table: toml::Table = toml::from_str(&self.index.manifest().rig).map_err(|e| {
            SessionError::new_err(format!("{}: the manifest's rig file: {e}", self.index.dir().display()))
        })?;
        object(py, &table)
    }

    /// The planner's method (`linear-light-source`, `fluorescent-immersion`, `brdf-display`,
    /// `bispectral`, `disco`), if it recorded one.
    #[getter]
    fn method(&self) -> Option<String> {
        self.index.manifest().plan.extra.get("method").and_then(|m| m.as_str()).map(str::to_string)
    }

    /// The device's tick rate, Hz: trigger ticks divided by it are seconds.
    #[getter]
    fn tick_hz(&self) -> u32 {
        self.index.manifest().device.tick_hz
    }

    /// Whether the session was completed (`SessionDone` written).
    #[getter]
    fn done(&self) -> bool {
        self.index.is_done()
    }

    /// The plan's steps in order, each a dict: `id`, `name`, `expected` (`{camera: triggers}`),
    /// `done`, `attempt` (the completed one, or None), `frames` (`{camera: paired frames}`) and
    /// the planner's `extra`.
    fn steps<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let list = PyList::empty(py);
        for s in &self.index.manifest().plan.steps {
            let attempt = self.index.done_attempt(s.id);
            let d = dict(py, |d| {
                d.set_item("id", s.id)?;
                d.set_item("name", &s.name)?;
                let expected = PyDict::new(py);
                let frames = PyDict::new(py);
                for t in &s.triggers {
                    expected.set_item(t.camera, t.count)?;
                    frames.set_item(t.camera, self.index.frame_count(s.id, t.camera))?;
                }
                d.set_item("expected", expected)?;
                d.set_item("done", attempt.is_some())?;
                d.set_item("attempt", attempt)?;
                d.set_item("frames", frames)?;
                d.set_item("extra", object(py, &s.extra)?)
            })?;
            list.append(d)?;
        }
        Ok(list)
    }

    /// Step `step`'s completed attempt: a dict of its `frames`, `missing` and `extra` records
    /// (journal records as dicts, docs/session-format.md §4) and its `triggers` events. Empty
    /// lists if the step is not done.
    fn records<'py>(&self, py: Python<'py>, step: StepId) -> PyResult<Bound<'py, PyDict>> {
        self.known(step)?;
        let r = py.detach(|| self.index.step(step)).map_err(session_err)?;
        let mut triggers: Vec<&TriggerEvent> = r.triggers.values().collect();
        triggers.sort_by_key(|t| (t.sequence, t.item));
        dict(py, |d| {
            d.set_item("frames", journal(py, r.frames.iter().cloned().map(Record::Frame))?)?;
            d.set_item("missing", journal(py, r.missing.iter().cloned().map(Record::FrameMissing))?)?;
            d.set_item("extra", journal(py, r.extra.iter().cloned().map(Record::FrameExtra))?)?;
            d.set_item("triggers", object(py, &triggers)?)
        })
    }

    /// Every missing frame of the completed steps (their `FrameMissing` records, with the
    /// reason), in plan order: what `lightrig resume --retake-missing` takes again.
    fn missing<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let all = py
            .detach(|| -> Result<Vec<_>, RustSessionError> {
                let mut all = Vec::new();
                for s in self.index.done_steps() {
                    all.extend(self.index.step(s)?.missing.into_iter().map(Record::FrameMissing));
                }
                Ok(all)
            })
            .map_err(session_err)?;
        object(py, &all)
    }

    /// Every extra frame of the completed steps (frames no trigger explains), in plan order.
    fn extras<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let all = py
            .detach(|| -> Result<Vec<_>, RustSessionError> {
                let mut all = Vec::new();
                for s in self.index.done_steps() {
                    all.extend(self.index.step(s)?.extra.into_iter().map(Record::FrameExtra));
                }
                Ok(all)
            })
            .map_err(session_err)?;
        object(py, &all)
    }

    /// The frames, read one at a time: of `step` (an id or a list of ids; every completed step
    /// in plan order if None) and `camera` (every camera if None). Each is a `Frame`.
    #[pyo3(signature = (step=None, camera=None))]
    fn frames(&self, step: Option<StepSelection>, camera: Option<u8>) -> PyResult<FrameIter> {
        let steps = step.map(|s| match s {
            StepSelection::One(s) => vec![s],
            StepSelection::Many(s) => s,
        });
        let frames = self.index.frames(steps, camera).map_err(session_err)?;
        Ok(FrameIter { frames, tick_hz: f64::from(self.index.manifest().device.tick_hz) })
    }

    /// Paired frames of the completed steps.
    fn __len__(&self) -> usize {
        let m = self.index.manifest();
        m.plan
            .steps
            .iter()
            .flat_map(|s| s.triggers.iter().map(move |t| self.index.frame_count(s.id, t.camera) as usize))
            .sum()
    }

    fn __repr__(&self) -> String {
        let m = self.index.manifest();
        let done = self.index.done_steps().len();
        format!(
            "Session('{}', rig={:?}, {} of {} steps done{})",
            self.index.dir().display(),
            rig_name(&m.rig).unwrap_or_default(),
            done,
            m.plan.steps.len(),
            if self.index.is_done() { ", complete" } else { "" }
        )
    }
}

impl Session {
    fn known(&self, step: StepId) -> PyResult<()> {
        self.index.check_step(step).map_err(session_err)
    }
}

/// Records as the journal has them (with their `type`).
fn journal<'py>(py: Python<'py>, records: impl Iterator<Item = Record>) -> PyResult<Bound<'py, PyAny>> {
    object(py, &records.collect::<Vec<_>>())
}

fn rig_name(rig: &str) -> Option<String> {
    let t: toml::Table = toml::from_str(rig).ok()?;
    t.get("rig")?.get("name")?.as_str().map(str::to_string)
}

/// `step=` as one id or several.
#[derive(FromPyObject)]
pub enum StepSelection {
    One(StepId),
    Many(Vec<StepId>),
}

/// The frames of a session, one at a time (`Session.frames`); each `next` reads and decodes one
/// file with the GIL released.
#[pyclass(module = "lightrig")]
pub struct FrameIter {
    frames: Frames,
    tick_hz: f64,
}

#[pymethods]
impl FrameIter {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__(mut slf: PyRefMut<'_, Self>, py: Python<'_>) -> PyResult<Option<Frame>> {
        let tick_hz = slf.tick_hz;
        let frames = &mut slf.frames;
        let Some(next) = py.detach(|| frames.next()) else { return Ok(None) };
        let f = next.map_err(session_err)?;
        Ok(Some(Frame {
            pixels: convert::image(py, f.image)?.unbind(),
            bits: f.bits,
            record: f.record,
            trigger: f.trigger,
            tick_hz,
        }))
    }
}

/// One frame: its pixels and the record and trigger it was paired with.
#[pyclass(frozen, module = "lightrig")]
pub struct Frame {
    record: FrameRecord,
    trigger: Option<TriggerEvent>,
    pixels: Py<PyAny>,
    bits: u8,
    tick_hz: f64,
}

#[pymethods]
impl Frame {
    /// The pixels, float32, `(height, width)` or `(height, width, channels)`: integer data as
    /// stored, normalised to [0, 1] (`* (2**bits - 1)` gives the camera's levels), float data as is.
    #[getter]
    fn pixels(&self, py: Python<'_>) -> Py<PyAny> {
        self.pixels.clone_ref(py)
    }

    /// Bits per sample in the file: 8, 16 or 32.
    #[getter]
    fn bits(&self) -> u8 {
        self.bits
    }

    #[getter]
    fn step(&self) -> StepId {
        self.record.step
    }

    #[getter]
    fn attempt(&self) -> u32 {
        self.record.attempt
    }

    #[getter]
    fn camera(&self) -> u8 {
        self.record.camera
    }

    /// The frame's number on its camera within the step (its trigger's `frame`).
    #[getter]
    fn frame(&self) -> u32 {
        self.record.frame
    }

    /// The device tick of the trigger's leading edge.
    #[getter]
    fn tick(&self) -> u64 {
        self.record.tick
    }

    /// The trigger pulse's width (the exposure of a camera exposing for the pulse), s.
    #[getter]
    fn exposure_s(&self) -> Option<f64> {
        self.trigger.as_ref().map(|t| f64::from(t.width) / self.tick_hz)
    }

    /// The file, relative to the session directory.
    #[getter]
    fn file(&self) -> String {
        self.record.file.clone()
    }

    /// The trigger event (`sequence`, `item`, `frame`, `camera`, `tick`, `width` and the rig's
    /// `snapshot` at that tick: `galvos`, `axes` in steps, `filters`, `lasers` as a bit mask),
    /// or None where the journal lost it.
    #[getter]
    fn trigger<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        object(py, &self.trigger)
    }

    /// The `Frame` journal record (docs/session-format.md §4).
    #[getter]
    fn record<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        object(py, &Record::Frame(self.record.clone()))
    }

    fn __repr__(&self) -> String {
        format!(
            "Frame(step={}, camera={}, frame={}, tick={}, file='{}')",
            self.record.step, self.record.camera, self.record.frame, self.record.tick, self.record.file
        )
    }
}
