//! Rust values as NumPy arrays and plain Python objects; a long call's progress, its release of
//! the GIL and its interruption by Ctrl-C.
//!
//! Arrays are made from the Rust `Vec` that holds the result, moved, not copied: NumPy's array
//! owns the Rust allocation (`PyArray::from_vec`) and `reshape` gives a view of it.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use lightrig_imaging::io::Image;
use numpy::{Element, PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use serde::Serialize;

/// `values` (row-major) as an array of `shape`, without a copy.
pub fn array<'py, T: Element>(
    py: Python<'py>,
    values: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    let flat = PyArray1::from_vec(py, values);
    Ok(flat.reshape(shape.to_vec())?.into_any())
}

/// An image as `(height, width)` for one channel, else `(height, width, channels)`.
pub fn image<'py>(py: Python<'py>, img: Image) -> PyResult<Bound<'py, PyAny>> {
    let (h, w, c) = (img.height as usize, img.width as usize, usize::from(img.channels));
    if c == 1 {
        array(py, img.data, &[h, w])
    } else {
        array(py, img.data, &[h, w, c])
    }
}

/// Optional 3-vectors as `(…shape, 3)` float32, NaN where absent.
pub fn vectors<'py>(py: Python<'py>, v: &[Option<[f64; 3]>], shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f32> = v.iter().flat_map(|p| p.map_or([f32::NAN; 3], |p| p.map(|x| x as f32))).collect();
    let mut s = shape.to_vec();
    s.push(3);
    array(py, flat, &s)
}

/// 3-vectors as `(n, 3)` float64.
pub fn points<'py>(py: Python<'py>, v: &[[f64; 3]]) -> PyResult<Bound<'py, PyAny>> {
    array(py, v.iter().flatten().copied().collect::<Vec<f64>>(), &[v.len(), 3])
}

/// Triangles as `(n, 3)` uint32.
pub fn triangles<'py>(py: Python<'py>, t: &[[u32; 3]]) -> PyResult<Bound<'py, PyAny>> {
    array(py, t.iter().flatten().copied().collect::<Vec<u32>>(), &[t.len(), 3])
}

/// A serialisable value as Python objects (dicts, lists, numbers, strings), as its JSON reads.
pub fn object<'py, T: Serialize + ?Sized>(py: Python<'py>, v: &T) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, v).map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))
}

/// Paths as a list of strings.
pub fn paths(files: &[PathBuf]) -> Vec<String> {
    files.iter().map(|p| p.display().to_string()).collect()
}

/// A dict built by `f`.
pub fn dict<'py>(
    py: Python<'py>,
    f: impl FnOnce(&Bound<'py, PyDict>) -> PyResult<()>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    f(&d)?;
    Ok(d)
}

/// The panic payload that unwinds a fit interrupted from its progress callback.
struct Interrupted;

/// Keeps the default panic message from being printed for [`Interrupted`], which is not a bug.
pub fn quiet_interrupts() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if info.payload().downcast_ref::<Interrupted>().is_none() {
                previous(info);
            }
        }));
    });
}

/// Runs `work` with the GIL released, on a thread of its own, giving it a progress function that
/// calls `callback(done, total)` (if any). Meanwhile this thread, Python's main thread where it
/// was called from there, checks for Ctrl-C every [`POLL`]. A `KeyboardInterrupt` (or the
/// callback's own exception) stops the work at its next progress report: the report unwinds the
/// work's stack, dropping what it held (scratch files included), and the exception is raised
/// here. Work that reports no progress runs to its end, and the exception is raised then.
pub fn interruptible<T: Send>(
    py: Python<'_>,
    callback: Option<Py<PyAny>>,
    work: impl FnOnce(&(dyn Fn(u64, u64) + Sync)) -> T + Send,
) -> PyResult<T> {
    interruptible_with(py, callback, &|| {}, work)
}

/// [`interruptible`], calling `on_cancel` once when Ctrl-C (or the callback's exception) stops
/// the work: for work that stops by a flag of its own (an acquisition's
/// [`lightrig_host::client::Interrupt`]) rather than at a progress report.
pub fn interruptible_with<T: Send>(
    py: Python<'_>,
    callback: Option<Py<PyAny>>,
    on_cancel: &(dyn Fn() + Sync),
    work: impl FnOnce(&(dyn Fn(u64, u64) + Sync)) -> T + Send,
) -> PyResult<T> {
    let cancel = AtomicBool::new(false);
    let raised: Mutex<Option<PyErr>> = Mutex::new(None);
    let stop = |e: PyErr| {
        let mut slot = raised.lock().unwrap_or_else(|p| p.into_inner());
        if slot.is_none() {
            *slot = Some(e);
        }
        if !cancel.swap(true, Ordering::SeqCst) {
            on_cancel();
        }
    };
    let progress = |done: u64, total: u64| {
        if !cancel.load(Ordering::SeqCst) {
            if let Some(cb) = &callback {
                if let Err(e) = Python::attach(|py| cb.call1(py, (done, total)).map(drop)) {
                    stop(e);
                }
            }
        }
        if cancel.load(Ordering::SeqCst) {
            std::panic::panic_any(Interrupted);
        }
    };
    let outcome = py.detach(|| {
        std::thread::scope(|s| {
            let waiting = std::thread::current();
            let worker = s.spawn(move || {
                let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(&progress)));
                waiting.unpark();
                r
            });
            while !worker.is_finished() {
                std::thread::park_timeout(POLL);
                if let Err(e) = Python::attach(|py| py.check_signals()) {
                    stop(e);
                }
            }
            worker.join().unwrap_or_else(Err)
        })
    });
    let stored = raised.lock().unwrap_or_else(|p| p.into_inner()).take();
    match outcome {
        // Ctrl-C during work that reports no progress: raised once it is done, not lost.
        Ok(v) => stored.map_or(Ok(v), Err),
        Err(payload) => match (payload.downcast_ref::<Interrupted>(), stored) {
            (Some(_), Some(e)) => Err(e),
            _ => std::panic::resume_unwind(payload),
        },
    }
}

/// How often a long call looks for Ctrl-C.
const POLL: std::time::Duration = std::time::Duration::from_millis(50);

/// A scratch directory removed when dropped: where a fit that must write files writes them
/// when the caller did not ask for the files.
pub struct Scratch(PathBuf);

impl Scratch {
    pub fn new(what: &str) -> std::io::Result<Scratch> {
        static COUNT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = COUNT.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("lightrig-{what}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)?;
        Ok(Scratch(dir))
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
