//! Camera calibration: chessboard corners, intrinsics with distortion, board pose, pixel rays.
//!
//! Camera model (OpenCV's): a world point `X` goes to camera coordinates `Xc = R·X + t`, to the
//! normalised image plane `(x, y) = (Xc/Zc, Yc/Zc)`, through the distortion
//!
//! ```text
//! r² = x² + y²,  ρ = 1 + k1·r² + k2·r⁴ + k3·r⁶
//! x' = x·ρ + 2·p1·x·y + p2·(r² + 2x²)
//! y' = y·ρ + p1·(r² + 2y²) + 2·p2·x·y
//! ```
//!
//! and to pixels `u = fx·x' + cx`, `v = fy·y' + cy`. Pixel centres are at integer coordinates.
//! Rotations are Rodrigues vectors (axis × angle).
//!
//! Calibration follows Zhang (2000): a normalised DLT homography per view, the image of the
//! absolute conic `B = K⁻ᵀK⁻¹` from `V·b = 0`, per-view extrinsics from `K⁻¹H`, then
//! Levenberg–Marquardt over all intrinsics, distortion and poses minimising the reprojection error.

// `!(x > 0.0)` deliberately rejects NaN too; small fixed-size matrices read best with index loops.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use std::fmt;

mod detect;
pub use detect::{find_chessboard, Miss};

/// Why a calibration step failed.
#[derive(Debug, Clone, PartialEq)]
pub enum CalibError {
    /// No chessboard with the requested inner-corner pattern was found in the image, and what
    /// the detector saw instead.
    BoardNotFound(Miss),
    /// Calibration needs at least `need` views.
    TooFewViews { got: usize, need: usize },
    /// The geometry does not determine the solution (collinear points, parallel views, ...).
    Degenerate(&'static str),
    /// Inputs inconsistent with each other (sizes, non-finite values).
    InvalidInput(String),
}

impl fmt::Display for CalibError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CalibError::BoardNotFound(miss) => write!(f, "chessboard not found: {miss}"),
            CalibError::TooFewViews { got, need } => {
                write!(f, "too few views for calibration: {got}, need at least {need}")
            }
            CalibError::Degenerate(what) => write!(f, "degenerate geometry: {what}"),
            CalibError::InvalidInput(what) => write!(f, "invalid input: {what}"),
        }
    }
}

impl std::error::Error for CalibError {}

/// Pinhole intrinsics with OpenCV's radial (k1, k2, k3) and tangential (p1, p2) distortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

impl Intrinsics {
    /// Distortion-free intrinsics.
    pub fn pinhole(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Intrinsics { fx, fy, cx, cy, k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 }
    }

    fn to_array(self) -> [f64; 9] {
        [self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    fn from_array(a: &[f64]) -> Self {
        Intrinsics {
            fx: a[0],
            fy: a[1],
            cx: a[2],
            cy: a[3],
            k1: a[4],
            k2: a[5],
            p1: a[6],
            p2: a[7],
            k3: a[8],
        }
    }

    /// Applies the distortion to a normalised image point `(x, y)` → `(x', y')`.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let rho = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * rho + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * rho + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }
}

/// A rigid transform world → camera: `Xc = R(rvec)·X + tvec`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rodrigues rotation vector (axis × angle in radians).
    pub rvec: [f64; 3],
    pub tvec: [f64; 3],
}

impl Pose {
    /// The rotation matrix (row-major).
    pub fn rotation(&self) -> [[f64; 3]; 3] {
        rodrigues(self.rvec)
    }

    /// Builds a pose from a rotation matrix (assumed orthonormal) and a translation.
    pub fn from_rotation(r: [[f64; 3]; 3], tvec: [f64; 3]) -> Self {
        Pose { rvec: rodrigues_inv(&r), tvec }
    }

    /// The camera centre in world coordinates, `−Rᵀ·t`.
    pub fn camera_centre(&self) -> [f64; 3] {
        let r = self.rotation();
        let t = self.tvec;
        [0, 1, 2].map(|j| -(r[0][j] * t[0] + r[1][j] * t[1] + r[2][j] * t[2]))
    }

    fn to_array(self) -> [f64; 6] {
        let (r, t) = (self.rvec, self.tvec);
        [r[0], r[1], r[2], t[0], t[1], t[2]]
    }

    fn from_array(a: &[f64]) -> Self {
        Pose { rvec: [a[0], a[1], a[2]], tvec: [a[3], a[4], a[5]] }
    }
}

/// A planar calibration target: points `(X, Y)` on the plane `Z = 0` of the board frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Board {
    pub points: Vec<[f64; 2]>,
}

impl Board {
    /// The inner corners of a chessboard, `cols × rows`, row-major from the first corner, with
    /// `X = col·square`, `Y = row·square` (OpenCV's object-point convention).
    pub fn chessboard(cols: usize, rows: usize, square: f64) -> Self {
        let points =
            (0..rows).flat_map(|r| (0..cols).map(move |c| [c as f64 * square, r as f64 * square])).collect();
        Board { points }
    }
}

/// Result of [`calibrate`].
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    pub intrinsics: Intrinsics,
    /// Board → camera pose per view, in input order.
    pub views: Vec<Pose>,
    /// Reprojection RMS in pixels, `sqrt(Σ‖uᵢ − ûᵢ‖² / N)` over all N points (OpenCV's figure).
    pub rms: f64,
}

/// Projects world point `x` to pixels; `None` when it is not in front of the camera.
pub fn project(k: &Intrinsics, pose: &Pose, x: [f64; 3]) -> Option<(f64, f64)> {
    let p = project_raw(&k.to_array(), &pose.to_array(), x);
    (p.2 > 0.0).then_some((p.0, p.1))
}

fn project_raw(k: &[f64], pose: &[f64], x: [f64; 3]) -> (f64, f64, f64) {
    let r = rodrigues([pose[0], pose[1], pose[2]]);
    let xc = [0, 1, 2].map(|i| r[i][0] * x[0] + r[i][1] * x[1] + r[i][2] * x[2] + pose[3 + i]);
    let k = Intrinsics::from_array(k);
    let (xd, yd) = k.distort(xc[0] / xc[2], xc[1] / xc[2]);
    (k.fx * xd + k.cx, k.fy * yd + k.cy, xc[2])
}

/// Reprojection RMS in pixels of one view: `sqrt(Σ‖uᵢ − π(k, pose, Xᵢ)‖² / N)` over the board's
/// points and their image positions `view` (a point behind the camera counts as infinite).
pub fn reprojection_rms(k: &Intrinsics, pose: &Pose, board: &Board, view: &[(f64, f64)]) -> f64 {
    let n = board.points.len().min(view.len());
    if n == 0 {
        return 0.0;
    }
    let sse: f64 = board
        .points
        .iter()
        .zip(view)
        .map(|(b, &(u, v))| match project(k, pose, [b[0], b[1], 0.0]) {
            Some((pu, pv)) => (pu - u).powi(2) + (pv - v).powi(2),
            None => f64::INFINITY,
        })
        .sum();
    (sse / n as f64).sqrt()
}

/// Inverts the distortion: pixel `(u, v)` → undistorted normalised point `(x, y)` such that
/// `distort(x, y) = ((u − cx)/fx, (v − cy)/fy)`, by Newton iteration (numeric 2×2 Jacobian).
/// Returns `None` when the iteration does not converge (far outside the model's valid range).
pub fn undistort_point(k: &Intrinsics, (u, v): (f64, f64)) -> Option<(f64, f64)> {
    let (xt, yt) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
    if !(xt.is_finite() && yt.is_finite()) {
        return None;
    }
    let (mut x, mut y) = (xt, yt);
    for _ in 0..50 {
        let (dx, dy) = k.distort(x, y);
        let (ex, ey) = (dx - xt, dy - yt);
        if ex.abs().max(ey.abs()) < 1e-14 {
            return Some((x, y));
        }
        let h = 1e-7;
        let (ax, ay) = k.distort(x + h, y);
        let (bx, by) = k.distort(x, y + h);
        let (j00, j10, j01, j11) = ((ax - dx) / h, (ay - dy) / h, (bx - dx) / h, (by - dy) / h);
        let det = j00 * j11 - j01 * j10;
        if det.abs() < 1e-12 || !det.is_finite() {
            return None;
        }
        x -= (j11 * ex - j01 * ey) / det;
        y -= (-j10 * ex + j00 * ey) / det;
    }
    let (dx, dy) = k.distort(x, y);
    ((dx - xt).abs().max((dy - yt).abs()) < 1e-9).then_some((x, y))
}

/// The viewing ray of pixel `(u, v)` in world (board) coordinates: `(origin, unit direction)`,
/// origin the camera centre `−Rᵀt`, direction `Rᵀ·normalise(x, y, 1)` for the undistorted point.
pub fn pixel_ray(k: &Intrinsics, pose: &Pose, uv: (f64, f64)) -> Option<([f64; 3], [f64; 3])> {
    let (x, y) = undistort_point(k, uv)?;
    let n = (x * x + y * y + 1.0).sqrt();
    let d = [x / n, y / n, 1.0 / n];
    let r = pose.rotation();
    let dir = [0, 1, 2].map(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]);
    Some((pose.camera_centre(), dir))
}

// ---------------------------------------------------------------------------------------------
// Rotations and small linear algebra.

type M3 = [[f64; 3]; 3];

/// The rotation matrix of rotation vector `r` (axis × angle, rad).
pub fn rodrigues(r: [f64; 3]) -> M3 {
    let th = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    let (s, c1, k) = if th < 1e-12 {
        (1.0, 0.0, r)
    } else {
        (th.sin(), 1.0 - th.cos(), [r[0] / th, r[1] / th, r[2] / th])
    };
    let c = 1.0 - c1;
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = c1 * k[i] * k[j] + if i == j { c } else { 0.0 };
        }
    }
    m[0][1] -= s * k[2];
    m[0][2] += s * k[1];
    m[1][0] += s * k[2];
    m[1][2] -= s * k[0];
    m[2][0] -= s * k[1];
    m[2][1] += s * k[0];
    m
}

/// The rotation vector of rotation matrix `m` (angle in 0..=π).
pub fn rodrigues_inv(m: &M3) -> [f64; 3] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let c = ((tr - 1.0) / 2.0).clamp(-1.0, 1.0);
    let th = c.acos();
    let w = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]];
    let s = th.sin();
    if s > 1e-6 {
        let f = th / (2.0 * s);
        return w.map(|x| x * f);
    }
    if c > 0.0 {
        return w.map(|x| x / 2.0);
    }
    // θ ≈ π: R ≈ 2kkᵀ − I.
    let d = [0, 1, 2].map(|i| ((m[i][i] + 1.0) / 2.0).max(0.0).sqrt());
    let i = if d[0] >= d[1] && d[0] >= d[2] {
        0
    } else if d[1] >= d[2] {
        1
    } else {
        2
    };
    let mut k = [0.0; 3];
    k[i] = d[i];
    for j in 0..3 {
        if j != i {
            k[j] = (m[i][j] + m[j][i]) / (4.0 * d[i]);
        }
    }
    let n = (k[0] * k[0] + k[1] * k[1] + k[2] * k[2]).sqrt();
    k.map(|x| x / n * th)
}

fn mul3(a: &M3, b: &M3) -> M3 {
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

fn inv3(a: &M3) -> Option<M3> {
    let c = |i: usize, j: usize| {
        let (i1, i2, j1, j2) = ((i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3);
        a[i1][j1] * a[i2][j2] - a[i1][j2] * a[i2][j1]
    };
    let det = a[0][0] * c(0, 0) + a[0][1] * c(0, 1) + a[0][2] * c(0, 2);
    if det.abs() < 1e-300 || !det.is_finite() {
        return None;
    }
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[j][i] = c(i, j) / det;
        }
    }
    Some(m)
}

/// Least-squares null vector of the `m×n` matrix `rows` (unit vector minimising ‖A·x‖), via the
/// smallest eigenvector of `AᵀA`. `None` when the null space is more than one-dimensional.
fn null_vector(rows: &[Vec<f64>], n: usize) -> Option<Vec<f64>> {
    let mut ata = vec![0.0; n * n];
    for r in rows {
        for i in 0..n {
            for j in 0..n {
                ata[i * n + j] += r[i] * r[j];
            }
        }
    }
    // Eigenvalues descending, eigenvectors as columns: the smallest is the last.
    let (vals, vecs) = crate::linalg::sym_eigen(&ata, n);
    let max = vals[0].abs();
    if !(max > 0.0) || vals[n - 2] <= 1e-13 * max {
        return None;
    }
    Some((0..n).map(|i| vecs[i * n + n - 1]).collect())
}

/// Solves the symmetric positive-definite system `a·x = b` by Cholesky; `None` if not SPD.
fn cholesky_solve(a: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let s: f64 = a[i * n + j] - (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum::<f64>();
            if i == j {
                if !(s > 0.0) {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        y[i] = (b[i] - (0..i).map(|k| l[i * n + k] * y[k]).sum::<f64>()) / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        x[i] = (y[i] - (i + 1..n).map(|k| l[k * n + i] * x[k]).sum::<f64>()) / l[i * n + i];
    }
    Some(x)
}

// ---------------------------------------------------------------------------------------------
// Homographies, Zhang's initialisation, extrinsics.

/// Similarity `T` moving the points' centroid to 0 and their mean distance to √2 (Hartley).
fn normaliser(p: &[[f64; 2]]) -> Option<M3> {
    let n = p.len() as f64;
    let (mx, my) = (p.iter().map(|q| q[0]).sum::<f64>() / n, p.iter().map(|q| q[1]).sum::<f64>() / n);
    let d = p.iter().map(|q| ((q[0] - mx).powi(2) + (q[1] - my).powi(2)).sqrt()).sum::<f64>() / n;
    if !(d > 0.0) || !d.is_finite() {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / d;
    Some([[s, 0.0, -s * mx], [0.0, s, -s * my], [0.0, 0.0, 1.0]])
}

fn apply_h(h: &M3, p: [f64; 2]) -> [f64; 2] {
    let w = h[2][0] * p[0] + h[2][1] * p[1] + h[2][2];
    [(h[0][0] * p[0] + h[0][1] * p[1] + h[0][2]) / w, (h[1][0] * p[0] + h[1][1] * p[1] + h[1][2]) / w]
}

/// Homography `H` with `dst ~ H·src`, by the normalised DLT.
fn homography(src: &[[f64; 2]], dst: &[[f64; 2]]) -> Result<M3, CalibError> {
    if src.len() < 4 || src.len() != dst.len() {
        return Err(CalibError::InvalidInput(format!("homography needs ≥ 4 point pairs, got {}", src.len())));
    }
    let degenerate = CalibError::Degenerate("points do not determine a homography");
    let ts = normaliser(src).ok_or(degenerate.clone())?;
    let td = normaliser(dst).ok_or(degenerate.clone())?;
    let mut rows = Vec::with_capacity(2 * src.len());
    for (s, d) in src.iter().zip(dst) {
        let [x, y] = apply_h(&ts, *s);
        let [u, v] = apply_h(&td, *d);
        rows.push(vec![x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]);
        rows.push(vec![0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y, -v]);
    }
    let h = null_vector(&rows, 9).ok_or(degenerate.clone())?;
    let hn = [[h[0], h[1], h[2]], [h[3], h[4], h[5]], [h[6], h[7], h[8]]];
    let h = mul3(&inv3(&td).ok_or(degenerate.clone())?, &mul3(&hn, &ts));
    if h.iter().flatten().any(|x| !x.is_finite()) {
        return Err(degenerate);
    }
    Ok(h)
}

/// Zhang's closed form: `hᵢᵀ·B·hⱼ` is linear in `b = (B11, B12, B22, B13, B23, B33)`; the constraints
/// `h1ᵀBh2 = 0` and `h1ᵀBh1 = h2ᵀBh2` per view stack into `V·b = 0`, solved by the null vector.
fn zhang_init(hs: &[M3]) -> Result<Intrinsics, CalibError> {
    let vij = |h: &M3, i: usize, j: usize| {
        let (a, b) = ([h[0][i], h[1][i], h[2][i]], [h[0][j], h[1][j], h[2][j]]);
        [
            a[0] * b[0],
            a[0] * b[1] + a[1] * b[0],
            a[1] * b[1],
            a[2] * b[0] + a[0] * b[2],
            a[2] * b[1] + a[1] * b[2],
            a[2] * b[2],
        ]
    };
    let mut rows = Vec::new();
    for h in hs {
        // Scale each homography to unit norm so every view weighs alike.
        let n = h.iter().flatten().map(|x| x * x).sum::<f64>().sqrt();
        let h = h.map(|r| r.map(|x| x / n));
        rows.push(vij(&h, 0, 1).to_vec());
        let (a, b) = (vij(&h, 0, 0), vij(&h, 1, 1));
        rows.push((0..6).map(|k| a[k] - b[k]).collect());
    }
    let degenerate =
        CalibError::Degenerate("views do not determine the intrinsics (too similar or parallel)");
    let b = null_vector(&rows, 6).ok_or(degenerate.clone())?;
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if !(alpha2 > 0.0 && beta2 > 0.0 && den.is_finite()) {
        return Err(degenerate);
    }
    let (alpha, beta) = (alpha2.sqrt(), beta2.sqrt());
    let gamma = -b12 * alpha2 * beta / lambda;
    let u0 = gamma * v0 / beta - b13 * alpha2 / lambda;
    let k = Intrinsics::pinhole(alpha, beta, u0, v0);
    if [alpha, beta, u0, v0].iter().all(|x| x.is_finite()) {
        Ok(k)
    } else {
        Err(degenerate)
    }
}

/// Extrinsics from a homography board → normalised image: `[r1 r2 t] = λ·H`, `λ = 1/‖h1‖`
/// (sign chosen so the board is in front, `t_z > 0`), `r3 = r1 × r2`, orthonormalised.
fn pose_from_normalised_h(h: &M3) -> Result<Pose, CalibError> {
    let col = |j: usize| [h[0][j], h[1][j], h[2][j]];
    let (h1, h2, h3) = (col(0), col(1), col(2));
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (n1, n2) = (norm(h1), norm(h2));
    if !(n1 > 0.0 && n2 > 0.0) {
        return Err(CalibError::Degenerate("homography has a null column"));
    }
    let mut lambda = 2.0 / (n1 + n2);
    if h3[2] * lambda < 0.0 {
        lambda = -lambda;
    }
    let a = h1.map(|x| x / n1 * lambda.signum());
    let b = h2.map(|x| x / n2 * lambda.signum());
    // Symmetric orthonormalisation of the two columns.
    let s = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let (ns, nd) = (norm(s), norm(d));
    if !(ns > 1e-12 && nd > 1e-12) {
        return Err(CalibError::Degenerate("board seen edge-on"));
    }
    let r = std::f64::consts::FRAC_1_SQRT_2;
    let r1 = [0, 1, 2].map(|i| (s[i] / ns + d[i] / nd) * r);
    let r2 = [0, 1, 2].map(|i| (s[i] / ns - d[i] / nd) * r);
    let r3 = [r1[1] * r2[2] - r1[2] * r2[1], r1[2] * r2[0] - r1[0] * r2[2], r1[0] * r2[1] - r1[1] * r2[0]];
    let rot = [[r1[0], r2[0], r3[0]], [r1[1], r2[1], r3[1]], [r1[2], r2[2], r3[2]]];
    Ok(Pose::from_rotation(rot, h3.map(|x| x * lambda)))
}

// ---------------------------------------------------------------------------------------------
// Levenberg–Marquardt.

/// Minimises `Σ‖uᵢ − π(K, dist, poseᵥ, Xᵢ)‖²` over the intrinsics (unless `fix_intrinsics`) and every
/// view's `(rvec, tvec)`, with per-point central-difference Jacobians (each residual depends on the
/// 9 intrinsics and its own view's 6 parameters) and Marquardt's `λ·diag(JᵀJ)` damping.
/// Returns the final sum of squared residuals.
fn refine(
    k: &mut [f64; 9],
    poses: &mut [[f64; 6]],
    board: &[[f64; 2]],
    views: &[&[(f64, f64)]],
    fix_intrinsics: bool,
) -> f64 {
    let ni = if fix_intrinsics { 0 } else { 9 };
    let np = ni + 6 * poses.len();
    let cost = |k: &[f64; 9], poses: &[[f64; 6]]| -> f64 {
        let mut s = 0.0;
        for (pose, view) in poses.iter().zip(views) {
            for (b, &(u, v)) in board.iter().zip(view.iter()) {
                let (pu, pv, z) = project_raw(k, pose, [b[0], b[1], 0.0]);
                s += if z > 0.0 { (pu - u).powi(2) + (pv - v).powi(2) } else { f64::INFINITY };
            }
        }
        if s.is_finite() {
            s
        } else {
            f64::INFINITY
        }
    };
    let mut current = cost(k, poses);
    let mut lambda = 1e-3;
    for _iter in 0..200 {
        let mut jtj = vec![0.0; np * np];
        let mut jte = vec![0.0; np];
        for (vi, (pose, view)) in poses.iter().zip(views).enumerate() {
            for (b, &(u, v)) in board.iter().zip(view.iter()) {
                let x = [b[0], b[1], 0.0];
                let (pu, pv, _) = project_raw(k, pose, x);
                let e = [pu - u, pv - v];
                // Local Jacobian over (intrinsics?, pose) → global indices.
                let mut cols: Vec<(usize, [f64; 2])> = Vec::with_capacity(15);
                for p in 0..ni {
                    let h = 1e-6 * k[p].abs().max(1e-2);
                    let (mut kp, mut km) = (*k, *k);
                    kp[p] += h;
                    km[p] -= h;
                    let a = project_raw(&kp, pose, x);
                    let c = project_raw(&km, pose, x);
                    cols.push((p, [(a.0 - c.0) / (2.0 * h), (a.1 - c.1) / (2.0 * h)]));
                }
                for p in 0..6 {
                    let h = 1e-6 * pose[p].abs().max(1e-2);
                    let (mut pp, mut pm) = (*pose, *pose);
                    pp[p] += h;
                    pm[p] -= h;
                    let a = project_raw(k, &pp, x);
                    let c = project_raw(k, &pm, x);
                    cols.push((ni + 6 * vi + p, [(a.0 - c.0) / (2.0 * h), (a.1 - c.1) / (2.0 * h)]));
                }
                for &(i, ji) in &cols {
                    jte[i] += ji[0] * e[0] + ji[1] * e[1];
                    for &(j, jj) in &cols {
                        jtj[i * np + j] += ji[0] * jj[0] + ji[1] * jj[1];
                    }
                }
            }
        }
        let mut improved = false;
        for _try in 0..20 {
            let mut a = jtj.clone();
            for i in 0..np {
                a[i * np + i] += lambda * jtj[i * np + i].max(1e-12);
            }
            let rhs: Vec<f64> = jte.iter().map(|x| -x).collect();
            let Some(delta) = cholesky_solve(&a, &rhs, np) else {
                lambda *= 10.0;
                continue;
            };
            let mut k2 = *k;
            for p in 0..ni {
                k2[p] += delta[p];
            }
            let mut poses2 = poses.to_vec();
            for (vi, pose) in poses2.iter_mut().enumerate() {
                for p in 0..6 {
                    pose[p] += delta[ni + 6 * vi + p];
                }
            }
            let c = cost(&k2, &poses2);
            if c < current {
                let rel = (current - c) / current.max(1e-300);
                *k = k2;
                poses.copy_from_slice(&poses2);
                current = c;
                lambda = (lambda / 10.0).max(1e-12);
                improved = rel > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    current
}

fn check_view(board: &Board, view: &[(f64, f64)]) -> Result<(), CalibError> {
    if view.len() != board.points.len() {
        return Err(CalibError::InvalidInput(format!(
            "view has {} points, board has {}",
            view.len(),
            board.points.len()
        )));
    }
    if view.iter().any(|p| !(p.0.is_finite() && p.1.is_finite())) {
        return Err(CalibError::InvalidInput("non-finite image point".into()));
    }
    Ok(())
}

/// Calibrates a camera from several views of a planar board: Zhang's closed-form intrinsics from
/// the views' homographies, poses from `K⁻¹H`, then Levenberg–Marquardt over fx, fy, cx, cy, k1,
/// k2, p1, p2, k3 and every pose. Needs at least 3 views of at least 4 points each.
pub fn calibrate(board: &Board, views: &[Vec<(f64, f64)>]) -> Result<Calibration, CalibError> {
    if views.len() < 3 {
        return Err(CalibError::TooFewViews { got: views.len(), need: 3 });
    }
    if board.points.len() < 4 {
        return Err(CalibError::InvalidInput(format!("board has {} points, need ≥ 4", board.points.len())));
    }
    let mut hs = Vec::with_capacity(views.len());
    for view in views {
        check_view(board, view)?;
        let dst: Vec<[f64; 2]> = view.iter().map(|p| [p.0, p.1]).collect();
        hs.push(homography(&board.points, &dst)?);
    }
    let k0 = zhang_init(&hs)?;
    let kinv = inv3(&[[k0.fx, 0.0, k0.cx], [0.0, k0.fy, k0.cy], [0.0, 0.0, 1.0]])
        .ok_or(CalibError::Degenerate("singular camera matrix"))?;
    let mut poses = Vec::with_capacity(views.len());
    for h in &hs {
        poses.push(pose_from_normalised_h(&mul3(&kinv, h))?.to_array());
    }
    let mut k = k0.to_array();
    let slices: Vec<&[(f64, f64)]> = views.iter().map(|v| v.as_slice()).collect();
    let sse = refine(&mut k, &mut poses, &board.points, &slices, false);
    let n = (views.len() * board.points.len()) as f64;
    let rms = (sse / n).sqrt();
    if !rms.is_finite() || k.iter().any(|x| !x.is_finite()) {
        return Err(CalibError::Degenerate("refinement diverged"));
    }
    Ok(Calibration {
        intrinsics: Intrinsics::from_array(&k),
        views: poses.iter().map(|p| Pose::from_array(p)).collect(),
        rms,
    })
}

/// Pose of a calibrated camera from one image of a known planar board (e.g. the board lying on the
/// rig's reference plane): homography board → undistorted normalised points, `[r1 r2 t] ~ H`,
/// then Levenberg–Marquardt on the 6 pose parameters. Returns the pose and its reprojection RMS.
pub fn pose_from_board(
    k: &Intrinsics,
    image_points: &[(f64, f64)],
    board: &Board,
) -> Result<(Pose, f64), CalibError> {
    check_view(board, image_points)?;
    if board.points.len() < 4 {
        return Err(CalibError::InvalidInput(format!("board has {} points, need ≥ 4", board.points.len())));
    }
    let mut norm = Vec::with_capacity(image_points.len());
    for &p in image_points {
        let (x, y) =
            undistort_point(k, p).ok_or(CalibError::Degenerate("point outside the distortion model"))?;
        norm.push([x, y]);
    }
    let h = homography(&board.points, &norm)?;
    let mut poses = [pose_from_normalised_h(&h)?.to_array()];
    let mut ka = k.to_array();
    let sse = refine(&mut ka, &mut poses, &board.points, &[image_points], true);
    let rms = (sse / image_points.len() as f64).sqrt();
    if !rms.is_finite() {
        return Err(CalibError::Degenerate("pose refinement diverged"));
    }
    Ok((Pose::from_array(&poses[0]), rms))
}
