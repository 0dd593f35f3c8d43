//! Bispectral images in the OpenEXR layout of Fichet, Pacanowski and Wilkie (2021), "An OpenEXR
//! Layout for Spectral Images" (JCGT 10(3)), as colour-science's `read_spectral_image_Fichet2021`
//! reads them: one channel per wavelength of the reflective diagonal, `T.<λ>nm`, and one per
//! reradiated pair, `T.<λi>nm.<λo>nm` (input first, then output); a wavelength is a number with
//! a comma for its decimal point (the dot separates the name's parts), a unit multiplier and `m`
//! or `Hz` (`550nm`, `550,5nm`, `0,55um`, or a frequency). The header carries
//! `spectralLayoutVersion = "1.0"`. Emissive (`S0`…`S3`) channels are refused: these images are
//! reflective.

use std::collections::BTreeMap;
use std::path::Path;

use exr::prelude::{
    self as x, AnyChannel, AnyChannels, AttributeValue, FlatSamples, ImageAttributes, IntegerBounds,
    LayerAttributes, ReadChannels, ReadLayers, Text, WritableImage,
};

use super::{write_atomically, IoError};

/// A bispectral image: per pixel, the diagonal (wavelength-preserving) values and the
/// reradiation of each `(input, output)` pair, wavelengths in nm.
#[derive(Debug, Clone, PartialEq)]
pub struct BispectralImage {
    pub width: u32,
    pub height: u32,
    /// `λ` (nm, as bits of an `f64` for ordering) → `width × height` values.
    pub diagonal: BTreeMap<Nm, Vec<f32>>,
    /// `(λi, λo)` → values.
    pub reradiation: BTreeMap<(Nm, Nm), Vec<f32>>,
}

/// A wavelength in nm, ordered (finite, positive).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nm(pub f64);

impl Eq for Nm {}

impl PartialOrd for Nm {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Nm {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0)
    }
}

/// The layout version written.
pub const LAYOUT_VERSION: &str = "1.0";

/// A wavelength as the layout writes it: `550nm`, or `550,25nm` with a fraction.
pub fn wavelength_name(nm: f64) -> String {
    let s = format!("{nm}");
    format!("{}nm", s.replace('.', ","))
}

const SPEED_OF_LIGHT: f64 = 299_792_458.0;

/// A wavelength part of a channel name (`550nm`, `550,5nm`, `5,5e2nm`, `0,55um`, `545THz`),
/// in nm.
pub fn parse_wavelength(part: &str) -> Option<f64> {
    let (body, hz) = match part.strip_suffix("Hz") {
        Some(b) => (b, true),
        None => (part.strip_suffix('m')?, false),
    };
    // SI prefixes as powers of ten ("da" before "d").
    let multipliers: [(&str, i32); 20] = [
        ("da", 1),
        ("Y", 24),
        ("Z", 21),
        ("E", 18),
        ("P", 15),
        ("T", 12),
        ("G", 9),
        ("M", 6),
        ("k", 3),
        ("h", 2),
        ("d", -1),
        ("c", -2),
        ("m", -3),
        ("u", -6),
        ("n", -9),
        ("p", -12),
        ("f", -15),
        ("a", -18),
        ("z", -21),
        ("y", -24),
    ];
    let (number, scale) = multipliers
        .iter()
        .find_map(|(p, s)| {
            body.strip_suffix(p)
                .filter(|n| n.chars().last().is_some_and(|c| c.is_ascii_digit()))
                .map(|n| (n, *s))
        })
        .unwrap_or((body, 0));
    if number.is_empty() || !number.chars().next().is_some_and(|c| c.is_ascii_digit() || c == ',') {
        return None;
    }
    let v: f64 = number.replace(',', ".").parse().ok()?;
    // Exact powers of ten: 550nm is 550, not 550 × 1e-9 × 1e9.
    let nm = if hz { SPEED_OF_LIGHT / (v * 10f64.powi(scale)) * 1e9 } else { v * 10f64.powi(scale + 9) };
    (nm.is_finite() && nm > 0.0).then_some(nm)
}

impl BispectralImage {
    /// An empty image of `width × height`.
    pub fn new(width: u32, height: u32) -> Self {
        BispectralImage { width, height, diagonal: BTreeMap::new(), reradiation: BTreeMap::new() }
    }

    /// Writes the image (ZIP-compressed, 32-bit float) to `path`.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), IoError> {
        let path = path.as_ref();
        let invalid = |detail: String| IoError::InvalidImage { path: path.into(), detail };
        let n = self.width as usize * self.height as usize;
        let mut channels = x::SmallVec::new();
        let mut add = |name: String, values: &Vec<f32>| -> Result<(), IoError> {
            if values.len() != n {
                return Err(invalid(format!(
                    "channel `{name}` holds {} values for {n} pixels",
                    values.len()
                )));
            }
            let text = Text::new_or_none(&name).ok_or_else(|| invalid(format!("channel name `{name}`")))?;
            channels.push(AnyChannel::new(text, FlatSamples::F32(values.clone())));
            Ok(())
        };
        for (nm, v) in &self.diagonal {
            add(format!("T.{}", wavelength_name(nm.0)), v)?;
        }
        for ((i, o), v) in &self.reradiation {
            add(format!("T.{}.{}", wavelength_name(i.0), wavelength_name(o.0)), v)?;
        }
        if channels.is_empty() {
            return Err(invalid("no channels to write".into()));
        }
        let size = (self.width as usize, self.height as usize);
        let mut attributes = ImageAttributes::new(IntegerBounds::from_dimensions(size));
        attributes.other.insert(
            Text::from_slice_unchecked(b"spectralLayoutVersion"),
            AttributeValue::Text(Text::from_slice_unchecked(LAYOUT_VERSION.as_bytes())),
        );
        let layer = x::Layer::new(
            size,
            LayerAttributes::default(),
            x::Encoding::SMALL_LOSSLESS,
            AnyChannels::sort(channels),
        );
        let image = x::Image { attributes, layer_data: layer };
        write_atomically(path, |file| {
            image.write().to_buffered(&mut *file).map_err(|e| e.to_string())?;
            super::flush(file)
        })
    }

    /// Reads a bispectral (or reflective) image in the layout from `path`. Channels of other
    /// names (an RGB preview, for one) are skipped; emissive ones are an error.
    pub fn read(path: impl AsRef<Path>) -> Result<Self, IoError> {
        let path = path.as_ref();
        let unsupported = |what: String| IoError::Unsupported { path: path.into(), what };
        let image = std::panic::catch_unwind(|| {
            x::read()
                .no_deep_data()
                .largest_resolution_level()
                .all_channels()
                .first_valid_layer()
                .all_attributes()
                .from_file(path)
        })
        .map_err(|_| IoError::Decode {
            path: path.into(),
            detail: "EXR decoder failed (corrupt file?)".into(),
        })?
        .map_err(|e| IoError::Decode { path: path.into(), detail: e.to_string() })?;
        let layer = &image.layer_data;
        let (w, h) = (layer.size.0 as u32, layer.size.1 as u32);
        let mut out = BispectralImage::new(w, h);
        for channel in &layer.channel_data.list {
            let name = channel.name.to_string();
            if name.starts_with('S') && name[1..].starts_with(|c: char| ('0'..='3').contains(&c)) {
                return Err(unsupported(format!(
                    "emissive channel `{name}`: a bispectral reflectance was expected"
                )));
            }
            let Some(rest) = name.strip_prefix("T.") else { continue };
            let parts: Vec<&str> = rest.split('.').collect();
            let values: Vec<f32> = channel.sample_data.values_as_f32().collect();
            match parts.as_slice() {
                [l] => {
                    let nm = parse_wavelength(l)
                        .ok_or_else(|| unsupported(format!("channel `{name}`: no wavelength")))?;
                    out.diagonal.insert(Nm(nm), values);
                }
                [a, b] => {
                    let (i, o) = parse_wavelength(a)
                        .zip(parse_wavelength(b))
                        .ok_or_else(|| unsupported(format!("channel `{name}`: no wavelengths")))?;
                    out.reradiation.insert((Nm(i), Nm(o)), values);
                }
                _ => return Err(unsupported(format!("channel `{name}`: not T.<λ> or T.<λi>.<λo>"))),
            }
        }
        if out.diagonal.is_empty() && out.reradiation.is_empty() {
            return Err(unsupported(
                "no `T.` channels: not a reflective spectral image in the Fichet et al. layout".into(),
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wavelengths_parse_as_the_layout_writes_them() {
        assert_eq!(parse_wavelength("550nm"), Some(550.0));
        assert_eq!(parse_wavelength("550,5nm"), Some(550.5));
        assert_eq!(parse_wavelength("380,000000nm"), Some(380.0));
        assert!((parse_wavelength("0,55um").unwrap() - 550.0).abs() < 1e-9);
        assert!((parse_wavelength("5,5e2nm").unwrap() - 550.0).abs() < 1e-9);
        // 545.077 THz is 550 nm.
        assert!((parse_wavelength("545,077THz").unwrap() - 550.0).abs() < 0.01);
        assert_eq!(parse_wavelength("nm"), None);
        assert_eq!(parse_wavelength("R"), None);
        assert_eq!(wavelength_name(550.0), "550nm");
        assert_eq!(wavelength_name(550.25), "550,25nm");
    }

    #[test]
    fn a_written_image_reads_back_the_same() {
        let mut img = BispectralImage::new(3, 2);
        img.diagonal.insert(Nm(400.0), vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
        img.diagonal.insert(Nm(420.5), vec![1.0; 6]);
        img.reradiation.insert((Nm(400.0), Nm(520.0)), vec![0.01, 0.02, 0.03, 0.04, 0.05, 0.06]);
        let path = std::env::temp_dir().join(format!("lightrig-bispectral-{}.exr", std::process::id()));
        img.write(&path).unwrap();
        let back = BispectralImage::read(&path).unwrap();
        assert_eq!(back, img);
        std::fs::remove_file(&path).ok();
    }
}
