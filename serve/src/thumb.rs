//! A frame for a person to look at: its statistics (histogram, clipped pixels, the laser spot)
//! and a small PNG of it. Plain functions of the decoded image; decoding is `lightrig_imaging`'s.

use lightrig_host::live::LiveFrame;
use lightrig_imaging::io::{self, Encoding, Image, ReadOptions};

/// Thumbnails are at most this wide, pixels.
pub const MAX_WIDTH: u32 = 320;
/// Histogram bins.
pub const BINS: usize = 64;

/// What a frame shows, for FRAME (docs/live-api.md).
#[derive(Debug, Clone, PartialEq)]
pub struct Stats {
    pub width: u32,
    pub height: u32,
    pub channels: u8,
    pub bits: u8,
    pub pixels: u64,
    /// Pixels at the largest code of an integer frame; `None` for float frames.
    pub clipped: Option<u64>,
    pub min: f32,
    pub max: f32,
    pub histogram: Vec<u64>,
    /// Centroid of the pixels above half the maximum, `(x, y)` in pixels (top-left pixel's
    /// centre at 0.5, 0.5).
    pub spot: Option<(f64, f64)>,
}

/// A frame's statistics and thumbnail.
#[derive(Debug, Clone)]
pub struct Thumb {
    pub stats: Stats,
    pub png: Vec<u8>,
}

/// The luminance of each pixel: the one channel, or Rec. 709 luma of the first three.
pub fn luma(image: &Image) -> Vec<f32> {
    let c = usize::from(image.channels);
    image
        .data
        .chunks_exact(c)
        .map(|p| if c >= 3 { 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2] } else { p[0] })
        .collect()
}

/// The statistics of `image` (read from a file of `bits` per sample), with the laser spot if
/// `spot`.
pub fn stats(image: &Image, bits: u8, spot: bool) -> Stats {
    let y = luma(image);
    let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
    for &v in y.iter().filter(|v| v.is_finite()) {
        min = min.min(v);
        max = max.max(v);
    }
    if min > max {
        (min, max) = (0.0, 0.0);
    }
    // Integer PNG/TIFF are read display-encoded; float TIFF and EXR (half too) linear.
    let float = image.encoding == Encoding::Linear;
    // Integer frames are read normalised: the largest code is 1.0 exactly.
    let clipped = (!float).then(|| {
        let c = usize::from(image.channels);
        image.data.chunks_exact(c).filter(|p| p.iter().any(|&v| v >= 1.0)).count() as u64
    });
    let full = if float { max.max(f32::MIN_POSITIVE) } else { 1.0 };
    let mut histogram = vec![0u64; BINS];
    for &v in y.iter().filter(|v| v.is_finite()) {
        let bin = ((v / full).clamp(0.0, 1.0) * BINS as f32) as usize;
        histogram[bin.min(BINS - 1)] += 1;
    }
    let spot = if spot && max > 0.0 { spot_of(&y, image.width, image.height) } else { None };
    Stats {
        width: image.width,
        height: image.height,
        channels: image.channels,
        bits,
        pixels: y.len() as u64,
        clipped,
        min,
        max,
        histogram,
        spot,
    }
}

/// The laser spot: the brightest 3 x 3 patch (one hot pixel or noise does not move it), then
/// the centroid, within [`SPOT_RADIUS`] of it, of the values above half the patch's mean,
/// weighted by their excess over that.
fn spot_of(y: &[f32], width: u32, height: u32) -> Option<(f64, f64)> {
    let (w, h) = (width as i64, height as i64);
    let at = |x: i64, r: i64| {
        let v = y[(r.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as usize];
        if v.is_finite() {
            v
        } else {
            0.0
        }
    };
    let mut best = (f32::NEG_INFINITY, 0i64, 0i64);
    for r in 0..h {
        for x in 0..w {
            let mut sum = 0.0;
            for dr in -1..=1 {
                for dx in -1..=1 {
                    sum += at(x + dx, r + dr);
                }
            }
            if sum > best.0 {
                best = (sum, x, r);
            }
        }
    }
    let threshold = best.0 / 9.0 / 2.0;
    // A frame of nothing (or NaN) has no spot.
    if threshold.is_nan() || threshold <= 0.0 {
        return None;
    }
    let (mut sw, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
    for r in (best.2 - SPOT_RADIUS).max(0)..(best.2 + SPOT_RADIUS + 1).min(h) {
        for x in (best.1 - SPOT_RADIUS).max(0)..(best.1 + SPOT_RADIUS + 1).min(w) {
            let v = at(x, r);
            if v > threshold {
                let wt = f64::from(v - threshold);
                sw += wt;
                sx += wt * (x as f64 + 0.5);
                sy += wt * (r as f64 + 0.5);
            }
        }
    }
    (sw > 0.0).then(|| (sx / sw, sy / sw))
}

/// How far from the brightest patch the spot's pixels are looked for, pixels.
pub const SPOT_RADIUS: i64 = 12;

/// A display picture of `image`, 8 bits, at most [`MAX_WIDTH`] wide (box-filtered): grey for
/// one or two channels, else RGB, scaled so that `max` is white (a dim frame is still seen;
/// its statistics give the true levels). Integer frames keep their encoding; float (linear)
/// frames are sRGB-encoded.
pub fn picture(image: &Image, max: f32) -> (u32, u32, u8, Vec<u8>) {
    let k = image.width.div_ceil(MAX_WIDTH).max(1);
    let (w, h) = (image.width.div_ceil(k), image.height.div_ceil(k));
    let c = usize::from(image.channels);
    let out_c: usize = if c >= 3 { 3 } else { 1 };
    let linear = image.encoding == Encoding::Linear;
    let scale = if max > 0.0 { 1.0 / max } else { 1.0 };
    let mut out = Vec::with_capacity((w * h) as usize * out_c);
    for ty in 0..h {
        for tx in 0..w {
            let mut sum = [0f32; 3];
            let mut n = 0f32;
            for y in ty * k..((ty + 1) * k).min(image.height) {
                for x in tx * k..((tx + 1) * k).min(image.width) {
                    let p = &image.data[(y * image.width + x) as usize * c..][..c];
                    for (ch, s) in sum.iter_mut().enumerate().take(out_c) {
                        let v = p[ch];
                        *s += if v.is_finite() { v } else { 0.0 };
                    }
                    n += 1.0;
                }
            }
            for s in sum.iter().take(out_c) {
                let mut v = (s / n * scale).clamp(0.0, 1.0);
                if linear {
                    v = io::linear_to_srgb(v);
                }
                out.push((v * 255.0).round() as u8);
            }
        }
    }
    (w, h, out_c as u8, out)
}

/// Decodes `frame` and makes its statistics and thumbnail; the error says which frame would
/// not decode and why.
pub fn make(frame: &LiveFrame, spot: bool) -> Result<Thumb, String> {
    let name = format!(
        "camera {} frame {}.{}",
        frame.camera,
        frame.frame.map_or("?".into(), |n| n.to_string()),
        frame.ext
    );
    let (image, bits) = io::decode(&frame.data, &name, ReadOptions::default()).map_err(|e| e.to_string())?;
    let stats = stats(&image, bits, spot);
    let (w, h, c, pixels) = picture(&image, stats.max);
    let mut png = Vec::new();
    let colour = if c == 3 { image::ExtendedColorType::Rgb8 } else { image::ExtendedColorType::L8 };
    image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut png), &pixels, w, h, colour)
        .map_err(|e| format!("{name}: thumbnail: {e}"))?;
    Ok(Thumb { stats, png })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grey(width: u32, height: u32, encoding: Encoding, f: impl Fn(u32, u32) -> f32) -> Image {
        Image::from_fn(width, height, 1, |x, y, _| f(x, y)).with_encoding(encoding)
    }

    #[test]
    fn an_integer_frame_counts_its_saturated_pixels_and_bins_by_code() {
        // 8 x 2: values 0/7 … 7/7; the last column saturated.
        let image = grey(8, 2, Encoding::Srgb, |x, _| x as f32 / 7.0);
        let s = stats(&image, 16, false);
        assert_eq!((s.pixels, s.clipped, s.min, s.max), (16, Some(2), 0.0, 1.0));
        // A half-float EXR is 16 bits too, but linear: no clip level.
        assert_eq!(stats(&image.clone().with_encoding(Encoding::Linear), 16, false).clipped, None);
        assert_eq!(s.histogram.iter().sum::<u64>(), 16);
        // x/7 of 64 bins: bins 0, 9, 18, 27, 36, 45, 54, 63 (the top one holds 1.0).
        for (x, bin) in [0usize, 9, 18, 27, 36, 45, 54, 63].into_iter().enumerate() {
            assert_eq!(s.histogram[bin], 2, "x = {x}");
        }
        assert_eq!(s.spot, None, "asked for no spot");
    }

    #[test]
    fn a_float_frame_has_no_clip_level_and_its_spot_is_the_bright_blob_centre() {
        // A 3 x 3 bright square centred on pixel (10, 4) of a 32 x 16 frame, dim background.
        let image =
            grey(
                32,
                16,
                Encoding::Linear,
                |x, y| if x.abs_diff(10) <= 1 && y.abs_diff(4) <= 1 { 5.0 } else { 0.1 },
            );
        let s = stats(&image, 32, true);
        assert_eq!(s.clipped, None);
        assert_eq!(s.max, 5.0);
        let (x, y) = s.spot.unwrap();
        assert!((x - 10.5).abs() < 1e-9 && (y - 4.5).abs() < 1e-9, "{x} {y}");
        assert_eq!(s.histogram[BINS - 1], 9, "the square at full scale");
        assert_eq!(s.histogram[1], 32 * 16 - 9, "0.1 of 5 is bin 1");
    }

    #[test]
    fn the_spot_is_found_among_hot_pixels_and_noise_brighter_than_half_its_peak() {
        // A Gaussian spot of σ 2 px at (40.5, 20.5) of 96 x 48, on noise up to 60 % of its peak
        // and one hot pixel at twice the peak far away (a threshold over the frame would fail).
        let noise = |x: u32, y: u32| {
            ((x.wrapping_mul(7919) ^ y.wrapping_mul(104_729)) % 1000) as f32 / 1000.0 * 0.6 - 0.3
        };
        let image = grey(96, 48, Encoding::Linear, |x, y| {
            let (dx, dy) = (x as f32 + 0.5 - 40.5, y as f32 + 0.5 - 20.5);
            let g = (-(dx * dx + dy * dy) / 8.0).exp();
            if (x, y) == (85, 40) {
                2.0
            } else {
                g + noise(x, y)
            }
        });
        let (x, y) = stats(&image, 16, true).spot.unwrap();
        assert!((x - 40.5).abs() < 0.3 && (y - 20.5).abs() < 0.3, "{x} {y}");
    }

    #[test]
    fn a_wide_frame_is_box_filtered_to_at_most_the_thumbnail_width() {
        let image = grey(1000, 10, Encoding::Srgb, |x, _| if x % 2 == 0 { 1.0 } else { 0.0 });
        let (w, h, c, px) = picture(&image, 1.0);
        // k = ceil(1000 / 320) = 4: 250 x 3, each the mean of 4 alternating columns.
        assert_eq!((w, h, c, px.len()), (250, 3, 1, 750));
        assert!(px.iter().all(|&v| v == 128), "{:?}", &px[..4]);
        // A dim integer frame is stretched to its maximum, its encoding kept.
        let dim = grey(2, 1, Encoding::Srgb, |x, _| [0.01, 0.005][x as usize]);
        assert_eq!(picture(&dim, 0.01).3, vec![255, 128]);
        // A linear frame is scaled to its maximum and sRGB-encoded.
        let lin = grey(2, 1, Encoding::Linear, |x, _| [2.0, 0.5][x as usize]);
        let (_, _, _, px) = picture(&lin, 2.0);
        assert_eq!(px, vec![255, (io::linear_to_srgb(0.25) * 255.0).round() as u8]);
    }

    #[test]
    fn a_frame_that_does_not_decode_says_which() {
        let frame = LiveFrame {
            camera: 1,
            seq: 1,
            step: Some(0),
            frame: Some(12),
            ext: "png".into(),
            data: std::sync::Arc::from(&b"\x89PNG\r\n\x1a\nbroken"[..]),
            host_us: 0.0,
            trigger: None,
        };
        let e = make(&frame, false).unwrap_err();
        assert!(e.contains("camera 1 frame 12.png"), "{e}");
    }
}
