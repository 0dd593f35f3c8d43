//! `lightrig._lightrig`: the Rust side of the `lightrig` Python package (python/lightrig). A thin
//! layer: every reader, fit and image operation is the Rust crates' own ([`lightrig_host`],
//! [`lightrig_imaging`], [`lightrig_cli::demo`]); this crate turns their results into NumPy
//! arrays and plain dicts and their errors into Python exceptions with the same text.
//!
//! - [`session`]: a session directory read-only, its frames streamed with their triggers.
//! - [`fit`]: each rig's fit, as `lightrig fit <rig>` runs it.
//! - [`imaging`]: image files, spectral EXR, HDR merge and response recovery, calibration.
//! - [`demo`]: the virtual rig's demos.
//! - [`convert`]: NumPy arrays and dicts from the Rust values; progress and Ctrl-C.

use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;

mod convert;
mod demo;
mod fit;
mod imaging;
mod session;

create_exception!(lightrig, LightrigError, PyException, "What lightrig could not do: the message says what was wrong, where (file, line, key) and what to do, as the `lightrig` command prints it.");
create_exception!(lightrig, SessionError, LightrigError, "A session directory that cannot be read: not a session, a damaged journal, a frame file that does not match its record.");
create_exception!(lightrig, FitError, LightrigError, "A fit that stopped: the session does not hold what the fit needs, or the rig file's `[plan.fit]` is wrong.");
create_exception!(
    lightrig,
    ImageError,
    LightrigError,
    "An image file or array that cannot be read, written or merged."
);
create_exception!(lightrig, DemoError, LightrigError, "A virtual-rig demo that failed.");

#[pymodule]
fn _lightrig(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    convert::quiet_interrupts();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("LightrigError", py.get_type::<LightrigError>())?;
    m.add("SessionError", py.get_type::<SessionError>())?;
    m.add("FitError", py.get_type::<FitError>())?;
    m.add("ImageError", py.get_type::<ImageError>())?;
    m.add("DemoError", py.get_type::<DemoError>())?;
    m.add_class::<session::Session>()?;
    m.add_class::<session::Frame>()?;
    m.add_class::<session::FrameIter>()?;
    m.add_function(wrap_pyfunction!(fit::fit_lls, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_firs_surface, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_firs_volume, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_display, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_brrdf, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_disco, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::read_image, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::write_image, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::read_spectral_exr, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::write_spectral_exr, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::hdr_merge, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::hdr_response, m)?)?;
    m.add_function(wrap_pyfunction!(imaging::calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(demo::demo, m)?)?;
    Ok(())
}
