//! Surface mode: the sheet's cut-off in the space-time stack (Hullin et al. 2008, §4).
//!
//! Frame `t` is the camera image while sheet `t` lights the liquid. A pixel whose ray meets
//! the object at `S` glows while the sheet crosses the ray in front of `S`, and goes dark once
//! the sheet passes behind `S` (the object is opaque, or at least not fluorescent). The
//! surface is that cut-off: the frame where the smoothed intensity falls fastest.
//!
//! The steps, per scanline `v` (a `u × t` slab):
//! 1. 3×3×3 median of the stack (speckle and sensor noise; a median keeps the edge sharp).
//! 2. Gradients `gu`, `gv`, `gt` by central differences.
//! 3. Candidates: local minima of `gt` along `t` with `−gt` above a threshold relative to the
//!    pixel's lit brightness, placed to a fraction of a frame by the parabola through the
//!    three samples around the minimum.
//! 4. Two rejections ([`SurfaceParams`]). At a cut-off the space-time gradient is
//!    `−gt·(∂t/∂u, ∂t/∂v, −1)`: its image part is the depth map's slope. The `gu` criterion
//!    bounds that slope along the scanline (`|gu| ≤ max_slope·|gt|`): steeper cut-offs are
//!    occluding contours, where neighbouring pixels' cut-offs blur into each other. The
//!    laser-direction criterion requires the depth map to descend along the laser, i.e. the
//!    surface to face the laser, which rejects the false cut-offs at the edge of the object's
//!    laser shadow ([`SurfaceParams::laser_dir`]).
//! 5. 8-neighbour softening: a weak candidate (above a lower threshold) is kept when an
//!    8-neighbour kept one at about the same `t` (hysteresis, as in Canny's edge linking), so
//!    the surface grows into dim regions only from confident ones.
//! 6. One cut-off per pixel: the first along `t` (transparent objects, whose far side lets the
//!    liquid behind them glow again and cut off again later) or the strongest.
//! 7. Segment filter: 8-connected regions of continuous `t` smaller than a minimum are dropped,
//!    and a rim of pixels along each region's edge (the median mixes those with the far side
//!    of the depth jump).
//!
//! Then [`depth_to_points`] triangulates `t(u, v)` against the calibrated sheets,
//! [`grid_mesh`] meshes the pixel grid, and [`merge_turntable`] brings several turntable
//! orientations into one frame.
//!
//! Memory: [`SurfaceDetector`] takes the stack one scanline slab at a time and holds three raw
//! and three median-filtered slabs (`6 × width × frames` floats: 4.9 MB for 512 × 400), plus
//! a few candidates per pixel (`width × height × 4` of 8 bytes); never the whole stack. A host
//! reading frames transposes them into slabs in blocks of scanlines (read a band of rows from
//! every frame, push its slabs, move on), so its buffer is one band, not the stack.

mod geometry;
mod median;
mod post;
#[cfg(test)]
mod synth;

pub use geometry::{depth_to_points, grid_mesh, merge_turntable, rotate_about_axis};

use rayon::prelude::*;

/// Why the detector refused its input.
#[derive(Debug, Clone, PartialEq)]
pub enum SurfaceError {
    /// Sizes that do not fit together, or a stack too small to filter.
    Dims(String),
    /// A parameter out of its range.
    Params(String),
}

impl std::fmt::Display for SurfaceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SurfaceError::Dims(m) => write!(f, "dimensions: {m}"),
            SurfaceError::Params(m) => write!(f, "parameters: {m}"),
        }
    }
}

impl std::error::Error for SurfaceError {}

/// The detector's thresholds and options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceParams {
    /// A candidate seeds the surface when the fall `−gt` (per frame) is at least this fraction
    /// of the pixel's lit brightness. A sheet `σ` frames thick gives `≈ 0.4/σ`.
    pub strong: f64,
    /// Candidates down to this fraction are kept when softening links them to the surface.
    pub weak: f64,
    /// The `gu` criterion: at most this many frames per pixel of depth slope along `u`
    /// (`|gu| ≤ max_slope·|gt|`).
    pub max_slope: f64,
    /// The laser-direction criterion: the image direction `(du, dv)` in which the laser
    /// travels within the sheet, or `None` to skip it.
    ///
    /// The laser lights a surface point only if the surface faces it. Walking along the laser
    /// in the image, such a surface comes towards the front sheets: the cut-off time falls.
    /// Where the surface faces away, the pixel's ray crosses the object's laser shadow before
    /// it reaches the surface, and the pixel goes dark where the sheet enters the shadow. The
    /// shadow's boundary in sheet `t` is made of laser rays, so along the laser's image
    /// direction that false cut-off time stays constant. Since the image gradient at a cut-off
    /// is `(gu, gv) = −gt·∇t(u, v)`, the criterion is a minimum descent of the depth map along
    /// the laser, `−(gu, gv)·l̂ / |gt| ≥ laser_min_descent`: it rejects the shadow's flat
    /// false surfaces and surfaces facing away from the laser. (A constant direction suits
    /// a laser whose rays are parallel to the image plane or a telecentric view; otherwise the
    /// direction's variation over the image must stay well inside the margin.)
    pub laser_dir: Option<[f64; 2]>,
    /// See [`laser_dir`](Self::laser_dir): frames per pixel. Surfaces that meet the laser at
    /// grazing incidence descend slowly and are rejected too.
    pub laser_min_descent: f64,
    /// Neighbouring pixels belong to one surface when their cut-offs differ by at most this
    /// many frames (softening and segments).
    pub max_step: f64,
    /// Keep the first cut-off along `t` (transparent objects) rather than the strongest.
    pub first_surface: bool,
    /// Segments (8-connected, continuous `t`) of fewer pixels are dropped.
    pub min_segment: usize,
    /// Pixels within this many pixels of a segment's edge are dropped: there the 3×3×3 median
    /// mixes the pixel's cut-off with its neighbours' across the depth jump, pulling it by a
    /// fraction of the jump.
    pub trim: usize,
    /// With `trim`, pixels where the depth map bends by more than this many frames (second
    /// difference across the pixel, in any of four directions) are dropped too: a crease next
    /// to a steep face pulls the median like a jump does.
    pub max_kink: f64,
    /// A cut-off must be followed by this many frames without a rise (`gt` above the weak
    /// threshold): behind a thin stretch of a transparent object the liquid lights up again
    /// within a few frames, and the blurred fall and rise no longer locate the surface.
    pub min_dark: usize,
    /// Pixels never brighter than this (the smoothed stack's maximum up to the cut-off) have
    /// no lit liquid in front of them: no candidates there.
    pub min_brightness: f32,
}

impl Default for SurfaceParams {
    fn default() -> Self {
        SurfaceParams {
            strong: 0.12,
            weak: 0.05,
            max_slope: 4.0,
            laser_dir: None,
            laser_min_descent: 0.03,
            max_step: 2.0,
            first_surface: false,
            min_segment: 20,
            trim: 1,
            max_kink: 1.0,
            min_dark: 3,
            min_brightness: 8.0,
        }
    }
}

impl SurfaceParams {
    fn check(&self) -> Result<(), SurfaceError> {
        let ok = self.strong.is_finite()
            && self.weak.is_finite()
            && self.weak > 0.0
            && self.weak <= self.strong
            && self.max_slope >= 0.0
            && self.max_step >= 0.0
            && self.max_kink >= 0.0
            && self.laser_min_descent.is_finite()
            && self.min_brightness.is_finite();
        if !ok {
            return Err(SurfaceError::Params(format!("{self:?}")));
        }
        if let Some(l) = self.laser_dir {
            if !(l[0].is_finite() && l[1].is_finite() && l[0].hypot(l[1]) > 0.0) {
                return Err(SurfaceError::Params(format!("laser direction {l:?}")));
            }
        }
        Ok(())
    }
}

/// Sub-frame cut-off time per pixel, row-major `width × height`.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Sheet parameter of the cut-off (frame index, fractional); `None` where none was found.
    pub t: Vec<Option<f64>>,
}

/// At most this many candidates per pixel.
pub(crate) const MAX_CANDS: usize = 4;

/// One cut-off candidate.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Cand {
    /// Sub-frame time.
    pub t: f32,
    /// `−gt` over the lit brightness.
    pub strength: f32,
}

/// Per-pixel candidate lists, in the order found (ascending `t`).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Cands {
    pub n: u8,
    pub c: [Cand; MAX_CANDS],
}

impl Cands {
    pub fn as_slice(&self) -> &[Cand] {
        &self.c[..self.n as usize]
    }

    /// Adds `c`: while there is room; when full, the first `MAX_CANDS` stay (first-surface
    /// mode), or `c` replaces the weakest if it is stronger.
    fn push(&mut self, c: Cand, first: bool) {
        if (self.n as usize) < MAX_CANDS {
            self.c[self.n as usize] = c;
            self.n += 1;
        } else if !first {
            let (k, weakest) = self.c.iter().enumerate().fold((0, f32::MAX), |(k, w), (i, x)| {
                if x.strength < w {
                    (i, x.strength)
                } else {
                    (k, w)
                }
            });
            if c.strength > weakest {
                // Keep the list in t order.
                self.c.copy_within(k + 1.., k);
                self.c[MAX_CANDS - 1] = c;
            }
        }
    }
}

/// The streaming detector: push the stack's scanline slabs in order `v = 0, 1, …`, then
/// [`finish`](Self::finish).
pub struct SurfaceDetector {
    width: usize,
    height: usize,
    frames: usize,
    params: SurfaceParams,
    /// Raw slabs of rows `r − 2, r − 1, r` (ring, by row mod 3).
    raw: [Vec<f32>; 3],
    /// Median-filtered slabs of rows `q − 2, q − 1, q` (ring, by row mod 3).
    smooth: [Vec<f32>; 3],
    /// Rows pushed so far.
    rows_in: usize,
    cands: Vec<Cands>,
}

impl SurfaceDetector {
    /// A detector for a `width × height` image and `frames` sheets (at least 3 × 3 × 5).
    pub fn new(
        width: usize,
        height: usize,
        frames: usize,
        params: SurfaceParams,
    ) -> Result<Self, SurfaceError> {
        params.check()?;
        if width < 3 || height < 3 || frames < 5 {
            return Err(SurfaceError::Dims(format!(
                "a {width}×{height} stack of {frames} frames is too small (at least 3×3×5)"
            )));
        }
        let slab =
            width.checked_mul(frames).ok_or_else(|| SurfaceError::Dims("slab size overflows".into()))?;
        let pixels =
            width.checked_mul(height).ok_or_else(|| SurfaceError::Dims("image size overflows".into()))?;
        Ok(SurfaceDetector {
            width,
            height,
            frames,
            params,
            raw: std::array::from_fn(|_| vec![0.0; slab]),
            smooth: std::array::from_fn(|_| vec![0.0; slab]),
            rows_in: 0,
            cands: vec![Cands::default(); pixels],
        })
    }

    /// Takes scanline `v` (the next one): `slab[u·frames + t]` is pixel `(u, v)` in frame `t`.
    pub fn push_scanline(&mut self, slab: &[f32]) -> Result<(), SurfaceError> {
        if slab.len() != self.width * self.frames {
            return Err(SurfaceError::Dims(format!(
                "a scanline slab of {}×{} needs {} values, got {}",
                self.width,
                self.frames,
                self.width * self.frames,
                slab.len()
            )));
        }
        if self.rows_in >= self.height {
            return Err(SurfaceError::Dims(format!("all {} scanlines were pushed already", self.height)));
        }
        let r = self.rows_in;
        self.raw[r % 3].copy_from_slice(slab);
        self.rows_in += 1;
        if r >= 1 {
            // Row r − 1 now has both neighbours (row −1 repeats row 0).
            self.smooth_row(r - 1, r.saturating_sub(2), r);
            if r >= 2 {
                self.detect_row(r - 2);
            }
        }
        Ok(())
    }

    /// The depth map, once every scanline is in.
    pub fn finish(mut self) -> Result<DepthMap, SurfaceError> {
        if self.rows_in != self.height {
            return Err(SurfaceError::Dims(format!(
                "{} of {} scanlines were pushed",
                self.rows_in, self.height
            )));
        }
        let h = self.height;
        // The last row repeats itself below.
        self.smooth_row(h - 1, h - 2, h - 1);
        self.detect_row(h - 2);
        let t = post::resolve(&self.cands, self.width, self.height, &self.params);
        Ok(DepthMap { width: self.width, height: self.height, t })
    }

    /// Median-filters raw row `q` (neighbours `below`, `above`) into the smooth ring.
    fn smooth_row(&mut self, q: usize, below: usize, above: usize) {
        let (w, f) = (self.width, self.frames);
        let rows = [&self.raw[below % 3][..], &self.raw[q % 3][..], &self.raw[above % 3][..]];
        let out = &mut self.smooth[q % 3];
        // Parallel over blocks of pixels; each block's median is independent.
        let block = 16;
        out.par_chunks_mut(block * f).enumerate().for_each(|(b, chunk)| {
            let u0 = b * block;
            let n = chunk.len() / f;
            // The block's pixels and one neighbour each side, from every row.
            let lo = u0.saturating_sub(1);
            let hi = (u0 + n + 1).min(w);
            let sub = rows.map(|r| &r[lo * f..hi * f]);
            let mut tmp = vec![0f32; (hi - lo) * f];
            median::median_row(sub, hi - lo, f, &mut tmp);
            let off = u0 - lo;
            chunk.copy_from_slice(&tmp[off * f..(off + n) * f]);
        });
    }

    /// Finds row `v`'s candidates (its smooth neighbours are in the ring). Border rows and
    /// columns have no candidates (their gradients would need voxels outside the image).
    fn detect_row(&mut self, v: usize) {
        if v == 0 || v + 1 >= self.height {
            return;
        }
        let (w, f) = (self.width, self.frames);
        let p = self.params;
        let rows = [&self.smooth[(v - 1) % 3][..], &self.smooth[v % 3][..], &self.smooth[(v + 1) % 3][..]];
        let cands = &mut self.cands[v * w..(v + 1) * w];
        cands.par_iter_mut().enumerate().skip(1).take(w - 2).for_each_init(
            || vec![0f32; f],
            |gt, (u, out)| {
                *out = Cands::default();
                detect_pixel(rows, u, f, &p, gt, out);
            },
        );
    }
}

/// Candidates of pixel `u` of the middle row of `rows` (smoothed rows `v − 1, v, v + 1`).
fn detect_pixel(rows: [&[f32]; 3], u: usize, f: usize, p: &SurfaceParams, gt: &mut [f32], out: &mut Cands) {
    let s = &rows[1][u * f..(u + 1) * f];
    for t in 1..f - 1 {
        gt[t] = 0.5 * (s[t + 1] - s[t - 1]);
    }
    let (weak, min_b) = (p.weak as f32, p.min_brightness);
    let mut lit = s[0].max(s[1]);
    for t in 2..f - 2 {
        lit = lit.max(s[t]);
        let g = gt[t];
        // Quick rejection first: most voxels are no cut-off.
        if g >= 0.0 || !(g < gt[t - 1] && g <= gt[t + 1]) || lit < min_b || -g < weak * lit {
            continue;
        }
        // The parabola through (−1, gt[t−1]), (0, gt[t]), (1, gt[t+1]): its vertex.
        let (a, c) = (gt[t - 1], gt[t + 1]);
        let den = a - 2.0 * g + c;
        let rise = weak * lit;
        if gt[t + 1..(t + 1 + p.min_dark).min(f - 1)].iter().any(|&x| x > rise) {
            continue;
        }
        let dt = if den > 0.0 { (0.5 * (a - c) / den).clamp(-0.5, 0.5) } else { 0.0 };
        let gu = 0.5 * (rows[1][(u + 1) * f + t] - rows[1][(u - 1) * f + t]);
        if f64::from(gu.abs()) > p.max_slope * f64::from(-g) {
            continue;
        }
        if let Some(l) = p.laser_dir {
            let gv = 0.5 * (rows[2][u * f + t] - rows[0][u * f + t]);
            let descent = -(f64::from(gu) * l[0] + f64::from(gv) * l[1]) / (l[0].hypot(l[1]) * f64::from(-g));
            if descent < p.laser_min_descent {
                continue;
            }
        }
        out.push(Cand { t: t as f32 + dt, strength: -g / lit }, p.first_surface);
    }
}

/// Runs the detector over a whole stack, frame-major (`stack[(t·height + v)·width + u]`, the
/// frames as the camera delivers them): for tests and small stacks; it transposes one scanline
/// at a time, so it adds one slab to the detector's memory, not a second stack.
pub fn detect_stack(
    stack: &[f32],
    width: usize,
    height: usize,
    frames: usize,
    params: SurfaceParams,
) -> Result<DepthMap, SurfaceError> {
    let n = width
        .checked_mul(height)
        .and_then(|p| p.checked_mul(frames))
        .ok_or_else(|| SurfaceError::Dims("stack size overflows".into()))?;
    if stack.len() != n {
        return Err(SurfaceError::Dims(format!(
            "a {width}×{height}×{frames} stack needs {n} values, got {}",
            stack.len()
        )));
    }
    let mut det = SurfaceDetector::new(width, height, frames, params)?;
    let mut slab = vec![0f32; width * frames];
    for v in 0..height {
        for t in 0..frames {
            let row = &stack[(t * height + v) * width..(t * height + v + 1) * width];
            for (u, x) in row.iter().enumerate() {
                slab[u * frames + t] = *x;
            }
        }
        det.push_scanline(&slab)?;
    }
    det.finish()
}
