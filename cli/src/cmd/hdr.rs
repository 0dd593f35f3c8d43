//! `lightrig hdr calibrate` and `lightrig hdr merge`: camera response from an exposure series,
//! and the series merged into linear radiance (EXR).
//!
//! Exposures are given as `FILE:SECONDS` arguments, or in a sidecar text file with one
//! `FILE SECONDS` pair per line (`#` starts a comment; paths relative to the sidecar).

use std::path::{Path, PathBuf};

pub use lightrig_host::response::ResponseFile;
use lightrig_imaging::hdr::{self, DebevecOptions, MergeOptions, Response, RobertsonOptions, Stack, Weights};
use lightrig_imaging::io::{self, BitDepth, ExrPrecision, Image, IoError, ReadOptions};

/// An exposure: file and time.
#[derive(Debug, Clone, PartialEq)]
pub struct Exposure {
    /// The image file.
    pub path: PathBuf,
    /// Exposure time, seconds.
    pub seconds: f32,
}

/// Parses `FILE:SECONDS`.
pub fn parse_exposure(s: &str) -> Result<Exposure, String> {
    let (file, t) =
        s.rsplit_once(':').ok_or_else(|| format!("`{s}`: expected FILE:SECONDS, e.g. img_01.png:0.004"))?;
    let seconds: f32 = t.parse().map_err(|_| format!("`{s}`: `{t}` is not a time in seconds"))?;
    Ok(Exposure { path: file.into(), seconds })
}

/// Reads a sidecar: `FILE SECONDS` per line.
pub fn read_sidecar(path: &Path) -> Result<Vec<Exposure>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let base = path.parent().unwrap_or(Path::new("."));
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (Some(file), Some(t), None) = (parts.next(), parts.next(), parts.next()) else {
            return Err(format!("{}:{}: expected `FILE SECONDS`", path.display(), n + 1));
        };
        let seconds =
            t.parse().map_err(|_| format!("{}:{}: `{t}` is not a time in seconds", path.display(), n + 1))?;
        out.push(Exposure { path: base.join(file), seconds });
    }
    Ok(out)
}

/// The stack's samples as integers at their file's bit depth.
enum Samples {
    Eight(Vec<Vec<u8>>),
    Sixteen(Vec<Vec<u16>>),
}

struct Loaded {
    width: usize,
    height: usize,
    channels: usize,
    samples: Samples,
    times: Vec<f32>,
}

fn load(exposures: &[Exposure]) -> Result<Loaded, String> {
    if exposures.len() < 2 {
        return Err(format!("an exposure series needs at least 2 images, got {}", exposures.len()));
    }
    let paths: Vec<&Path> = exposures.iter().map(|e| e.path.as_path()).collect();
    let times = exposures.iter().map(|e| e.seconds).collect();
    // The data as the camera wrote it: 8-bit if the first file is, else 16-bit.
    let eight = ReadOptions { expect_depth: Some(BitDepth::Eight), ..Default::default() };
    let (images, depth): (Vec<Image>, BitDepth) = match io::read_stack_with(&paths, eight) {
        Ok(v) => (v, BitDepth::Eight),
        Err(IoError::BitDepth { .. }) => {
            let sixteen = ReadOptions { expect_depth: Some(BitDepth::Sixteen), ..Default::default() };
            (io::read_stack_with(&paths, sixteen).map_err(|e| e.to_string())?, BitDepth::Sixteen)
        }
        Err(e) => return Err(e.to_string()),
    };
    let first = &images[0];
    let (width, height, channels) = (first.width as usize, first.height as usize, first.channels as usize);
    let samples = match depth {
        BitDepth::Eight => Samples::Eight(
            images.iter().map(|im| im.data.iter().map(|&v| (v * 255.0).round() as u8).collect()).collect(),
        ),
        BitDepth::Sixteen => {
            let mut v: Vec<Vec<u16>> = images
                .iter()
                .map(|im| im.data.iter().map(|&v| (v * 65535.0).round() as u16).collect())
                .collect();
            // 10/12/14-bit data in 16-bit files: MSB-aligned data (low bits always zero) are
            // shifted down, so that levels are the sensor's and its clip level is the top one.
            let all = v.iter().flatten().fold(0u16, |a, &z| a | z);
            let shift = if all == 0 { 0 } else { all.trailing_zeros().min(8) };
            if shift > 0 {
                v.iter_mut().flatten().for_each(|z| *z >>= shift);
            }
            Samples::Sixteen(v)
        }
    };
    Ok(Loaded { width, height, channels, samples, times })
}

/// Runs `f` on the loaded series as a [`Stack`] of its own sample type.
fn on_stack<R>(
    l: &Loaded,
    f8: impl FnOnce(&Stack<u8>) -> Result<R, hdr::HdrError>,
    f16: impl FnOnce(&Stack<u16>) -> Result<R, hdr::HdrError>,
) -> Result<R, String> {
    fn stack<'a, T: hdr::Sample>(l: &Loaded, v: &'a [Vec<T>]) -> Result<Stack<'a, T>, hdr::HdrError> {
        Stack::new(l.width, l.height, l.channels, v.iter().map(|x| x.as_slice()).collect(), l.times.clone())
    }
    let r = match &l.samples {
        Samples::Eight(v) => stack(l, v).and_then(|s| f8(&s)),
        Samples::Sixteen(v) => stack(l, v).and_then(|s| f16(&s)),
    };
    r.map_err(|e| e.to_string())
}

/// Levels of the data: 256 for 8-bit files, else the smallest power of two (≥ 256) above the
/// largest sample, e.g. 4096 for 12-bit data in 16-bit files (whose clipped samples then sit
/// at the top level and get zero weight).
fn data_levels(l: &Loaded) -> usize {
    match &l.samples {
        Samples::Eight(_) => 256,
        Samples::Sixteen(v) => {
            let max = v.iter().flatten().copied().max().unwrap_or(0) as usize;
            (max + 1).next_power_of_two().max(256)
        }
    }
}

/// How `hdr calibrate` recovers the response.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    /// Debevec–Malik: least squares on sampled pixels with a smoothness penalty.
    #[default]
    Debevec,
    /// Robertson et al.: alternating radiance and response estimates over every pixel.
    Robertson,
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "debevec" => Ok(Method::Debevec),
            "robertson" => Ok(Method::Robertson),
            _ => Err(format!("unknown response method `{s}`: use debevec or robertson")),
        }
    }
}

fn recover(l: &Loaded, method: Method) -> Result<ResponseFile, String> {
    let levels = data_levels(l);
    let curves = match method {
        Method::Debevec => {
            let o = DebevecOptions::new(levels);
            on_stack(l, |s| hdr::debevec(s, levels, &o), |s| hdr::debevec(s, levels, &o))?
        }
        Method::Robertson => {
            let o = RobertsonOptions::new(levels);
            on_stack(l, |s| hdr::robertson(s, levels, &o), |s| hdr::robertson(s, levels, &o))?
        }
    };
    Ok(ResponseFile { levels, g: curves.into_iter().map(|r| r.g).collect() })
}

/// `lightrig hdr calibrate`: recovers the response by `method` and writes it as JSON.
pub fn calibrate(exposures: &[Exposure], method: Method, out: &Path) -> Result<ResponseFile, String> {
    let r = recover(&load(exposures)?, method)?;
    r.save(out)?;
    Ok(r)
}

/// `lightrig hdr merge`: merges the series into linear radiance with `response` (recovered from
/// the series itself when `None`) and writes a float EXR. Levels at or below `black` get no
/// weight. Returns the count of pixels clipped or black in every exposure.
pub fn merge(
    exposures: &[Exposure],
    response: Option<&Path>,
    black: u32,
    out: &Path,
) -> Result<usize, String> {
    let l = load(exposures)?;
    let r = match response {
        Some(p) => ResponseFile::load(p)?,
        None => recover(&l, Method::Debevec)?,
    };
    if r.levels < data_levels(&l) {
        return Err(format!("the response has {} levels, the images need {}", r.levels, data_levels(&l)));
    }
    if r.g.len() != l.channels {
        return Err(format!("the response has {} channels, the images {}", r.g.len(), l.channels));
    }
    let responses: Vec<Response> = r.g.iter().map(|g| Response { levels: r.levels, g: g.clone() }).collect();
    let weights = Weights { black, ..Weights::snr(r.levels) };
    if weights.saturation < black + 2 {
        return Err(format!(
            "--black {black} leaves no usable levels below saturation ({}): give the black level in the data's levels",
            weights.saturation
        ));
    }
    let opts = MergeOptions { weights, threads: 0 };
    let merged = on_stack(&l, |s| hdr::merge(s, &responses, &opts), |s| hdr::merge(s, &responses, &opts))?;
    let mut image = Image::new(l.width as u32, l.height as u32, l.channels as u8);
    image.data = merged.radiance;
    io::write_exr(out, &image, ExrPrecision::Float).map_err(|e| e.to_string())?;
    Ok(merged.unreliable.iter().filter(|&&u| u).count() / l.channels.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The worst relative error of `out`'s radiance ratios to pixel (96, 3) against `radiance`'s
    /// (scaled per channel by `1 − 0.1·c`, which the ratio cancels), over the two brighter
    /// decades of a 128-wide gradient.
    fn worst_ratio_error(out: &Image, radiance: impl Fn(u32, u32) -> f64) -> f64 {
        let (rx, ry) = (96, 3);
        let mut worst = 0.0f64;
        for c in 0..out.channels {
            let at = |x: u32, y: u32| f64::from(out.get(x, y, c));
            for y in (0..out.height).step_by(5) {
                for x in (out.width / 3..out.width - 4).step_by(3) {
                    let got = at(x, y) / at(rx, ry);
                    let want = radiance(x, y) / radiance(rx, ry);
                    worst = worst.max((got / want - 1.0).abs());
                }
            }
        }
        worst
    }

    /// A scene spanning three decades, seen through a gamma-2.2 camera at four exposures.
    #[test]
    fn merge_recovers_relative_radiance_from_png_files() {
        let dir = std::env::temp_dir().join(format!("lightrig-hdr-cli-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (128u32, 64u32);
        let radiance = |x: u32, y: u32| {
            10f64.powf(-3.0 + 3.0 * f64::from(x) / f64::from(w - 1)) * (1.0 + 0.2 * f64::from(y % 7) / 7.0)
        };
        let mut exposures = Vec::new();
        let mut sidecar = String::new();
        for (k, t) in [1.0f32, 4.0, 16.0, 64.0, 256.0].iter().enumerate() {
            let img = Image::from_fn(w, h, 1, |x, y, _| {
                let e = (radiance(x, y) * f64::from(*t) / 256.0).min(1.0);
                ((e.powf(1.0 / 2.2) * 255.0).round() / 255.0) as f32
            })
            .with_encoding(io::Encoding::Srgb);
            let name = format!("e{k}.png");
            io::write_png(dir.join(&name), &img, BitDepth::Eight).unwrap();
            exposures.push(Exposure { path: dir.join(&name), seconds: *t });
            sidecar.push_str(&format!("{name} {t} # exposure {k}\n"));
        }
        std::fs::write(dir.join("times.txt"), sidecar).unwrap();
        assert_eq!(read_sidecar(&dir.join("times.txt")).unwrap(), exposures);
        let resp = calibrate(&exposures, Method::Debevec, &dir.join("response.json")).unwrap();
        assert_eq!((resp.levels, resp.g.len()), (256, 1));
        merge(&exposures, Some(&dir.join("response.json")), 0, &dir.join("hdr.exr")).unwrap();
        let out = io::read(dir.join("hdr.exr")).unwrap();
        // Relative radiance: ratios to a reference pixel. 8-bit data through a recovered curve:
        // within 5 % over the two brighter decades (in the darkest decade the longest exposure
        // reads below level 30, where one quantisation step alone is ~3.5 % of exposure).
        let at = |x: u32, y: u32| f64::from(out.get(x, y, 0));
        let (rx, ry) = (96, 3);
        let mut worst = 0.0f64;
        for y in (0..h).step_by(5) {
            for x in (w / 3..w - 4).step_by(3) {
                let got = at(x, y) / at(rx, ry);
                let want = radiance(x, y) / radiance(rx, ry);
                worst = worst.max((got / want - 1.0).abs());
            }
        }
        assert!(worst < 0.05, "worst relative error {worst}");
        assert!(parse_exposure("a.png").unwrap_err().contains("FILE:SECONDS"));
        assert_eq!(
            parse_exposure("dir/a.png:0.5").unwrap(),
            Exposure { path: "dir/a.png".into(), seconds: 0.5 }
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// 12-bit data in 16-bit PNGs, LSB-aligned (0..=4095) and MSB-aligned (×16): the data's
    /// 4096 levels are found, so clipped samples sit at the top level and get zero weight.
    #[test]
    fn twelve_bit_data_in_16_bit_png_files() {
        for (align, mult) in [("lsb", 1.0), ("msb", 16.0)] {
            let dir = std::env::temp_dir().join(format!("lightrig-hdr-cli16-{align}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            let (w, h) = (128u32, 64u32);
            let radiance = |x: u32, y: u32| {
                10f64.powf(-3.0 + 3.0 * f64::from(x) / f64::from(w - 1))
                    * (1.0 + 0.2 * f64::from(y % 7) / 7.0)
            };
            let mut exposures = Vec::new();
            for (k, t) in [1.0f32, 4.0, 16.0, 64.0, 256.0].iter().enumerate() {
                let img = Image::from_fn(w, h, 1, |x, y, _| {
                    let e = (radiance(x, y) * f64::from(*t) / 256.0).min(1.0);
                    ((e.powf(1.0 / 2.2) * 4095.0).round() * mult / 65535.0) as f32
                })
                .with_encoding(io::Encoding::Srgb);
                let name = format!("e{k}.png");
                io::write_png(dir.join(&name), &img, BitDepth::Sixteen).unwrap();
                exposures.push(Exposure { path: dir.join(&name), seconds: *t });
            }
            let resp = calibrate(&exposures, Method::Debevec, &dir.join("response.json")).unwrap();
            assert_eq!((resp.levels, resp.g.len()), (4096, 1), "{align}");
            merge(&exposures, Some(&dir.join("response.json")), 0, &dir.join("hdr.exr")).unwrap();
            let out = io::read(dir.join("hdr.exr")).unwrap();
            let worst = worst_ratio_error(&out, radiance);
            eprintln!("12-bit in 16-bit PNG ({align}): worst relative error {worst}");
            // Noise-free 12-bit data over the two brighter decades: quantisation-limited.
            assert!(worst < 0.005, "{align}: worst relative error {worst}");
            std::fs::remove_dir_all(&dir).unwrap();
        }
    }

    /// 12-bit data in 16-bit TIFF files, the response recovered by each method: the CLI's
    /// whole path (read, levels, recover, merge, EXR) on the other container.
    #[test]
    fn sixteen_bit_tiff_files_with_either_method() {
        // Robertson's iteration gets 1-stop steps: on 2-stop ones it converges slowly from its
        // linear start (2 % after its 80 iterations here, 1 % after 800), which is why
        // Debevec is the default.
        for (method, times) in [
            (Method::Debevec, vec![1.0f32, 4.0, 16.0, 64.0, 256.0]),
            (Method::Robertson, (0..9).map(|k| 2f32.powi(k)).collect()),
        ] {
            let dir =
                std::env::temp_dir().join(format!("lightrig-hdr-tiff-{method:?}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            let (w, h) = (128u32, 64u32);
            let radiance = |x: u32, y: u32| {
                10f64.powf(-3.0 + 3.0 * f64::from(x) / f64::from(w - 1))
                    * (1.0 + 0.2 * f64::from(y % 7) / 7.0)
            };
            let mut exposures = Vec::new();
            for (k, t) in times.iter().enumerate() {
                let img = Image::from_fn(w, h, 3, |x, y, c| {
                    let e = (radiance(x, y) * f64::from(*t) / 256.0 * (1.0 - 0.1 * f64::from(c))).min(1.0);
                    ((e.powf(1.0 / 2.2) * 4095.0).round() / 65535.0) as f32
                })
                .with_encoding(io::Encoding::Srgb);
                let name = format!("e{k}.tif");
                io::write_tiff(dir.join(&name), &img, BitDepth::Sixteen).unwrap();
                exposures.push(Exposure { path: dir.join(&name), seconds: *t });
            }
            let resp = calibrate(&exposures, method, &dir.join("response.json")).unwrap();
            assert_eq!((resp.levels, resp.g.len()), (4096, 3), "{method:?}");
            merge(&exposures, Some(&dir.join("response.json")), 0, &dir.join("hdr.exr")).unwrap();
            let out = io::read(dir.join("hdr.exr")).unwrap();
            assert_eq!((out.width, out.height, out.channels), (w, h, 3));
            let worst = worst_ratio_error(&out, radiance);
            eprintln!("12-bit in 16-bit TIFF, {method:?}: worst relative error {worst}");
            // As for the PNGs: noise-free 12-bit data over the two brighter decades.
            assert!(worst < 0.005, "{method:?}: worst relative error {worst}");
            std::fs::remove_dir_all(&dir).unwrap();
        }
        assert_eq!("robertson".parse::<Method>(), Ok(Method::Robertson));
        assert!("mitsunaga".parse::<Method>().unwrap_err().contains("debevec or robertson"));
    }
}

/// `lightrig hdr`'s subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Cmd {
    /// Recover the camera response from an exposure series; write it as JSON.
    Calibrate {
        /// Exposures as FILE:SECONDS.
        exposures: Vec<String>,
        /// A sidecar file of `FILE SECONDS` lines instead.
        #[arg(long)]
        times: Option<PathBuf>,
        /// `debevec` (Debevec–Malik, sampled pixels) or `robertson` (every pixel, iterated).
        #[arg(long, default_value = "debevec")]
        method: Method,
        /// Response file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Merge an exposure series into linear radiance (float EXR).
    Merge {
        /// Exposures as FILE:SECONDS.
        exposures: Vec<String>,
        /// A sidecar file of `FILE SECONDS` lines instead.
        #[arg(long)]
        times: Option<PathBuf>,
        /// Response from `hdr calibrate` (recovered from the series itself if absent).
        #[arg(long)]
        response: Option<PathBuf>,
        /// Largest level treated as black (weight zero), in the data's levels (0–4095 for
        /// 12-bit data). Set it near 3σ of the camera's read noise: levels below the noise
        /// floor cannot be inverted and only add error (docs/benchmarks.md, HDR accuracy).
        #[arg(long, default_value_t = 0)]
        black: u32,
        /// EXR file to write.
        #[arg(long)]
        out: PathBuf,
    },
}

fn exposures(list: &[String], times: Option<&Path>) -> Result<Vec<Exposure>, String> {
    match times {
        Some(p) if list.is_empty() => read_sidecar(p),
        Some(_) => {
            Err("give the exposures either as FILE:SECONDS arguments or with --times, not both".into())
        }
        None => list.iter().map(|s| parse_exposure(s)).collect(),
    }
}

/// Runs `lightrig hdr calibrate|merge`.
pub fn run(cmd: &Cmd) -> std::process::ExitCode {
    let result = match cmd {
        Cmd::Calibrate { exposures: list, times, method, out } => {
            exposures(list, times.as_deref()).and_then(|e| calibrate(&e, *method, out)).map(|r| {
                eprintln!("response: {} channel(s), {} levels -> {}", r.g.len(), r.levels, out.display())
            })
        }
        Cmd::Merge { exposures: list, times, response, black, out } => exposures(list, times.as_deref())
            .and_then(|e| merge(&e, response.as_deref(), *black, out))
            .map(|bad| {
                eprintln!("merged -> {} ({bad} pixels clipped or black in every exposure)", out.display())
            }),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::from(crate::error::INPUT)
        }
    }
}
