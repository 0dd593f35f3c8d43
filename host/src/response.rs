//! A camera's response curve, as `lightrig hdr calibrate` writes it, applied to the frames a
//! fit reads.
//!
//! A rig file names a camera's response (`[[camera]] response = "cam0-response.json"`);
//! when a session starts, the host keeps a copy in the session directory
//! (`camera<N>-response.json`, [`attach`]), so the session fits wherever it is moved and
//! whatever later happens to the original. Every fit that merges exposures takes its samples
//! through [`CameraResponse::linearize`]; a camera without a response is taken as linear.
//!
//! Units: a recovered response is known only up to a factor (Debevec's `g(mid) = 0`). It is
//! scaled here so that the level at 90 % of full scale reads 0.9, as a linear camera's
//! would: a fit's values stay "full scale per second" whichever camera took them, and the
//! fits' absolute thresholds mean the same with and without a response.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::rigfile::RigFile;

/// Response curves as stored by `lightrig hdr calibrate`: one per channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResponseFile {
    /// Levels per channel (256 for 8-bit files; for 16-bit files the data's: 4096 for 12-bit).
    pub levels: usize,
    /// `g = ln f⁻¹` per channel, `levels` values each.
    pub g: Vec<Vec<f32>>,
}

impl ResponseFile {
    /// Reads and checks a response file.
    pub fn load(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| {
            format!("{}: {e}; make it with `lightrig hdr calibrate` (see docs/imaging.md)", path.display())
        })?;
        let r: ResponseFile = serde_json::from_str(&text).map_err(|e| {
            format!("{}: not a response file (`lightrig hdr calibrate`'s output): {e}", path.display())
        })?;
        if !(4..=65536).contains(&r.levels) || !r.levels.is_power_of_two() {
            return Err(format!(
                "{}: levels = {}: must be a power of two from 4 to 65536 (the data's levels)",
                path.display(),
                r.levels
            ));
        }
        if r.g.is_empty() {
            return Err(format!("{}: g holds no curve; give one per channel", path.display()));
        }
        for (c, g) in r.g.iter().enumerate() {
            if g.len() != r.levels {
                return Err(format!(
                    "{}: g[{c}] has {} values where levels = {}",
                    path.display(),
                    g.len(),
                    r.levels
                ));
            }
            let reference = ((r.levels - 1) as f64 * 0.9).round() as usize;
            if !g[reference].is_finite() {
                return Err(format!(
                    "{}: g[{c}] is not finite at 90 % of full scale (level {reference})",
                    path.display()
                ));
            }
            if g.iter().any(|v| v.is_nan() || *v == f32::INFINITY) {
                return Err(format!(
                    "{}: g[{c}] holds NaN or +∞: recalibrate with a longer exposure series",
                    path.display()
                ));
            }
        }
        Ok(r)
    }

    /// Writes it as JSON.
    pub fn save(&self, path: &Path) -> Result<(), String> {
        let json = serde_json::to_string_pretty(self).map_err(|e| e.to_string())?;
        std::fs::write(path, json).map_err(|e| format!("{}: {e}", path.display()))
    }
}

/// How a camera's stored samples become linear values.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraResponse {
    /// Stored values are proportional to the light (a machine-vision camera, EXR frames).
    Linear,
    /// A recovered curve: per channel, the linear value of each level.
    Curve {
        /// Levels of the data.
        levels: usize,
        /// Per channel, `levels` linear values, scaled as the module says.
        table: Vec<Vec<f32>>,
        /// Where it came from (for messages).
        path: PathBuf,
    },
}

impl CameraResponse {
    /// From a response file.
    pub fn from_file(r: &ResponseFile, path: &Path) -> Self {
        let reference = ((r.levels - 1) as f64 * 0.9).round() as usize;
        let table =
            r.g.iter()
                .map(|g| {
                    let offset = 0.9f64.ln() - f64::from(g[reference]);
                    g.iter().map(|&v| (f64::from(v) + offset).exp() as f32).collect()
                })
                .collect();
        CameraResponse::Curve { levels: r.levels, table, path: path.to_path_buf() }
    }

    /// Reads a response file.
    pub fn load(path: &Path) -> Result<Self, String> {
        Ok(Self::from_file(&ResponseFile::load(path)?, path))
    }

    /// Whether samples are taken as linear.
    pub fn is_linear(&self) -> bool {
        matches!(self, CameraResponse::Linear)
    }

    /// The first `out_channels` channels of `data` (interleaved samples in `[0, 1]` as image
    /// files read back, `channels` a pixel), linearised into `out`; samples at or above
    /// `clip` of full scale become NaN (clipped). 16-bit files holding fewer levels (10-,
    /// 12-, 14-bit data) may be LSB- or MSB-aligned: data whose low bits are all zero are
    /// taken as MSB-aligned, as `lightrig hdr` does.
    pub fn linearize(
        &self,
        data: &[f32],
        channels: usize,
        out_channels: usize,
        clip: f32,
        out: &mut Vec<f32>,
    ) -> Result<(), String> {
        out.clear();
        let pixels = data.len() / channels.max(1);
        match self {
            CameraResponse::Linear => {
                for px in data.chunks_exact(channels) {
                    out.extend(px[..out_channels].iter().map(|&v| if v < clip { v } else { f32::NAN }));
                }
            }
            CameraResponse::Curve { levels, table, path } => {
                if table.len() < out_channels {
                    return Err(format!(
                        "{}: {} channel(s) in the response, the fit needs {out_channels}",
                        path.display(),
                        table.len()
                    ));
                }
                let levels = *levels;
                // The file's levels: 8-bit data read back in steps of 1/255, else 16-bit.
                let eight = levels <= 256
                    && data.iter().take(4096).all(|&v| ((v * 255.0).round() - v * 255.0).abs() < 1e-4);
                let full = if eight { 255.0 } else { 65535.0 };
                let shift = if eight || levels >= 65536 {
                    0
                } else {
                    let all = data.iter().fold(0u32, |a, &v| a | (v * full).round() as u32);
                    let spare = 16 - levels.trailing_zeros();
                    if all != 0 && all.trailing_zeros() >= spare {
                        spare
                    } else {
                        0
                    }
                };
                let top = levels - 1;
                let clip_level = (clip * top as f32) as usize;
                for px in data.chunks_exact(channels) {
                    for (c, &v) in px[..out_channels].iter().enumerate() {
                        let z = (((v * full).round() as u32) >> shift) as usize;
                        if z > top {
                            return Err(format!(
                                "{}: the response has {levels} levels but a frame holds level {z}: \
                                 recalibrate from frames of this camera at this bit depth",
                                path.display()
                            ));
                        }
                        out.push(if z < clip_level { table[c][z] } else { f32::NAN });
                    }
                }
            }
        }
        debug_assert_eq!(out.len(), pixels * out_channels);
        Ok(())
    }
}

/// The session's copy of camera `camera`'s response.
pub fn session_copy(session_dir: &Path, camera: u8) -> PathBuf {
    session_dir.join(format!("camera{camera}-response.json"))
}

/// Checks every camera response the rig file names (before a session starts).
pub fn check(rig: &RigFile) -> Result<(), String> {
    for c in &rig.cameras {
        if let Some(src) = &c.response {
            ResponseFile::load(src)
                .map_err(|e| format!("camera {} ({}): {e}", c.camera, rig.path.display()))?;
        }
    }
    Ok(())
}

/// Copies every camera response the rig file names into the session directory (checked
/// first: a session never starts with a response its fit would refuse).
pub fn attach(rig: &RigFile, session_dir: &Path) -> Result<(), String> {
    for c in &rig.cameras {
        if let Some(src) = &c.response {
            let r = ResponseFile::load(src)
                .map_err(|e| format!("camera {} ({}): {e}", c.camera, rig.path.display()))?;
            // Written as the session writes its own files: never through a planted link.
            let json = serde_json::to_string_pretty(&r).map_err(|e| e.to_string())?;
            let copy = session_copy(session_dir, c.camera);
            let name = copy.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
            crate::session::write_session_file(session_dir, &name, json.as_bytes())
                .map_err(|e| e.to_string())?;
        }
    }
    Ok(())
}

/// Camera `camera`'s response for a fit of the session in `session_dir` whose rig file is
/// `rig`: the session's copy if the rig names one (an error if the copy is gone), else linear.
pub fn for_session(rig: &RigFile, session_dir: &Path, camera: u8) -> Result<CameraResponse, String> {
    let named = rig.cameras.iter().find(|c| c.camera == camera).and_then(|c| c.response.as_ref());
    let copy = session_copy(session_dir, camera);
    match named {
        None => Ok(CameraResponse::Linear),
        Some(original) => CameraResponse::load(&copy).map_err(|e| {
            format!(
                "{e}\nthe rig file names the camera's response ({}); the session keeps a copy as {}: \
                 copy the response file there",
                original.display(),
                copy.display()
            )
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gamma_file(levels: usize, gamma: f64) -> ResponseFile {
        let g = (0..levels)
            .map(|z| ((z.max(1) as f64 / (levels - 1) as f64).powf(gamma) * 7.0).ln() as f32)
            .collect::<Vec<_>>();
        ResponseFile { levels, g: vec![g.clone(), g.clone(), g] }
    }

    #[test]
    fn a_curve_is_scaled_to_read_point_nine_at_ninety_percent() {
        let r = CameraResponse::from_file(&gamma_file(256, 2.2), Path::new("r.json"));
        let mut out = Vec::new();
        let z = (255.0f32 * 0.9).round();
        r.linearize(&[z / 255.0; 3], 3, 3, 0.98, &mut out).unwrap();
        assert!((out[0] - 0.9).abs() < 1e-5, "{out:?}");
        // Half the level, a gamma-2.2 camera: 2^-2.2 of the linear value.
        r.linearize(&[(z / 2.0).round() / 255.0; 3], 3, 3, 0.98, &mut out).unwrap();
        let want = 0.9 * (((z / 2.0).round() / z) as f64).powf(2.2);
        assert!((f64::from(out[1]) / want - 1.0).abs() < 1e-4, "{} vs {want}", out[1]);
    }

    #[test]
    fn clipped_samples_are_nan_and_linear_passes_values() {
        let mut out = Vec::new();
        CameraResponse::Linear.linearize(&[0.5, 0.99, 0.1, 1.0], 4, 3, 0.98, &mut out).unwrap();
        assert_eq!(out[0], 0.5);
        assert!(out[1].is_nan());
        assert_eq!(out[2], 0.1);
        assert_eq!(out.len(), 3);
        let r = CameraResponse::from_file(&gamma_file(65536, 1.0), Path::new("r.json"));
        r.linearize(&[1.0, 0.5, 0.25], 3, 3, 0.98, &mut out).unwrap();
        assert!(out[0].is_nan());
        assert!((out[1] / out[2] - 2.0).abs() < 1e-3);
    }

    #[test]
    fn twelve_bit_data_msb_aligned_in_sixteen_bit_files() {
        let r = CameraResponse::from_file(&gamma_file(4096, 1.0), Path::new("r.json"));
        let mut out = Vec::new();
        // Levels 1000 and 2000 stored shifted up by 4 bits.
        let v = |z: u32| (z << 4) as f32 / 65535.0;
        r.linearize(&[v(1000), v(2000), v(4000)], 3, 3, 0.98, &mut out).unwrap();
        assert!((out[1] / out[0] - 2.0).abs() < 1e-6, "{out:?}");
        // LSB-aligned (low bits in use): read as they are.
        let u = |z: u32| z as f32 / 65535.0;
        r.linearize(&[u(1001), u(2002), u(3)], 3, 3, 0.98, &mut out).unwrap();
        assert!((out[1] / out[0] - 2.0).abs() < 1e-6, "{out:?}");
        // A level beyond the response: an error naming the file.
        let e = r.linearize(&[u(5000), u(1), u(1)], 3, 3, 0.98, &mut out).unwrap_err();
        assert!(e.contains("r.json") && e.contains("4096 levels"), "{e}");
    }

    #[test]
    fn a_bad_file_is_refused_with_its_path() {
        let dir = std::env::temp_dir().join(format!("lightrig-response-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("r.json");
        let mut f = gamma_file(256, 2.2);
        f.g[1].pop();
        f.save(&p).unwrap();
        let e = ResponseFile::load(&p).unwrap_err();
        assert!(e.contains("r.json") && e.contains("g[1] has 255 values where levels = 256"), "{e}");
        std::fs::write(&p, "{}").unwrap();
        assert!(ResponseFile::load(&p).unwrap_err().contains("not a response file"));
        let e = ResponseFile::load(&dir.join("missing.json")).unwrap_err();
        assert!(e.contains("lightrig hdr calibrate"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
