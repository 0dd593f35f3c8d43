//! Figures for reports: maps side by side, each scalar map through a colour map with its scale
//! bar beneath it, pixels outside what was compared drawn grey; histograms against a model.
//!
//! A figure is an sRGB [`Image`] (write it with [`crate::io::write_png`] as it is); the report
//! that shows it gives each panel's name and the colour bar's range in its caption.

use crate::io::{Encoding, Image};

/// Viridis (van der Walt and Smith, matplotlib's default map), sRGB at 0, 1/8, …, 1; linear
/// between them. Perceptually even and readable in grey and by the colour blind, as a map of
/// errors must be.
const VIRIDIS: [[f32; 3]; 9] = [
    [0.267, 0.005, 0.329],
    [0.283, 0.141, 0.458],
    [0.254, 0.265, 0.530],
    [0.207, 0.372, 0.553],
    [0.164, 0.471, 0.558],
    [0.128, 0.567, 0.551],
    [0.135, 0.659, 0.518],
    [0.267, 0.749, 0.441],
    [0.993, 0.906, 0.144],
];

/// Drawn where a panel has no value (outside the sample, not fitted).
pub const MASKED: [f32; 3] = [0.35, 0.35, 0.35];

/// The colour of `t` in `[0, 1]` (clamped), sRGB.
pub fn viridis(t: f32) -> [f32; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let x = t * 8.0;
    let k = (x.floor() as usize).min(7);
    let f = x - k as f32;
    let (a, b) = (VIRIDIS[k], VIRIDIS[k + 1]);
    std::array::from_fn(|c| a[c] + (b[c] - a[c]) * f)
}

/// One panel of a figure: `width × height` sRGB pixels, `None` where masked, and for a scalar
/// panel the colour bar drawn beneath it.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<Option<[f32; 3]>>,
    /// Whether a colour bar (low to high, left to right) goes beneath the panel.
    pub bar: bool,
}

impl Panel {
    /// Scalar `values` mapped through [`viridis`] from `range.0` (dark) to `range.1` (yellow);
    /// a value that is not finite is masked.
    pub fn scalar(width: u32, height: u32, values: &[Option<f32>], range: (f32, f32)) -> Panel {
        let span = (range.1 - range.0).max(f32::MIN_POSITIVE);
        let rgb = values
            .iter()
            .map(|v| v.filter(|v| v.is_finite()).map(|v| viridis((v - range.0) / span)))
            .collect();
        Panel { width, height, rgb, bar: true }
    }

    /// Linear RGB `values` times `gain`, clamped to `[0, 1]` and sRGB-encoded; a value that is
    /// not finite is masked.
    pub fn colour(width: u32, height: u32, values: &[Option<[f32; 3]>], gain: f32) -> Panel {
        let rgb = values
            .iter()
            .map(|v| {
                v.filter(|v| v.iter().all(|x| x.is_finite()))
                    .map(|v| v.map(|x| linear_to_srgb((x * gain).clamp(0.0, 1.0))))
            })
            .collect();
        Panel { width, height, rgb, bar: false }
    }
}

fn linear_to_srgb(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// `panels` left to right, each enlarged `zoom` times (nearest: a pixel stays a pixel),
/// `zoom` pixels of white between them; beneath a scalar panel its colour bar, `2 × zoom`
/// pixels high after a gap of `zoom`. An sRGB image.
pub fn row(panels: &[Panel], zoom: u32) -> Image {
    let z = zoom.max(1);
    let width = panels.iter().map(|p| p.width * z).sum::<u32>() + z * panels.len().saturating_sub(1) as u32;
    let tallest = panels.iter().map(|p| p.height * z).max().unwrap_or(0);
    let bars = panels.iter().any(|p| p.bar);
    let height = tallest + if bars { 3 * z } else { 0 };
    let mut img = Image::from_fn(width, height, 3, |_, _, _| 1.0);
    let mut put = |x: u32, y: u32, rgb: [f32; 3]| {
        let i = ((y * width + x) * 3) as usize;
        img.data[i..i + 3].copy_from_slice(&rgb);
    };
    let mut left = 0;
    for p in panels {
        for y in 0..p.height * z {
            for x in 0..p.width * z {
                let v = p.rgb[((y / z) * p.width + x / z) as usize].unwrap_or(MASKED);
                put(left + x, y, v);
            }
        }
        if p.bar {
            let w = p.width * z;
            for x in 0..w {
                let c = viridis(x as f32 / (w.max(2) - 1) as f32);
                for y in tallest + z..tallest + 3 * z {
                    put(left + x, y, c);
                }
            }
        }
        left += p.width * z + z;
    }
    img.with_encoding(Encoding::Srgb)
}

/// The share of `samples` in each of `bins` equal bins over `range` (samples outside it are
/// left out of every bin, but counted in the total).
pub fn bin_shares(samples: &[f64], range: (f64, f64), bins: usize) -> Vec<f64> {
    let mut counts = vec![0usize; bins];
    let width = (range.1 - range.0) / bins as f64;
    for &x in samples {
        let k = ((x - range.0) / width).floor();
        if k >= 0.0 && (k as usize) < bins {
            counts[k as usize] += 1;
        }
    }
    let n = samples.len().max(1) as f64;
    counts.iter().map(|&c| c as f64 / n).collect()
}

/// A histogram figure: `samples`' share per bin over `range` as bars (`bar_px` wide, at most
/// `height` px tall), and the share a model's CDF `expected` puts in each bin as a dark mark
/// across its bar, both on one scale (the larger peak at 90 % of the height). An sRGB image.
pub fn histogram(
    samples: &[f64],
    range: (f64, f64),
    bins: usize,
    expected: &dyn Fn(f64) -> f64,
    (bar_px, height): (u32, u32),
) -> Image {
    let got = bin_shares(samples, range, bins);
    let width = (range.1 - range.0) / bins as f64;
    let model: Vec<f64> = (0..bins)
        .map(|k| expected(range.0 + (k + 1) as f64 * width) - expected(range.0 + k as f64 * width))
        .collect();
    let peak = got.iter().chain(&model).copied().fold(0.0, f64::max).max(f64::MIN_POSITIVE);
    let to_px = |share: f64| ((share / peak) * 0.9 * f64::from(height)).round() as u32;
    let (w, h) = (bar_px * bins as u32, height);
    let bar = viridis(0.55);
    let mark = [0.05, 0.05, 0.05];
    let mut img = Image::from_fn(w, h, 3, |_, _, _| 1.0);
    let mut put = |x: u32, y: u32, rgb: [f32; 3]| {
        let i = ((y * w + x) * 3) as usize;
        img.data[i..i + 3].copy_from_slice(&rgb);
    };
    for k in 0..bins as u32 {
        let (top, at) = (to_px(got[k as usize]), to_px(model[k as usize]).min(h - 1));
        for x in k * bar_px..(k + 1) * bar_px {
            // A pixel's gap between bars keeps them apart.
            if x + 1 < (k + 1) * bar_px || bar_px == 1 {
                for y in h - top.min(h)..h {
                    put(x, y, bar);
                }
            }
            // Two pixels thick, the upper at the model's share.
            for y in h - 1 - at..=(h - at).min(h - 1) {
                put(x, y, mark);
            }
        }
    }
    img.with_encoding(Encoding::Srgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viridis_runs_from_its_dark_end_to_its_yellow_end_through_its_anchors() {
        let near = |a: [f32; 3], b: [f32; 3]| (0..3).all(|c| (a[c] - b[c]).abs() < 1e-6);
        assert_eq!(viridis(0.0), VIRIDIS[0]);
        assert!(near(viridis(1.0), VIRIDIS[8]));
        assert_eq!(viridis(-3.0), VIRIDIS[0]);
        assert_eq!(viridis(f32::NAN), VIRIDIS[0]);
        let at = |k: usize| viridis(k as f32 / 8.0);
        for (k, anchor) in VIRIDIS.iter().enumerate() {
            let got = at(k);
            assert!((0..3).all(|c| (got[c] - anchor[c]).abs() < 1e-6), "{k}: {got:?}");
        }
        // Luminance grows along the map (it reads in grey).
        let lum = |c: [f32; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
        let l: Vec<f32> = (0..=20).map(|k| lum(viridis(k as f32 / 20.0))).collect();
        assert!(l.windows(2).all(|w| w[1] > w[0]), "{l:?}");
    }

    #[test]
    fn a_histogram_bins_the_samples_and_marks_the_model_s_share_on_one_scale() {
        let samples = [0.1, 0.2, 0.3, 1.5, 1.6, 5.0];
        assert_eq!(bin_shares(&samples, (0.0, 2.0), 2), vec![0.5, 2.0 / 6.0]);
        // A uniform model over [0, 2]: half in each bin. Peak 0.5 at 90 % of 20 px: 18 px.
        let img = histogram(&samples, (0.0, 2.0), 2, &|x| (x / 2.0).clamp(0.0, 1.0), (4, 20));
        assert_eq!((img.width, img.height), (8, 20));
        let px = |x: u32, y: u32| -> [f32; 3] {
            let i = ((y * img.width + x) * 3) as usize;
            [img.data[i], img.data[i + 1], img.data[i + 2]]
        };
        let bar = viridis(0.55);
        // Bin 0: 18 px of bar, the model's mark at its top (0.5 too); bin 1: 12 px of bar.
        assert_eq!((px(0, 19), px(0, 3), px(0, 0)), (bar, bar, [1.0; 3]));
        assert_eq!(px(0, 1), [0.05; 3]);
        assert_eq!((px(4, 19), px(4, 8), px(4, 7)), (bar, bar, [1.0; 3]));
        assert_eq!(px(4, 1), [0.05; 3], "the model's half in bin 1 as well");
        assert_eq!(px(3, 19), [1.0; 3], "the gap between bars");
    }

    #[test]
    fn a_row_lays_panels_out_enlarged_with_gaps_masks_and_bars() {
        let a = Panel::scalar(2, 1, &[Some(0.0), None], (0.0, 1.0));
        let b = Panel::colour(1, 1, &[Some([1.0, 0.0, 0.25])], 1.0);
        let img = row(&[a, b], 2);
        // 2·2 + 2 + 1·2 wide; 1·2 tall and the bar's 3·2.
        assert_eq!((img.width, img.height, img.encoding), (8, 8, Encoding::Srgb));
        let px = |x: u32, y: u32| -> [f32; 3] {
            let i = ((y * img.width + x) * 3) as usize;
            [img.data[i], img.data[i + 1], img.data[i + 2]]
        };
        assert_eq!(px(0, 0), VIRIDIS[0]);
        assert_eq!(px(1, 1), VIRIDIS[0]);
        assert_eq!(px(2, 0), MASKED);
        assert_eq!(px(4, 0), [1.0; 3], "the gap");
        let near = |a: [f32; 3], b: [f32; 3]| (0..3).all(|c| (a[c] - b[c]).abs() < 1e-6);
        assert!(near(px(6, 1), [1.0, 0.0, linear_to_srgb(0.25)]));
        // The scalar panel's bar runs dark to yellow beneath it; the colour panel has none.
        assert_eq!(px(0, 4), VIRIDIS[0]);
        assert!(near(px(3, 5), VIRIDIS[8]));
        assert_eq!(px(0, 3), [1.0; 3]);
        assert_eq!(px(6, 5), [1.0; 3]);
    }
}
