//! Each rig's fit as `lightrig fit <rig>` runs it ([`lightrig_host::fit`]), its result as NumPy
//! arrays and dicts. With `out`, the same files the command writes are written there and listed
//! under `files`; without, nothing is left on disk.

use std::path::PathBuf;

use lightrig_host::fit::{brrdf, disco, display, firs, lls, with_overrides, FitError as RustFitError};
use lightrig_host::overrides::Override;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::convert::{array, dict, image, interruptible, object, paths, points, triangles, vectors, Scratch};
use crate::FitError;

fn fit_err(e: RustFitError) -> PyErr {
    FitError::new_err(e.0)
}

/// `set=`: the rig-file changes `lightrig fit --set KEY=VALUE` takes, one `"KEY=VALUE"` each.
fn overrides(set: Option<Vec<String>>) -> PyResult<Vec<Override>> {
    set.unwrap_or_default()
        .iter()
        .map(|s| s.parse::<Override>().map_err(|e| FitError::new_err(format!("set: {e}"))))
        .collect()
}

/// `fit` with `set`'s overrides applied to the session's rig file, on the calling thread (the
/// worker's: the overrides are thread-local), its refusal of a key no fit may change a
/// [`RustFitError`] like the fit's own.
fn overridden<T>(set: &[Override], fit: impl FnOnce() -> Result<T, RustFitError>) -> Result<T, RustFitError> {
    with_overrides(set, fit)?
}

/// `out`, created, or a scratch directory removed after the call.
fn out_dir(out: &Option<PathBuf>, what: &str) -> PyResult<(PathBuf, Option<Scratch>)> {
    match out {
        Some(dir) => {
            std::fs::create_dir_all(dir).map_err(|e| {
                FitError::new_err(format!("{}: cannot create the output directory: {e}", dir.display()))
            })?;
            Ok((dir.clone(), None))
        }
        None => {
            let s = Scratch::new(what).map_err(|e| FitError::new_err(format!("a scratch directory: {e}")))?;
            Ok((s.path().to_path_buf(), Some(s)))
        }
    }
}

/// `lightrig fit lls`: the linear-light-source maps of `session`, `(height, width, …)` arrays.
#[pyfunction]
#[pyo3(signature = (session, calibration=None, out=None, progress=None, set=None))]
pub fn fit_lls<'py>(
    py: Python<'py>,
    session: PathBuf,
    calibration: Option<PathBuf>,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "lls")?;
    let written = out.is_some();
    let (maps, files) = interruptible(py, progress, |p| -> Result<_, RustFitError> {
        overridden(&set, || {
            let maps = lls::fit_session(&session, calibration.as_deref(), &dir, p)?;
            let files = if written { lls::write_outputs(&maps, &dir)? } else { Vec::new() };
            Ok((maps, files))
        })
    })?
    .map_err(fit_err)?;
    let (w, h) = (maps.width as usize, maps.height as usize);
    let n = w * h;
    let per = |f: &dyn Fn(&lightrig_pipelines::lls::TraceFit) -> f64| -> Vec<f32> {
        maps.fit.iter().zip(&maps.fitted).map(|(t, &ok)| if ok { f(t) as f32 } else { f32::NAN }).collect()
    };
    let rgb = |f: &dyn Fn(&lightrig_pipelines::lls::TraceFit) -> [f64; 3]| -> Vec<f32> {
        maps.fit
            .iter()
            .zip(&maps.fitted)
            .flat_map(|(t, &ok)| if ok { f(t).map(|x| x as f32) } else { [f32::NAN; 3] })
            .collect()
    };
    dict(py, |d| {
        d.set_item("width", w)?;
        d.set_item("height", h)?;
        d.set_item("fitted", array(py, maps.fitted.clone(), &[h, w])?)?;
        d.set_item("diffuse", array(py, rgb(&|t| t.diffuse), &[h, w, 3])?)?;
        d.set_item("specular", array(py, rgb(&|t| t.specular), &[h, w, 3])?)?;
        d.set_item("alpha", array(py, per(&|t| t.alpha), &[h, w])?)?;
        d.set_item("residual", array(py, per(&|t| t.residual), &[h, w])?)?;
        // The GGX fit of the same traces (`maps.exr`'s `ggx.*` layers), where it was made.
        match &maps.ggx {
            Some(g) => {
                let per = |f: &dyn Fn(&lightrig_pipelines::lls::TraceFit) -> Vec<f64>| -> Vec<f32> {
                    g.iter()
                        .zip(&maps.fitted)
                        .flat_map(|(t, &ok)| {
                            let v = f(t);
                            v.iter().map(|&x| if ok { x as f32 } else { f32::NAN }).collect::<Vec<_>>()
                        })
                        .collect()
                };
                d.set_item(
                    "ggx",
                    dict(py, |gd| {
                        gd.set_item("diffuse", array(py, per(&|t| t.diffuse.to_vec()), &[h, w, 3])?)?;
                        gd.set_item("specular", array(py, per(&|t| t.specular.to_vec()), &[h, w, 3])?)?;
                        gd.set_item("alpha", array(py, per(&|t| vec![t.alpha]), &[h, w])?)?;
                        gd.set_item("residual", array(py, per(&|t| vec![t.residual]), &[h, w])?)
                    })?,
                )?;
            }
            None => d.set_item("ggx", py.None())?,
        }
        d.set_item("points", vectors(py, &maps.points, &[h, w])?)?;
        d.set_item("normals", vectors(py, &maps.normals, &[h, w])?)?;
        d.set_item("geometric_normals", vectors(py, &maps.geometric_normals, &[h, w])?)?;
        d.set_item("photometric_normals", vectors(py, &maps.photometric_normals, &[h, w])?)?;
        debug_assert_eq!(maps.translucency.len(), n);
        if maps.measured.translucency {
            d.set_item("translucency", array(py, maps.translucency.clone(), &[h, w])?)?;
        } else {
            d.set_item("translucency", py.None())?;
        }
        // What was measured (`maps.exr`'s `valid` layer) and the fit's checks (`quality.json`).
        let valid = lls::quality::validity(&maps);
        let quality = lls::quality::assess(&maps, &valid);
        d.set_item(
            "valid",
            dict(py, |vd| {
                vd.set_item("reflectance", array(py, valid.reflectance.clone(), &[h, w])?)?;
                vd.set_item("roughness", array(py, valid.roughness.clone(), &[h, w])?)?;
                vd.set_item("height", array(py, valid.height.clone(), &[h, w])?)?;
                vd.set_item("translucency", array(py, valid.translucency.clone(), &[h, w])?)?;
                vd.set_item("physical", array(py, valid.physical.clone(), &[h, w])?)
            })?,
        )?;
        d.set_item("quality", object(py, &quality)?)?;
        d.set_item("normal_blend", format!("{:?}", maps.normal_blend).to_lowercase())?;
        d.set_item("diagonal_mounts", maps.diagonal_mounts.clone())?;
        d.set_item("registration_rms", maps.registration_rms)?;
        d.set_item("scale", maps.scale.to_vec())?;
        d.set_item("specular_strip", (maps.specular_strip.0, maps.specular_strip.1))?;
        let t = maps.timing;
        d.set_item(
            "timing",
            dict(py, |td| {
                td.set_item("frames", t.frames)?;
                td.set_item("read_s", t.read_s)?;
                td.set_item("fit_s", t.fit_s)?;
                td.set_item("threads", t.threads)
            })?,
        )?;
        d.set_item("notes", maps.tables_note.clone())?;
        d.set_item("files", paths(&files))
    })
}

/// `lightrig fit firs-surface`: the surface points of every orientation and merged.
#[pyfunction]
#[pyo3(signature = (session, out=None, progress=None, set=None))]
pub fn fit_firs_surface<'py>(
    py: Python<'py>,
    session: PathBuf,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "firs")?;
    let written = out.is_some();
    let (s, files) = interruptible(py, progress, |p| -> Result<_, RustFitError> {
        overridden(&set, || {
            let s = firs::fit_surface(&session, &|done, total| p(done, total))?;
            let files = if written { firs::write_outputs(&s, &dir)? } else { Vec::new() };
            Ok((s, files))
        })
    })?
    .map_err(fit_err)?;
    let (w, h) = (s.width, s.height);
    dict(py, |d| {
        d.set_item("width", w)?;
        d.set_item("height", h)?;
        d.set_item("points", points(py, &s.merged)?)?;
        let scans = PyList::empty(py);
        for sc in &s.scans {
            scans.append(dict(py, |sd| {
                sd.set_item("angle_deg", sc.angle_deg)?;
                sd.set_item("points", vectors(py, &sc.points, &[h, w])?)
            })?)?;
        }
        d.set_item("scans", scans)?;
        d.set_item("ray_pixels", s.ray_pixels)?;
        d.set_item("ray_rms_mm", s.ray_rms)?;
        d.set_item("sheet_samples", s.sheet_samples)?;
        d.set_item("sheet_rms_mm", s.sheet_rms)?;
        d.set_item("files", paths(&files))
    })
}

/// `lightrig fit firs-volume`: the occupancy volume (`(z, y, x)`, read back from the
/// `volume.raw` the fit streams it to) and its isosurface.
#[pyfunction]
#[pyo3(signature = (session, out=None, progress=None, set=None))]
pub fn fit_firs_volume<'py>(
    py: Python<'py>,
    session: PathBuf,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "firs-volume")?;
    let written = out.is_some();
    let (v, files, occupancy) = interruptible(py, progress, |p| -> Result<_, RustFitError> {
        overridden(&set, || {
            let v = firs::fit_volume(&session, &dir, &|done, total| p(done, total))?;
            let files = if written { firs::write_volume_outputs(&v, &dir)? } else { Vec::new() };
            let bytes =
                std::fs::read(&v.raw[0]).map_err(|e| RustFitError(format!("{}: {e}", v.raw[0].display())))?;
            let occupancy: Vec<f32> =
                bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            Ok((v, files, occupancy))
        })
    })?
    .map_err(fit_err)?;
    let [nx, ny, nz] = v.grid.dims;
    if occupancy.len() != nx * ny * nz {
        return Err(FitError::new_err(format!(
            "{}: {} values, the grid has {nx}×{ny}×{nz}",
            v.raw[0].display(),
            occupancy.len()
        )));
    }
    dict(py, |d| {
        d.set_item("occupancy", array(py, occupancy, &[nz, ny, nx])?)?;
        d.set_item("origin_mm", v.grid.origin.to_vec())?;
        d.set_item("voxel_mm", v.grid.voxel.to_vec())?;
        d.set_item("vertices", points(py, &v.mesh.vertices)?)?;
        d.set_item("triangles", triangles(py, &v.mesh.triangles)?)?;
        d.set_item("enclosed_mm3", v.enclosed_mm3)?;
        d.set_item("ray_pixels", v.ray_pixels)?;
        d.set_item("sheet_samples", v.sheet_samples)?;
        d.set_item("sheet_rms_mm", v.sheet_rms)?;
        d.set_item("map_rms_mm", v.map_rms)?;
        d.set_item("files", paths(&files))
    })
}

/// `lightrig fit display`: a calibration session's calibration, or what a display session's
/// targets showed.
#[pyfunction]
#[pyo3(signature = (session, calibration=None, out=None, set=None))]
pub fn fit_display<'py>(
    py: Python<'py>,
    session: PathBuf,
    calibration: Option<PathBuf>,
    out: Option<PathBuf>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "display")?;
    let written = out.is_some();
    let (fitted, files) = interruptible(py, None, |_| {
        overridden(&set, || display::fit_session(&session, calibration.as_deref(), &dir))
    })?
    .map_err(fit_err)?;
    let files = if written { files } else { Vec::new() };
    dict(py, |d| {
        match &fitted {
            display::Fitted::Calibration(c) => {
                d.set_item("kind", "calibration")?;
                d.set_item("calibration", object(py, c)?)?;
            }
            display::Fitted::Shown(shown, c) => {
                d.set_item("kind", "shown")?;
                let list = PyList::empty(py);
                for s in shown {
                    list.append(dict(py, |sd| {
                        sd.set_item("step", s.step)?;
                        sd.set_item("target", s.target.to_vec())?;
                        sd.set_item("asked", s.asked.to_vec())?;
                        sd.set_item("shown", s.shown.to_vec())?;
                        sd.set_item("shape_error", s.shape_error)?;
                        sd.set_item("error", s.error().to_vec())
                    })?)?;
                }
                d.set_item("shown", list)?;
                d.set_item("calibration", object(py, c)?)?;
            }
        }
        d.set_item("files", paths(&files))
    })
}

/// `lightrig fit brrdf`: the wavelength pairs, each sphere's samples and binned BRRDF, and the
/// PCA's figures.
#[pyfunction]
#[pyo3(signature = (session, spectralon=None, out=None, progress=None, set=None))]
pub fn fit_brrdf<'py>(
    py: Python<'py>,
    session: PathBuf,
    spectralon: Option<PathBuf>,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "brrdf")?;
    let written = out.is_some();
    let (f, files) = interruptible(py, progress, |p| -> Result<_, RustFitError> {
        overridden(&set, || {
            let f = brrdf::fit_session(&session, spectralon.as_deref(), p)?;
            let files = if written { brrdf::write_outputs(&f, &dir)? } else { Vec::new() };
            Ok((f, files))
        })
    })?
    .map_err(fit_err)?;
    let np = f.pairs.len();
    dict(py, |d| {
        let pairs: Vec<u16> = f.pairs.iter().flat_map(|&(i, o)| [i, o]).collect();
        d.set_item("pairs", array(py, pairs, &[np, 2])?)?;
        d.set_item("pca_angles", f.pca_angles.clone())?;
        d.set_item("notes", f.notes.clone())?;
        d.set_item("size", (f.size.0, f.size.1))?;
        let spheres = PyList::empty(py);
        for s in &f.spheres {
            let b = &s.binned;
            let ns = s.samples.len();
            spheres.append(dict(py, |sd| {
                sd.set_item("name", &s.name)?;
                sd.set_item("bins", array(py, b.values.clone(), &[b.n, b.n, b.n, b.k])?)?;
                sd.set_item("bin_counts", array(py, b.count.clone(), &[b.n, b.n, b.n])?)?;
                let values: Vec<f64> = s.samples.iter().flat_map(|x| x.values.iter().copied()).collect();
                let width = values.len().checked_div(ns).unwrap_or(np);
                sd.set_item("values", array(py, values, &[ns, width])?)?;
                let angles: Vec<f64> =
                    s.samples.iter().flat_map(|x| [x.angles.0, x.angles.1, x.angles.2]).collect();
                sd.set_item("angles", array(py, angles, &[ns, 3])?)?;
                sd.set_item(
                    "light_deg",
                    array(py, s.samples.iter().map(|x| x.light_deg).collect::<Vec<_>>(), &[ns])?,
                )?;
                sd.set_item("normals", points(py, &s.samples.iter().map(|x| x.normal).collect::<Vec<_>>())?)?;
                let xy: Vec<u32> = s.samples.iter().flat_map(|x| [x.x, x.y]).collect();
                sd.set_item("pixels", array(py, xy, &[ns, 2])?)?;
                sd.set_item(
                    "reconstructed",
                    array(py, s.samples.iter().map(|x| x.reconstructed).collect::<Vec<_>>(), &[ns])?,
                )?;
                sd.set_item("same_angle", object(py, &s.same_angle)?)?;
                sd.set_item("transfer", object(py, &s.transfer)?)
            })?)?;
        }
        d.set_item("spheres", spheres)?;
        d.set_item("files", paths(&files))
    })
}

/// `lightrig fit disco`: the throughput factor matrix `F` over the mesh's vertices and the
/// fit's figures.
#[pyfunction]
#[pyo3(signature = (session, mesh=None, out=None, progress=None, set=None))]
pub fn fit_disco<'py>(
    py: Python<'py>,
    session: PathBuf,
    mesh: Option<PathBuf>,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    set: Option<Vec<String>>,
) -> PyResult<Bound<'py, PyDict>> {
    let set = overrides(set)?;
    let (dir, _scratch) = out_dir(&out, "disco")?;
    let written = out.is_some();
    let (f, files) = interruptible(py, progress, |p| -> Result<_, RustFitError> {
        overridden(&set, || {
            let f = disco::fit_session(&session, mesh.as_deref(), p)?;
            let files = if written { disco::write_outputs(&f, &dir)? } else { Vec::new() };
            Ok((f, files))
        })
    })?
    .map_err(fit_err)?;
    let n = f.matrix.n;
    dict(py, |d| {
        let values: Vec<f32> = f.matrix.values.iter().flatten().copied().collect();
        d.set_item("F", array(py, values, &[n, n, 3])?)?;
        d.set_item("observed", array(py, f.observed.clone(), &[n, n])?)?;
        d.set_item("vertices", points(py, &f.mesh.vertices)?)?;
        d.set_item("normals", points(py, &f.mesh.normals)?)?;
        d.set_item("triangles", triangles(py, &f.mesh.triangles)?)?;
        d.set_item("flux", f.flux.to_vec())?;
        d.set_item("beam_sigma_mm", f.beam_sigma_mm)?;
        d.set_item("eta", f.eta)?;
        d.set_item("views", f.views)?;
        d.set_item("frames", f.frames)?;
        d.set_item("used", f.used)?;
        d.set_item("missed", f.missed)?;
        d.set_item("held_out_frames", f.held_out_frames)?;
        d.set_item("lit_columns", f.lit_columns)?;
        d.set_item(
            "held_out",
            dict(py, |h| {
                h.set_item("frames", f.held_out.frames)?;
                h.set_item("pixels", f.held_out.pixels)?;
                h.set_item("median_rel_rms", f.held_out.median_rel_rms)?;
                h.set_item("near_mm", f.held_out.near_mm)
            })?,
        )?;
        d.set_item("local_spots", f.spots.len())?;
        // The local term on its atlas: each texture `(height, width, 3)` as `<name>.exr` holds it,
        // the masks of the texels on the charts and of those a spot (or a frame) gave.
        let (w, h) = (f.atlas.width.max(1) as usize, f.atlas.height.max(1) as usize);
        d.set_item(
            "textures",
            dict(py, |t| {
                for (name, im) in disco::local_textures(&f) {
                    t.set_item(name, image(py, im)?)?;
                }
                Ok(())
            })?,
        )?;
        let mask = |m: &[bool]| {
            array(py, (0..w * h).map(|i| m.get(i).copied().unwrap_or(false)).collect::<Vec<_>>(), &[h, w])
        };
        let covered: Vec<bool> = f.atlas.texels.iter().map(Option::is_some).collect();
        d.set_item("covered", mask(&covered)?)?;
        d.set_item("kernel_observed", mask(&f.local.observed)?)?;
        d.set_item("detail_observed", mask(&f.detail.observed)?)?;
        d.set_item("atlas", object(py, &disco::atlas_json(&f))?)?;
        d.set_item("spots", object(py, &disco::spots_json(&f))?)?;
        d.set_item("scan", object(py, &disco::scan_json(&f.scan))?)?;
        d.set_item("local_hidden", f.local_hidden)?;
        d.set_item("local_failed", f.local_failed)?;
        d.set_item("files", paths(&files))
    })
}
