//! A texture atlas of the object's surface for the local term (Goesele et al. 2004, section 7).
//!
//! The local term models light transport over a few millimetres by 7×7-texel filter kernels on
//! a texture atlas "with a border and with a low guaranteed upper limit for texture stretch",
//! and filters the kernels over the atlas's 4-neighbourhoods, where "each boundary texel links
//! to a corresponding non-boundary texel in a different map of the atlas".
//!
//! - Charts: triangles grouped by the dominant axis of their face normal (±x, ±y, ±z), split
//!   into edge-connected components and projected orthographically along that axis at
//!   `1/texel_mm` texels per mm. The projection keeps lengths along the axis plane and shortens
//!   those across it by `|n·axis|`, which is at least `1/√3` (the dominant of three unit
//!   components), so the stretch (the ratio of the map's singular values) is at most
//!   `√3 = 1/cos 54.7° ≈ 1.73`.
//! - A chart is grown triangle by triangle and refuses one whose texel centres another of its
//!   triangles already holds (a non-convex object folds over itself in projection); the refused
//!   triangle starts a chart of its own later. No texel belongs to two triangles.
//! - Charts' boxes, with a gutter of `border` texels on every side, are shelf-packed.
//! - Border: a texel within `border` (Chebyshev) of a chart's covered texels that is not covered
//!   is a boundary texel. It is lifted onto the plane of its nearest covered texel's triangle
//!   (where the surface would continue) and linked to the covered texel nearest that point in 3D,
//!   of a different chart where one lies within 2 texels, else its own nearest covered texel.

use std::collections::{HashMap, VecDeque};

use crate::vec3::{add, cross, dot, norm, scale, sub, V3};

use super::mesh::SurfaceMesh;

/// No chart (a degenerate triangle).
const NONE: u32 = u32::MAX;
/// An atlas is not built beyond this many texels (a texel size far too small for the mesh).
const MAX_TEXELS: f64 = (1u64 << 28) as f64;

/// A chart's texel-grid cells (axis-plane units of texels) and the triangle and barycentrics
/// that hold each.
type Claims = HashMap<[i64; 2], (u32, [f64; 3])>;

/// A covered ("inside") texel: the surface point its centre maps to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Texel {
    pub triangle: u32,
    /// Barycentrics on `triangle` (non-negative, summing to 1 up to f32 rounding).
    pub bary: [f32; 3],
    /// `Σ bary·vertex / Σ bary`, mm, object frame.
    pub point: V3,
    pub chart: u32,
}

/// One chart: a projection along an axis onto a rectangle of the atlas.
#[derive(Debug, Clone, PartialEq)]
pub struct Chart {
    /// 0..6: projected along +x, −x, +y, −y, +z, −z.
    pub axis: u8,
    /// The chart's rectangle in the atlas, gutter included: x, y, width, height (all 0 for a
    /// chart whose triangles cover no texel centre).
    pub rect: [u32; 4],
    /// Atlas position = axis-plane position / texel_mm + shift.
    pub shift: [i64; 2],
    /// Covered texels.
    pub texels: u32,
}

/// A boundary texel with where it lies on the surface and what it stands for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Boundary {
    pub texel: u32,
    pub chart: u32,
    /// The nearest covered texel of its own chart.
    pub source: u32,
    /// The texel's centre lifted onto the plane of `source`'s triangle, mm.
    pub point: V3,
}

#[derive(Debug, Clone, Default)]
pub struct Atlas {
    pub width: u32,
    pub height: u32,
    pub texel_mm: f64,
    pub border: u32,
    /// Row-major, `width·height`; `Some` for covered texels.
    pub texels: Vec<Option<Texel>>,
    /// Per texel: a boundary texel's inside texel; `None` elsewhere.
    pub links: Vec<Option<u32>>,
    pub charts: Vec<Chart>,
    /// Each triangle's chart (`u32::MAX`: degenerate, skipped).
    pub triangle_chart: Vec<u32>,
    /// Boundary texels, sorted by `texel`.
    pub boundary: Vec<Boundary>,
    covered_mm2: f64,
    /// Inside texels by 3D cell of side `texel_mm`.
    grid: HashMap<[i64; 3], Vec<u32>>,
}

/// A point's position in the plane of `axis`, mm; oriented so that triangles facing along the
/// axis are counter-clockwise.
fn plane(axis: u8, p: V3) -> [f64; 2] {
    let k = (axis / 2) as usize;
    let u = p[(k + 1) % 3];
    [if axis % 2 == 1 { -u } else { u }, p[(k + 2) % 3]]
}

/// The point on the plane through `a` with normal `n` that projects to `uv` along `axis`.
fn lift(axis: u8, uv: [f64; 2], a: V3, n: V3) -> V3 {
    let k = (axis / 2) as usize;
    let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
    let mut p = [0.0; 3];
    p[k1] = if axis % 2 == 1 { -uv[0] } else { uv[0] };
    p[k2] = uv[1];
    p[k] = a[k] - (n[k1] * (p[k1] - a[k1]) + n[k2] * (p[k2] - a[k2])) / n[k];
    p
}

fn orient(p: [f64; 2], q: [f64; 2], c: [f64; 2]) -> f64 {
    (q[0] - p[0]) * (c[1] - p[1]) - (q[1] - p[1]) * (c[0] - p[0])
}

/// The texel-grid cells whose centres a counter-clockwise triangle (grid units) covers, with
/// barycentrics. A shared edge is evaluated from its lower vertex index on both sides, so the
/// two values are exact negatives and a centre on it goes to exactly one triangle.
fn raster(pv: [[f64; 2]; 3], ids: [u32; 3], out: &mut Vec<([i64; 2], [f64; 3])>) {
    out.clear();
    let area2 = orient(pv[0], pv[1], pv[2]);
    if area2.is_nan() || area2 <= 1e-12 {
        return;
    }
    let lo = |d: usize| (pv[0][d].min(pv[1][d]).min(pv[2][d]) - 0.5).ceil() as i64;
    let hi = |d: usize| (pv[0][d].max(pv[1][d]).max(pv[2][d]) - 0.5).floor() as i64;
    for j in lo(1)..=hi(1) {
        'cell: for i in lo(0)..=hi(0) {
            let c = [i as f64 + 0.5, j as f64 + 0.5];
            let mut b = [0.0; 3];
            for (k, bk) in b.iter_mut().enumerate() {
                let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
                let forward = ids[k1] < ids[k2];
                let e = if forward { orient(pv[k1], pv[k2], c) } else { -orient(pv[k2], pv[k1], c) };
                if e < 0.0 || (e == 0.0 && !forward) {
                    continue 'cell;
                }
                *bk = e / area2;
            }
            out.push(([i, j], b));
        }
    }
}

/// Boxes placed left to right in rows (shelves) no wider than `shelf_width`: the atlas's
/// width and height and each box's corner.
fn shelves(sizes: &[[i64; 2]], shelf_width: i64) -> (i64, i64, Vec<[i64; 2]>) {
    let (mut x, mut y, mut row, mut width) = (0i64, 0i64, 0i64, 0i64);
    let mut places = Vec::with_capacity(sizes.len());
    for &[w, h] in sizes {
        if x + w > shelf_width && x > 0 {
            (x, y, row) = (0, y + row, 0);
        }
        places.push([x, y]);
        (x, row, width) = (x + w, row.max(h), width.max(x + w));
    }
    (width, y + row, places)
}

fn cell(p: V3, size: f64) -> [i64; 3] {
    p.map(|x| (x / size).floor() as i64)
}

impl Atlas {
    /// The atlas of `mesh` at `texel_mm` mm per texel with `border` texels of gutter. Degenerate
    /// triangles are skipped; an empty mesh, a non-positive texel size or one whose triangles'
    /// bounding boxes would span over 2²⁸ texels gives an empty atlas.
    pub fn build(mesh: &SurfaceMesh, texel_mm: f64, border: u32) -> Atlas {
        let empty = Atlas { texel_mm, border, ..Atlas::default() };
        let nt = mesh.triangles.len();
        let nv = mesh.vertices.len();
        if !(texel_mm > 0.0 && texel_mm.is_finite()) || nt == 0 {
            return empty;
        }
        // Face normals (unnormalised) and each triangle's axis; degenerate ones get none.
        let mut axis = vec![u8::MAX; nt];
        let mut visits = 0.0;
        for (t, tri) in mesh.triangles.iter().enumerate() {
            if tri.iter().any(|&i| i as usize >= nv)
                || tri[0] == tri[1]
                || tri[1] == tri[2]
                || tri[0] == tri[2]
            {
                continue;
            }
            let [a, b, c] = tri.map(|i| mesh.vertices[i as usize]);
            let n = cross(sub(b, a), sub(c, a));
            let len = norm(n);
            if !(len > 1e-12 && len.is_finite()) {
                continue;
            }
            let k = (0..3).max_by(|&i, &j| n[i].abs().total_cmp(&n[j].abs())).unwrap_or(0);
            axis[t] = 2 * k as u8 + u8::from(n[k] < 0.0);
            // The rasteriser visits the triangle's bounding box.
            let box_of = |d: usize| {
                let v = [a, b, c].map(|p| plane(axis[t], p)[d]);
                (v[0].max(v[1]).max(v[2]) - v[0].min(v[1]).min(v[2])) / texel_mm + 1.0
            };
            visits += box_of(0) * box_of(1);
        }
        if visits.is_nan() || visits > MAX_TEXELS {
            return empty;
        }
        // Edge adjacency.
        let mut edges: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (t, tri) in mesh.triangles.iter().enumerate() {
            if axis[t] != u8::MAX {
                for k in 0..3 {
                    let (a, b) = (tri[k], tri[(k + 1) % 3]);
                    edges.entry((a.min(b), a.max(b))).or_default().push(t as u32);
                }
            }
        }
        let grid_of = |t: usize| -> [[f64; 2]; 3] {
            mesh.triangles[t].map(|i| plane(axis[t], mesh.vertices[i as usize]).map(|x| x / texel_mm))
        };

        // Grow charts breadth-first over edges within one axis; a triangle whose texel centres
        // the chart already holds is refused (left for a later chart).
        let mut triangle_chart = vec![NONE; nt];
        let mut claims: Vec<(u8, Claims)> = Vec::new();
        let mut cells = Vec::new();
        let mut queue = VecDeque::new();
        for seed in 0..nt {
            if axis[seed] == u8::MAX || triangle_chart[seed] != NONE {
                continue;
            }
            let c = claims.len() as u32;
            let mut held = Claims::new();
            queue.push_back(seed);
            while let Some(t) = queue.pop_front() {
                if triangle_chart[t] != NONE {
                    continue;
                }
                raster(grid_of(t), mesh.triangles[t], &mut cells);
                if cells.iter().any(|(g, _)| held.contains_key(g)) {
                    continue;
                }
                held.extend(cells.iter().map(|&(g, b)| (g, (t as u32, b))));
                triangle_chart[t] = c;
                let tri = mesh.triangles[t];
                for k in 0..3 {
                    let (a, b) = (tri[k], tri[(k + 1) % 3]);
                    for &u in &edges[&(a.min(b), a.max(b))] {
                        let u = u as usize;
                        if triangle_chart[u] == NONE && axis[u] == axis[seed] {
                            queue.push_back(u);
                        }
                    }
                }
            }
            claims.push((axis[seed], held));
        }

        // Shelf-pack the charts' boxes (gutter included), tallest first.
        let b = border as i64;
        let boxes: Vec<Option<[i64; 4]>> = claims
            .iter()
            .map(|(_, held)| {
                let mut it = held.keys();
                let first = *it.next()?;
                Some(it.fold([first[0], first[1], first[0], first[1]], |m, g| {
                    [m[0].min(g[0]), m[1].min(g[1]), m[2].max(g[0]), m[3].max(g[1])]
                }))
            })
            .collect();
        let size = |bx: &[i64; 4]| [bx[2] - bx[0] + 1 + 2 * b, bx[3] - bx[1] + 1 + 2 * b];
        let mut order: Vec<usize> = (0..claims.len()).filter(|&c| boxes[c].is_some()).collect();
        order.sort_by_key(|&c| (std::cmp::Reverse(boxes[c].map_or(0, |bx| size(&bx)[1])), c));
        let sizes: Vec<[i64; 2]> = order.iter().filter_map(|&c| boxes[c]).map(|bx| size(&bx)).collect();
        let total: i64 = sizes.iter().map(|s| s[0] * s[1]).sum();
        let widest = sizes.iter().map(|s| s[0]).max().unwrap_or(0);
        // Few large charts pack unevenly: try shelf widths from the widest box to twice the
        // square root of the boxes' area, keeping the squarest (then smallest) atlas.
        let hi = widest.max(2 * (total as f64).sqrt().ceil() as i64);
        let step = ((hi - widest) / 64).max(1);
        let (width, height, places) = (widest..=hi)
            .step_by(step as usize)
            .map(|w| shelves(&sizes, w))
            .min_by_key(|&(w, h, _)| (w.max(h), w * h))
            .unwrap_or((0, 0, Vec::new()));
        let mut charts: Vec<Chart> = claims
            .iter()
            .map(|(a, held)| Chart { axis: *a, rect: [0; 4], shift: [0; 2], texels: held.len() as u32 })
            .collect();
        for (&c, (&[x, y], s)) in order.iter().zip(places.iter().zip(&sizes)) {
            let Some(bx) = boxes[c] else { continue };
            charts[c].rect = [x as u32, y as u32, s[0] as u32, s[1] as u32];
            charts[c].shift = [x + b - bx[0], y + b - bx[1]];
        }
        if width == 0 || height == 0 || (width * height) as f64 > MAX_TEXELS {
            return Atlas { triangle_chart, charts, ..empty };
        }

        // Covered texels.
        let (wu, n) = (width as usize, (width * height) as usize);
        let mut texels: Vec<Option<Texel>> = vec![None; n];
        let mut covered_mm2 = 0.0;
        for (c, (a, held)) in claims.iter().enumerate() {
            let k = (*a / 2) as usize;
            let sh = charts[c].shift;
            for (g, &(t, bary)) in held {
                let tri = mesh.triangles[t as usize];
                let bary = bary.map(|x| x as f32);
                let sum: f64 = bary.iter().map(|&x| x as f64).sum();
                let point = (0..3).fold([0.0; 3], |p, i| {
                    add(p, scale(mesh.vertices[tri[i] as usize], bary[i] as f64 / sum))
                });
                let i = (g[1] + sh[1]) as usize * wu + (g[0] + sh[0]) as usize;
                texels[i] = Some(Texel { triangle: t, bary, point, chart: c as u32 });
                // The surface a texel stands for: its square divided by the cosine to the axis.
                let nrm = mesh.face_normal(t as usize);
                covered_mm2 += texel_mm * texel_mm / nrm[k].abs();
            }
        }
        let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
        for (i, t) in texels.iter().enumerate() {
            if let Some(t) = t {
                grid.entry(cell(t.point, texel_mm)).or_default().push(i as u32);
            }
        }
        let mut atlas = Atlas {
            width: width as u32,
            height: height as u32,
            texel_mm,
            border,
            links: vec![None; n],
            texels,
            charts,
            triangle_chart,
            boundary: Vec::new(),
            covered_mm2,
            grid,
        };
        atlas.link_borders(mesh);
        atlas
    }

    /// Finds each chart's boundary texels by a breadth-first (8-neighbour, so Chebyshev)
    /// distance from its covered texels within its rectangle, and links them.
    fn link_borders(&mut self, mesh: &SurfaceMesh) {
        let w = self.width as usize;
        let mut boundary = Vec::new();
        for (c, chart) in self.charts.iter().enumerate() {
            let [rx, ry, rw, rh] = chart.rect.map(|v| v as usize);
            if rw == 0 || self.border == 0 {
                continue;
            }
            // Local distance and nearest covered texel (global index).
            let mut dist = vec![u32::MAX; rw * rh];
            let mut src = vec![0u32; rw * rh];
            let mut queue = VecDeque::new();
            for ly in 0..rh {
                for lx in 0..rw {
                    let i = (ry + ly) * w + rx + lx;
                    if self.texels[i].is_some() {
                        dist[ly * rw + lx] = 0;
                        src[ly * rw + lx] = i as u32;
                        queue.push_back((lx, ly));
                    }
                }
            }
            while let Some((lx, ly)) = queue.pop_front() {
                let d = dist[ly * rw + lx];
                if d >= self.border {
                    continue;
                }
                for (dx, dy) in [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                    let (nx, ny) = (lx as i64 + dx, ly as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= rw as i64 || ny >= rh as i64 {
                        continue;
                    }
                    let j = ny as usize * rw + nx as usize;
                    if dist[j] == u32::MAX {
                        dist[j] = d + 1;
                        src[j] = src[ly * rw + lx];
                        queue.push_back((nx as usize, ny as usize));
                    }
                }
            }
            for ly in 0..rh {
                for lx in 0..rw {
                    let l = ly * rw + lx;
                    if dist[l] == 0 || dist[l] == u32::MAX {
                        continue;
                    }
                    let i = ((ry + ly) * w + rx + lx) as u32;
                    let s = src[l];
                    let Some(st) = self.texels[s as usize] else { continue };
                    let tri = mesh.triangles[st.triangle as usize];
                    let a = mesh.vertices[tri[0] as usize];
                    let nrm = mesh.face_normal(st.triangle as usize);
                    let uv = [
                        ((rx + lx) as f64 + 0.5 - chart.shift[0] as f64) * self.texel_mm,
                        ((ry + ly) as f64 + 0.5 - chart.shift[1] as f64) * self.texel_mm,
                    ];
                    let point = lift(chart.axis, uv, a, nrm);
                    boundary.push(Boundary { texel: i, chart: c as u32, source: s, point });
                }
            }
        }
        let reach = 2.0 * self.texel_mm;
        for bd in &boundary {
            let mut other: Option<(f64, u32)> = None;
            let mut own: Option<(f64, u32)> = None;
            for j in self.texels_near(bd.point, reach) {
                let Some(t) = self.texels[j as usize] else { continue };
                let d = norm(sub(t.point, bd.point));
                let best = if t.chart == bd.chart { &mut own } else { &mut other };
                if best.is_none_or(|(e, _)| d < e) {
                    *best = Some((d, j));
                }
            }
            let link = other.or(own).map_or(bd.source, |(_, j)| j);
            self.links[bd.texel as usize] = Some(link);
        }
        self.boundary = boundary;
    }

    /// Inside texel `i`'s 4-neighbours (left, right, up, down): covered texels of its own chart
    /// within 2.5 texels in 3D, boundary texels replaced by their link; `None` off the atlas,
    /// unlinked or elsewhere on the surface. All `None` for a texel that is not inside.
    pub fn neighbours(&self, i: u32) -> [Option<u32>; 4] {
        let mut out = [None; 4];
        let Some(Some(t)) = self.texels.get(i as usize) else { return out };
        let (x, y) = ((i % self.width) as i64, (i / self.width) as i64);
        for (o, (dx, dy)) in out.iter_mut().zip([(-1, 0), (1, 0), (0, -1), (0, 1)]) {
            let (nx, ny) = (x + dx, y + dy);
            if nx < 0 || ny < 0 || nx >= self.width as i64 || ny >= self.height as i64 {
                continue;
            }
            let j = (ny * self.width as i64 + nx) as usize;
            *o = match self.texels[j] {
                // A fold or gap of the chart can put far surface points side by side.
                Some(u) if u.chart == t.chart && norm(sub(u.point, t.point)) <= 2.5 * self.texel_mm => {
                    Some(j as u32)
                }
                Some(_) => None,
                None => self.links[j],
            };
        }
        out
    }

    /// The inside texel that holds the surface point on `triangle` at `bary`: the texel under it
    /// in its triangle's chart, else that chart's covered texel nearest it in the atlas, else
    /// (a triangle in no chart, or a chart without texels) the inside texel nearest in 3D.
    pub fn texel_of(&self, mesh: &SurfaceMesh, triangle: u32, bary: [f64; 3]) -> Option<u32> {
        let tri = *mesh.triangles.get(triangle as usize)?;
        if tri.iter().any(|&i| i as usize >= mesh.vertices.len()) || self.texels.is_empty() {
            return None;
        }
        let sum: f64 = bary.iter().sum();
        if !(sum.is_finite() && sum != 0.0) {
            return None;
        }
        let p = (0..3).fold([0.0; 3], |p, k| add(p, scale(mesh.vertices[tri[k] as usize], bary[k] / sum)));
        let c = self.triangle_chart.get(triangle as usize).copied().unwrap_or(NONE);
        if let Some(chart) = self.charts.get(c as usize).filter(|ch| ch.texels > 0) {
            let uv = plane(chart.axis, p);
            let xy = [0, 1].map(|d| uv[d] / self.texel_mm + chart.shift[d] as f64);
            let [rx, ry, rw, rh] = chart.rect.map(|v| v as f64);
            let (x, y) = (xy[0].floor(), xy[1].floor());
            if x >= rx && y >= ry && x < rx + rw && y < ry + rh {
                let i = y as usize * self.width as usize + x as usize;
                if self.texels[i].is_some_and(|t| t.chart == c) {
                    return Some(i as u32);
                }
                if let Ok(b) = self.boundary.binary_search_by_key(&(i as u32), |b| b.texel) {
                    return Some(self.boundary[b].source);
                }
            }
            // Off the chart's gutter: scan its rectangle.
            let [rx, ry, rw, rh] = chart.rect;
            let mut best: Option<(f64, u32)> = None;
            for yy in ry..ry + rh {
                for xx in rx..rx + rw {
                    let i = yy * self.width + xx;
                    if self.texels[i as usize].is_some() {
                        let d = (xx as f64 + 0.5 - xy[0]).powi(2) + (yy as f64 + 0.5 - xy[1]).powi(2);
                        if best.is_none_or(|(e, _)| d < e) {
                            best = Some((d, i));
                        }
                    }
                }
            }
            return best.map(|(_, i)| i);
        }
        self.nearest(p)
    }

    /// The inside texel nearest `p` (object frame) in 3D.
    pub fn nearest(&self, p: V3) -> Option<u32> {
        let d = |i: &u32| self.texels[*i as usize].map_or(f64::MAX, |t| norm(sub(t.point, p)));
        let mut r = 2.0 * self.texel_mm;
        // Grow the search while it is cheaper than a scan of every texel.
        while (r / self.texel_mm).powi(3) < self.texels.len() as f64 {
            if let Some(i) = self.texels_near(p, r).into_iter().min_by(|a, b| d(a).total_cmp(&d(b))) {
                return Some(i);
            }
            r *= 2.0;
        }
        (0..self.texels.len() as u32)
            .filter(|&i| self.texels[i as usize].is_some())
            .min_by(|a, b| d(a).total_cmp(&d(b)))
    }

    /// Inside texels whose 3D point lies within `radius_mm` of `p` (object frame), in no
    /// particular order.
    pub fn texels_near(&self, p: V3, radius_mm: f64) -> Vec<u32> {
        let mut out = Vec::new();
        if self.grid.is_empty() || radius_mm.is_nan() || radius_mm < 0.0 || p.iter().any(|x| !x.is_finite()) {
            return out;
        }
        let lo = cell(sub(p, [radius_mm; 3]), self.texel_mm);
        let hi = cell(add(p, [radius_mm; 3]), self.texel_mm);
        let cells = (0..3).map(|d| (hi[d] - lo[d] + 1) as f64).product::<f64>();
        let mut take = |i: u32| {
            if self.texels[i as usize].is_some_and(|t| norm(sub(t.point, p)) <= radius_mm) {
                out.push(i);
            }
        };
        if cells > self.grid.len() as f64 {
            self.grid.values().flatten().for_each(|&i| take(i));
        } else {
            for x in lo[0]..=hi[0] {
                for y in lo[1]..=hi[1] {
                    for z in lo[2]..=hi[2] {
                        self.grid.get(&[x, y, z]).into_iter().flatten().for_each(|&i| take(i));
                    }
                }
            }
        }
        out
    }

    /// The largest ratio of the chart map's singular values over the charted triangles (texture
    /// stretch; 1 for an empty atlas).
    pub fn max_stretch(&self, mesh: &SurfaceMesh) -> f64 {
        let mut worst = 1.0f64;
        for (t, &c) in self.triangle_chart.iter().enumerate() {
            let Some(chart) = self.charts.get(c as usize) else { continue };
            let [a, b, cc] = mesh.triangles[t].map(|i| mesh.vertices[i as usize]);
            let (e1, e2) = (sub(b, a), sub(cc, a));
            // An orthonormal frame of the triangle's plane, and the edges in it and in the chart.
            let x = scale(e1, 1.0 / norm(e1));
            let n = cross(e1, e2);
            let y = cross(scale(n, 1.0 / norm(n)), x);
            let (p1, p2) = ([dot(e1, x), dot(e1, y)], [dot(e2, x), dot(e2, y)]);
            let (q1, q2) = (plane(chart.axis, e1), plane(chart.axis, e2));
            // J = Q·P⁻¹ (columns: edges).
            let det = p1[0] * p2[1] - p2[0] * p1[1];
            let inv = [[p2[1] / det, -p2[0] / det], [-p1[1] / det, p1[0] / det]];
            let j = [0, 1].map(|r| {
                let qr = [q1[r], q2[r]];
                [0, 1].map(|col| qr[0] * inv[0][col] + qr[1] * inv[1][col])
            });
            let s = j.iter().flatten().map(|v| v * v).sum::<f64>();
            let d = (j[0][0] * j[1][1] - j[0][1] * j[1][0]).abs();
            let root = (s * s - 4.0 * d * d).max(0.0).sqrt();
            let ratio = ((s + root) / (s - root)).sqrt();
            if ratio.is_finite() {
                worst = worst.max(ratio);
            }
        }
        worst
    }

    /// The surface area the inside texels stand for, mm²: each texel's `texel_mm²` divided by
    /// the cosine between its triangle's normal and its chart's axis (plain `texels·texel_mm²`
    /// is the projected area, up to √3 times smaller).
    pub fn covered_mm2(&self) -> f64 {
        self.covered_mm2
    }

    /// The continuous atlas position of `p` under `chart`'s projection (texel centres at +0.5).
    pub fn to_atlas(&self, chart: u32, p: V3) -> Option<[f64; 2]> {
        let ch = self.charts.get(chart as usize)?;
        let uv = plane(ch.axis, p);
        Some([0, 1].map(|d| uv[d] / self.texel_mm + ch.shift[d] as f64))
    }
}

#[cfg(test)]
mod tests {
    use super::super::mesh::{pebble, SurfaceMesh};
    use super::*;
    use crate::firs::mesh::Mesh;

    fn surface_area(m: &SurfaceMesh) -> f64 {
        m.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                0.5 * norm(cross(sub(b, a), sub(c, a)))
            })
            .sum()
    }

    /// Every triangle's texel centres, rasterised again in its chart, are held by it: no pixel
    /// is claimed by two triangles, and none is lost.
    fn assert_each_pixel_claimed_once(atlas: &Atlas, m: &SurfaceMesh) {
        let mut cells = Vec::new();
        let mut seen = 0usize;
        for (t, &c) in atlas.triangle_chart.iter().enumerate() {
            let Some(ch) = atlas.charts.get(c as usize) else { continue };
            let pv =
                m.triangles[t].map(|i| plane(ch.axis, m.vertices[i as usize]).map(|x| x / atlas.texel_mm));
            raster(pv, m.triangles[t], &mut cells);
            for (g, _) in &cells {
                let i = (g[1] + ch.shift[1]) as usize * atlas.width as usize + (g[0] + ch.shift[0]) as usize;
                let tx = atlas.texels[i].expect("a rasterised centre is covered");
                assert_eq!((tx.triangle, tx.chart), (t as u32, c), "pixel {i}");
                seen += 1;
            }
        }
        assert_eq!(seen, atlas.texels.iter().flatten().count());
    }

    /// An open spiral ramp of 1.5 turns (annulus 10..20 mm, 3 mm rise a turn): every normal
    /// is near +z, and the last half turn lies over the first in projection.
    fn helix() -> SurfaceMesh {
        let (nr, na) = (4usize, 90usize);
        let mut vertices = Vec::new();
        for j in 0..=na {
            let th = j as f64 / na as f64 * 3.0 * std::f64::consts::PI;
            for i in 0..=nr {
                let r = 10.0 + 10.0 * i as f64 / nr as f64;
                vertices.push([r * th.cos(), r * th.sin(), 3.0 * th / (2.0 * std::f64::consts::PI)]);
            }
        }
        let v = |i: usize, j: usize| (j * (nr + 1) + i) as u32;
        let mut triangles = Vec::new();
        for j in 0..na {
            for i in 0..nr {
                triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        SurfaceMesh::new(&Mesh { vertices, triangles })
    }

    fn egg() -> (SurfaceMesh, Atlas) {
        let m = SurfaceMesh::new(&pebble(2, [24.0, 20.0, 30.0]));
        let atlas = Atlas::build(&m, 0.5, 3);
        (m, atlas)
    }

    #[test]
    fn the_pebble_atlas_covers_its_surface_with_stretch_under_root_3() {
        let (m, atlas) = egg();
        let area = surface_area(&m);
        let covered = atlas.covered_mm2();
        assert!((covered / area - 1.0).abs() < 0.03, "covered {covered} of {area} mm²");
        let stretch = atlas.max_stretch(&m);
        assert!((1.0..=3f64.sqrt() + 1e-9).contains(&stretch), "stretch {stretch}");
        assert!(atlas.triangle_chart.iter().all(|&c| c != NONE));
        assert!(atlas.charts.len() >= 6);
        assert_eq!(atlas.texels.len(), (atlas.width * atlas.height) as usize);
        // Square-ish.
        let aspect = atlas.width.max(atlas.height) as f64 / atlas.width.min(atlas.height) as f64;
        assert!(aspect < 2.0, "{}×{}", atlas.width, atlas.height);
        assert_each_pixel_claimed_once(&atlas, &m);
    }

    #[test]
    fn texels_lie_on_their_triangles_under_their_centres_and_map_back_to_themselves() {
        let (m, atlas) = egg();
        for (i, tx) in atlas.texels.iter().enumerate() {
            let Some(tx) = tx else { continue };
            let tri = m.triangles[tx.triangle as usize];
            assert!(tx.bary.iter().all(|&b| b >= 0.0), "{:?}", tx.bary);
            let sum: f64 = tx.bary.iter().map(|&b| b as f64).sum();
            assert!((sum - 1.0).abs() < 1e-6);
            let on = (0..3)
                .fold([0.0; 3], |p, k| add(p, scale(m.vertices[tri[k] as usize], tx.bary[k] as f64 / sum)));
            assert!(norm(sub(on, tx.point)) <= 1e-9);
            // The texel centre lifted onto the triangle's plane through the chart's projection.
            let ch = &atlas.charts[tx.chart as usize];
            let (x, y) = (i as u32 % atlas.width, i as u32 / atlas.width);
            let uv = [x, y].map(|v| v as f64 + 0.5);
            let uv = [0, 1].map(|d| (uv[d] - ch.shift[d] as f64) * atlas.texel_mm);
            let back = lift(ch.axis, uv, m.vertices[tri[0] as usize], m.face_normal(tx.triangle as usize));
            assert!(norm(sub(back, tx.point)) <= 0.75 * atlas.texel_mm, "texel {i}");
            assert_eq!(atlas.texel_of(&m, tx.triangle, tx.bary.map(|b| b as f64)), Some(i as u32));
            assert!(atlas.texels_near(tx.point, 1e-9).contains(&(i as u32)));
        }
        // Every point of every triangle finds a texel of its chart within a texel or two.
        for (t, tri) in m.triangles.iter().enumerate() {
            let i = atlas.texel_of(&m, t as u32, [0.8, 0.1, 0.1]).unwrap();
            let tx = atlas.texels[i as usize].unwrap();
            assert_eq!(tx.chart, atlas.triangle_chart[t]);
            let p = add(
                scale(m.vertices[tri[0] as usize], 0.8),
                scale(add(m.vertices[tri[1] as usize], m.vertices[tri[2] as usize]), 0.1),
            );
            assert!(norm(sub(p, tx.point)) < 2.0 * atlas.texel_mm);
        }
    }

    #[test]
    fn boundary_texels_link_to_the_neighbouring_chart_where_the_surface_goes_on() {
        let (m, atlas) = egg();
        // Charts that share a mesh edge with another chart.
        let mut neighbouring = vec![false; atlas.charts.len()];
        let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
        for (t, tri) in m.triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                let c = atlas.triangle_chart[t];
                if let Some(&d) = edges.get(&(a.min(b), a.max(b))) {
                    if d != c {
                        neighbouring[c as usize] = true;
                        neighbouring[d as usize] = true;
                    }
                } else {
                    edges.insert((a.min(b), a.max(b)), c);
                }
            }
        }
        let (mut total, mut good) = (0usize, 0usize);
        for bd in &atlas.boundary {
            assert!(atlas.texels[bd.texel as usize].is_none());
            let link = atlas.links[bd.texel as usize].expect("every boundary texel is linked");
            let target = atlas.texels[link as usize].expect("links go to inside texels");
            if neighbouring[bd.chart as usize] {
                total += 1;
                if target.chart != bd.chart && norm(sub(target.point, bd.point)) <= 2.0 * atlas.texel_mm {
                    good += 1;
                }
            }
        }
        assert!(total > 1000 && good as f64 >= 0.95 * total as f64, "{good} of {total}");
        // Neighbourhoods: never a boundary texel, always near in 3D, four of them for most.
        let mut full = (0usize, 0usize);
        for (i, tx) in atlas.texels.iter().enumerate() {
            let Some(tx) = tx else { continue };
            let nb = atlas.neighbours(i as u32);
            for j in nb.iter().flatten() {
                let u = atlas.texels[*j as usize].expect("a neighbour is an inside texel");
                assert!(norm(sub(u.point, tx.point)) < 4.0 * atlas.texel_mm);
            }
            full.0 += 1;
            full.1 += usize::from(nb.iter().all(Option::is_some));
        }
        assert!(full.1 as f64 > 0.99 * full.0 as f64, "{full:?}");
        // Uncovered texels have no neighbourhood.
        let gap = atlas.texels.iter().position(Option::is_none).unwrap() as u32;
        assert_eq!(atlas.neighbours(gap), [None; 4]);
    }

    #[test]
    fn a_surface_folded_over_itself_in_projection_is_split_into_charts() {
        let m = helix();
        let atlas = Atlas::build(&m, 0.5, 2);
        let plus_z = atlas.charts.iter().filter(|c| c.axis == 4 && c.texels > 0).count();
        assert!(plus_z >= 2, "{:?}", atlas.charts);
        assert_each_pixel_claimed_once(&atlas, &m);
        let (area, covered) = (surface_area(&m), atlas.covered_mm2());
        assert!((covered / area - 1.0).abs() < 0.03, "covered {covered} of {area} mm²");
        // Each texel's point projects back into its own pixel (the two turns' texels sit in
        // different charts, not on top of each other).
        for (i, tx) in atlas.texels.iter().enumerate() {
            let Some(tx) = tx else { continue };
            let xy = atlas.to_atlas(tx.chart, tx.point).unwrap();
            assert_eq!(xy.map(|v| v.floor() as u32), [i as u32 % atlas.width, i as u32 / atlas.width]);
        }
    }

    #[test]
    fn degenerate_input_gives_an_empty_or_partial_atlas() {
        let empty = SurfaceMesh::new(&Mesh { vertices: Vec::new(), triangles: Vec::new() });
        let a = Atlas::build(&empty, 0.5, 3);
        assert_eq!((a.width, a.height, a.texels.len(), a.links.len()), (0, 0, 0, 0));
        assert_eq!(a.covered_mm2(), 0.0);
        assert_eq!(a.max_stretch(&empty), 1.0);
        assert!(a.texels_near([0.0; 3], 10.0).is_empty());
        assert_eq!(a.neighbours(0), [None; 4]);
        assert_eq!(a.texel_of(&empty, 0, [1.0, 0.0, 0.0]), None);
        // A zero-area triangle beside a real one; silly texel sizes.
        let m = SurfaceMesh::new(&Mesh {
            vertices: vec![[0.0; 3], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [8.0, 0.0, 0.0]],
            triangles: vec![[0, 1, 2], [0, 1, 3]],
        });
        let a = Atlas::build(&m, 0.5, 1);
        assert_eq!(a.triangle_chart, vec![0, NONE]);
        // 8 mm², its legs on texel edges: 36 texel centres of 32 texels' area fall inside.
        assert!((a.covered_mm2() - 8.0).abs() <= 1.0, "{}", a.covered_mm2());
        assert!(a.texel_of(&m, 1, [0.0, 0.0, 1.0]).is_some());
        for bad in [0.0, -1.0, f64::NAN, 1e-9] {
            assert!(Atlas::build(&m, bad, 1).texels.is_empty());
        }
    }
}
