//! The in-memory image and the sRGB transfer function.

/// What the sample values of an [`Image`] mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Encoding {
    /// Proportional to light: what HDR merging, calibration and shading maths need.
    Linear,
    /// Encoded with the sRGB transfer function (IEC 61966-2-1), as display images are.
    Srgb,
}

/// An image of 1–4 interleaved `f32` channels, row-major.
///
/// Integer sources are normalised to `[0, 1]` (8-bit: `/255`, 16-bit: `/65535`); float and half
/// sources keep their raw values. With 2 or 4 channels the last one is alpha, which the transfer
/// function never touches.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Samples per pixel, 1..=4 (gray, gray+alpha, RGB, RGBA).
    pub channels: u8,
    /// `width * height * channels` samples, interleaved.
    pub data: Vec<f32>,
    pub encoding: Encoding,
}

impl Image {
    /// A black linear image.
    ///
    /// # Panics
    /// If `channels` is not in `1..=4` (a programming error, not a data error).
    pub fn new(width: u32, height: u32, channels: u8) -> Image {
        assert!((1..=4).contains(&channels), "an Image has 1 to 4 channels, not {channels}");
        let len = width as usize * height as usize * channels as usize;
        Image { width, height, channels, data: vec![0.0; len], encoding: Encoding::Linear }
    }

    /// A linear image whose sample `(x, y, c)` is `f(x, y, c)`.
    ///
    /// # Panics
    /// If `channels` is not in `1..=4`.
    pub fn from_fn(width: u32, height: u32, channels: u8, mut f: impl FnMut(u32, u32, u8) -> f32) -> Image {
        let mut image = Image::new(width, height, channels);
        let mut i = 0;
        for y in 0..height {
            for x in 0..width {
                for c in 0..channels {
                    image.data[i] = f(x, y, c);
                    i += 1;
                }
            }
        }
        image
    }

    /// The same image labelled with another encoding, values untouched: for data whose meaning the
    /// caller knows better than the file did.
    pub fn with_encoding(mut self, encoding: Encoding) -> Image {
        self.encoding = encoding;
        self
    }

    fn index(&self, x: u32, y: u32) -> usize {
        assert!(x < self.width && y < self.height, "pixel ({x}, {y}) outside {}x{}", self.width, self.height);
        (y as usize * self.width as usize + x as usize) * self.channels as usize
    }

    /// Sample `c` of pixel `(x, y)`. Panics when out of bounds, like slice indexing.
    pub fn get(&self, x: u32, y: u32, c: u8) -> f32 {
        assert!(c < self.channels, "channel {c} of a {}-channel image", self.channels);
        self.data[self.index(x, y) + c as usize]
    }

    /// All samples of pixel `(x, y)`. Panics when out of bounds.
    pub fn pixel(&self, x: u32, y: u32) -> &[f32] {
        let i = self.index(x, y);
        &self.data[i..i + self.channels as usize]
    }

    /// Mutable samples of pixel `(x, y)`. Panics when out of bounds.
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [f32] {
        let i = self.index(x, y);
        let n = self.channels as usize;
        &mut self.data[i..i + n]
    }

    /// Whether the last channel is alpha (2 or 4 channels).
    pub fn has_alpha(&self) -> bool {
        self.channels == 2 || self.channels == 4
    }

    /// The image in linear encoding: decodes sRGB colour channels, alpha untouched; a linear image is
    /// returned unchanged.
    pub fn to_linear(&self) -> Image {
        self.convert(Encoding::Linear, srgb_to_linear)
    }

    /// The image in sRGB encoding: encodes linear colour channels, alpha untouched; an sRGB image is
    /// returned unchanged.
    pub fn to_srgb(&self) -> Image {
        self.convert(Encoding::Srgb, linear_to_srgb)
    }

    fn convert(&self, to: Encoding, f: fn(f32) -> f32) -> Image {
        let mut out = self.clone();
        if self.encoding == to {
            return out;
        }
        let ch = self.channels as usize;
        let colour = if self.has_alpha() { ch - 1 } else { ch };
        for px in out.data.chunks_exact_mut(ch) {
            for v in &mut px[..colour] {
                *v = f(*v);
            }
        }
        out.encoding = to;
        out
    }
}

/// sRGB decoding (IEC 61966-2-1): `v / 12.92` up to 0.04045, `((v + 0.055) / 1.055)^2.4` above.
/// Odd-symmetric for negative values so out-of-gamut data survives a round trip.
pub fn srgb_to_linear(v: f32) -> f32 {
    let a = f64::from(v).abs();
    let l = if a <= 0.04045 { a / 12.92 } else { ((a + 0.055) / 1.055).powf(2.4) };
    (l.copysign(f64::from(v))) as f32
}

/// sRGB encoding (IEC 61966-2-1): `12.92 v` up to 0.0031308, `1.055 v^(1/2.4) - 0.055` above.
/// Odd-symmetric for negative values.
pub fn linear_to_srgb(v: f32) -> f32 {
    let a = f64::from(v).abs();
    let s = if a <= 0.0031308 { a * 12.92 } else { 1.055 * a.powf(1.0 / 2.4) - 0.055 };
    (s.copysign(f64::from(v))) as f32
}
