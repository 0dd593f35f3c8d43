//! OpenEXR through the `exr` crate: single images and multi-layer files of named maps.

use std::path::Path;

use exr::prelude::{
    self as x, AnyChannel, AnyChannels, AttributeValue, FlatSamples, ImageAttributes, IntegerBounds,
    LayerAttributes, ReadChannels, ReadLayers, Text, WritableImage,
};

use super::raster::validate;
use super::{write_atomically, Encoding, Image, IoError};

/// Sample type of EXR output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ExrPrecision {
    /// 16-bit half float: ~3 significant digits, range ±65504; half the size.
    Half,
    /// 32-bit float: exact round trip of `f32` data.
    Float,
}

/// One named map of a multi-layer EXR, e.g. `diffuse` with channels `R, G, B` or `normal` with
/// `X, Y, Z`. `channels[i]` names sample `i` of each pixel of `image`.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    /// Layer name; empty for the unnamed layer of a plain single-image file.
    pub name: String,
    pub channels: Vec<String>,
    pub image: Image,
}

impl Layer {
    /// A layer of linear `w × h` data, `channels.len()` samples a pixel, named as `channels`.
    pub fn linear(name: &str, channels: &[&str], w: u32, h: u32, data: Vec<f32>) -> Self {
        Layer {
            name: name.into(),
            channels: channels.iter().map(|c| c.to_string()).collect(),
            image: Image {
                width: w,
                height: h,
                channels: channels.len() as u8,
                data,
                encoding: Encoding::Linear,
            },
        }
    }
}

/// Custom layer attribute recording the caller's channel order: EXR stores channels sorted by name,
/// which would turn `R, G, B` into `B, G, R`.
const ORDER_ATTRIBUTE: &str = "lightrigChannelOrder";

/// Conventional order for files without [`ORDER_ATTRIBUTE`]; other names follow alphabetically.
const CANONICAL: [&str; 10] = ["R", "G", "B", "A", "X", "Y", "Z", "U", "V", "W"];

/// Writes a linear image as a ZIP-compressed EXR with channels `Y`, `Y A`, `R G B` or `R G B A`.
/// An sRGB image is refused ([`IoError::Encoding`]): convert with [`Image::to_linear`] first.
pub fn write_exr(path: impl AsRef<Path>, image: &Image, precision: ExrPrecision) -> Result<(), IoError> {
    let names: &[&str] = match image.channels {
        1 => &["Y"],
        2 => &["Y", "A"],
        3 => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    let layer = Layer {
        name: String::new(),
        channels: names.iter().take(image.channels as usize).map(|s| s.to_string()).collect(),
        image: image.clone(),
    };
    write_exr_layers(path, std::slice::from_ref(&layer), precision)
}

/// Writes several same-sized linear maps into one ZIP-compressed multi-part EXR (one part per layer,
/// named by [`Layer::name`]), e.g. `diffuse`, `specular`, `roughness` and `normal` from one fit.
pub fn write_exr_layers(
    path: impl AsRef<Path>,
    layers: &[Layer],
    precision: ExrPrecision,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let invalid = |detail: String| IoError::InvalidImage { path: path.into(), detail };
    let text = |s: &str, what: &str| {
        Text::new_or_none(s)
            .filter(|_| !s.is_empty())
            .ok_or_else(|| invalid(format!("{what} `{s}` must be non-empty ASCII")))
    };
    let Some(first) = layers.first() else {
        return Err(invalid("no layers to write".into()));
    };
    let size = (first.image.width, first.image.height);
    let mut out = Vec::with_capacity(layers.len());
    for (i, layer) in layers.iter().enumerate() {
        let image = &layer.image;
        validate(path, image)?;
        if image.encoding != Encoding::Linear {
            return Err(IoError::Encoding {
                path: path.into(),
                detail: format!(
                    "layer `{}` is sRGB-encoded but EXR holds linear values: convert with to_linear() first",
                    layer.name
                ),
            });
        }
        if (image.width, image.height) != size {
            return Err(IoError::SizeMismatch {
                path: path.into(),
                expected: (size.0, size.1, image.channels),
                found: (image.width, image.height, image.channels),
            });
        }
        if layer.channels.len() != image.channels as usize {
            return Err(invalid(format!(
                "layer `{}` names {} channels for a {}-channel image",
                layer.name,
                layer.channels.len(),
                image.channels
            )));
        }
        if layers[..i].iter().any(|l| l.name == layer.name) {
            return Err(invalid(format!("two layers named `{}`", layer.name)));
        }
        let ch = image.channels as usize;
        let mut channels = x::SmallVec::new();
        for (c, name) in layer.channels.iter().enumerate() {
            if layer.channels[..c].contains(name) || name.contains(',') {
                return Err(invalid(format!("channel name `{name}` repeated or containing a comma")));
            }
            let plane = image.data.iter().skip(c).step_by(ch).copied();
            let samples = match precision {
                ExrPrecision::Half => FlatSamples::F16(plane.map(x::f16::from_f32).collect()),
                ExrPrecision::Float => FlatSamples::F32(plane.collect()),
            };
            channels.push(AnyChannel::new(text(name, "channel name")?, samples));
        }
        let mut attributes = if layer.name.is_empty() && layers.len() == 1 {
            LayerAttributes::default()
        } else {
            LayerAttributes::named(text(&layer.name, "layer name")?)
        };
        let order = layer.channels.join(",");
        attributes.other.insert(
            Text::from_slice_unchecked(ORDER_ATTRIBUTE.as_bytes()),
            AttributeValue::Text(text(&order, "channel name")?),
        );
        out.push(x::Layer::new(
            (size.0 as usize, size.1 as usize),
            attributes,
            x::Encoding::SMALL_LOSSLESS, // ZIP, 16 scanlines per block
            AnyChannels::sort(channels),
        ));
    }
    let bounds = IntegerBounds::from_dimensions((size.0 as usize, size.1 as usize));
    let exr_image = x::Image::from_layers(ImageAttributes::new(bounds), out);
    write_atomically(path, |file| {
        exr_image.write().to_buffered(&mut *file).map_err(|e| e.to_string())?;
        super::flush(file)
    })
}

/// Reads every layer of an EXR as linear images. A single-part file whose channels are named
/// `layer.channel` (the OpenEXR convention for multi-layer single-part files) is split into those
/// layers. Channel order follows what [`write_exr_layers`] recorded, else `R G B A` / `X Y Z`
/// convention, else alphabetical. Layers of more than 4 channels or subsampled channels are
/// [`IoError::Unsupported`].
pub fn read_exr_layers(path: impl AsRef<Path>) -> Result<Vec<Layer>, IoError> {
    read_layers(path.as_ref(), None).map(|(layers, _)| layers)
}

/// Reads a single-image EXR for [`super::read`]; also returns its bits per sample (16 or 32).
pub(super) fn read_single(path: &Path) -> Result<(Image, u8), IoError> {
    single(path, read_layers(path, None)?)
}

/// [`read_single`] of a file's bytes in memory; `path` names it in errors.
pub(super) fn decode_single(bytes: &[u8], path: &Path) -> Result<(Image, u8), IoError> {
    single(path, read_layers(path, Some(bytes))?)
}

fn single(path: &Path, (mut layers, bits): (Vec<Layer>, u8)) -> Result<(Image, u8), IoError> {
    if layers.len() != 1 {
        let names: Vec<_> = layers.iter().map(|l| format!("`{}`", l.name)).collect();
        return Err(IoError::Unsupported {
            path: path.into(),
            what: format!(
                "EXR with {} layers ({}); read it with read_exr_layers",
                layers.len(),
                names.join(", ")
            ),
        });
    }
    Ok((layers.remove(0).image, bits))
}

/// No EXR compression in the `exr` crate expands data by more than deflate's ~1032:1, so a header
/// promising more pixels than that is corrupt; checking first keeps a damaged file from making the
/// decoder allocate gigabytes.
const MAX_EXPANSION: u64 = 1100;
/// Decoded size always allowed, whatever the file size.
const MIN_BUDGET: u64 = 64 << 20;

/// The layers of the EXR at `path`, or of its `bytes` if given (`path` then only names it).
fn read_layers(path: &Path, bytes: Option<&[u8]>) -> Result<(Vec<Layer>, u8), IoError> {
    let meta = match bytes {
        Some(b) => x::MetaData::read_from_buffered(std::io::Cursor::new(b), false),
        None => x::MetaData::read_from_file(path, false),
    }
    .map_err(|e| map_exr_error(path, e))?;
    let file_len = match bytes {
        Some(b) => b.len() as u64,
        None => std::fs::metadata(path).map_err(|source| IoError::Open { path: path.into(), source })?.len(),
    };
    let decoded: u64 = meta
        .headers
        .iter()
        .map(|h| (h.layer_size.area() as u64).saturating_mul(h.channels.bytes_per_pixel as u64))
        .fold(0, u64::saturating_add);
    if decoded > file_len.saturating_mul(MAX_EXPANSION).max(MIN_BUDGET) {
        return Err(IoError::Decode {
            path: path.into(),
            detail: format!(
                "header promises {decoded} bytes of pixels, impossible for a {file_len}-byte file (corrupt or \
                 truncated)"
            ),
        });
    }
    if meta.headers.iter().any(|h| h.deep) {
        return Err(IoError::Unsupported { path: path.into(), what: "deep EXR data".into() });
    }
    // The decoder is third-party code fed untrusted bytes: a panic in it is a bad file, not a crash.
    let file = std::panic::catch_unwind(|| read_file(path, bytes))
        .map_err(|_| IoError::Decode {
            path: path.into(),
            detail: "EXR decoder failed (corrupt file?)".into(),
        })?
        .map_err(|e| map_exr_error(path, e))?;
    let unsupported = |what: String| IoError::Unsupported { path: path.into(), what };
    let mut bits = 16;
    let mut layers = Vec::new();
    for part in &file.layer_data {
        let (w, h) = (part.size.0, part.size.1);
        let (Ok(width), Ok(height)) = (u32::try_from(w), u32::try_from(h)) else {
            return Err(unsupported(format!("layer of {w}x{h} pixels")));
        };
        let part_name = part.attributes.layer_name.as_ref().map(|t| t.to_string()).unwrap_or_default();
        let order: Vec<String> =
            match part.attributes.other.get(&Text::from_slice_unchecked(ORDER_ATTRIBUTE.as_bytes())) {
                Some(AttributeValue::Text(t)) => t.to_string().split(',').map(str::to_owned).collect(),
                _ => Vec::new(),
            };
        // Group channels by the prefix before their last dot (single-part multi-layer convention).
        let mut groups: Vec<ChannelGroup> = Vec::new();
        for channel in &part.channel_data.list {
            if channel.sampling != x::Vec2(1, 1) {
                return Err(unsupported(format!("subsampled channel `{}`", channel.name)));
            }
            if !matches!(channel.sample_data, FlatSamples::F16(_)) {
                bits = 32;
            }
            let full = channel.name.to_string();
            let (prefix, short) = match full.rsplit_once('.') {
                Some((p, s)) if order.is_empty() => (p.to_owned(), s.to_owned()),
                _ => (String::new(), full.clone()),
            };
            match groups.iter_mut().find(|(p, _)| *p == prefix) {
                Some((_, list)) => list.push((short, channel)),
                None => groups.push((prefix, vec![(short, channel)])),
            }
        }
        for (prefix, mut list) in groups {
            let name = match (part_name.is_empty(), prefix.is_empty()) {
                (_, true) => part_name.clone(),
                (true, false) => prefix,
                (false, false) => format!("{part_name}.{prefix}"),
            };
            if list.len() > 4 {
                return Err(unsupported(format!("layer `{name}` has {} channels (at most 4)", list.len())));
            }
            list.sort_by_key(|(short, _)| rank(short, &order));
            let ch = list.len();
            let mut data = vec![0.0f32; w * h * ch];
            for (c, (short, channel)) in list.iter().enumerate() {
                if channel.sample_data.len() != w * h {
                    return Err(IoError::Decode {
                        path: path.into(),
                        detail: format!("channel `{short}` of layer `{name}` has the wrong sample count"),
                    });
                }
                for (i, v) in channel.sample_data.values_as_f32().enumerate() {
                    data[i * ch + c] = v;
                }
            }
            let image = Image { width, height, channels: ch as u8, data, encoding: Encoding::Linear };
            layers.push(Layer { name, channels: list.into_iter().map(|(s, _)| s).collect(), image });
        }
    }
    Ok((layers, bits))
}

/// Channels sharing a `prefix.` in a part: `(prefix, [(short name, channel)])`.
type ChannelGroup<'a> = (String, Vec<(String, &'a AnyChannel<FlatSamples>)>);

type ExrFile = x::Image<x::Layers<AnyChannels<FlatSamples>>>;

fn read_file(path: &Path, bytes: Option<&[u8]>) -> x::Result<ExrFile> {
    let read =
        x::read().no_deep_data().largest_resolution_level().all_channels().all_layers().all_attributes();
    match bytes {
        Some(b) => read.from_buffered(std::io::Cursor::new(b)),
        None => read.from_file(path),
    }
}

/// Sort key: the recorded order if the name is in it, else the conventional rank, else alphabetical.
fn rank(name: &str, order: &[String]) -> (usize, String) {
    if let Some(i) = order.iter().position(|o| o == name) {
        return (i, String::new());
    }
    let i = CANONICAL.iter().position(|c| *c == name).unwrap_or(CANONICAL.len());
    (order.len() + i, name.to_owned())
}

fn map_exr_error(path: &Path, e: x::Error) -> IoError {
    match e {
        x::Error::Io(source) if source.kind() == std::io::ErrorKind::NotFound => {
            IoError::Open { path: path.into(), source }
        }
        x::Error::Invalid(msg) if msg.contains("missing bytes") => {
            let size = std::fs::metadata(path).map(|m| format!("; the file has only {} bytes", m.len()));
            IoError::Truncated {
                path: path.into(),
                detail: format!("data ends early{}", size.unwrap_or_default()),
            }
        }
        x::Error::NotSupported(msg) => IoError::Unsupported { path: path.into(), what: format!("EXR {msg}") },
        other => IoError::Decode { path: path.into(), detail: other.to_string() },
    }
}

/// Rows `rows` (clamped to the image) of a one-channel EXR, only the blocks of scanlines that
/// hold them decompressed: what a fit needs from a frame whose light falls in a band of it.
/// Returns the image at full size, every row outside the blocks read left at 0, and the rows
/// actually read (`rows` widened to whole blocks). Any other EXR (several channels or parts,
/// tiles, an offset data window, integer samples) is read whole, and all its rows reported read.
pub fn read_exr_rows(
    path: impl AsRef<Path>,
    rows: std::ops::Range<u32>,
) -> Result<(Image, std::ops::Range<u32>), IoError> {
    let path = path.as_ref();
    // Third-party decoder fed untrusted bytes, as in `read_layers`.
    let band = std::panic::catch_unwind(|| read_band(path, rows)).map_err(|_| IoError::Decode {
        path: path.into(),
        detail: "EXR decoder failed (corrupt file?)".into(),
    })??;
    match band {
        Some(b) => Ok(b),
        None => {
            let (image, _) = read_single(path)?;
            let h = image.height;
            Ok((image, 0..h))
        }
    }
}

/// [`read_exr_rows`]'s block-level path; `None` for a file it leaves to the whole-image reader.
fn read_band(
    path: &Path,
    rows: std::ops::Range<u32>,
) -> Result<Option<(Image, std::ops::Range<u32>)>, IoError> {
    use exr::block::chunk::Chunk;
    use exr::block::reader::ChunksReader;
    use exr::block::UncompressedBlock;
    use exr::meta::attribute::SampleType;
    let file = std::fs::File::open(path).map_err(|source| IoError::Open { path: path.into(), source })?;
    let file_len = file.metadata().map_err(|source| IoError::Open { path: path.into(), source })?.len();
    let reader =
        exr::block::read(std::io::BufReader::new(file), false).map_err(|e| map_exr_error(path, e))?;
    let [header] = reader.headers() else { return Ok(None) };
    let channels = &header.channels.list;
    let simple = channels.len() == 1
        && channels[0].sampling == x::Vec2(1, 1)
        && matches!(channels[0].sample_type, SampleType::F32 | SampleType::F16)
        && !header.deep
        && matches!(header.blocks, exr::meta::BlockDescription::ScanLines)
        && header.own_attributes.layer_position == x::Vec2(0, 0);
    if !simple {
        return Ok(None);
    }
    let (w, h) = (header.layer_size.0, header.layer_size.1);
    let (Ok(width), Ok(height)) = (u32::try_from(w), u32::try_from(h)) else { return Ok(None) };
    // The same guard as `read_layers`: a header cannot promise more pixels than the file holds.
    if (w as u64).saturating_mul(h as u64).saturating_mul(4)
        > file_len.saturating_mul(MAX_EXPANSION).max(MIN_BUDGET)
    {
        return Err(IoError::Decode {
            path: path.into(),
            detail: format!("header promises {w} × {h} pixels, impossible for a {file_len}-byte file (corrupt or truncated)"),
        });
    }
    let half = channels[0].sample_type == SampleType::F16;
    let (y0, y1) = (rows.start.min(height) as usize, rows.end.min(height) as usize);
    let (mut lo, mut hi) = (usize::MAX, 0usize);
    let chunks = reader
        .filter_chunks(false, |_, _, b| {
            let keep = b.pixel_position.y() < y1 && b.pixel_position.y() + b.pixel_size.height() > y0;
            if keep {
                lo = lo.min(b.pixel_position.y());
                hi = hi.max(b.pixel_position.y() + b.pixel_size.height());
            }
            keep
        })
        .map_err(|e| map_exr_error(path, e))?;
    let meta = chunks.meta_data().clone();
    let mut data = vec![0.0f32; w * h];
    let mut chunks = chunks;
    let mut line16: Vec<x::f16> = Vec::new();
    while let Some(chunk) = chunks.read_next_chunk() {
        let chunk: Chunk = chunk.map_err(|e| map_exr_error(path, e))?;
        let block =
            UncompressedBlock::decompress_chunk(chunk, &meta, false).map_err(|e| map_exr_error(path, e))?;
        for line in block.lines(&meta.headers[0].channels) {
            let (x0, y, n) =
                (line.location.position.x(), line.location.position.y(), line.location.sample_count);
            if y >= h || x0 + n > w {
                return Err(IoError::Decode {
                    path: path.into(),
                    detail: format!("scanline {y} outside the image"),
                });
            }
            let out = &mut data[y * w + x0..y * w + x0 + n];
            let read = if half {
                line16.resize(n, x::f16::ZERO);
                line.read_samples_into_slice(&mut line16).map(|()| {
                    use half::slice::HalfFloatSliceExt;
                    line16.convert_to_f32_slice(out);
                })
            } else {
                line.read_samples_into_slice(out)
            };
            read.map_err(|e| map_exr_error(path, e))?;
        }
    }
    let read = if lo < hi { lo as u32..hi as u32 } else { y0 as u32..y0 as u32 };
    Ok(Some((Image { width, height, channels: 1, data, encoding: Encoding::Linear }, read)))
}
