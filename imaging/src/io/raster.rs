//! PNG and TIFF through the `image` crate.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use image::{DynamicImage, ImageBuffer, ImageError, ImageFormat, ImageReader};

use super::{write_atomically, Encoding, Format, Image, IoError, ReadOptions};

/// Bits per sample of an integer PNG or TIFF.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BitDepth {
    Eight,
    Sixteen,
}

impl BitDepth {
    /// Bits per sample: 8 or 16.
    pub fn bits(self) -> u8 {
        match self {
            BitDepth::Eight => 8,
            BitDepth::Sixteen => 16,
        }
    }
}

/// How to store an image in an integer file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct WriteOptions {
    /// Convert a linear image to sRGB before quantising (colour channels only). Without it a linear
    /// image is refused at 8 bits and stored as linear data at 16 bits. No effect on sRGB images.
    pub encode_srgb: bool,
}

/// Writes a PNG with [`WriteOptions::default`]: a linear image is refused at 8 bits.
pub fn write_png(path: impl AsRef<Path>, image: &Image, depth: BitDepth) -> Result<(), IoError> {
    write_png_with(path, image, depth, WriteOptions::default())
}

/// Writes a PNG; samples are clamped to `[0, 1]` and rounded (NaN becomes 0).
pub fn write_png_with(
    path: impl AsRef<Path>,
    image: &Image,
    depth: BitDepth,
    opts: WriteOptions,
) -> Result<(), IoError> {
    write_raster(path.as_ref(), image, depth, opts, ImageFormat::Png)
}

/// Writes an uncompressed TIFF with [`WriteOptions::default`]: a linear image is refused at 8 bits.
/// 2-channel (gray + alpha) images are not supported by the TIFF encoder.
pub fn write_tiff(path: impl AsRef<Path>, image: &Image, depth: BitDepth) -> Result<(), IoError> {
    write_tiff_with(path, image, depth, WriteOptions::default())
}

/// Writes an uncompressed TIFF; samples are clamped to `[0, 1]` and rounded (NaN becomes 0).
pub fn write_tiff_with(
    path: impl AsRef<Path>,
    image: &Image,
    depth: BitDepth,
    opts: WriteOptions,
) -> Result<(), IoError> {
    write_raster(path.as_ref(), image, depth, opts, ImageFormat::Tiff)
}

/// Checks that the sample vector matches the declared shape, so a bad `Image` is an error, not a
/// panic deep in an encoder.
pub(super) fn validate(path: &Path, image: &Image) -> Result<(), IoError> {
    let detail = if !(1..=4).contains(&image.channels) {
        format!("{} channels (1 to 4 supported)", image.channels)
    } else if image.data.len() as u64
        != u64::from(image.width) * u64::from(image.height) * u64::from(image.channels)
    {
        format!(
            "{} samples for {}x{} with {} channel(s)",
            image.data.len(),
            image.width,
            image.height,
            image.channels
        )
    } else {
        return Ok(());
    };
    Err(IoError::InvalidImage { path: path.into(), detail })
}

fn write_raster(
    path: &Path,
    image: &Image,
    depth: BitDepth,
    opts: WriteOptions,
    format: ImageFormat,
) -> Result<(), IoError> {
    validate(path, image)?;
    let name = if format == ImageFormat::Png { "PNG" } else { "TIFF" };
    let converted;
    let image = if opts.encode_srgb && image.encoding == Encoding::Linear {
        converted = image.to_srgb();
        &converted
    } else if image.encoding == Encoding::Linear && depth == BitDepth::Eight {
        return Err(IoError::Encoding {
            path: path.into(),
            detail: format!(
                "refusing to store a linear image in an 8-bit {name} (it bands in the shadows): convert \
                 with to_srgb() or WriteOptions {{ encode_srgb: true }}, or write 16-bit"
            ),
        });
    } else {
        image
    };
    if format == ImageFormat::Tiff && image.channels == 2 {
        return Err(IoError::Unsupported {
            path: path.into(),
            what: "writing 2-channel (gray + alpha) TIFF; use PNG or drop the alpha".into(),
        });
    }
    let (w, h) = (image.width, image.height);
    let dynamic = match depth {
        BitDepth::Eight => {
            let data: Vec<u8> = image.data.iter().map(|&v| quantise(v, 255.0) as u8).collect();
            match image.channels {
                1 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageLuma8),
                2 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageLumaA8),
                3 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageRgb8),
                _ => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageRgba8),
            }
        }
        BitDepth::Sixteen => {
            let data: Vec<u16> = image.data.iter().map(|&v| quantise(v, 65535.0) as u16).collect();
            match image.channels {
                1 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageLuma16),
                2 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageLumaA16),
                3 => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageRgb16),
                _ => ImageBuffer::from_raw(w, h, data).map(DynamicImage::ImageRgba16),
            }
        }
    };
    let dynamic = dynamic.ok_or_else(|| IoError::InvalidImage {
        path: path.into(),
        detail: "sample buffer does not match the image size".into(),
    })?;
    write_atomically(path, |out| {
        dynamic.write_to(&mut *out, format).map_err(|e| e.to_string())?;
        super::flush(out)
    })
}

/// Maps `[0, 1]` to `0..=max`, clamping and sending NaN to 0.
fn quantise(v: f32, max: f32) -> f32 {
    if v.is_nan() {
        0.0
    } else {
        (v.clamp(0.0, 1.0) * max).round()
    }
}

/// Reads an integer or float PNG/TIFF; returns the image and its bits per sample.
pub(super) fn read(path: &Path, format: Format, opts: ReadOptions) -> Result<(Image, u8), IoError> {
    let file = File::open(path).map_err(|source| IoError::Open { path: path.into(), source })?;
    read_from(BufReader::new(file), path, format, opts)
}

/// [`read`] of a file's bytes in memory; `path` names it in errors.
pub(super) fn decode(
    bytes: &[u8],
    path: &Path,
    format: Format,
    opts: ReadOptions,
) -> Result<(Image, u8), IoError> {
    read_from(std::io::Cursor::new(bytes), path, format, opts)
}

fn read_from<R: std::io::BufRead + std::io::Seek + std::panic::UnwindSafe>(
    reader: R,
    path: &Path,
    format: Format,
    opts: ReadOptions,
) -> Result<(Image, u8), IoError> {
    let image_format = if format == Format::Png { ImageFormat::Png } else { ImageFormat::Tiff };
    // Third-party decoder fed untrusted bytes: a panic in it is a bad file, not a crash.
    let dynamic = std::panic::catch_unwind(|| ImageReader::with_format(reader, image_format).decode())
        .map_err(|_| IoError::Decode { path: path.into(), detail: "decoder failed (corrupt file?)".into() })?
        .map_err(|e| map_decode_error(path, e))?;
    let (w, h) = (dynamic.width(), dynamic.height());
    let int8 = |raw: &[u8], ch: u8| (raw.iter().map(|&v| f32::from(v) / 255.0).collect(), ch, 8);
    let int16 = |raw: &[u16], ch: u8| (raw.iter().map(|&v| f32::from(v) / 65535.0).collect(), ch, 16);
    let (data, channels, bits): (Vec<f32>, u8, u8) = match &dynamic {
        DynamicImage::ImageLuma8(b) => int8(b.as_raw(), 1),
        DynamicImage::ImageLumaA8(b) => int8(b.as_raw(), 2),
        DynamicImage::ImageRgb8(b) => int8(b.as_raw(), 3),
        DynamicImage::ImageRgba8(b) => int8(b.as_raw(), 4),
        DynamicImage::ImageLuma16(b) => int16(b.as_raw(), 1),
        DynamicImage::ImageLumaA16(b) => int16(b.as_raw(), 2),
        DynamicImage::ImageRgb16(b) => int16(b.as_raw(), 3),
        DynamicImage::ImageRgba16(b) => int16(b.as_raw(), 4),
        DynamicImage::ImageRgb32F(b) => (b.as_raw().clone(), 3, 32),
        DynamicImage::ImageRgba32F(b) => (b.as_raw().clone(), 4, 32),
        other => {
            return Err(IoError::Unsupported {
                path: path.into(),
                what: format!("pixel layout {:?}", other.color()),
            })
        }
    };
    if let Some(expected) = opts.expect_depth {
        if bits != expected.bits() {
            return Err(IoError::BitDepth { path: path.into(), found: bits, expected: expected.bits() });
        }
    }
    // Float data is scene-referred by convention; only integer data needs the caller's word.
    let encoding = if bits == 32 { Encoding::Linear } else { opts.assume };
    Ok((Image { width: w, height: h, channels, data, encoding }, bits))
}

fn map_decode_error(path: &Path, e: ImageError) -> IoError {
    let size = std::fs::metadata(path).map(|m| m.len()).ok();
    let truncated = |what: String| IoError::Truncated {
        path: path.into(),
        detail: match size {
            Some(n) => format!("{what}; the file has only {n} bytes"),
            None => what,
        },
    };
    match e {
        ImageError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            truncated("data ends before the image is complete".into())
        }
        ImageError::IoError(io) => IoError::Decode { path: path.into(), detail: io.to_string() },
        ImageError::Unsupported(u) => IoError::Unsupported { path: path.into(), what: u.to_string() },
        ImageError::Limits(l) => IoError::Unsupported {
            path: path.into(),
            what: format!("image exceeds the decoder's memory limits ({l})"),
        },
        other => {
            let detail = other.to_string();
            let lower = detail.to_ascii_lowercase();
            if lower.contains("eof") || lower.contains("unexpected end") || lower.contains("truncat") {
                truncated(detail)
            } else {
                IoError::Decode { path: path.into(), detail }
            }
        }
    }
}
