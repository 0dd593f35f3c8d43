//! Image files, spectral EXR, HDR merging and response recovery, camera calibration: the
//! [`lightrig_imaging`] functions on NumPy arrays.

use std::collections::BTreeMap;
use std::path::PathBuf;

use lightrig_imaging::calib_file::{self, BoardSpec};
use lightrig_imaging::hdr::{
    self, DebevecOptions, MergeOptions, Response, RobertsonOptions, Stack, WeightShape, Weights,
};
use lightrig_imaging::io::{self, BispectralImage, BitDepth, Encoding, ExrPrecision, Image, Nm, ReadOptions};
use numpy::{PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{array, dict, image, object};
use crate::ImageError;

fn image_err(e: impl std::fmt::Display) -> PyErr {
    ImageError::new_err(e.to_string())
}

/// Reads a PNG, TIFF or EXR file as float32 `(height, width[, channels])`. Integer data is
/// normalised to [0, 1]; `linear=True` takes it as linear levels (a camera's raw output), else
/// as sRGB-encoded (the values as stored either way: no transfer function is applied). Returns
/// `(pixels, bits)`.
#[pyfunction]
#[pyo3(signature = (path, linear=true))]
pub fn read_image<'py>(py: Python<'py>, path: PathBuf, linear: bool) -> PyResult<(Bound<'py, PyAny>, u8)> {
    let assume = if linear { Encoding::Linear } else { Encoding::Srgb };
    let (img, bits) = py
        .detach(|| {
            let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
            io::decode(&bytes, &path, ReadOptions { assume, expect_depth: None }).map_err(|e| e.to_string())
        })
        .map_err(ImageError::new_err)?;
    Ok((image(py, img)?, bits))
}

/// `(height, width[, channels])` float32 as an [`Image`] (the samples copied into it).
fn from_array(a: &PyReadonlyArrayDyn<'_, f32>, what: &str) -> PyResult<Image> {
    let shape = a.shape();
    let (h, w, c) = match *shape {
        [h, w] => (h, w, 1),
        [h, w, c] if (1..=4).contains(&c) => (h, w, c),
        _ => {
            return Err(ImageError::new_err(format!(
                "{what}: an array of shape {shape:?}; give (height, width) or (height, width, channels) with 1 to 4 channels"
            )))
        }
    };
    let data = a.as_slice().map(<[f32]>::to_vec).unwrap_or_else(|_| a.as_array().iter().copied().collect());
    Ok(Image { width: w as u32, height: h as u32, channels: c as u8, data, encoding: Encoding::Linear })
}

/// Writes float32 `pixels` to `path`, the format by its extension: `.exr` (`precision`
/// `"half"` or `"float"`), `.png` or `.tif`/`.tiff` (`bits` 8 or 16, values in [0, 1]).
#[pyfunction]
#[pyo3(signature = (path, pixels, precision="half", bits=16))]
pub fn write_image(
    py: Python<'_>,
    path: PathBuf,
    pixels: PyReadonlyArrayDyn<'_, f32>,
    precision: &str,
    bits: u8,
) -> PyResult<()> {
    let img = from_array(&pixels, &path.display().to_string())?;
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    let depth = match bits {
        8 => BitDepth::Eight,
        16 => BitDepth::Sixteen,
        other => {
            return Err(ImageError::new_err(format!("bits={other}: PNG and TIFF are written with 8 or 16")))
        }
    };
    let precision = match precision {
        "half" => ExrPrecision::Half,
        "float" => ExrPrecision::Float,
        other => return Err(ImageError::new_err(format!("precision={other:?}: give \"half\" or \"float\""))),
    };
    py.detach(|| match ext.as_str() {
        "exr" => io::write_exr(&path, &img, precision).map_err(|e| e.to_string()),
        "png" => io::write_png(&path, &img, depth).map_err(|e| e.to_string()),
        "tif" | "tiff" => io::write_tiff(&path, &img, depth).map_err(|e| e.to_string()),
        _ => Err(format!("{}: write .exr, .png or .tif", path.display())),
    })
    .map_err(ImageError::new_err)
}

/// Reads a bispectral EXR (Fichet et al. 2021's layout, as colour-science reads it): a dict of
/// `width`, `height`, `diagonal` (`{λ nm: (height, width)}`) and `reradiation` (`{(λi, λo):
/// (height, width)}`).
#[pyfunction]
pub fn read_spectral_exr<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let b = py.detach(|| BispectralImage::read(&path)).map_err(image_err)?;
    let (w, h) = (b.width as usize, b.height as usize);
    dict(py, |d| {
        d.set_item("width", w)?;
        d.set_item("height", h)?;
        let diag = PyDict::new(py);
        for (nm, v) in b.diagonal {
            diag.set_item(nm.0, array(py, v, &[h, w])?)?;
        }
        let rerad = PyDict::new(py);
        for ((i, o), v) in b.reradiation {
            rerad.set_item((i.0, o.0), array(py, v, &[h, w])?)?;
        }
        d.set_item("diagonal", diag)?;
        d.set_item("reradiation", rerad)
    })
}

/// Writes a bispectral EXR: `diagonal` `{λ nm: (height, width)}` and `reradiation` `{(λi, λo):
/// (height, width)}`, float32, all of one size.
#[pyfunction]
#[pyo3(signature = (path, diagonal, reradiation=None))]
pub fn write_spectral_exr(
    py: Python<'_>,
    path: PathBuf,
    diagonal: BTreeMap<Wavelength, PyReadonlyArrayDyn<'_, f32>>,
    reradiation: Option<BTreeMap<(Wavelength, Wavelength), PyReadonlyArrayDyn<'_, f32>>>,
) -> PyResult<()> {
    let mut size: Option<(usize, usize)> = None;
    let mut plane = |a: &PyReadonlyArrayDyn<'_, f32>, name: String| -> PyResult<Vec<f32>> {
        let s = a.shape();
        let [h, w] = *s else {
            return Err(ImageError::new_err(format!(
                "{name}: shape {s:?}; each wavelength is one (height, width) plane"
            )));
        };
        match size {
            None => size = Some((h, w)),
            Some(first) if first != (h, w) => {
                return Err(ImageError::new_err(format!(
                    "{name}: {h}×{w}, the first plane is {}×{}; every plane has one size",
                    first.0, first.1
                )))
            }
            Some(_) => {}
        }
        Ok(a.as_array().iter().copied().collect())
    };
    let mut b = BispectralImage::new(0, 0);
    for (nm, a) in &diagonal {
        b.diagonal.insert(nm.0, plane(a, format!("diagonal[{}]", nm.0 .0))?);
    }
    for ((i, o), a) in reradiation.iter().flatten() {
        b.reradiation.insert((i.0, o.0), plane(a, format!("reradiation[({}, {})]", i.0 .0, o.0 .0))?);
    }
    let (h, w) = size.ok_or_else(|| ImageError::new_err("no planes given"))?;
    b.width = w as u32;
    b.height = h as u32;
    py.detach(|| b.write(&path)).map_err(image_err)
}

/// A wavelength key, nm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Wavelength(Nm);
impl<'a, 'py> FromPyObject<'a, 'py> for Wavelength {
    type Error = PyErr;
    fn extract(ob: pyo3::Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        Ok(Wavelength(Nm(ob.extract::<f64>()?)))
    }
}

/// An exposure series of 8- or 16-bit images.
#[derive(FromPyObject)]
pub enum Series<'py> {
    U8(Vec<PyReadonlyArrayDyn<'py, u8>>),
    U16(Vec<PyReadonlyArrayDyn<'py, u16>>),
}

/// `(height, width, channels)` of an exposure series, all alike.
fn series_shape(shapes: &[&[usize]]) -> PyResult<(usize, usize, usize)> {
    let shape = |s: &[usize]| match *s {
        [h, w] => Ok((h, w, 1)),
        [h, w, c] => Ok((h, w, c)),
        _ => Err(ImageError::new_err(format!("an image of shape {s:?}: give (height, width[, channels])"))),
    };
    let first = shape(shapes.first().ok_or_else(|| ImageError::new_err("no images given"))?)?;
    for (j, s) in shapes.iter().enumerate() {
        if shape(s)? != first {
            return Err(ImageError::new_err(format!(
                "image {j} has shape {s:?}, image 0 {first:?}: one series, one size"
            )));
        }
    }
    Ok(first)
}

/// An exposure series' arrays as a [`Stack`] (views of them, not copies).
fn stack_of<'a, T: hdr::Sample + numpy::Element>(
    arrays: &'a [PyReadonlyArrayDyn<'_, T>],
    times: Vec<f32>,
) -> PyResult<Stack<'a, T>> {
    let shapes: Vec<&[usize]> = arrays.iter().map(|a| a.shape()).collect();
    let (h, w, c) = series_shape(&shapes)?;
    let slices: Vec<&[T]> = arrays
        .iter()
        .map(|a| {
            a.as_slice().map_err(|_| {
                ImageError::new_err("an image that is not C-contiguous: np.ascontiguousarray it")
            })
        })
        .collect::<PyResult<_>>()?;
    Stack::new(w, h, c, slices, times).map_err(image_err)
}

fn weights(levels: usize, black: u32, saturation: Option<u32>, shape: &str) -> PyResult<Weights> {
    let shape = match shape {
        "snr" => WeightShape::Snr,
        "hat" => WeightShape::Hat,
        other => return Err(ImageError::new_err(format!("weights={other:?}: give \"snr\" or \"hat\""))),
    };
    Ok(Weights { black, saturation: saturation.unwrap_or(levels as u32 - 1), shape })
}

/// Merges an exposure series (`images`: uint8 or uint16 arrays, `times`: exposures in s)
/// through the camera's response (`response`: one `g = ln f⁻¹` table per channel, as
/// `hdr_response` returns; a linear sensor if None). Returns `(radiance, unreliable)`: float32
/// radiance per unit time and a bool array of samples clipped or black in every exposure.
#[pyfunction]
#[pyo3(signature = (images, times, response=None, black=0, saturation=None, weights="snr", levels=None))]
#[allow(clippy::too_many_arguments)]
pub fn hdr_merge<'py>(
    py: Python<'py>,
    images: Series<'py>,
    times: Vec<f32>,
    response: Option<Vec<Vec<f32>>>,
    black: u32,
    saturation: Option<u32>,
    weights: &str,
    levels: Option<usize>,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    fn run<T: hdr::Sample + numpy::Element>(
        py: Python<'_>,
        arrays: &[PyReadonlyArrayDyn<'_, T>],
        times: Vec<f32>,
        response: &Option<Vec<Vec<f32>>>,
        w: Weights,
        levels: usize,
    ) -> PyResult<hdr::Hdr> {
        let stack = stack_of(arrays, times)?;
        let options = MergeOptions { weights: w, threads: 0 };
        py.detach(|| match response {
            None => hdr::merge_linear(&stack, levels, &options),
            Some(g) => {
                let rs: Vec<Response> =
                    g.iter().map(|g| Response { levels: g.len(), g: g.clone() }).collect();
                hdr::merge(&stack, &rs, &options)
            }
        })
        .map_err(image_err)
    }
    let merged = match &images {
        Series::U8(a) => {
            let lv = levels.unwrap_or(256);
            run(py, a, times, &response, self::weights(lv, black, saturation, weights)?, lv)?
        }
        Series::U16(a) => {
            let lv = levels.unwrap_or(65536);
            run(py, a, times, &response, self::weights(lv, black, saturation, weights)?, lv)?
        }
    };
    let shape: Vec<usize> = if merged.channels == 1 {
        vec![merged.height, merged.width]
    } else {
        vec![merged.height, merged.width, merged.channels]
    };
    Ok((array(py, merged.radiance, &shape)?, array(py, merged.unreliable, &shape)?))
}

/// Recovers the camera's response from an exposure series (`method` `"debevec"` or
/// `"robertson"`, as `lightrig hdr calibrate`): float32 `(channels, levels)`, `g = ln f⁻¹`.
#[pyfunction]
#[pyo3(signature = (images, times, method="debevec", levels=None, smoothness=1e-4))]
pub fn hdr_response<'py>(
    py: Python<'py>,
    images: Series<'py>,
    times: Vec<f32>,
    method: &str,
    levels: Option<usize>,
    smoothness: f64,
) -> PyResult<Bound<'py, PyAny>> {
    fn run<T: hdr::Sample + numpy::Element>(
        py: Python<'_>,
        arrays: &[PyReadonlyArrayDyn<'_, T>],
        times: Vec<f32>,
        method: &str,
        levels: usize,
        lambda: f64,
    ) -> PyResult<Vec<Response>> {
        let stack = stack_of(arrays, times)?;
        let robertson = match method {
            "debevec" => false,
            "robertson" => true,
            other => {
                return Err(ImageError::new_err(format!(
                    "method={other:?}: give \"debevec\" or \"robertson\""
                )))
            }
        };
        py.detach(|| {
            if robertson {
                hdr::robertson(&stack, levels, &RobertsonOptions { lambda, ..RobertsonOptions::new(levels) })
            } else {
                hdr::debevec(&stack, levels, &DebevecOptions { lambda, ..DebevecOptions::new(levels) })
            }
        })
        .map_err(image_err)
    }
    let rs = match &images {
        Series::U8(a) => run(py, a, times, method, levels.unwrap_or(256), smoothness)?,
        Series::U16(a) => run(py, a, times, method, levels.unwrap_or(65536), smoothness)?,
    };
    let lv = rs.first().map_or(0, |r| r.levels);
    let g: Vec<f32> = rs.iter().flat_map(|r| r.g.iter().copied()).collect();
    array(py, g, &[rs.len(), lv])
}

/// Calibrates a camera from chessboard images, as `lightrig calibrate` does: `cols` × `rows`
/// inner corners, squares of `square_mm`. Returns the calibration file's contents as a dict
/// (docs/calibration-format.md); with `out`, writes that file.
#[pyfunction]
#[pyo3(signature = (images, cols, rows, square_mm, skip_missing=false, out=None))]
pub fn calibrate<'py>(
    py: Python<'py>,
    images: Vec<PathBuf>,
    cols: usize,
    rows: usize,
    square_mm: f64,
    skip_missing: bool,
    out: Option<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    let spec = BoardSpec { cols, rows, square: square_mm, unit: "mm".into() };
    let tool = format!("lightrig {} (Python)", env!("CARGO_PKG_VERSION"));
    let (text, _) = py
        .detach(|| -> Result<(String, ()), String> {
            let files = lightrig_cli::cmd::calibrate::collect_images(&images)?;
            let c = lightrig_cli::cmd::calibrate::calibrate_files(&files, &spec, skip_missing, &tool)?;
            if let Some(out) = &out {
                calib_file::write(out, &c).map_err(|e| e.to_string())?;
            }
            let text = calib_file::to_toml(&c).map_err(|(what, e)| format!("{what}: {e}"))?;
            Ok((text, ()))
        })
        .map_err(ImageError::new_err)?;
    let table: toml::Table = toml::from_str(&text).map_err(image_err)?;
    object(py, &table)
}
