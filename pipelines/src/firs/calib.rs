//! Calibration through the tank wall.
//!
//! The tank wall refracts every viewing ray, and the galvo's sheets bend where they cross it,
//! so neither a pinhole camera nor planar sheets describe the rig. Following Hullin et al.
//! (2008) the calibration is model-free where it can be:
//!
//! 1. **Rays.** A planar target is imaged at two or more known poses inside the tank (front and
//!    back of the working volume). [`target_world_map`] turns each view's detected corner grid
//!    into a world point per pixel; [`fit_pixel_rays`] fits a 3D line per pixel through its
//!    points. Inside the liquid the ray is straight, so no refraction model is needed.
//! 2. **Sheets.** Sheet `t` (the galvo step) lights a curve on the target; its pixels, lifted
//!    through the view's world map ([`lift`]), give world points `(x, y, z)` at sheet `t`.
//!    [`Sheet18::fit`] fits the whole family `z = f(x, y, t)`, quadratic in `y` and `t` and
//!    linear in `x`, by least squares, so sparsely sampled sheets calibrate every frame.
//! 3. **Triangulation.** [`Sheet18::intersect`]: the ray `o + s·d` against sheet `t` is a cubic
//!    in `s`; the root inside the calibrated volume is the surface point.
//!
//! Coordinates: world millimetres; pixel `(x, y)` is the point `(x, y)` of the image plane in
//! the same units the corner detector reports (pixel centres at integers).

use crate::vec3::{add, dot, norm, scale, sub, V3};

/// Why a calibration step refused its input.
#[derive(Debug, Clone, PartialEq)]
pub enum CalibError {
    /// Sizes or counts that do not fit together.
    Input(String),
    /// The data do not determine the model (too few or degenerate samples).
    Degenerate(String),
}

impl std::fmt::Display for CalibError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CalibError::Input(m) => write!(f, "input: {m}"),
            CalibError::Degenerate(m) => write!(f, "degenerate: {m}"),
        }
    }
}

impl std::error::Error for CalibError {}

/// A planar target's detected corner grid in one view.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetView {
    /// Corners per row.
    pub cols: usize,
    /// Rows of corners.
    pub rows: usize,
    /// Image positions of the corners, row-major.
    pub pixels: Vec<[f64; 2]>,
    /// World positions of the same corners (the target's known pose), mm.
    pub world: Vec<V3>,
}

/// Each pixel's world point on the target plane of `view`, row-major `width × height`; `None`
/// outside the detected grid.
///
/// Per grid cell, the homography that maps the cell's four image corners onto the unit square
/// gives the pixel's cell coordinates, and the world point is the bilinear blend of the cell's
/// world corners. For a camera that is a pinhole across one cell this is exact (the plane-to-image
/// map is a homography and the world cell a parallelogram); through a curved or thick wall it is
/// the local approximation, with an error that shrinks with the cell size.
pub fn target_world_map(
    view: &TargetView,
    width: usize,
    height: usize,
) -> Result<Vec<Option<V3>>, CalibError> {
    let n = view.cols * view.rows;
    if view.cols < 2 || view.rows < 2 || view.pixels.len() != n || view.world.len() != n {
        return Err(CalibError::Input(format!(
            "a {}×{} grid needs at least 2×2 corners and {} pixels and world points (got {} and {})",
            view.cols,
            view.rows,
            n,
            view.pixels.len(),
            view.world.len()
        )));
    }
    let mut map = vec![None; width * height];
    for r in 0..view.rows - 1 {
        for c in 0..view.cols - 1 {
            let idx = [
                r * view.cols + c,
                r * view.cols + c + 1,
                (r + 1) * view.cols + c + 1,
                (r + 1) * view.cols + c,
            ];
            let quad = idx.map(|i| view.pixels[i]);
            let wc = idx.map(|i| view.world[i]);
            let Some(inv) = square_to_quad(&quad).and_then(|m| invert3(&m)) else {
                continue;
            };
            let (lo, hi) = quad.iter().fold(([f64::MAX; 2], [f64::MIN; 2]), |(lo, hi), p| {
                ([lo[0].min(p[0]), lo[1].min(p[1])], [hi[0].max(p[0]), hi[1].max(p[1])])
            });
            // Pixels whose centres fall in the cell's bounding box, clipped to the image.
            let x0 = lo[0].ceil().max(0.0) as usize;
            let y0 = lo[1].ceil().max(0.0) as usize;
            let x1 = (hi[0].floor().min(width as f64 - 1.0)).max(-1.0);
            let y1 = (hi[1].floor().min(height as f64 - 1.0)).max(-1.0);
            if x1 < 0.0 || y1 < 0.0 {
                continue;
            }
            for y in y0..=y1 as usize {
                for x in x0..=x1 as usize {
                    if map[y * width + x].is_some() {
                        continue;
                    }
                    let h = [x as f64, y as f64, 1.0];
                    let w = dot(inv[2], h);
                    if w.abs() < 1e-300 {
                        continue;
                    }
                    let (a, b) = (dot(inv[0], h) / w, dot(inv[1], h) / w);
                    // A hair of slack so pixels on shared cell edges are not lost to rounding.
                    let e = 1e-9;
                    if a < -e || a > 1.0 + e || b < -e || b > 1.0 + e {
                        continue;
                    }
                    let p = add(
                        add(scale(wc[0], (1.0 - a) * (1.0 - b)), scale(wc[1], a * (1.0 - b))),
                        add(scale(wc[2], a * b), scale(wc[3], (1.0 - a) * b)),
                    );
                    map[y * width + x] = Some(p);
                }
            }
        }
    }
    Ok(map)
}

/// The projective map taking the unit square's corners `(0,0), (1,0), (1,1), (0,1)` onto
/// `q[0..4]` (Heckbert's closed form), as a 3×3 matrix acting on `(a, b, 1)`.
fn square_to_quad(q: &[[f64; 2]; 4]) -> Option<[[f64; 3]; 3]> {
    let [[x0, y0], [x1, y1], [x2, y2], [x3, y3]] = *q;
    let (sx, sy) = (x0 - x1 + x2 - x3, y0 - y1 + y2 - y3);
    let (dx1, dx2, dy1, dy2) = (x1 - x2, x3 - x2, y1 - y2, y3 - y2);
    let den = dx1 * dy2 - dx2 * dy1;
    if den.abs() < 1e-300 {
        return None;
    }
    let g = (sx * dy2 - dx2 * sy) / den;
    let h = (dx1 * sy - sx * dy1) / den;
    Some([[x1 - x0 + g * x1, x3 - x0 + h * x3, x0], [y1 - y0 + g * y1, y3 - y0 + h * y3, y0], [g, h, 1.0]])
}

/// The inverse of a 3×3 matrix by its adjugate; `None` when singular.
fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c = |r: usize, k: usize| {
        let (r1, r2, k1, k2) = ((r + 1) % 3, (r + 2) % 3, (k + 1) % 3, (k + 2) % 3);
        m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    let mut inv = [[0.0; 3]; 3];
    for (r, row) in inv.iter_mut().enumerate() {
        for (k, v) in row.iter_mut().enumerate() {
            *v = c(k, r) / det;
        }
    }
    Some(inv)
}

/// The world point at sub-pixel `pixel` of a per-pixel map (as from [`target_world_map`]),
/// bilinear between the four surrounding pixels; `None` if any of them is missing. Lifts the
/// detected laser line on the target to world points for [`Sheet18::fit`].
pub fn lift(map: &[Option<V3>], width: usize, pixel: [f64; 2]) -> Option<V3> {
    if width == 0 || !pixel[0].is_finite() || !pixel[1].is_finite() || pixel[0] < 0.0 || pixel[1] < 0.0 {
        return None;
    }
    let height = map.len() / width;
    let (x0, y0) = (pixel[0].floor() as usize, pixel[1].floor() as usize);
    let (fx, fy) = (pixel[0] - x0 as f64, pixel[1] - y0 as f64);
    // On the last row or column the far neighbour has weight zero; reuse the near one.
    let x1 = if fx > 0.0 { x0 + 1 } else { x0 };
    let y1 = if fy > 0.0 { y0 + 1 } else { y0 };
    if x1 >= width || y1 >= height {
        return None;
    }
    let p00 = map[y0 * width + x0]?;
    let p10 = map[y0 * width + x1]?;
    let p01 = map[y1 * width + x0]?;
    let p11 = map[y1 * width + x1]?;
    Some(add(
        add(scale(p00, (1.0 - fx) * (1.0 - fy)), scale(p10, fx * (1.0 - fy))),
        add(scale(p01, (1.0 - fx) * fy), scale(p11, fx * fy)),
    ))
}

/// One pixel's viewing ray inside the tank.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// A point on the ray (the centroid of the target points it was fitted to), mm.
    pub origin: V3,
    /// Unit direction, pointing away from the camera (from the first view's point towards the
    /// last one's).
    pub dir: V3,
    /// RMS distance of the fitted points from the line, mm.
    pub rms: f64,
}

impl Ray {
    /// The point at parameter `s`.
    pub fn at(&self, s: f64) -> V3 {
        add(self.origin, scale(self.dir, s))
    }
}

/// Per-pixel viewing rays, row-major `width × height`.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelRays {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// The rays; `None` where too few views saw the pixel on a target.
    pub rays: Vec<Option<Ray>>,
}

impl PixelRays {
    /// The ray of pixel `(x, y)`.
    pub fn get(&self, x: usize, y: usize) -> Option<&Ray> {
        if x >= self.width || y >= self.height {
            return None;
        }
        self.rays[y * self.width + x].as_ref()
    }
}

/// The least-squares 3D line through `points`: the centroid and the principal direction of the
/// scatter (the eigenvector of the covariance with the largest eigenvalue), oriented from the
/// first point towards the last. `None` for fewer than two points or coincident points.
pub fn fit_line(points: &[V3]) -> Option<Ray> {
    if points.len() < 2 {
        return None;
    }
    let n = points.len() as f64;
    let c = scale(points.iter().fold([0.0; 3], |a, p| add(a, *p)), 1.0 / n);
    let mut cov = [[0.0; 3]; 3];
    for p in points {
        let d = sub(*p, c);
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += d[i] * d[j];
            }
        }
    }
    let (vals, vecs) = sym_eigen3(cov);
    let k = (0..3).fold(0, |k, i| if vals[i] > vals[k] { i } else { k });
    if vals[k] <= 0.0 || !vals[k].is_finite() {
        return None;
    }
    let mut dir = [vecs[0][k], vecs[1][k], vecs[2][k]];
    dir = scale(dir, 1.0 / norm(dir));
    if dot(dir, sub(points[points.len() - 1], points[0])) < 0.0 {
        dir = scale(dir, -1.0);
    }
    // Squared distances from the line: total scatter minus the part along the line.
    let ss: f64 = points
        .iter()
        .map(|p| {
            let d = sub(*p, c);
            (dot(d, d) - dot(d, dir).powi(2)).max(0.0)
        })
        .sum();
    Some(Ray { origin: c, dir, rms: (ss / n).sqrt() })
}

/// Eigenvalues and eigenvectors (as the columns of the matrix) of a symmetric 3×3 matrix, by
/// cyclic Jacobi rotations.
fn sym_eigen3(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        let diag = a[0][0].powi(2) + a[1][1].powi(2) + a[2][2].powi(2);
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // a ← Jᵀ a J with J the rotation in the (p, q) plane.
            for row in a.iter_mut() {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (rp, rq) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * rp[k] - s * rq[k]);
            a[q] = std::array::from_fn(|k| s * rp[k] + c * rq[k]);
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// Per-pixel rays from per-pixel target points: `maps[k]` is view `k`'s world point per pixel
/// (row-major `width × height`, e.g. from [`target_world_map`]), the views ordered from the
/// front of the volume (nearest the camera) to the back. A pixel seen on at least two targets
/// gets the least-squares line through its points ([`fit_line`]).
pub fn fit_pixel_rays(
    width: usize,
    height: usize,
    maps: &[Vec<Option<V3>>],
) -> Result<PixelRays, CalibError> {
    if maps.len() < 2 {
        return Err(CalibError::Input(format!("rays need at least two target views, got {}", maps.len())));
    }
    if let Some(m) = maps.iter().find(|m| m.len() != width * height) {
        return Err(CalibError::Input(format!(
            "a {width}×{height} map has {} pixels, not {}",
            m.len(),
            width * height
        )));
    }
    let mut pts = Vec::with_capacity(maps.len());
    let rays = (0..width * height)
        .map(|i| {
            pts.clear();
            pts.extend(maps.iter().filter_map(|m| m[i]));
            fit_line(&pts)
        })
        .collect();
    Ok(PixelRays { width, height, rays })
}

/// A point on sheet `t`: world position `p` (mm) and the sheet's parameter (galvo step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SheetSample {
    /// World point, mm.
    pub p: V3,
    /// Sheet parameter.
    pub t: f64,
}

/// An axis-aligned box: the calibrated volume, where triangulated points may lie.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Lower corner, mm.
    pub min: V3,
    /// Upper corner, mm.
    pub max: V3,
}

impl Aabb {
    /// Whether `p` lies inside (boundary included).
    pub fn contains(&self, p: V3) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// The parameter interval of `ray` inside the box (slab method), `None` if it misses.
    pub fn clip(&self, ray: &Ray) -> Option<(f64, f64)> {
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        for i in 0..3 {
            let (o, d) = (ray.origin[i], ray.dir[i]);
            if d == 0.0 {
                if o < self.min[i] || o > self.max[i] {
                    return None;
                }
                continue;
            }
            let (a, b) = ((self.min[i] - o) / d, (self.max[i] - o) / d);
            lo = lo.max(a.min(b));
            hi = hi.min(a.max(b));
        }
        (lo <= hi && lo.is_finite() && hi.is_finite()).then_some((lo, hi))
    }
}

/// The sheet family `z = f(x, y, t)`, a sum of the 18 monomials `xᵃ yᵇ tᶜ` with `a ∈ {0, 1}`,
/// `b, c ∈ {0, 1, 2}`, in normalised coordinates.
///
/// The sheets are nearly planes `z ≈ z₀ + k·t` that the tank wall bends: quadratic in the
/// sheet's height `y` and in the galvo step `t` (the wall's refraction grows with the angle),
/// linear across the sheet (`x`). The fit and the evaluation work in `x' = (x − cₓ)/sₓ` and
/// likewise for `y`, `t` and `z`, with the centre the sample mean and the scale the largest
/// distance from it, so every monomial is of order one on the calibrated volume: raw
/// millimetres and galvo steps would put `x·y²·t²` some ten decades above the constant and
/// leave the least-squares system numerically rank-deficient.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sheet18 {
    /// Coefficient of `x'ᵃ y'ᵇ t'ᶜ` at index `9a + 3b + c`; `z' = Σ coef·monomial`.
    pub coef: [f64; 18],
    /// Normalisation centres of `x, y, t, z`.
    pub centre: [f64; 4],
    /// Normalisation scales of `x, y, t, z` (positive).
    pub scale: [f64; 4],
}

/// The 18 monomials `x^a y^b t^c` at index `9a + 3b + c`.
fn monomials(x: f64, y: f64, t: f64) -> [f64; 18] {
    let (ys, ts) = ([1.0, y, y * y], [1.0, t, t * t]);
    std::array::from_fn(|i| {
        let (a, b, c) = (i / 9, (i / 3) % 3, i % 3);
        (if a == 1 { x } else { 1.0 }) * ys[b] * ts[c]
    })
}

impl Sheet18 {
    /// The family with raw coefficients (`z = Σ coef·xᵃ yᵇ tᶜ` in world units, no
    /// normalisation).
    pub fn from_raw(coef: [f64; 18]) -> Self {
        Sheet18 { coef, centre: [0.0; 4], scale: [1.0; 4] }
    }

    /// `z` of sheet `t` at `(x, y)`.
    pub fn eval(&self, x: f64, y: f64, t: f64) -> f64 {
        let [cx, cy, ct, cz] = self.centre;
        let [sx, sy, st, sz] = self.scale;
        let m = monomials((x - cx) / sx, (y - cy) / sy, (t - ct) / st);
        cz + sz * m.iter().zip(&self.coef).map(|(m, c)| m * c).sum::<f64>()
    }

    /// The least-squares family through `samples` (Householder QR on the normalised design
    /// matrix, so the conditioning is that of the matrix, not its square).
    ///
    /// Needs at least 18 samples spread over at least three sheets, three heights and two
    /// positions across the sheet; otherwise some coefficient is undetermined and the fit is
    /// refused.
    pub fn fit(samples: &[SheetSample]) -> Result<Self, CalibError> {
        let n = samples.len();
        if n < 18 {
            return Err(CalibError::Degenerate(format!("18 coefficients need at least 18 samples, got {n}")));
        }
        if samples.iter().any(|s| !(s.p.iter().all(|v| v.is_finite()) && s.t.is_finite())) {
            return Err(CalibError::Input("a sheet sample is not finite".into()));
        }
        let get = |s: &SheetSample, k: usize| {
            if k < 2 {
                s.p[k]
            } else if k == 2 {
                s.t
            } else {
                s.p[2]
            }
        };
        let mut centre = [0.0; 4];
        let mut sc = [0.0; 4];
        for k in 0..4 {
            centre[k] = samples.iter().map(|s| get(s, k)).sum::<f64>() / n as f64;
            sc[k] = samples.iter().map(|s| (get(s, k) - centre[k]).abs()).fold(0.0, f64::max);
        }
        for (k, name) in ["x", "y", "t"].iter().enumerate() {
            if sc[k] == 0.0 {
                return Err(CalibError::Degenerate(format!("all samples share one {name}")));
            }
        }
        if sc[3] == 0.0 {
            sc[3] = 1.0;
        }
        // Column-major design matrix and right-hand side.
        let mut a = vec![0.0; n * 18];
        let mut b = vec![0.0; n];
        for (i, s) in samples.iter().enumerate() {
            let m = monomials(
                (s.p[0] - centre[0]) / sc[0],
                (s.p[1] - centre[1]) / sc[1],
                (s.t - centre[2]) / sc[2],
            );
            for (j, v) in m.iter().enumerate() {
                a[j * n + i] = *v;
            }
            b[i] = (s.p[2] - centre[3]) / sc[3];
        }
        let coef = lstsq_qr(&mut a, &mut b, n, 18).ok_or_else(|| {
            CalibError::Degenerate("the samples do not determine all 18 coefficients".into())
        })?;
        let mut c = [0.0; 18];
        c.copy_from_slice(&coef);
        Ok(Sheet18 { coef: c, centre, scale: sc })
    }

    /// RMS of `z − f(x, y, t)` over `samples`, mm.
    pub fn residual_rms(&self, samples: &[SheetSample]) -> f64 {
        if samples.is_empty() {
            return 0.0;
        }
        let ss: f64 = samples.iter().map(|s| (s.p[2] - self.eval(s.p[0], s.p[1], s.t)).powi(2)).sum();
        (ss / samples.len() as f64).sqrt()
    }

    /// `z'(s) − f'(x'(s), y'(s), t')` along `ray` as a cubic in `s`, coefficients of
    /// `s⁰ … s³`, in the normalised `z` unit.
    pub fn ray_cubic(&self, ray: &Ray, t: f64) -> [f64; 4] {
        let [cx, cy, ct, cz] = self.centre;
        let [sx, sy, st, sz] = self.scale;
        let xl = [(ray.origin[0] - cx) / sx, ray.dir[0] / sx];
        let yl = [(ray.origin[1] - cy) / sy, ray.dir[1] / sy];
        let tn = (t - ct) / st;
        let tp = [1.0, tn, tn * tn];
        // Powers of the linear polynomials x'(s), y'(s): y'⁰, y'¹, y'².
        let y2 = [yl[0] * yl[0], 2.0 * yl[0] * yl[1], yl[1] * yl[1]];
        let ypow: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [yl[0], yl[1], 0.0], y2];
        let mut g = [(ray.origin[2] - cz) / sz, ray.dir[2] / sz, 0.0, 0.0];
        for a in 0..2 {
            for (b, yp) in ypow.iter().enumerate() {
                let k: f64 = (0..3).map(|c| self.coef[9 * a + 3 * b + c] * tp[c]).sum();
                if k == 0.0 {
                    continue;
                }
                // k · x'(s)ᵃ · y'(s)ᵇ, subtracted.
                for (i, yc) in yp.iter().enumerate() {
                    if a == 0 {
                        g[i] -= k * yc;
                    } else {
                        g[i] -= k * yc * xl[0];
                        g[i + 1] -= k * yc * xl[1];
                    }
                }
            }
        }
        g
    }

    /// Where `ray` meets sheet `t` inside `volume`: the parameter `s` and the point. Of several
    /// roots in the volume (a sheet folded by the wall can meet a ray more than once) the one
    /// nearest the camera is kept; `None` if the ray meets the sheet nowhere in the volume.
    pub fn intersect(&self, ray: &Ray, t: f64, volume: &Aabb) -> Option<(f64, V3)> {
        let (lo, hi) = volume.clip(ray)?;
        let c = self.ray_cubic(ray, t);
        let s = *real_roots_in(c, lo, hi).first()?;
        Some((s, ray.at(s)))
    }
}

/// Least squares `min |A x − b|` for a column-major `m × n` matrix `a` (overwritten) by
/// Householder QR; `None` when a column is (numerically) dependent on the others.
fn lstsq_qr(a: &mut [f64], b: &mut [f64], m: usize, n: usize) -> Option<Vec<f64>> {
    let mut rdiag = vec![0.0; n];
    let col_norm0: Vec<f64> =
        (0..n).map(|j| a[j * m..(j + 1) * m].iter().map(|v| v * v).sum::<f64>().sqrt()).collect();
    for k in 0..n {
        let col = &a[k * m..(k + 1) * m];
        let nrm = col[k..].iter().map(|v| v * v).sum::<f64>().sqrt();
        // Relative to the column's own size: a column that reduces to rounding noise is dependent.
        if nrm <= 1e-10 * col_norm0[k].max(1e-300) {
            return None;
        }
        let alpha = if col[k] > 0.0 { -nrm } else { nrm };
        let mut v: Vec<f64> = col[k..].to_vec();
        v[0] -= alpha;
        let vv: f64 = v.iter().map(|x| x * x).sum();
        rdiag[k] = alpha;
        if vv > 0.0 {
            for j in k..n {
                let cj = &mut a[j * m + k..(j + 1) * m];
                let f = 2.0 * v.iter().zip(cj.iter()).map(|(x, y)| x * y).sum::<f64>() / vv;
                for (c, x) in cj.iter_mut().zip(&v) {
                    *c -= f * x;
                }
            }
            let f = 2.0 * v.iter().zip(&b[k..]).map(|(x, y)| x * y).sum::<f64>() / vv;
            for (c, x) in b[k..].iter_mut().zip(&v) {
                *c -= f * x;
            }
        }
    }
    // Back substitution on R (its diagonal is `rdiag`, above it the reflected columns).
    let mut x = vec![0.0; n];
    for k in (0..n).rev() {
        let mut s = b[k];
        for j in k + 1..n {
            s -= a[j * m + k] * x[j];
        }
        x[k] = s / rdiag[k];
    }
    Some(x)
}

/// `c[0] + c[1]·s + c[2]·s² + c[3]·s³`.
pub fn poly3(c: [f64; 4], s: f64) -> f64 {
    ((c[3] * s + c[2]) * s + c[1]) * s + c[0]
}

/// The real roots of `a·s² + b·s + c` (any of `a`, `b` may be zero), ascending, by the
/// cancellation-free form (`q = −(b + sign(b)·√disc)/2`, roots `q/a` and `c/q`), so a tiny `a`
/// still gives the finite root to full precision.
pub fn quadratic_roots(a: f64, b: f64, c: f64) -> Vec<f64> {
    if a == 0.0 {
        return if b != 0.0 { vec![-c / b] } else { Vec::new() };
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return Vec::new();
    }
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    let mut r = if q == 0.0 { vec![0.0, 0.0] } else { vec![q / a, c / q] };
    r.retain(|v| v.is_finite());
    r.sort_by(f64::total_cmp);
    r
}

/// The real roots of the cubic `c` (coefficients of `s⁰ … s³`) in `[lo, hi]`, ascending, each
/// once (a double root is reported once).
///
/// The derivative's roots (a quadratic, solved without cancellation) cut `[lo, hi]` into
/// pieces on which the cubic is monotone; a piece whose ends differ in sign holds exactly one
/// root, found by Newton steps safeguarded by bisection. A critical point where the cubic
/// vanishes to rounding is a double (or triple) root. Nothing divides by the leading
/// coefficient, so `c[3] ≈ 0` (the quadratic limit) needs no special case.
pub fn real_roots_in(c: [f64; 4], lo: f64, hi: f64) -> Vec<f64> {
    if lo.partial_cmp(&hi).is_none_or(|o| o == std::cmp::Ordering::Greater)
        || c.iter().any(|v| !v.is_finite())
    {
        return Vec::new();
    }
    let dc = [c[1], 2.0 * c[2], 3.0 * c[3]];
    let mut knots = vec![lo];
    knots.extend(quadratic_roots(dc[2], dc[1], dc[0]).into_iter().filter(|&s| s > lo && s < hi));
    knots.push(hi);
    // Rounding size of the cubic at s: where |value| is below it, the sign is noise.
    let tol = |s: f64| {
        16.0 * f64::EPSILON
            * (c[0].abs() + (c[1].abs() + (c[2].abs() + c[3].abs() * s.abs()) * s.abs()) * s.abs())
    };
    let vals: Vec<f64> = knots
        .iter()
        .map(|&s| {
            let v = poly3(c, s);
            if v.abs() <= tol(s) {
                0.0
            } else {
                v
            }
        })
        .collect();
    let mut roots = Vec::new();
    for i in 0..knots.len() {
        if vals[i] == 0.0 {
            // An all-zero cubic has no isolated roots.
            if c.iter().any(|v| *v != 0.0) {
                roots.push(knots[i]);
            }
            continue;
        }
        if i + 1 < knots.len() && vals[i + 1] != 0.0 && (vals[i] < 0.0) != (vals[i + 1] < 0.0) {
            roots.push(bracketed_root(c, dc, knots[i], knots[i + 1], vals[i]));
        }
    }
    roots.dedup();
    roots
}

/// The root of the monotone cubic `c` in `[l, r]`, given the sign of `c(l)` (`c(r)` has the
/// other sign).
fn bracketed_root(c: [f64; 4], dc: [f64; 3], mut l: f64, mut r: f64, fl: f64) -> f64 {
    let neg_left = fl < 0.0;
    let mut x = 0.5 * (l + r);
    for _ in 0..200 {
        let f = poly3(c, x);
        if f == 0.0 {
            return x;
        }
        if (f < 0.0) == neg_left {
            l = x;
        } else {
            r = x;
        }
        if r - l <= 2.0 * f64::EPSILON * l.abs().max(r.abs()) {
            break;
        }
        let d = (dc[2] * x + dc[1]) * x + dc[0];
        let newton = x - f / d;
        // Newton when it stays inside the bracket, bisection otherwise.
        x = if d != 0.0 && newton > l && newton < r { newton } else { 0.5 * (l + r) };
    }
    x
}

/// All real roots of the cubic `c` (coefficients of `s⁰ … s³`), ascending; roots beyond
/// `1e100` in magnitude (the far root of a cubic whose leading coefficient is rounding noise)
/// are dropped. An identically zero polynomial has no isolated roots: empty.
pub fn cubic_roots(c: [f64; 4]) -> Vec<f64> {
    let Some(deg) = (0..4).rev().find(|&k| c[k] != 0.0) else {
        return Vec::new();
    };
    if deg == 0 {
        return Vec::new();
    }
    // Cauchy's bound on the roots' magnitude.
    let bound = 1.0 + (0..deg).map(|k| (c[k] / c[deg]).abs()).fold(0.0, f64::max);
    let bound = if bound.is_finite() { bound.min(1e100) } else { 1e100 };
    real_roots_in(c, -bound, bound)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::vec3::normalize;

    /// A small deterministic generator (SplitMix64) and Box–Muller normals for test noise.
    pub(crate) struct Rng(pub u64);
    impl Rng {
        pub fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        pub fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        pub fn normal(&mut self) -> f64 {
            let u1 = self.uniform().max(1e-300);
            let u2 = self.uniform();
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }
    }

    fn check_roots(c: [f64; 4], want: &[f64], tol: f64) {
        let got = cubic_roots(c);
        assert_eq!(got.len(), want.len(), "{c:?}: got {got:?}, want {want:?}");
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() <= tol * (1.0 + w.abs()), "{c:?}: got {got:?}, want {want:?}");
        }
    }

    #[test]
    fn cubic_hand_cases() {
        // (s − 1)(s − 2)(s − 3) = s³ − 6s² + 11s − 6.
        check_roots([-6.0, 11.0, -6.0, 1.0], &[1.0, 2.0, 3.0], 1e-14);
        // Double root: (s − 1)²(s − 2) = s³ − 4s² + 5s − 2.
        check_roots([-2.0, 5.0, -4.0, 1.0], &[1.0, 2.0], 1e-12);
        // Double root at the other end: (s + 1)(s − 2)² = s³ − 3s² + 4.
        check_roots([4.0, 0.0, -3.0, 1.0], &[-1.0, 2.0], 1e-12);
        // Triple root (s − 0.5)³: the sign changes, so it is found to about ∛ε.
        check_roots([-0.125, 0.75, -1.5, 1.0], &[0.5], 1e-5);
        // One real root: (s − 2)(s² + 1) = s³ − 2s² + s − 2.
        check_roots([-2.0, 1.0, -2.0, 1.0], &[2.0], 1e-14);
        // Leading coefficient zero: the quadratic (s − 1)(s + 4) = s² + 3s − 4.
        check_roots([-4.0, 3.0, 1.0, 0.0], &[-4.0, 1.0], 1e-14);
        // Leading coefficient tiny: the quadratic's roots survive, the far root −1e12 appears.
        let a = 1e-12;
        let got = cubic_roots([-4.0, 3.0, 1.0, a]);
        assert_eq!(got.len(), 3, "{got:?}");
        assert!((got[0] + 1.0 / a).abs() < 1e-3 / a, "{got:?}");
        // Perturbation of the near roots: δs ≈ −a·s³/p'(s): about 1e-12 here.
        assert!((got[1] + 4.0).abs() < 1e-10 && (got[2] - 1.0).abs() < 1e-10, "{got:?}");
        // Linear and constant.
        check_roots([3.0, -1.5, 0.0, 0.0], &[2.0], 1e-15);
        check_roots([3.0, 0.0, 0.0, 0.0], &[], 0.0);
        check_roots([0.0; 4], &[], 0.0);
        // A double root at zero: s²(s − 1).
        check_roots([0.0, 0.0, -1.0, 1.0], &[0.0, 1.0], 1e-14);
        // Interval restriction.
        assert_eq!(real_roots_in([-6.0, 11.0, -6.0, 1.0], 1.5, 2.5).len(), 1);
        assert!(real_roots_in([-6.0, 11.0, -6.0, 1.0], 3.5, 9.0).is_empty());
    }

    #[test]
    fn cubic_random_roots_recovered() {
        let mut rng = Rng(7);
        for _ in 0..2000 {
            let r: [f64; 3] = std::array::from_fn(|_| rng.uniform() * 20.0 - 10.0);
            let k = rng.uniform() * 4.0 + 0.1;
            // k (s − r0)(s − r1)(s − r2).
            let c = [
                -k * r[0] * r[1] * r[2],
                k * (r[0] * r[1] + r[0] * r[2] + r[1] * r[2]),
                -k * (r[0] + r[1] + r[2]),
                k,
            ];
            let mut want = r.to_vec();
            want.sort_by(f64::total_cmp);
            let got = cubic_roots(c);
            // Close roots are ill-conditioned (δs ~ √(ε/gap)); skip pairs closer than 1e-3.
            if want.windows(2).any(|w| w[1] - w[0] < 1e-3) {
                continue;
            }
            assert_eq!(got.len(), 3, "{c:?}: {got:?} vs {want:?}");
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-9, "{c:?}: {got:?} vs {want:?}");
            }
        }
    }

    /// A sheet family with refraction-like bending: the galvo steps the sheet by ~0.5 mm along
    /// `z`, the wall bows it quadratically in `y` and fans it with `t`.
    pub(crate) fn curved_sheet() -> Sheet18 {
        let mut c = [0.0; 18];
        let ix = |a: usize, b: usize, t: usize| 9 * a + 3 * b + t;
        c[ix(0, 0, 0)] = -20.0;
        c[ix(0, 0, 1)] = 0.5;
        c[ix(0, 0, 2)] = 4e-4;
        c[ix(0, 1, 0)] = 0.02;
        c[ix(0, 2, 0)] = 2.5e-3;
        c[ix(0, 2, 1)] = -2e-5;
        c[ix(1, 0, 0)] = 0.03;
        c[ix(1, 0, 1)] = 2e-4;
        c[ix(1, 1, 0)] = 1e-4;
        c[ix(1, 2, 0)] = 5e-6;
        c[ix(1, 2, 2)] = 1e-9;
        c[ix(0, 1, 2)] = 1e-6;
        Sheet18::from_raw(c)
    }

    #[test]
    fn sheet_fit_recovers_the_family_from_noisy_sparse_samples() {
        let truth = curved_sheet();
        let mut rng = Rng(11);
        // 9 sheets of the 80, each seen on the target at 5 depths... as the target's laser line:
        // points along the sheet's intersection with a plane, here sampled in x at 21 heights.
        let mut samples = Vec::new();
        let noise = 0.01; // mm, the lifted laser line's error
        for t in (0..=80).step_by(10) {
            for yi in 0..21 {
                for xi in 0..5 {
                    let (x, y) = (-30.0 + 15.0 * xi as f64, -30.0 + 3.0 * yi as f64);
                    let z = truth.eval(x, y, t as f64) + noise * rng.normal();
                    samples.push(SheetSample { p: [x, y, z], t: t as f64 });
                }
            }
        }
        let fit = Sheet18::fit(&samples).unwrap();
        let rms = fit.residual_rms(&samples);
        assert!((rms / noise - 1.0).abs() < 0.1, "residual {rms} vs noise {noise}");
        // Over the whole volume, every frame (not only the sampled sheets).
        let mut worst = 0.0f64;
        for t in 0..=80 {
            for yi in 0..=12 {
                for xi in 0..=12 {
                    let (x, y) = (-30.0 + 5.0 * xi as f64, -30.0 + 5.0 * yi as f64);
                    worst = worst.max((fit.eval(x, y, t as f64) - truth.eval(x, y, t as f64)).abs());
                }
            }
        }
        // 945 samples at 10 µm: the 18-parameter fit's error is a few µm, worst at the corners.
        assert!(worst < 0.01, "max error over the volume {worst} mm");
        // Noise-free samples reproduce the family to rounding.
        let exact: Vec<SheetSample> = samples
            .iter()
            .map(|s| SheetSample { p: [s.p[0], s.p[1], truth.eval(s.p[0], s.p[1], s.t)], t: s.t })
            .collect();
        let fit = Sheet18::fit(&exact).unwrap();
        assert!(fit.residual_rms(&exact) < 1e-10);
        assert!((fit.eval(7.0, -3.0, 33.3) - truth.eval(7.0, -3.0, 33.3)).abs() < 1e-9);
    }

    #[test]
    fn sheet_fit_refuses_undetermined_families() {
        let truth = curved_sheet();
        // Two sheets only: the t² terms are undetermined.
        let samples: Vec<SheetSample> = (0..200)
            .map(|i| {
                let (x, y, t) = ((i % 10) as f64, (i / 10) as f64, (i % 2) as f64 * 5.0);
                SheetSample { p: [x, y, truth.eval(x, y, t)], t }
            })
            .collect();
        assert!(matches!(Sheet18::fit(&samples), Err(CalibError::Degenerate(_))));
        assert!(matches!(Sheet18::fit(&samples[..10]), Err(CalibError::Degenerate(_))));
    }

    #[test]
    fn triangulation_round_trip_is_exact() {
        let sheet = curved_sheet();
        let volume = Aabb { min: [-40.0, -40.0, -30.0], max: [40.0, 40.0, 40.0] };
        let mut rng = Rng(3);
        let mut worst = 0.0f64;
        for _ in 0..500 {
            // A surface point on sheet t, seen along a ray from a camera ~200 mm away.
            let t = rng.uniform() * 80.0;
            let (x, y) = (rng.uniform() * 60.0 - 30.0, rng.uniform() * 60.0 - 30.0);
            let p = [x, y, sheet.eval(x, y, t)];
            let cam = [rng.uniform() * 100.0 - 50.0, rng.uniform() * 40.0 - 20.0, -200.0];
            let dir = normalize(sub(p, cam));
            // The ray's origin anywhere on it: here 150 mm from the camera.
            let ray = Ray { origin: add(cam, scale(dir, 150.0)), dir, rms: 0.0 };
            let (_, q) = sheet.intersect(&ray, t, &volume).unwrap();
            worst = worst.max(norm(sub(q, p)));
        }
        assert!(worst < 1e-9, "round trip error {worst} mm");
        // A ray that meets the sheet only outside the volume.
        let ray = Ray { origin: [0.0, 0.0, 100.0], dir: [1.0, 0.0, 0.0], rms: 0.0 };
        assert!(sheet.intersect(&ray, 10.0, &volume).is_none());
    }

    #[test]
    fn rays_from_two_and_more_noisy_planes() {
        // A pinhole at c viewing targets at z = −20, 0, 20; noisy target points.
        let c = [5.0, -3.0, -250.0];
        let mut rng = Rng(5);
        let sigma = 0.02;
        let mut worst_dir = 0.0f64;
        let mut worst_pos = 0.0f64;
        for views in [2usize, 4] {
            for _ in 0..200 {
                let d = normalize([rng.uniform() * 0.3 - 0.15, rng.uniform() * 0.3 - 0.15, 1.0]);
                let pts: Vec<V3> = (0..views)
                    .map(|k| {
                        let z = -20.0 + 40.0 * k as f64 / (views - 1) as f64;
                        let s = (z - c[2]) / d[2];
                        let p = add(c, scale(d, s));
                        [p[0] + sigma * rng.normal(), p[1] + sigma * rng.normal(), z]
                    })
                    .collect();
                let ray = fit_line(&pts).unwrap();
                worst_dir = worst_dir.max(crate::vec3::angle(ray.dir, d));
                // Distance of the true ray's point at z = 0 from the fitted line.
                let p0 = add(c, scale(d, -c[2] / d[2]));
                let off = sub(p0, ray.origin);
                worst_pos = worst_pos.max(norm(sub(off, scale(ray.dir, dot(off, ray.dir)))));
            }
        }
        // 20 µm of noise over a 40 mm baseline: direction error ~ √2·σ/40 ≈ 0.7 mrad, at most
        // ~4σ over 400 rays.
        assert!(worst_dir < 3e-3, "direction error {worst_dir} rad");
        assert!(worst_pos < 0.1, "position error {worst_pos} mm");
        // Noise-free: exact.
        let d = normalize([0.1, -0.05, 1.0]);
        let pts: Vec<V3> = [-20.0, 20.0].iter().map(|&z| add(c, scale(d, (z - c[2]) / d[2]))).collect();
        let ray = fit_line(&pts).unwrap();
        assert!(crate::vec3::angle(ray.dir, d) < 1e-12 && ray.rms < 1e-12);
        assert!(fit_line(&pts[..1]).is_none());
        assert!(fit_line(&[pts[0], pts[0]]).is_none());
    }

    #[test]
    fn target_map_and_pixel_rays_through_a_pinhole() {
        // A pinhole camera (focal 400 px, centre (32, 24), looking along +z from z = −300) and a
        // 7×5 target of 10 mm squares at two depths, tilted; the world map must reproduce the
        // plane point on each pixel's ray, and the fitted rays the pinhole's.
        let (w, h) = (64usize, 48usize);
        let cam = [0.0, 0.0, -300.0];
        let f = 400.0;
        let project = |p: V3| {
            let d = sub(p, cam);
            [32.0 + f * d[0] / d[2], 24.0 + f * d[1] / d[2]]
        };
        let ray_dir = |x: f64, y: f64| normalize([(x - 32.0) / f, (y - 24.0) / f, 1.0]);
        let mut maps = Vec::new();
        for (z0, tilt) in [(-20.0, 0.1), (25.0, -0.15)] {
            let (cols, rows) = (7, 5);
            let mut view = TargetView { cols, rows, pixels: Vec::new(), world: Vec::new() };
            for r in 0..rows {
                for c in 0..cols {
                    let (x, y) = (-35.0 + 11.0 * c as f64, -28.0 + 13.0 * r as f64);
                    let p = [x, y, z0 + tilt * x];
                    view.world.push(p);
                    view.pixels.push(project(p));
                }
            }
            let map = target_world_map(&view, w, h).unwrap();
            let mut seen = 0;
            for y in 0..h {
                for x in 0..w {
                    let Some(p) = map[y * w + x] else { continue };
                    seen += 1;
                    // On the plane and on the pixel's ray.
                    assert!((p[2] - z0 - tilt * p[0]).abs() < 1e-9);
                    let q = project(p);
                    assert!(
                        (q[0] - x as f64).abs() < 1e-9 && (q[1] - y as f64).abs() < 1e-9,
                        "{x},{y}: {q:?}"
                    );
                }
            }
            // The grid covers most of the image.
            assert!(seen > w * h / 2, "{seen} pixels");
            maps.push(map);
        }
        let rays = fit_pixel_rays(w, h, &maps).unwrap();
        let mut n = 0;
        for y in 0..h {
            for x in 0..w {
                if let Some(r) = rays.get(x, y) {
                    n += 1;
                    assert!(crate::vec3::angle(r.dir, ray_dir(x as f64, y as f64)) < 1e-10);
                }
            }
        }
        assert!(n > w * h / 3);
        // Lifting a sub-pixel position: on the plane, between the pixels.
        let p = lift(&maps[0], w, [30.5, 20.25]).unwrap();
        assert!((p[2] - (-20.0 + 0.1 * p[0])).abs() < 1e-9);
        assert!(lift(&maps[0], w, [-1.0, 3.0]).is_none());
        assert!(matches!(fit_pixel_rays(w, h, &maps[..1]), Err(CalibError::Input(_))));
        assert!(matches!(fit_pixel_rays(w + 1, h, &maps), Err(CalibError::Input(_))));
    }
}
