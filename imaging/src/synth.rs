//! Synthetic images with known truth: chessboards seen through a calibrated camera, for the
//! calibration tests and the virtual camera.
//!
//! The board is rendered analytically rather than by supersampling: a supersampled edge that runs
//! along a pixel row or column is quantised to 1/n of a pixel (¼ px at 4×4), which would bias the
//! "truth" of an axis-aligned board by up to 0.18 px. Here each pixel takes the Gaussian-blurred
//! square wave of its board coordinates: across a grid line at signed pixel distance `d` the wave
//! is `erf(d / (√2·σ))`, and the checker is the product of the two families. Every edge passes
//! exactly through the projected corners and each X-junction is point-symmetric to first order,
//! so a corner detector's error is its own, not the renderer's.

use crate::calib::{pixel_ray, rodrigues, rodrigues_inv, Intrinsics, Pose};

/// What to render: a chessboard of `cols × rows` inner corners with [`crate::calib::Board::chessboard`]'s
/// geometry (corner `(c, r)` at `(c·square, r·square, 0)`), its squares spanning
/// `[−border, cols − 1 + border] × [−border, rows − 1 + border]` squares, square `(0, 0)` dark,
/// surrounded by a light margin one square wide, and `background` beyond.
#[derive(Debug, Clone, PartialEq)]
pub struct ChessboardScene {
    pub cols: usize,
    pub rows: usize,
    /// Square side in world units (those of the pose's translation).
    pub square: f64,
    /// Grey levels (0–255) of the dark squares, light squares and margin, and the background.
    pub dark: f64,
    pub light: f64,
    pub background: f64,
    /// Width of the outermost row and column of squares, in squares: 1 for full squares; printed
    /// boards often cut them short.
    pub border: f64,
    /// Standard deviation in pixels of the Gaussian point spread (optics plus pixel area).
    pub blur: f64,
    /// Standard deviation of additive Gaussian noise in grey levels, before rounding to 8 bits.
    pub noise: f64,
    /// Seed of the noise.
    pub seed: u64,
    /// Uneven light: every grey level is scaled by `1 + shading·u`, `u`
    /// running from −1 at the image's left edge to +1 at its right (0: even light; 0.6 makes
    /// the right side four times as bright as the left).
    pub shading: f64,
}

impl ChessboardScene {
    /// Full border squares, dark 30, light 220, background 90, blur 0.7 px, no noise.
    pub fn new(cols: usize, rows: usize, square: f64) -> Self {
        ChessboardScene {
            cols,
            rows,
            square,
            border: 1.0,
            dark: 30.0,
            light: 220.0,
            background: 90.0,
            blur: 0.7,
            noise: 0.0,
            seed: 1,
            shading: 0.0,
        }
    }

    /// The board turned `tilt_deg` about its own x (`axis` 0) or y (`axis` 1) axis through its
    /// centre, which lies on the optical axis `dist` world units in front of the camera.
    pub fn tilted_pose(&self, tilt_deg: f64, axis: usize, dist: f64) -> Pose {
        let t = tilt_deg.to_radians();
        let (cx, cy) =
            ((self.cols - 1) as f64 * self.square / 2.0, (self.rows - 1) as f64 * self.square / 2.0);
        // Where the rotation moves the centre; the translation brings it back onto the axis.
        let (rvec, rc) = if axis == 0 {
            ([t, 0.0, 0.0], [cx, cy * t.cos(), cy * t.sin()])
        } else {
            ([0.0, t, 0.0], [cx * t.cos(), cy, -cx * t.sin()])
        };
        Pose { rvec, tvec: [-rc[0], -rc[1], dist - rc[2]] }
    }

    /// [`Self::tilted_pose`], then turned `turn_deg` about the optical axis (the board turned in
    /// the image plane) and moved `shift` world units across it.
    pub fn turned_pose(&self, tilt_deg: f64, axis: usize, dist: f64, turn_deg: f64, shift: [f64; 2]) -> Pose {
        let tilted = self.tilted_pose(tilt_deg, axis, dist);
        let rz = rodrigues([0.0, 0.0, turn_deg.to_radians()]);
        let r = rodrigues(tilted.rvec);
        let mut m = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = (0..3).map(|k| rz[i][k] * r[k][j]).sum();
            }
        }
        let t = [0, 1, 2].map(|i| (0..3).map(|j| rz[i][j] * tilted.tvec[j]).sum::<f64>());
        Pose { rvec: rodrigues_inv(&m), tvec: [t[0] + shift[0], t[1] + shift[1], t[2]] }
    }
}

/// Renders `scene` as seen by a camera with intrinsics `k` at board → camera pose `pose`, as an
/// 8-bit grey image `w × h` (row-major). Pixels whose ray misses the board's plane (or lies outside
/// the distortion model's range) show the background.
pub fn render_chessboard(
    scene: &ChessboardScene,
    k: &Intrinsics,
    pose: &Pose,
    w: usize,
    h: usize,
) -> Vec<u8> {
    render(scene, k, pose, w, h, &|_| scene.background)
}

/// [`render_chessboard`] in front of `background` (`w·h` grey levels, row-major; see
/// [`office_clutter`]) instead of the scene's constant one: the card hides it, its outline is
/// blurred into it as the board's own edges are, and the uneven light falls on both.
///
/// # Panics
/// If `background` is not `w·h` long.
pub fn render_chessboard_over(
    scene: &ChessboardScene,
    k: &Intrinsics,
    pose: &Pose,
    w: usize,
    h: usize,
    background: &[f64],
) -> Vec<u8> {
    assert_eq!(background.len(), w * h, "background is not {w}×{h}");
    render(scene, k, pose, w, h, &|i| background[i])
}

fn render(
    scene: &ChessboardScene,
    k: &Intrinsics,
    pose: &Pose,
    w: usize,
    h: usize,
    background: &dyn Fn(usize) -> f64,
) -> Vec<u8> {
    // Board coordinates (in squares) of every pixel centre, with a one-pixel border for the
    // finite-difference gradients.
    let (gw, gh) = (w + 2, h + 2);
    let mut board = vec![[f64::NAN; 2]; gw * gh];
    for gy in 0..gh {
        for gx in 0..gw {
            let uv = (gx as f64 - 1.0, gy as f64 - 1.0);
            if let Some((o, d)) = pixel_ray(k, pose, uv) {
                let s = -o[2] / d[2];
                if s > 0.0 && s.is_finite() {
                    board[gy * gw + gx] =
                        [(o[0] + s * d[0]) / scene.square, (o[1] + s * d[1]) / scene.square];
                }
            }
        }
    }
    let mut rng = Rng(scene.seed);
    // The checker's extent and the card's (one square of margin beyond), in board squares.
    let (x0, x1) = (-scene.border, scene.cols as f64 - 1.0 + scene.border);
    let (y0, y1) = (-scene.border, scene.rows as f64 - 1.0 + scene.border);
    let scale = std::f64::consts::SQRT_2 * scene.blur.max(1e-6);
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let at = |dx: usize, dy: usize| board[(y + dy) * gw + (x + dx)];
            let (c, l, r, t, b) = (at(1, 1), at(0, 1), at(2, 1), at(1, 0), at(1, 2));
            let bg = background(y * w + x);
            let lit = 1.0 + scene.shading * (2.0 * x as f64 / (w.max(2) - 1) as f64 - 1.0);
            let value = if [c, l, r, t, b].iter().flatten().any(|v| v.is_nan()) {
                bg * lit
            } else {
                // |∇b| per axis: board squares per pixel, to turn board distances into pixels.
                let g = [0, 1].map(|i| ((r[i] - l[i]) / 2.0).hypot((b[i] - t[i]) / 2.0));
                // Smoothed step: 0 well before `edge`, 1 well after, along board axis i.
                let step = |i: usize, edge: f64| 0.5 * (1.0 + erf((c[i] - edge) / (g[i] * scale)));
                // Square wave (−1)^floor(b) blurred across its nearest line n: (−1)^n·erf(d).
                let wave = |i: usize| {
                    let n = c[i].round();
                    let sign = if (n as i64).rem_euclid(2) == 0 { 1.0 } else { -1.0 };
                    sign * erf((c[i] - n) / (g[i] * scale))
                };
                // +1 on squares whose floor sum is even (dark), −1 on the others.
                let checker = wave(0) * wave(1);
                let squares = scene.light + (scene.dark - scene.light) * 0.5 * (1.0 + checker);
                let inside = step(0, x0) * (1.0 - step(0, x1)) * step(1, y0) * (1.0 - step(1, y1));
                let on_card = step(0, x0 - 1.0)
                    * (1.0 - step(0, x1 + 1.0))
                    * step(1, y0 - 1.0)
                    * (1.0 - step(1, y1 + 1.0));
                let card = inside * squares + (1.0 - inside) * scene.light;
                (on_card * card + (1.0 - on_card) * bg) * lit
            };
            let noisy = if scene.noise > 0.0 { value + scene.noise * rng.gauss() } else { value };
            out.push(noisy.round().clamp(0.0, 255.0) as u8);
        }
    }
    out
}

/// A cluttered office behind the board, as in the photographs labs calibrate from (OpenCV's
/// samples among them): a shirt with bold dark stripes (14 px in 28, at 20–40°) over most of
/// the frame, a keyboard's keys (26 px, 6 px dark gaps) across the bottom left, lines of
/// "writing" (glyph-sized bars) at the top right, and a small 3 × 3 checker patch (2 × 2 inner
/// corners, a printed logo) at the bottom right. Edges are anti-aliased over a pixel. `seed`
/// moves the stripes' angle and phase and the patch. Grey levels 0–255, `w·h`, row-major.
pub fn office_clutter(w: usize, h: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng(seed);
    let angle = (20.0 + 20.0 * rng.uniform()).to_radians();
    let phase = 28.0 * rng.uniform();
    let patch = [w as f64 * (0.6 + 0.2 * rng.uniform()), h as f64 * (0.62 + 0.15 * rng.uniform())];
    let (ca, sa) = (angle.cos(), angle.sin());
    // 1 inside a band of `width` starting at 0 of a pattern repeating every `period`,
    // anti-aliased over a pixel.
    let band = |u: f64, period: f64, width: f64| {
        let v = u.rem_euclid(period);
        let cover = |v: f64| (v + 0.5).min(width + 0.5 - v).clamp(0.0, 1.0);
        cover(v).max(cover(v - period))
    };
    let (wf, hf) = (w as f64, h as f64);
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (xf, yf) = (x as f64 + 0.5, y as f64 + 0.5);
            let v = if xf < 0.45 * wf && yf > 0.7 * hf {
                // Keys: light squares, dark gaps.
                let key = band(xf, 32.0, 26.0) * band(yf, 32.0, 26.0);
                25.0 + 165.0 * key
            } else if xf > 0.6 * wf && yf < 0.35 * hf {
                // Writing on a whiteboard: bars 4 px wide in 7, lines 9 px tall in 20, some
                // glyphs left out.
                let glyph =
                    ((xf / 7.0).floor() as i64 * 31 + (yf / 20.0).floor() as i64 * 17).rem_euclid(5) < 3;
                let ink = if glyph { band(xf, 7.0, 4.0) * band(yf, 20.0, 9.0) } else { 0.0 };
                230.0 - 200.0 * ink
            } else if (0.0..60.0).contains(&(xf - patch[0])) && (0.0..60.0).contains(&(yf - patch[1])) {
                let (u, v) = (xf - patch[0], yf - patch[1]);
                let dark = ((u / 20.0).floor() as i64 + (v / 20.0).floor() as i64) % 2 == 0;
                if dark {
                    30.0
                } else {
                    220.0
                }
            } else {
                // The shirt: dark stripes on light cloth.
                let stripe = band(xf * ca + yf * sa + phase, 28.0, 14.0);
                200.0 - 165.0 * stripe
            };
            out.push(v);
        }
    }
    out
}

/// One board of [`photograph_like_boards`].
#[derive(Debug, Clone, PartialEq)]
pub struct PhotoBoard {
    /// `t{tilt}_a{axis}_r{turn}_d{dist}`.
    pub name: String,
    pub tilt_deg: f64,
    /// 8-bit grey, `w × h`.
    pub image: Vec<u8>,
    /// The 9 × 6 inner corners, row-major, in pixels.
    pub truth: Vec<(f64, f64)>,
}

/// Forty 9 × 6 boards as a lab photographs them: in front of [`office_clutter`], which touches
/// the board on every side; turned 0, 15, 30 and 45° in the image plane on top of a tilt of 0,
/// 35 or 50° about either board axis; 11 or 16 squares away and off the optical axis, through
/// a wide lens (fx 430 px on 640 × 480, k1 −0.32, k2 0.12); under light three times brighter on
/// one side, blurred (σ 1 px), noisy (σ 2 grey levels) and saved as JPEG at quality 75; the
/// nearer boards with their outer squares cut to 0.4 of a square, as OpenCV's sample board's
/// are. For the calibration tests and the comparison with OpenCV
/// (`imaging/examples/chessboard_grid.rs`).
pub fn photograph_like_boards() -> Vec<PhotoBoard> {
    let (w, h) = (640, 480);
    let k = Intrinsics { k1: -0.32, k2: 0.12, ..Intrinsics::pinhole(430.0, 430.0, 322.0, 236.0) };
    let base = ChessboardScene { noise: 2.0, blur: 1.0, shading: 0.5, ..ChessboardScene::new(9, 6, 1.0) };
    let board = crate::calib::Board::chessboard(9, 6, 1.0);
    let mut out = Vec::new();
    for (t, (tilt, axis)) in [(0.0, 0), (35.0, 0), (35.0, 1), (50.0, 0), (50.0, 1)].into_iter().enumerate() {
        for (r, turn) in [0.0f64, 15.0, 30.0, 45.0].into_iter().enumerate() {
            for (d, dist) in [11.0, 16.0].into_iter().enumerate() {
                let pose = base.turned_pose(tilt, axis, dist, turn, [[1.2, -0.8], [-1.0, 0.9]][d]);
                let truth = board
                    .points
                    .iter()
                    .filter_map(|b| crate::calib::project(&k, &pose, [b[0], b[1], 0.0]))
                    .collect();
                let seed = (t * 8 + r * 2 + d) as u64 + 1;
                let scene = ChessboardScene { seed, border: [0.4, 1.0][d], ..base.clone() };
                let clutter = office_clutter(w, h, seed);
                let image =
                    jpeg_round_trip(&render_chessboard_over(&scene, &k, &pose, w, h, &clutter), w, h, 75);
                let name = format!("t{tilt}_a{axis}_r{turn}_d{dist}");
                out.push(PhotoBoard { name, tilt_deg: tilt, image, truth });
            }
        }
    }
    out
}

/// `gray` (`w × h`, 8-bit) through a baseline JPEG of `quality` (1–100) and back: the 8 × 8
/// block artefacts and ringing a camera's or a phone's JPEG puts around every edge.
///
/// # Panics
/// If `gray` is not `w·h` long.
pub fn jpeg_round_trip(gray: &[u8], w: usize, h: usize, quality: u8) -> Vec<u8> {
    let mut buf = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality)
        .encode(gray, w as u32, h as u32, image::ExtendedColorType::L8)
        .expect("an in-memory JPEG of a w × h grey image");
    image::load_from_memory_with_format(&buf, image::ImageFormat::Jpeg)
        .expect("the JPEG just written")
        .to_luma8()
        .into_raw()
}

/// The error function, Abramowitz & Stegun 7.1.26 (absolute error below 1.5·10⁻⁷).
pub fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let y = 1.0 - poly * (-x * x).exp();
    if x < 0.0 {
        -y
    } else {
        y
    }
}

/// The standard normal distribution function Φ, from erfc (Numerical Recipes' Chebyshev fit,
/// relative error below 1.2·10⁻⁷, so far tails keep their digits): the fraction of a Gaussian
/// profile (a laser sheet's, a blurred edge's) on one side of a point.
pub fn normal_cdf(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// SplitMix64 with Box–Muller normals: deterministic noise without a dependency.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        (((z ^ (z >> 31)) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn gauss(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_cdf_matches_reference_values() {
        // Φ(0.5), Φ(1), Φ(2), and Φ(−4) = 3.167124183e−5 to 1e−7 relative.
        for (x, want) in [(0.5, 0.691_462_461), (1.0, 0.841_344_746), (2.0, 0.977_249_868)] {
            assert!((normal_cdf(x) - want).abs() < 1e-7, "Φ({x}) = {}", normal_cdf(x));
            assert!((normal_cdf(-x) - (1.0 - want)).abs() < 1e-7);
        }
        assert!((normal_cdf(-4.0) / 3.167_124_183e-5 - 1.0).abs() < 2e-7);
    }

    #[test]
    fn erf_matches_reference_values() {
        // erf(0.5), erf(1), erf(2) to 9 digits.
        for (x, want) in [(0.0, 0.0), (0.5, 0.520_499_878), (1.0, 0.842_700_793), (2.0, 0.995_322_265)] {
            assert!((erf(x) - want).abs() < 2e-7, "erf({x}) = {}", erf(x));
            assert!((erf(-x) + want).abs() < 2e-7);
        }
    }

    #[test]
    fn frontal_board_has_the_stated_levels_and_symmetric_corners() {
        // Square 40 px, corner (0, 0) exactly at pixel (100.5, 80.25).
        let k = Intrinsics::pinhole(400.0, 400.0, 100.5, 80.25);
        let pose = Pose { rvec: [0.0; 3], tvec: [0.0, 0.0, 10.0] };
        let scene = ChessboardScene::new(4, 3, 1.0);
        let (w, h) = (320, 240);
        let img = render_chessboard(&scene, &k, &pose, w, h);
        let px = |x: usize, y: usize| img[y * w + x];
        // Centres of square (0, 0) (dark), (1, 0) (light), the margin and the background.
        assert_eq!(px(120, 100), 30);
        assert_eq!(px(160, 100), 220);
        assert_eq!(px(40, 100), 220);
        assert_eq!(px(5, 5), 90);
        // Point symmetry about the corner (100.5, 80.25) along the vertical edge: values mirrored
        // across x = 100.5 sum to light + dark within rounding.
        for y in [60, 70, 95] {
            let (a, b) = (f64::from(px(100, y)), f64::from(px(101, y)));
            assert!((a + b - 250.0).abs() <= 1.0, "row {y}: {a} + {b}");
        }
    }
}
