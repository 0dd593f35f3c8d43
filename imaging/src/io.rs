//! Image and EXR I/O shared by the pipelines.
//!
//! One in-memory type, [`Image`]: interleaved `f32` samples plus an [`Encoding`] that says whether the
//! values are linear or sRGB-encoded. Nothing here converts between the two behind the caller's back:
//!
//! - **Reading.** Integer PNG and TIFF hold display-referred data by convention, so they are read as
//!   [`Encoding::Srgb`] (values normalised to `[0, 1]`: `/255` or `/65535`). Machine-vision cameras
//!   write *linear* 16-bit TIFFs that look identical on disk; the file cannot tell us, so the caller
//!   must say so with [`ReadOptions::assume`] = [`Encoding::Linear`]. Float TIFF and EXR are always
//!   [`Encoding::Linear`], values untouched.
//! - **Writing PNG/TIFF.** An sRGB image is stored as-is. A linear image is stored as-is at 16 bits
//!   (enough precision for linear data; read it back with `assume: Linear`), but refused at 8 bits
//!   ([`IoError::Encoding`]): 8-bit linear bands visibly in the shadows and is almost always a
//!   forgotten conversion. Set [`WriteOptions::encode_srgb`] to convert to sRGB while writing.
//! - **Writing EXR.** EXR holds linear values; an sRGB image is refused — call [`Image::to_linear`].
//!
//! Every write goes to a temporary file beside the target that is renamed over it at the end, so a
//! crash never leaves a half-written output. Errors ([`IoError`]) name the file and what was wrong.

mod buffer;
mod error;
mod exr_io;
mod raster;
mod spectral_exr;

pub use self::buffer::{linear_to_srgb, srgb_to_linear, Encoding, Image};
pub use self::error::IoError;
pub use self::exr_io::{read_exr_layers, read_exr_rows, write_exr, write_exr_layers, ExrPrecision, Layer};
pub use self::raster::{write_png, write_png_with, write_tiff, write_tiff_with, BitDepth, WriteOptions};
pub use self::spectral_exr::{parse_wavelength, wavelength_name, BispectralImage, Nm};

use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

/// How to interpret files whose format does not record linear vs sRGB.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadOptions {
    /// Encoding given to integer PNG/TIFF data (default [`Encoding::Srgb`]). Use
    /// [`Encoding::Linear`] for raw-ish machine-vision TIFFs. Ignored for EXR and float TIFF, which
    /// are always linear.
    pub assume: Encoding,
    /// Reject integer files of another bit depth ([`IoError::BitDepth`]); `None` accepts 8 and 16.
    pub expect_depth: Option<BitDepth>,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions { assume: Encoding::Srgb, expect_depth: None }
    }
}

/// File formats this module reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Png,
    Tiff,
    Exr,
}

/// Reads a PNG, TIFF or EXR file with [`ReadOptions::default`] (integer data taken as sRGB).
pub fn read(path: impl AsRef<Path>) -> Result<Image, IoError> {
    read_with(path, ReadOptions::default())
}

/// Reads a PNG, TIFF or EXR file; the format is recognised by its magic bytes, not its extension.
pub fn read_with(path: impl AsRef<Path>, opts: ReadOptions) -> Result<Image, IoError> {
    read_inner(path.as_ref(), opts).map(|(image, _)| image)
}

/// Reads rows `rows` of an image: of a one-channel EXR only the blocks of scanlines that hold them
/// are decompressed (see [`read_exr_rows`]); anything else is read whole. Returns the image at
/// full size, zero outside the rows read, and the rows read (a superset of `rows` within the
/// image: whole EXR blocks, or every row).
pub fn read_rows(
    path: impl AsRef<Path>,
    rows: std::ops::Range<u32>,
) -> Result<(Image, std::ops::Range<u32>), IoError> {
    let path = path.as_ref();
    match sniff(path)? {
        Format::Exr => read_exr_rows(path, rows),
        _ => read(path).map(|image| {
            let h = image.height;
            (image, 0..h)
        }),
    }
}

/// Reads a series of frames (e.g. an exposure stack) that must share size, channel count and bit
/// depth; the first file sets the expectation and the error names the first one that differs.
pub fn read_stack<P: AsRef<Path>>(paths: &[P]) -> Result<Vec<Image>, IoError> {
    read_stack_with(paths, ReadOptions::default())
}

/// [`read_stack`] with explicit [`ReadOptions`].
pub fn read_stack_with<P: AsRef<Path>>(paths: &[P], opts: ReadOptions) -> Result<Vec<Image>, IoError> {
    let mut images = Vec::with_capacity(paths.len());
    let mut first: Option<((u32, u32, u8), u8)> = None;
    for path in paths {
        let path = path.as_ref();
        let (image, bits) = read_inner(path, opts)?;
        let shape = (image.width, image.height, image.channels);
        match first {
            None => first = Some((shape, bits)),
            Some((expected, _)) if expected != shape => {
                return Err(IoError::SizeMismatch { path: path.into(), expected, found: shape });
            }
            Some((_, expected_bits)) if expected_bits != bits => {
                return Err(IoError::BitDepth { path: path.into(), found: bits, expected: expected_bits });
            }
            Some(_) => {}
        }
        images.push(image);
    }
    Ok(images)
}

/// An 8-bit grey image, row-major: what the chessboard detector takes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Gray8 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

/// Reads any image the `image` crate decodes (PNG, TIFF, JPEG — cameras' own output included)
/// as 8-bit grey: the encoded values as stored (no linearisation), colour reduced to luma and
/// 16-bit scaled to 8, as OpenCV's `imread(…, IMREAD_GRAYSCALE)` does for detection.
pub fn read_gray8(path: impl AsRef<Path>) -> Result<Gray8, IoError> {
    let path = path.as_ref();
    let reader = image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|source| IoError::Open { path: path.into(), source })?;
    let decoded = reader.decode().map_err(|e| match e {
        image::ImageError::Unsupported(u) => IoError::Unsupported { path: path.into(), what: u.to_string() },
        other => IoError::Decode { path: path.into(), detail: other.to_string() },
    })?;
    let grey = decoded.to_luma8();
    let (width, height) = grey.dimensions();
    Ok(Gray8 { width, height, data: grey.into_raw() })
}

/// Decodes a PNG, TIFF or EXR file's `bytes` held in memory (a frame as a camera delivered it),
/// as [`read_with`] reads the file; `name` names it in errors. Also returns its bits per sample
/// (8, 16, 16 for half, 32 for float).
pub fn decode(bytes: &[u8], name: impl AsRef<Path>, opts: ReadOptions) -> Result<(Image, u8), IoError> {
    let path = name.as_ref();
    match sniff_bytes(bytes, path)? {
        Format::Exr => exr_io::decode_single(bytes, path),
        format => raster::decode(bytes, path, format, opts),
    }
}

/// Reads one file; also returns the bits per sample on disk (8, 16, 16 for half, 32 for float).
fn read_inner(path: &Path, opts: ReadOptions) -> Result<(Image, u8), IoError> {
    let format = sniff(path)?;
    match format {
        Format::Exr => exr_io::read_single(path),
        Format::Png | Format::Tiff => raster::read(path, format, opts),
    }
}

/// Recognises the format from the first bytes, so misnamed files still read correctly; falls back to
/// the extension only to explain a file too short to hold a signature.
fn sniff(path: &Path) -> Result<Format, IoError> {
    let mut file = File::open(path).map_err(|source| IoError::Open { path: path.into(), source })?;
    let mut magic = [0u8; 8];
    let mut n = 0;
    while n < magic.len() {
        match file.read(&mut magic[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(source) => return Err(IoError::Open { path: path.into(), source }),
        }
    }
    sniff_bytes(&magic[..n], path)
}

/// [`sniff`] of a file's first bytes (`m`, up to 8).
fn sniff_bytes(m: &[u8], path: &Path) -> Result<Format, IoError> {
    let n = m.len().min(8);
    let m = &m[..n];
    if m.starts_with(b"\x89PNG\r\n\x1a\n") {
        return Ok(Format::Png);
    }
    if m.starts_with(b"II*\0") || m.starts_with(b"MM\0*") {
        return Ok(Format::Tiff);
    }
    if m.starts_with(b"II+\0") || m.starts_with(b"MM\0+") {
        return Err(IoError::Unsupported { path: path.into(), what: "BigTIFF".into() });
    }
    if m.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
        return Ok(Format::Exr);
    }
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    let known = matches!(ext.as_deref(), Some("png" | "tif" | "tiff" | "exr"));
    if n < 8 && known {
        return Err(IoError::Truncated {
            path: path.into(),
            detail: format!("only {n} bytes, too short for a file signature"),
        });
    }
    let what = if known {
        "file contents are not the PNG, TIFF or EXR its extension says".to_owned()
    } else {
        format!("unrecognised format (first bytes {m:02x?}); expected PNG, TIFF or EXR")
    };
    Err(IoError::Unsupported { path: path.into(), what })
}

/// Writes through a temporary file in the target's directory and renames it into place, so readers
/// (and a crash) only ever see the old file or the complete new one.
pub(crate) fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> Result<(), String>,
) -> Result<(), IoError> {
    let tmp = temp_path(path);
    let result = (|| {
        let file = File::create(&tmp).map_err(|source| IoError::Open { path: path.into(), source })?;
        let mut out = BufWriter::new(file);
        write(&mut out).map_err(|detail| IoError::Encode { path: path.into(), detail })?;
        let file = out
            .into_inner()
            .map_err(|e| IoError::Encode { path: path.into(), detail: e.error().to_string() })?;
        file.sync_all().map_err(|e| IoError::Encode { path: path.into(), detail: e.to_string() })?;
        std::fs::rename(&tmp, path).map_err(|source| IoError::Open { path: path.into(), source })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    // Unique per process and call, so concurrent writers of the same target never share a temp file.
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    path.with_file_name(format!(".{name}.tmp-{}-{n}", std::process::id()))
}

/// Flushes a writer, turning the error into the message an [`IoError::Encode`] carries.
fn flush(out: &mut impl Write) -> Result<(), String> {
    out.flush().map_err(|e| e.to_string())
}
