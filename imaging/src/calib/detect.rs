//! Chessboard inner-corner detection with sub-pixel refinement.
//!
//! 1. **Candidates**: local maxima of the saddle response `Ixy² − Ixx·Iyy` (the negative Hessian
//!    determinant, large at X-junctions) of the image blurred at a few scales.
//! 2. **Verification** of a point as an X-junction: on a ring around it the blurred image shows
//!    exactly four alternating light/dark arcs, is point-symmetric (opposite samples agree), and
//!    in a grid its edges run towards the neighbouring corners. An edge, a T-junction on the
//!    board's border, a blob or texture fails one of these.
//! 3. **Grid growth** from strong verified seeds with a basis from two non-parallel neighbours:
//!    each neighbour of a grid node is predicted (by extrapolating the line through the node, or
//!    from its local basis), snapped to a candidate near the prediction (or refined from the
//!    prediction itself when no candidate is there), and accepted when it is an X-junction of the
//!    alternating polarity. The board is found when the grid is exactly `cols × rows`.
//! 4. **Refinement** (OpenCV's `cornerSubPix` principle): at the corner `q` every gradient `g(p)` in
//!    a window is orthogonal to `p − q`, so `q = (Σ w·g·gᵀ)⁻¹ Σ w·g·gᵀ·p`, iterated. Gradients
//!    are taken at whole pixels, not resampled around the estimate: resampling every window
//!    sample at the estimate's sub-pixel phase biases the result by a few hundredths of a pixel.
//!    On the outer ring the window stops short of the board's outline, measured per corner.
//!    Windows grow with the squares (and are retried larger where a small one fails): on a
//!    blurred board a window much smaller than the blur leaves the weak gradients at the corner's
//!    centre to decide, and the estimate slides along an edge.

use std::collections::{HashMap, HashSet, VecDeque};

use super::CalibError;

/// A grey image as `f64`, row-major, with bilinear sampling (clamped at the border).
struct Img {
    w: usize,
    h: usize,
    px: Vec<f64>,
}

impl Img {
    fn at(&self, x: usize, y: usize) -> f64 {
        self.px[y * self.w + x]
    }

    fn sample(&self, x: f64, y: f64) -> f64 {
        let x = x.clamp(0.0, (self.w - 1) as f64);
        let y = y.clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let top = self.at(x0, y0) * (1.0 - fx) + self.at(x1, y0) * fx;
        let bot = self.at(x0, y1) * (1.0 - fx) + self.at(x1, y1) * fx;
        top * (1.0 - fy) + bot * fy
    }

    /// Separable Gaussian blur with standard deviation `sigma` (edges clamped).
    fn blur(&self, sigma: f64) -> Img {
        let r = (3.0 * sigma).ceil() as usize;
        let k: Vec<f64> =
            (0..=2 * r).map(|i| (-((i as f64 - r as f64).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
        let s: f64 = k.iter().sum();
        let k: Vec<f64> = k.iter().map(|x| x / s).collect();
        let (w, h) = (self.w, self.h);
        let mut tmp = vec![0.0; self.px.len()];
        for y in 0..h {
            let row = &self.px[y * w..(y + 1) * w];
            for x in 0..w {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    acc += kv * row[(x + i).saturating_sub(r).min(w - 1)];
                }
                tmp[y * w + x] = acc;
            }
        }
        let mut out = vec![0.0; self.px.len()];
        for (i, kv) in k.iter().enumerate() {
            for y in 0..h {
                let src = (y + i).saturating_sub(r).min(h - 1);
                let (dst, src) = (&mut out[y * w..(y + 1) * w], &tmp[src * w..(src + 1) * w]);
                for (d, s) in dst.iter_mut().zip(src) {
                    *d += kv * s;
                }
            }
        }
        Img { w, h, px: out }
    }
}

/// Central-difference gradients of an image at whole pixels (zero on the border).
struct Gradient {
    w: usize,
    h: usize,
    gx: Vec<f64>,
    gy: Vec<f64>,
}

impl Gradient {
    fn of(img: &Img) -> Self {
        let (w, h) = (img.w, img.h);
        let (mut gx, mut gy) = (vec![0.0; w * h], vec![0.0; w * h]);
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                gx[y * w + x] = (img.at(x + 1, y) - img.at(x - 1, y)) / 2.0;
                gy[y * w + x] = (img.at(x, y + 1) - img.at(x, y - 1)) / 2.0;
            }
        }
        Gradient { w, h, gx, gy }
    }
}

/// Sub-pixel corner refinement from `start` with a window of half-size `win` pixels: solves the
/// gradient-orthogonality least squares `Σ w·g·gᵀ·(p − q) = 0` for `q`, re-centring the Gaussian
/// weights (σ = win/2) on each new estimate, until the step is below 10⁻³ px. `None` when the
/// system is singular (a flat or single-edge window) or the estimate drifts more than
/// `max_shift` from `start`.
fn refine_corner(g: &Gradient, start: [f64; 2], win: usize, max_shift: f64) -> Option<[f64; 2]> {
    let win_f = win as f64;
    let inv2s2 = 2.0 / (win_f * win_f);
    let mut c = start;
    for _ in 0..30 {
        let (x0, y0) = (c[0].round() as i64, c[1].round() as i64);
        let (lo_x, hi_x) = ((x0 - win as i64).max(1), (x0 + win as i64).min(g.w as i64 - 2));
        let (lo_y, hi_y) = ((y0 - win as i64).max(1), (y0 + win as i64).min(g.h as i64 - 2));
        let (mut a, mut b, mut d, mut bx, mut by) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for y in lo_y..=hi_y {
            let dy = y as f64 - c[1];
            let row = y as usize * g.w;
            for x in lo_x..=hi_x {
                let dx = x as f64 - c[0];
                let (gx, gy) = (g.gx[row + x as usize], g.gy[row + x as usize]);
                let wgt = (-(dx * dx + dy * dy) * inv2s2).exp();
                let (gxx, gxy, gyy) = (wgt * gx * gx, wgt * gx * gy, wgt * gy * gy);
                a += gxx;
                b += gxy;
                d += gyy;
                bx += gxx * dx + gxy * dy;
                by += gxy * dx + gyy * dy;
            }
        }
        let det = a * d - b * b;
        // Both eigenvalues of the structure tensor must be substantial: two edge directions.
        if !(det > 1e-6 * (a + d) * (a + d)) {
            return None;
        }
        let (sx, sy) = ((d * bx - b * by) / det, (a * by - b * bx) / det);
        c = [c[0] + sx, c[1] + sy];
        if (c[0] - start[0]).hypot(c[1] - start[1]) > max_shift || !c[0].is_finite() {
            return None;
        }
        if sx * sx + sy * sy < 1e-6 {
            break;
        }
    }
    Some(c)
}

/// Saddle-point candidates: local maxima (radius 3) of `Ixy² − Ixx·Iyy` on the blurred image,
/// strongest first, at most `max`.
fn saddle_candidates(b: &Img, max: usize) -> Vec<([f64; 2], f64)> {
    let (w, h) = (b.w, b.h);
    let mut resp = vec![0.0; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = b.at(x, y);
            let ixx = b.at(x + 1, y) - 2.0 * c + b.at(x - 1, y);
            let iyy = b.at(x, y + 1) - 2.0 * c + b.at(x, y - 1);
            let ixy =
                (b.at(x + 1, y + 1) - b.at(x - 1, y + 1) - b.at(x + 1, y - 1) + b.at(x - 1, y - 1)) / 4.0;
            resp[y * w + x] = (ixy * ixy - ixx * iyy).max(0.0);
        }
    }
    let peak = resp.iter().cloned().fold(0.0, f64::max);
    if peak <= 0.0 {
        return Vec::new();
    }
    let r = 3usize;
    let mut out = Vec::new();
    for y in r..h.saturating_sub(r) {
        for x in r..w.saturating_sub(r) {
            let v = resp[y * w + x];
            if v < 1e-3 * peak {
                continue;
            }
            let mut is_max = true;
            'n: for yy in y - r..=y + r {
                for xx in x - r..=x + r {
                    let o = resp[yy * w + xx];
                    if o > v || (o == v && (yy, xx) < (y, x)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max {
                out.push(([x as f64, y as f64], v));
            }
        }
    }
    out.sort_by(|a, b| b.1.total_cmp(&a.1));
    out.truncate(max);
    out
}

/// Samples on the verification ring.
const RING: usize = 48;

/// What the verification ring saw around an X-junction.
struct Ring {
    /// max − min of the samples (grey levels).
    contrast: f64,
    /// Angles (radians, image coordinates) of the four light/dark transitions: the edges.
    edges: [f64; 4],
}

impl Ring {
    /// Whether the edges point along `±ei` and `±ej` (within 20°): a chessboard corner's edges
    /// run to its four neighbours.
    fn edges_along(&self, ei: [f64; 2], ej: [f64; 2]) -> bool {
        let tol = 20f64.to_radians();
        [ei, ej, ei.map(|x| -x), ej.map(|x| -x)].iter().all(|d| {
            let a = d[1].atan2(d[0]);
            self.edges.iter().any(|&e| {
                let diff = (a - e).rem_euclid(std::f64::consts::TAU);
                diff.min(std::f64::consts::TAU - diff) <= tol
            })
        })
    }
}

/// Whether `p` looks like an X-junction on a ring of radius `r`: contrast (max − min) of at least
/// `min_contrast`, exactly four alternating light/dark arcs, and point symmetry (at least 85 % of
/// opposite sample pairs in the same class). Samples within 15 % of the range from the midpoint
/// are left unclassified so that noise on an edge does not count as an arc.
fn x_junction(img: &Img, p: [f64; 2], r: f64, min_contrast: f64) -> Option<Ring> {
    let step = std::f64::consts::TAU / RING as f64;
    let mut v = [0.0; RING];
    for (k, s) in v.iter_mut().enumerate() {
        let a = k as f64 * step;
        *s = img.sample(p[0] + r * a.cos(), p[1] + r * a.sin());
    }
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &x| (l.min(x), h.max(x)));
    let range = hi - lo;
    if !(range >= min_contrast) {
        return None;
    }
    let mid = (hi + lo) / 2.0;
    let class: Vec<i8> = v
        .iter()
        .map(|&x| {
            if x > mid + 0.15 * range {
                1
            } else if x < mid - 0.15 * range {
                -1
            } else {
                0
            }
        })
        .collect();
    // Classified samples in ring order; a transition lies between consecutive ones that differ.
    let known: Vec<usize> = (0..RING).filter(|&k| class[k] != 0).collect();
    if known.len() < RING / 2 {
        return None;
    }
    let mut edges = Vec::new();
    for (n, &k) in known.iter().enumerate() {
        let next = known[(n + 1) % known.len()];
        if class[k] != class[next] {
            let gap = (next + RING - k) % RING;
            edges.push((k as f64 + gap as f64 / 2.0) * step);
        }
    }
    let edges: [f64; 4] = edges.try_into().ok()?;
    let (mut pairs, mut agree) = (0, 0);
    for k in 0..RING / 2 {
        let (a, b) = (class[k], class[k + RING / 2]);
        if a != 0 && b != 0 {
            pairs += 1;
            agree += usize::from(a == b);
        }
    }
    (pairs >= RING / 4 && agree * 100 >= pairs * 85).then_some(Ring { contrast: range, edges })
}

/// Polarity of an X-junction at `p` in the local grid basis `(ei, ej)` (steps to the neighbouring
/// corners), sampled at distance `r` along the diagonals: `Some(+1)` when the squares towards
/// `±(êi + êj)` are both clearly brighter than those towards `±(êi − êj)`, `Some(−1)` for the
/// reverse, `None` otherwise.
fn x_polarity(img: &Img, p: [f64; 2], ei: [f64; 2], ej: [f64; 2], r: f64) -> Option<i32> {
    let (ui, uj) = (ei.map(|x| x / norm(ei)), ej.map(|x| x / norm(ej)));
    let s = |a: f64, b: f64| {
        let d = [a * ui[0] + b * uj[0], a * ui[1] + b * uj[1]];
        let n = norm(d);
        img.sample(p[0] + r * d[0] / n, p[1] + r * d[1] / n)
    };
    let (pp, mm, pm, mp) = (s(1.0, 1.0), s(-1.0, -1.0), s(1.0, -1.0), s(-1.0, 1.0));
    let range = pp.max(mm).max(pm).max(mp) - pp.min(mm).min(pm).min(mp);
    if pp.min(mm) - pm.max(mp) > 0.3 * range {
        Some(1)
    } else if pm.min(mp) - pp.max(mm) > 0.3 * range {
        Some(-1)
    } else {
        None
    }
}

/// Spatial hash of the candidates for nearest-neighbour queries.
struct Buckets {
    cell: f64,
    map: HashMap<(i64, i64), Vec<usize>>,
}

impl Buckets {
    fn new(pts: &[[f64; 2]], cell: f64) -> Self {
        let mut map: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (i, p) in pts.iter().enumerate() {
            map.entry(((p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64)).or_default().push(i);
        }
        Buckets { cell, map }
    }

    /// Candidates within `r` of `q`, nearest first, with their distances.
    fn within(&self, pts: &[[f64; 2]], q: [f64; 2], r: f64) -> Vec<(usize, f64)> {
        let (x0, x1) = (((q[0] - r) / self.cell).floor() as i64, ((q[0] + r) / self.cell).floor() as i64);
        let (y0, y1) = (((q[1] - r) / self.cell).floor() as i64, ((q[1] + r) / self.cell).floor() as i64);
        let mut out = Vec::new();
        for cy in y0..=y1 {
            for cx in x0..=x1 {
                for &i in self.map.get(&(cx, cy)).into_iter().flatten() {
                    let d = (pts[i][0] - q[0]).hypot(pts[i][1] - q[1]);
                    if d <= r {
                        out.push((i, d));
                    }
                }
            }
        }
        out.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        out
    }
}

fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn norm(a: [f64; 2]) -> f64 {
    a[0].hypot(a[1])
}

/// A grid node: its position and the steps to its `+i` and `+j` neighbours.
#[derive(Clone, Copy)]
struct Node {
    p: [f64; 2],
    ei: [f64; 2],
    ej: [f64; 2],
}

type Grid = HashMap<(i32, i32), Node>;

/// Everything the detector derives from the image once.
struct Scene<'a> {
    /// Lightly blurred image for verification (ring and polarity).
    smooth: &'a Img,
    /// Gradients of the raw image for refinement.
    grad: &'a Gradient,
    /// Candidate positions and their saddle strengths.
    pts: Vec<[f64; 2]>,
    buckets: Buckets,
}

/// Minimum contrast (grey levels) of an X-junction.
const MIN_CONTRAST: f64 = 12.0;

impl Scene<'_> {
    /// Verifies `p` as an X-junction at the scale of steps `ei`, `ej`, and returns its polarity.
    /// Tries a ring of 0.3 steps, then one of 0.15: printed boards often cut their outermost
    /// squares short, and a ring reaching past them into the margin is not an X-junction; then
    /// one of 0.45, for a blurred board whose short squares leave too little contrast close in.
    fn verify(&self, p: [f64; 2], ei: [f64; 2], ej: [f64; 2], min_contrast: f64) -> Option<i32> {
        let len = norm(ei).min(norm(ej));
        [0.3, 0.15, 0.45].into_iter().map(|f| (f * len).clamp(2.5, 12.0)).find_map(|r| {
            let ring = x_junction(self.smooth, p, r, min_contrast)?;
            if !ring.edges_along(ei, ej) {
                return None;
            }
            x_polarity(self.smooth, p, ei, ej, r)
        })
    }

    /// Grows a grid from candidate `seed` with basis `(ei, ej)`. Stops (returning what it has)
    /// when the grid spans two rows or columns more than a `cols × rows` pattern either way
    /// round could.
    fn grow(&self, seed: [f64; 2], ei: [f64; 2], ej: [f64; 2], cols: usize, rows: usize) -> Grid {
        let mut grid: Grid = HashMap::new();
        let Some(pol0) = self.verify(seed, ei, ej, MIN_CONTRAST) else { return grid };
        let contrast = x_junction(self.smooth, seed, (0.3 * norm(ei).min(norm(ej))).clamp(2.5, 12.0), 0.0)
            .map_or(MIN_CONTRAST, |r| r.contrast);
        let min_contrast = (0.25 * contrast).max(MIN_CONTRAST);
        grid.insert((0, 0), Node { p: seed, ei, ej });
        let mut used: HashSet<usize> = HashSet::new();
        let mut queue = VecDeque::from([(0, 0)]);
        let (mut imin, mut imax, mut jmin, mut jmax) = (0, 0, 0, 0);
        let (small, large) = (cols.min(rows) as i32, cols.max(rows) as i32);
        while let Some((i, j)) = queue.pop_front() {
            let node = grid[&(i, j)];
            for (di, dj) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                let t = (i + di, j + dj);
                if grid.contains_key(&t) {
                    continue;
                }
                // Extrapolate the line through the node when the node behind it is known: it
                // follows perspective better than the node's own basis.
                let step = match grid.get(&(i - di, j - dj)) {
                    Some(back) => sub(node.p, back.p),
                    None => {
                        let (s, e) = if di != 0 { (di as f64, node.ei) } else { (dj as f64, node.ej) };
                        [s * e[0], s * e[1]]
                    }
                };
                let len = norm(step);
                let pred = [node.p[0] + step[0], node.p[1] + step[1]];
                let tol = 0.35 * len;
                let win = ((0.25 * len).round() as usize).clamp(2, 8);
                let mut tries: Vec<(Option<usize>, [f64; 2])> = self
                    .buckets
                    .within(&self.pts, pred, tol)
                    .into_iter()
                    .filter(|(c, _)| !used.contains(c))
                    .take(2)
                    .map(|(c, _)| (Some(c), self.pts[c]))
                    .collect();
                tries.push((None, pred));
                let wide = ((0.4 * len).round() as usize).clamp(win, 12);
                for (cand, start) in tries {
                    let refined = [win, wide].into_iter().find_map(|w| {
                        refine_corner(self.grad, start, w, tol).filter(|q| norm(sub(*q, pred)) <= tol)
                    });
                    let Some(q) = refined else { continue };
                    // Steps measured at the new node from the grid nodes around it.
                    let mut ni = if di != 0 { sub(q, node.p).map(|x| x * di as f64) } else { node.ei };
                    let mut nj = if dj != 0 { sub(q, node.p).map(|x| x * dj as f64) } else { node.ej };
                    let mut clash = false;
                    for (si, sj) in [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)] {
                        if let Some(o) = grid.get(&(t.0 + si, t.1 + sj)) {
                            let v = sub(o.p, q);
                            clash |= norm(v) < 0.5 * len;
                            if sj == 0 {
                                ni = v.map(|x| x * si as f64);
                            } else if si == 0 {
                                nj = v.map(|x| x * sj as f64);
                            }
                        }
                    }
                    let want = if (t.0 + t.1).rem_euclid(2) == 0 { pol0 } else { -pol0 };
                    if clash || self.verify(q, ni, nj, min_contrast) != Some(want) {
                        continue;
                    }
                    grid.insert(t, Node { p: q, ei: ni, ej: nj });
                    if let Some(c) = cand {
                        used.insert(c);
                    }
                    (imin, imax, jmin, jmax) = (imin.min(t.0), imax.max(t.0), jmin.min(t.1), jmax.max(t.1));
                    // One row or column beyond the pattern is grown, so that a stray corner
                    // (see [`STRAY_CORNERS`]) can be told from a larger board.
                    let (ni, nj) = (imax - imin + 1, jmax - jmin + 1);
                    if ni.max(nj) > large + 1 || ni.min(nj) > small + 1 {
                        return grid;
                    }
                    queue.push_back(t);
                    break;
                }
            }
        }
        grid
    }
}

impl Scene<'_> {
    /// Fills the few corners growth left out of a grid that already spans the pattern: on a
    /// strongly tilted board whose outermost squares are cut short, an outer corner's far
    /// squares are a few pixels wide and the verification ring reaches past them. Such a corner
    /// is predicted from its neighbours (the parallelogram through the nearest three), refined,
    /// and accepted when its diagonal squares show the polarity its neighbour's imply. At most
    /// three holes, each with known neighbours on two sides.
    fn fill_holes(&self, grid: &mut Grid, cols: usize, rows: usize) {
        let Some((i0, i1, j0, j1)) = extent(grid) else { return };
        let (ni, nj) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
        if !((ni, nj) == (cols, rows) || (ni, nj) == (rows, cols)) || grid.len() + 3 < cols * rows {
            return;
        }
        // A hole next to another is predicted once its neighbour is in: a second pass.
        for _ in 0..2 {
            let holes: Vec<(i32, i32)> = (i0..=i1)
                .flat_map(|i| (j0..=j1).map(move |j| (i, j)))
                .filter(|t| !grid.contains_key(t))
                .collect();
            for t in holes {
                self.fill_hole(grid, t);
            }
        }
    }

    /// One hole of [`Self::fill_holes`].
    fn fill_hole(&self, grid: &mut Grid, t: (i32, i32)) {
        let mut preds = Vec::new();
        for (si, sj) in [(1, 1), (1, -1), (-1, 1), (-1, -1)] {
            if let (Some(a), Some(b), Some(c)) =
                (grid.get(&(t.0 + si, t.1)), grid.get(&(t.0, t.1 + sj)), grid.get(&(t.0 + si, t.1 + sj)))
            {
                preds.push([a.p[0] + b.p[0] - c.p[0], a.p[1] + b.p[1] - c.p[1]]);
            }
        }
        let Some(near) =
            [(1, 0), (-1, 0), (0, 1), (0, -1)].iter().find_map(|d| grid.get(&(t.0 + d.0, t.1 + d.1)))
        else {
            return;
        };
        if preds.is_empty() {
            return;
        }
        let n = preds.len() as f64;
        let pred = [preds.iter().map(|p| p[0]).sum::<f64>() / n, preds.iter().map(|p| p[1]).sum::<f64>() / n];
        let (ei, ej) = (near.ei, near.ej);
        let len = norm(ei).min(norm(ej));
        let win = ((0.2 * len).round() as usize).clamp(2, 6);
        let wide = ((0.4 * len).round() as usize).clamp(win, 12);
        let q = [wide, win].into_iter().find_map(|w| refine_corner(self.grad, pred, w, 0.3 * len));
        // The diagonal squares a fifth of a step out; on a blurred board, further out. On a
        // blurred board's outline the refinement can fail or be pulled off the corner: then the
        // prediction itself is checked, and the final refinement (which keeps its window inside
        // the outline) places it.
        let opposite = |p: [f64; 2]| {
            [0.2, 0.3, 0.4].into_iter().any(|f| {
                let r = (f * len).max(2.0);
                match (x_polarity(self.smooth, p, ei, ej, r), x_polarity(self.smooth, near.p, ei, ej, r)) {
                    (Some(here), Some(there)) => here == -there,
                    _ => false,
                }
            })
        };
        if let Some(p) = q.into_iter().chain([pred]).find(|&p| opposite(p)) {
            grid.insert(t, Node { p, ei, ej });
        }
    }
}

/// Corners a grown grid may have outside the pattern and still be taken as the pattern: where
/// a board's outer squares are cut short against its frame, the end of a cut square on the
/// frame's edge can pass as one more corner (OpenCV's `right13.jpg`). A board larger than the
/// pattern shows a whole row or column more.
const STRAY_CORNERS: usize = 2;

/// The `cols × rows` window (either way round) of `grid` holding most of its corners, and how
/// many corners lie outside it; a grid no larger than the pattern is its own window.
fn pattern_window(grid: &Grid, cols: usize, rows: usize) -> (Grid, usize) {
    let Some((i0, i1, j0, j1)) = extent(grid) else { return (grid.clone(), 0) };
    let (ni, nj) = (i1 - i0 + 1, j1 - j0 + 1);
    let mut best: Option<(usize, (i32, i32, i32, i32))> = None;
    for (a, b) in [(cols as i32, rows as i32), (rows as i32, cols as i32)] {
        let (a, b) = (a.min(ni), b.min(nj));
        for wi in i0..=i1 - a + 1 {
            for wj in j0..=j1 - b + 1 {
                let n = grid
                    .keys()
                    .filter(|k| (wi..wi + a).contains(&k.0) && (wj..wj + b).contains(&k.1))
                    .count();
                if best.is_none_or(|(m, _)| n > m) {
                    best = Some((n, (wi, wi + a, wj, wj + b)));
                }
            }
        }
    }
    let Some((n, (a0, a1, b0, b1))) = best else { return (grid.clone(), 0) };
    let window: Grid = grid
        .iter()
        .filter(|(k, _)| (a0..a1).contains(&k.0) && (b0..b1).contains(&k.1))
        .map(|(k, v)| (*k, *v))
        .collect();
    (window, grid.len() - n)
}

/// The grid's index ranges `(imin, imax, jmin, jmax)`.
fn extent(grid: &Grid) -> Option<(i32, i32, i32, i32)> {
    let mut keys = grid.keys();
    let &(i, j) = keys.next()?;
    Some(keys.fold((i, i, j, j), |(a, b, c, d), &(i, j)| (a.min(i), b.max(i), c.min(j), d.max(j))))
}

/// Why [`find_chessboard`] found no board: the furthest the detector got, so that a user knows
/// what to change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Miss {
    /// No point of the image is an X-junction (the corner where four squares meet): no board
    /// in view, or one too blurred, too dark or too small to show its corners.
    NoCorners,
    /// `junctions` points are X-junctions, but no grid of squares grows from any of them: the
    /// corners are clutter's (stripes, text, a keyboard) or the board's squares are too
    /// distorted to predict one corner from the next.
    NoGrid { junctions: usize },
    /// A grid of squares larger than the pattern: at least `cols × rows` inner corners.
    TooLarge { cols: usize, rows: usize },
    /// The largest grid found spans `cols × rows` corners, `corners` of them found: smaller
    /// than the pattern (part of the board hidden or out of the image, or its far side too
    /// steep or blurred) or with corners missing.
    Partial { cols: usize, rows: usize, corners: usize },
}

impl std::fmt::Display for Miss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Miss::NoCorners => write!(
                f,
                "no corner of four squares anywhere in the image (is the board in view, in focus and lit?)"
            ),
            Miss::NoGrid { junctions } => write!(
                f,
                "{junctions} corner-like points but no grid of squares among them (clutter, or a board too blurred or distorted to follow)"
            ),
            Miss::TooLarge { cols, rows } => write!(
                f,
                "a grid larger than the pattern, at least {cols}×{rows} inner corners (do --cols/--rows count inner corners, squares minus one?)"
            ),
            Miss::Partial { cols, rows, corners } if corners == cols * rows => write!(
                f,
                "the largest grid found is {cols}×{rows} inner corners (part of the board hidden or outside the image, or the pattern given larger than the board)"
            ),
            Miss::Partial { cols, rows, corners } => write!(
                f,
                "the largest grid found spans {cols}×{rows} inner corners with {} of them missing (part of the board hidden, glare, or its far side too steep or blurred)",
                cols * rows - corners
            ),
        }
    }
}

impl Miss {
    /// The larger of two misses: the one that got further.
    fn further(self, other: Miss) -> Miss {
        let rank = |m: &Miss| match *m {
            Miss::NoCorners => (0, 0),
            Miss::NoGrid { junctions } => (1, junctions),
            Miss::Partial { corners, .. } => (2, corners),
            Miss::TooLarge { cols, rows } => (3, cols * rows),
        };
        if rank(&other) > rank(&self) {
            other
        } else {
            self
        }
    }
}

/// Finds the `cols × rows` inner corners of a chessboard in an 8-bit grey image (`w·h` bytes,
/// row-major) with sub-pixel accuracy.
///
/// Ordering: row-major, `cols` corners per row, with the board axes (col, row) having the image's
/// handedness (x right, y down), i.e. matching [`super::Board::chessboard`] seen from the front.
/// When `cols + rows` is odd the board itself fixes which corner comes first: corner 0 is the
/// one whose square towards corners 1 and `cols` is dark (square `(0, 0)` dark, as on OpenCV's
/// pattern), so the order — and a pose from it — does not depend on how the board is turned.
/// Otherwise (a board symmetric under a half turn) corner 0 is the end nearest the image's
/// top-left.
///
/// Fails with [`CalibError::BoardNotFound`] unless exactly that pattern is found (a larger or
/// partly hidden board is not accepted), saying how far it got ([`Miss`]).
pub fn find_chessboard(
    gray: &[u8],
    w: usize,
    h: usize,
    pattern: (usize, usize),
) -> Result<Vec<(f64, f64)>, CalibError> {
    let (cols, rows) = pattern;
    if gray.len() != w * h || w < 16 || h < 16 {
        return Err(CalibError::InvalidInput(format!(
            "image of {} bytes is not {w}×{h} (≥ 16×16)",
            gray.len()
        )));
    }
    if cols < 2 || rows < 2 {
        return Err(CalibError::InvalidInput(format!("pattern {cols}×{rows} needs ≥ 2 corners each way")));
    }
    let raw = Img { w, h, px: gray.iter().map(|&v| v as f64).collect() };
    let smooth = raw.blur(1.0);
    let grad = Gradient::of(&raw);
    let mut miss = Miss::NoCorners;
    // Candidates at a fine scale first (small squares), then a coarse one (blurred or large ones).
    for sigma in [1.5, 3.0] {
        let cand = saddle_candidates(&raw.blur(sigma), 1500);
        let pts: Vec<[f64; 2]> = cand.iter().map(|c| c.0).collect();
        let scene = Scene { smooth: &smooth, grad: &grad, buckets: Buckets::new(&pts, 16.0), pts };
        let mut visited: HashSet<usize> = HashSet::new();
        let mut tried = 0;
        for seed in 0..scene.pts.len() {
            if visited.contains(&seed) || tried >= 60 {
                continue;
            }
            let sp = scene.pts[seed];
            if x_junction(&smooth, sp, 3.0, MIN_CONTRAST).is_none() {
                continue;
            }
            tried += 1;
            miss = miss.further(Miss::NoGrid { junctions: tried });
            // A small window first (small squares); a blurred corner needs a larger one, or the
            // weak gradients at its centre let the estimate slide along an edge.
            let Some(start) = [3, 5, 8].into_iter().find_map(|win| refine_corner(&grad, sp, win, 3.0)) else {
                continue;
            };
            // Basis candidates: the nearest verified candidates around the seed.
            let near: Vec<[f64; 2]> = scene
                .buckets
                .within(&scene.pts, sp, (w.max(h) / 4) as f64)
                .into_iter()
                .filter(|&(i, d)| i != seed && d >= 5.0)
                .map(|(i, _)| scene.pts[i])
                .filter(|&p| x_junction(&smooth, p, 3.0, MIN_CONTRAST).is_some())
                .take(6)
                .collect();
            let mut pairs = Vec::new();
            for a in &near {
                for b in &near {
                    let (d1, d2) = (sub(*a, sp), sub(*b, sp));
                    let (l1, l2) = (norm(d1), norm(d2));
                    let cos = (d1[0] * d2[0] + d1[1] * d2[1]) / (l1 * l2);
                    let cross = d1[0] * d2[1] - d1[1] * d2[0];
                    if cos.abs() < 0.6 && cross > 0.0 && l1 < 2.0 * l2 && l2 < 2.0 * l1 {
                        pairs.push((l1 + l2, d1, d2));
                    }
                }
            }
            pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
            for (_, d1, d2) in pairs {
                let grown = scene.grow(start, d1, d2, cols, rows);
                let (mut grid, outside) = pattern_window(&grown, cols, rows);
                if outside <= STRAY_CORNERS.min(cols.min(rows) / 3) {
                    scene.fill_holes(&mut grid, cols, rows);
                    if let Some(corners) = order_grid(&grid, &smooth, cols, rows) {
                        return Ok(final_refinement(&smooth, &grad, &corners, cols, rows));
                    }
                } else {
                    // A board larger than the pattern: named by all it showed.
                    grid = grown;
                }
                if grid.len() >= 4 {
                    if let Some((i0, i1, j0, j1)) = extent(&grid) {
                        let (a, b) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
                        // Named the pattern's way round.
                        let (gc, gr) = if (a >= b) == (cols >= rows) { (a, b) } else { (b, a) };
                        miss = miss.further(if gc > cols || gr > rows {
                            Miss::TooLarge { cols: gc.max(cols), rows: gr.max(rows) }
                        } else {
                            Miss::Partial { cols: gc, rows: gr, corners: grid.len() }
                        });
                    }
                    // A real grid that is not the pattern: its corners need not seed again.
                    for n in grid.values() {
                        for (i, _) in scene.buckets.within(&scene.pts, n.p, 3.0) {
                            visited.insert(i);
                        }
                    }
                    break;
                }
            }
        }
    }
    Err(CalibError::BoardNotFound(miss))
}

/// Refines every corner once more with a window scaled to its distance from its nearest grid
/// neighbour (about a third of it, 2–11 px) and, on the outer ring, kept inside the outermost
/// squares (see [`outer_extent`]); keeps the growth estimate where refinement fails.
fn final_refinement(
    smooth: &Img,
    grad: &Gradient,
    c: &[[f64; 2]],
    cols: usize,
    rows: usize,
) -> Vec<(f64, f64)> {
    let at = |r: i64, col: i64| {
        ((0..rows as i64).contains(&r) && (0..cols as i64).contains(&col))
            .then(|| c[r as usize * cols + col as usize])
    };
    let mut out = Vec::with_capacity(c.len());
    for r in 0..rows as i64 {
        for col in 0..cols as i64 {
            let p = c[(r * cols as i64 + col) as usize];
            let mut d = f64::INFINITY;
            let mut d_far: f64 = 0.0;
            let mut limit = f64::INFINITY;
            for (dr, dc) in [(0, 1), (0, -1), (1, 0), (-1, 0)] {
                if let Some(q) = at(r + dr, col + dc) {
                    d = d.min(norm(sub(q, p)));
                    d_far = d_far.max(norm(sub(q, p)));
                } else if let Some(q) = at(r - dr, col - dc) {
                    // No neighbour this way: the board's outline is out there, as close as the
                    // outermost squares are wide.
                    let out_dir = sub(p, q);
                    let across = match (at(r + dc, col + dr), at(r - dc, col - dr)) {
                        (Some(a), _) => sub(a, p),
                        (None, Some(b)) => sub(p, b),
                        (None, None) => [-out_dir[1], out_dir[0]],
                    };
                    limit = limit.min(outer_extent(smooth, p, out_dir, across));
                }
            }
            // A third of the nearest neighbour's distance; on a foreshortened board at least a
            // quarter of the farthest's, or a blurred corner's weak centre lets the estimate
            // slide along an edge of the short squares.
            let base = (0.35 * d).max(0.25 * d_far);
            let win = (base.round().min((limit - 2.0).floor()) as usize).clamp(2, 11);
            let q = refine_corner(grad, p, win, 0.25 * d).unwrap_or(p);
            out.push((q[0], q[1]));
        }
    }
    out
}

/// How far (pixels) the edge leaving corner `p` along `out_dir` (the step from its inner
/// neighbour) runs before the board's outline starts to end it: the distance along that line at
/// which the two outermost squares on either side of it (sampled 2 px to each side, `across`
/// being the direction to the next corner on the outline) have lost 15 % of their contrast near
/// the corner — the start of the outline's blurred edge. Printed boards often cut the outermost
/// squares short, and a refinement window reaching the outline is pulled towards it (by up to a
/// pixel on a board whose outer squares are a quarter wide).
fn outer_extent(smooth: &Img, p: [f64; 2], out_dir: [f64; 2], across: [f64; 2]) -> f64 {
    let len = norm(out_dir);
    let (u, v) = (out_dir.map(|x| x / len), across.map(|x| x / norm(across)));
    let diff = |t: f64| {
        let c = [p[0] + t * u[0], p[1] + t * u[1]];
        (smooth.sample(c[0] + 2.0 * v[0], c[1] + 2.0 * v[1])
            - smooth.sample(c[0] - 2.0 * v[0], c[1] - 2.0 * v[1]))
        .abs()
    };
    let reference = diff(3.0);
    let mut t = 3.0;
    while t < len {
        if diff(t) < 0.85 * reference {
            return t;
        }
        t += 0.5;
    }
    len
}

/// Orders a grown grid as `cols × rows` row-major (see [`find_chessboard`]); `None` unless the grid
/// is exactly that pattern (either way round).
fn order_grid(grid: &Grid, smooth: &Img, cols: usize, rows: usize) -> Option<Vec<[f64; 2]>> {
    if grid.len() != cols * rows {
        return None;
    }
    let (i0, i1) = (grid.keys().map(|k| k.0).min()?, grid.keys().map(|k| k.0).max()?);
    let (j0, j1) = (grid.keys().map(|k| k.1).min()?, grid.keys().map(|k| k.1).max()?);
    let (ni, nj) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
    let at = |i: i32, j: i32| grid.get(&(i0 + i, j0 + j)).map(|e| e.p);
    let mut out = Vec::with_capacity(cols * rows);
    for r in 0..rows as i32 {
        for c in 0..cols as i32 {
            out.push(if (ni, nj) == (cols, rows) {
                at(c, r)?
            } else if (ni, nj) == (rows, cols) {
                at(r, c)?
            } else {
                return None;
            });
        }
    }
    let idx = |r: usize, c: usize| r * cols + c;
    let (o, a, b) = (out[0], out[idx(0, 1)], out[idx(1, 0)]);
    let cross = (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    if cross < 0.0 {
        // Mirror the columns to restore the image's handedness.
        for r in 0..rows {
            out[r * cols..(r + 1) * cols].reverse();
        }
    }
    // The remaining choice is a half turn (reversing the whole order).
    let turn = if (cols + rows) % 2 == 1 {
        // Square (0, 0), between corners 0, 1, cols and cols + 1, must be the dark one; its
        // counterpart after a half turn has the other colour because cols + rows is odd.
        let centre = |k: [usize; 4]| {
            let s = k.iter().fold([0.0, 0.0], |s, &i| [s[0] + out[i][0] / 4.0, s[1] + out[i][1] / 4.0]);
            smooth.sample(s[0], s[1])
        };
        let first = centre([0, 1, cols, cols + 1]);
        let n = cols * rows;
        let last = centre([n - 1, n - 2, n - 1 - cols, n - 2 - cols]);
        first > last
    } else {
        let (f, l) = (out[0], out[cols * rows - 1]);
        f[0] + f[1] > l[0] + l[1]
    };
    if turn {
        out.reverse();
    }
    Some(out)
}
