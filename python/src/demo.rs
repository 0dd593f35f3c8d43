//! `lightrig.demo`: a virtual-rig demo as `lightrig demo` runs it ([`lightrig_cli::demo`]): the
//! acquisition, the fit and the report against the ground truth.

use std::path::{Path, PathBuf};

use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{dict, interruptible_with, paths};
use crate::DemoError;

/// The session directories under `dir` (those with a `manifest.json`), sorted.
fn sessions_under(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        if d.join(lightrig_host::session::MANIFEST).is_file() {
            found.push(d);
            continue;
        }
        if let Ok(entries) = std::fs::read_dir(&d) {
            for e in entries.flatten() {
                if e.file_type().is_ok_and(|t| t.is_dir()) {
                    stack.push(e.path());
                }
            }
        }
    }
    found.sort();
    found
}

/// Runs `lightrig demo METHOD` (`lls`, `firs`, `display`, `brrdf`, `disco`) into `out/METHOD`.
/// Returns a dict: `dir`, `report` (report.md's text), `report_path`, `missed` (the accuracy
/// targets missed) and `sessions` (the session directories it acquired). With `check`, a missed
/// target raises `DemoError`.
#[pyfunction]
#[pyo3(
    signature = (method="lls", quick=true, out=PathBuf::from("lightrig-demo"), seed=1, check=false, progress=false),
    text_signature = "(method='lls', quick=True, out='lightrig-demo', seed=1, check=False, progress=False)"
)]
pub fn demo<'py>(
    py: Python<'py>,
    method: &str,
    quick: bool,
    out: PathBuf,
    seed: u64,
    check: bool,
    progress: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let interrupt = std::sync::Arc::new(lightrig_host::client::Interrupt::default());
    let args = lightrig_cli::demo::Args {
        method: method.to_string(),
        quick,
        out: out.clone(),
        seed,
        check,
        real_time: false,
        step_mm: None,
        camera_gamma: None,
        serve: None,
        quiet: !progress,
        interrupt: Some(interrupt.clone()),
    };
    // Ctrl-C stops the virtual device at once (an emergency stop, as on a real rig); a fit the
    // demo is running finishes first.
    let run = interruptible_with(py, None, &|| interrupt.request(), |_| lightrig_cli::demo::run_demo(&args))?
        .map_err(|e| DemoError::new_err(e.message))?;
    let dir = run.report.parent().map(Path::to_path_buf).unwrap_or(out);
    let report = std::fs::read_to_string(&run.report)
        .map_err(|e| DemoError::new_err(format!("{}: {e}", run.report.display())))?;
    if check && !run.missed.is_empty() {
        return Err(DemoError::new_err(format!("accuracy targets missed: {}", run.missed.join(", "))));
    }
    let sessions = sessions_under(&dir);
    dict(py, |d| {
        d.set_item("method", method)?;
        d.set_item("dir", dir.display().to_string())?;
        d.set_item("report", report)?;
        d.set_item("report_path", run.report.display().to_string())?;
        d.set_item("missed", run.missed.clone())?;
        d.set_item("sessions", paths(&sessions))
    })
}
