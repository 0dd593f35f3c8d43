//! One exposure bracket merged into a rate image: every sample linearised through the camera's
//! response, weighted by its exposure time, clipped samples dropped. The LLS and bispectral fits
//! merge their series this way.

use std::path::PathBuf;

use lightrig_imaging::io::{read_with, Encoding, ReadOptions};

use crate::fit::{fail, FitError};
use crate::response::CameraResponse;

/// Samples at or above this share of full scale count as clipped.
pub const CLIP: f32 = 0.98;

/// Decodes `images` (`(file, exposure s)`) and merges the first `channels` channels of each
/// pixel: value per second, NaN where every exposure clipped. `size`, when known, is the size
/// every image must have.
pub fn merge(
    images: &[(PathBuf, f64)],
    size: Option<(u32, u32)>,
    channels: usize,
    response: &CameraResponse,
) -> Result<((u32, u32), Vec<f32>), FitError> {
    let (mut sum, mut weight): (Vec<f32>, Vec<f32>) = (Vec::new(), Vec::new());
    let mut size = size;
    let mut linear = Vec::new();
    for (path, exposure) in images {
        let img = read_with(path, ReadOptions { assume: Encoding::Linear, expect_depth: None })
            .map_err(|e| fail(format!("{}: {e}", path.display())))?;
        if usize::from(img.channels) < channels {
            return Err(fail(format!(
                "{}: {} channel(s), the fit needs {channels}",
                path.display(),
                img.channels
            )));
        }
        if let Some(s) = size.filter(|&s| s != (img.width, img.height)) {
            return Err(fail(format!(
                "{}: {}×{} pixels where {}×{} were expected",
                path.display(),
                img.width,
                img.height,
                s.0,
                s.1
            )));
        }
        size = Some((img.width, img.height));
        let n = (img.width * img.height) as usize * channels;
        if sum.is_empty() {
            (sum, weight) = (vec![0.0; n], vec![0.0; n]);
        }
        response
            .linearize(&img.data, usize::from(img.channels), channels, CLIP, &mut linear)
            .map_err(|e| fail(format!("{}: {e}", path.display())))?;
        // Weight by exposure time (collected light); clipped samples (NaN) get none.
        for ((s, w), &v) in sum.iter_mut().zip(weight.iter_mut()).zip(&linear) {
            if !v.is_nan() {
                *s += v;
                *w += *exposure as f32;
            }
        }
    }
    let rate = sum.iter().zip(&weight).map(|(s, w)| if *w > 0.0 { s / w } else { f32::NAN }).collect();
    Ok((size.unwrap_or((0, 0)), rate))
}
