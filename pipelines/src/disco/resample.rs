//! Sections 5 and 6.1: each view's per-vertex look-up computed once, then every frame resampled
//! into a column of the throughput factor matrix `F`.
//!
//! A frame's pixel at vertex `r` (bilinear) is outgoing radiance `Lo`; inverting the paper's
//! equation 1 for a beam of flux `Φ` entering at `xi`:
//! `Rd(xi, xr) = π·Lo / (Ft(η, ωo)·Ft(η, ωi)·Φ)`. The camera's gain times each laser's flux
//! comes from the white target ([`flux_scale`]). The incident point is split over the enclosing
//! triangle's vertices by barycentric weight ([`Accumulator::add`]).
//!
//! `F(r, k)` is `Rd` between the vertices themselves (what Gouraud shading interpolates). A
//! spot lands beside vertex `k`, not on it, and `Rd` falls off by tens of percent per millimetre:
//! averaging the split samples as they are measures `Rd` somewhere in `k`'s fan, biased by
//! where the few spots happened to land. So the samples are averaged in log (where the fall-off
//! is nearly linear) together with their offset from `k`, and [`Accumulator::nodal`] moves each
//! mean back to the vertex along the gradient that the neighbouring columns show.

use crate::vec3::{dot, norm, normalize, sub, V3};

use super::dipole::fresnel_transmittance;
use super::mesh::SurfaceMesh;
use super::optics::{at_hit, point_of, surface_map, turned, Hit, Pinhole};

/// Limits of what a view may contribute.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewLimits {
    /// Vertices seen more grazing than this are rejected, degrees from the normal.
    pub max_view_deg: f64,
    /// Spots entering more grazing than this are rejected (the beam's footprint and the
    /// Fresnel term are least certain there), degrees.
    pub max_incidence_deg: f64,
    /// Relative index of refraction for the Fresnel terms (the paper follows Jensen et al.: 1.3).
    pub eta: f64,
    /// A spot the camera sees within this of its beam's mirror direction may show the surface's
    /// reflection of the beam (a glint, section 5: "we also reject … all pixels that are close
    /// to a specular highlight"), degrees.
    pub glint_deg: f64,
    /// Around such a spot, pixels within this of its entry point are not data, mm (the beam's
    /// footprint: three of the paper's beam σ).
    pub glint_radius_mm: f64,
}

impl Default for ViewLimits {
    fn default() -> Self {
        ViewLimits {
            max_view_deg: 70.0,
            max_incidence_deg: 60.0,
            eta: 1.3,
            glint_deg: 20.0,
            glint_radius_mm: 3.0,
        }
    }
}

/// One vertex as a view sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VertexView {
    pub vertex: u32,
    /// Continuous pixel position.
    pub px: [f32; 2],
    /// `π / Ft(η, ωo)`: radiance → radiant exitance leaving through the boundary.
    pub factor: f32,
    /// Confidence: the cosine of the viewing angle.
    pub confidence: f32,
}

/// Everything a view (turntable angle × camera position) needs, computed once.
#[derive(Debug, Clone)]
pub struct ViewMap {
    pub camera: Pinhole,
    pub turntable_deg: f64,
    /// The object's vertices turned, world.
    pub world: Vec<V3>,
    /// The object's vertex normals turned, world (per-pixel normals without a turn each).
    pub normals: Vec<V3>,
    /// Which surface point each pixel sees.
    pub surface: Vec<Option<Hit>>,
    /// The visible vertices.
    pub vertices: Vec<VertexView>,
}

impl ViewMap {
    /// The view of `mesh` from `camera` with the turntable at `deg`: a vertex is visible when the
    /// four pixels of its bilinear look-up all see the surface within a fifth of an edge of its
    /// depth, and it faces the camera within `limits.max_view_deg`.
    pub fn new(mesh: &SurfaceMesh, camera: &Pinhole, deg: f64, limits: &ViewLimits) -> Self {
        let world = turned(mesh, deg);
        let surface = surface_map(mesh, &world, camera);
        let tol = 0.2 * mesh.mean_edge();
        let cos_max = limits.max_view_deg.to_radians().cos();
        let mut vertices = Vec::new();
        for (v, &p) in world.iter().enumerate() {
            let Some((px, _)) = camera.project(p) else { continue };
            if !seen_at(&surface, camera, px, p, tol) {
                continue;
            }
            let n = super::optics::turn(mesh.normals[v], deg);
            let cos_o = dot(n, normalize(sub(camera.eye, p)));
            if cos_o < cos_max {
                continue;
            }
            let ft = fresnel_transmittance(limits.eta, cos_o);
            vertices.push(VertexView {
                vertex: v as u32,
                px: [px[0] as f32, px[1] as f32],
                factor: (std::f64::consts::PI / ft) as f32,
                confidence: cos_o as f32,
            });
        }
        let normals = mesh.normals.iter().map(|&n| super::optics::turn(n, deg)).collect();
        ViewMap { camera: *camera, turntable_deg: deg, world, normals, surface, vertices }
    }

    /// The world point and interpolated unit normal of `hit` ([`point_of`], from the turned
    /// normals).
    pub fn point(&self, mesh: &SurfaceMesh, hit: &Hit) -> (V3, V3) {
        (at_hit(mesh, &self.world, hit), normalize(at_hit(mesh, &self.normals, hit)))
    }

    /// The beam `(origin, dir)` entering the mesh in this view ([`incidence`]), its glint
    /// radius set where this camera sees the spot within `limits.glint_deg` of the beam's
    /// mirror direction.
    pub fn incidence(
        &self,
        mesh: &SurfaceMesh,
        origin: V3,
        dir: V3,
        limits: &ViewLimits,
    ) -> Option<Incidence> {
        let mut inc = incidence(mesh, &self.world, self.turntable_deg, origin, dir, limits)?;
        if glint_angle_deg(inc.mirror, normalize(sub(self.camera.eye, inc.point))) < limits.glint_deg {
            inc.glint_mm = limits.glint_radius_mm;
        }
        Some(inc)
    }
}

/// Whether the camera sees world point `p` at its projection `px`: the four pixels of its
/// bilinear look-up all see the surface within `tol` (plus 0.1 % of the distance) of `p`'s
/// distance; `false` where they leave the image.
pub fn seen_at(surface: &[Option<Hit>], camera: &Pinhole, px: [f64; 2], p: V3, tol: f64) -> bool {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let (x0, y0) = ((px[0] - 0.5).floor(), (px[1] - 0.5).floor());
    if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= w as f64 || y0 + 1.0 >= h as f64 {
        return false;
    }
    let dist = norm(sub(p, camera.eye));
    [(0, 0), (1, 0), (0, 1), (1, 1)].iter().all(|&(dx, dy)| {
        let (x, y) = (x0 as usize + dx, y0 as usize + dy);
        // Compare along the point's own ray: the pixel's hit distance scaled to it.
        surface[y * w + x].is_some_and(|hit| (f64::from(hit.t) - dist).abs() < tol + dist * 1e-3)
    })
}

/// Bilinear look-up of a one-channel image at continuous position `(x, y)` (pixel centres at
/// +0.5); `None` outside.
pub fn bilinear(img: &[f32], w: usize, h: usize, x: f32, y: f32) -> Option<f32> {
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    if x0 < 0.0 || y0 < 0.0 || x0 as usize + 1 >= w || y0 as usize + 1 >= h {
        return None;
    }
    let (ax, ay) = (fx - x0, fy - y0);
    let i = y0 as usize * w + x0 as usize;
    let top = img[i] * (1.0 - ax) + img[i + 1] * ax;
    let bottom = img[i + w] * (1.0 - ax) + img[i + w + 1] * ax;
    Some(top * (1.0 - ay) + bottom * ay)
}

/// The noise of a frame's dark background: 1.4826 × the median absolute value of the pixels that
/// see no surface, every `stride`-th one (the room is dark while a laser is on).
pub fn background_sigma(img: &[f32], surface: &[Option<Hit>], stride: usize) -> f32 {
    let mut v: Vec<f32> = img
        .iter()
        .zip(surface)
        .step_by(stride.max(1))
        .filter(|(_, s)| s.is_none())
        .map(|(p, _)| p.abs())
        .collect();
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
    1.4826 * *m
}

/// Where the beam enters for a frame: the projector's ray cast on the turned object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Incidence {
    pub hit: Hit,
    /// World point, mm.
    pub point: V3,
    /// The same point in the object's frame.
    pub object: V3,
    /// `Ft(η, ωi)`.
    pub fresnel: f64,
    /// Angle of incidence, degrees.
    pub angle_deg: f64,
    /// The beam's mirror direction at the entry point (world, unit): where the surface
    /// reflects it.
    pub mirror: V3,
    /// Pixels within this of the entry point may hold the beam's glint and are not data, mm
    /// (0: no glint; [`ViewMap::incidence`] sets it).
    pub glint_mm: f64,
}

/// The beam `(origin, dir)` entering `mesh` turned to `deg`, if it hits within
/// `limits.max_incidence_deg`.
pub fn incidence(
    mesh: &SurfaceMesh,
    world: &[V3],
    deg: f64,
    origin: V3,
    dir: V3,
    limits: &ViewLimits,
) -> Option<Incidence> {
    let hit = super::optics::cast(mesh, world, origin, dir)?;
    let (point, n) = point_of(mesh, world, deg, &hit);
    let cos_i = -dot(n, dir);
    let angle_deg = cos_i.clamp(-1.0, 1.0).acos().to_degrees();
    let t = mesh.triangles[hit.triangle as usize];
    let object = (0..3).fold([0.0; 3], |p, j| {
        crate::vec3::add(p, crate::vec3::scale(mesh.vertices[t[j] as usize], f64::from(hit.bary[j])))
    });
    (angle_deg <= limits.max_incidence_deg).then(|| Incidence {
        hit,
        point,
        object,
        fresnel: fresnel_transmittance(limits.eta, cos_i),
        angle_deg,
        mirror: crate::vec3::add(dir, crate::vec3::scale(n, 2.0 * cos_i)),
        glint_mm: 0.0,
    })
}

/// The angle between `to_eye` and the `mirror` direction, degrees: how far from the beam's
/// specular reflection a camera looks.
pub fn glint_angle_deg(mirror: V3, to_eye: V3) -> f64 {
    crate::vec3::angle(mirror, to_eye).to_degrees()
}

/// The spot's sub-pixel peak near `expected` (within `radius` pixels): the brightest pixel, then
/// a Gaussian (three-point, in log) fit along each axis. `None` where the window holds nothing
/// above `floor` or the brightest pixel is on the window's edge (the spot is elsewhere or hidden).
pub fn spot_peak(
    img: &[f32],
    w: usize,
    h: usize,
    expected: [f64; 2],
    radius: usize,
    floor: f32,
) -> Option<[f64; 2]> {
    let (cx, cy) = (expected[0].floor() as i64, expected[1].floor() as i64);
    let r = radius as i64;
    let (x0, x1) = ((cx - r).max(1), (cx + r).min(w as i64 - 2));
    let (y0, y1) = ((cy - r).max(1), (cy + r).min(h as i64 - 2));
    let mut best: Option<(usize, usize, f32)> = None;
    for y in y0..=y1 {
        for x in x0..=x1 {
            let v = img[y as usize * w + x as usize];
            if v > floor && best.is_none_or(|b| v > b.2) {
                best = Some((x as usize, y as usize, v));
            }
        }
    }
    let (bx, by, _) = best?;
    if bx as i64 == x0 || bx as i64 == x1 || by as i64 == y0 || by as i64 == y1 {
        return None;
    }
    let at = |x: usize, y: usize| f64::from(img[y * w + x].max(1e-30)).ln();
    let fit = |a: f64, b: f64, c: f64| {
        let den = a - 2.0 * b + c;
        if den < 0.0 {
            (0.5 * (a - c) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let dx = fit(at(bx - 1, by), at(bx, by), at(bx + 1, by));
    let dy = fit(at(bx, by - 1), at(bx, by), at(bx, by + 1));
    Some([bx as f64 + 0.5 + dx, by as f64 + 0.5 + dy])
}

/// Per entry and channel: Σw, Σw·ln Rd, Σw·u, Σw·v (the spot's offset from the incident
/// vertex in its tangent plane, mm), Σw·(the noise floor in Rd units).
type Sums = [[f32; 5]; 3];

/// Running, confidence-weighted log means of `F`'s entries per channel, with their spots'
/// offsets: entry `(r, k)` (response at `r` to light entering near `k`) at `k·n + r`.
#[derive(Debug, Clone)]
pub struct Accumulator {
    pub n: usize,
    sums: Vec<Sums>,
    /// The near field's plain sums, per column `k` and slot (0: `k` itself, then `k`'s ring in
    /// order), per channel: Σw, Σw·Rd.
    near: Vec<[[f32; 2]; 3]>,
    /// Each vertex's tangent axes (object frame).
    tangents: Vec<[V3; 2]>,
}

/// Two unit axes perpendicular to `n` and to each other.
pub fn tangent_axes(n: V3) -> [V3; 2] {
    let a = if n[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let t1 = normalize(crate::vec3::cross(n, a));
    [t1, crate::vec3::cross(n, t1)]
}

/// Near-field slots per column: the vertex and up to this many less one ring neighbours.
const NEAR_SLOTS: usize = 9;

/// The near-field slot of entry `(r, k)`: 0 for `r = k`, `1 + i` for `r` the `i`-th of `k`'s ring.
fn near_slot(mesh: &SurfaceMesh, r: usize, k: usize) -> Option<usize> {
    if r == k {
        return Some(0);
    }
    mesh.rings[k].iter().position(|&(j, _)| j as usize == r).map(|i| i + 1).filter(|&s| s < NEAR_SLOTS)
}

/// An entry's mean is trusted when it is at least this many times its samples' noise floor
/// (near the floor, the floor's cut keeps only the upward noise and biases the mean).
pub const MIN_FLOOR_RATIO: f32 = 4.0;

impl Accumulator {
    /// An empty matrix for `mesh`.
    pub fn new(mesh: &SurfaceMesh) -> Self {
        let n = mesh.vertices.len();
        Accumulator {
            n,
            sums: vec![[[0.0; 5]; 3]; n * n],
            near: vec![[[0.0; 2]; 3]; n * NEAR_SLOTS],
            tangents: mesh.normals.iter().map(|&v| tangent_axes(v)).collect(),
        }
    }

    /// Adds one frame of channel `channel` (the laser's colour): each visible vertex's pixel
    /// (not within the spot's glint radius, [`Incidence::glint_mm`]), above `floor` (else it says nothing: the entry stays unobserved rather than zero),
    /// turned into `Rd` with `flux` (gain × the laser's flux) and split over the incident
    /// triangle's vertices by barycentric weight times the view's confidence. Returns the
    /// vertices that took a sample.
    #[allow(clippy::too_many_arguments)]
    pub fn add(
        &mut self,
        mesh: &SurfaceMesh,
        view: &ViewMap,
        inc: &Incidence,
        img: &[f32],
        channel: usize,
        flux: f64,
        floor: f32,
    ) -> usize {
        let (w, h) = (view.camera.width as usize, view.camera.height as usize);
        let scale = 1.0 / (inc.fresnel * flux);
        let tri = mesh.triangles[inc.hit.triangle as usize];
        let offsets: [[f32; 2]; 3] = tri.map(|k| {
            let d = sub(inc.object, mesh.vertices[k as usize]);
            let t = &self.tangents[k as usize];
            [dot(d, t[0]) as f32, dot(d, t[1]) as f32]
        });
        let mut taken = 0;
        for vv in &view.vertices {
            if inc.glint_mm > 0.0 && norm(sub(view.world[vv.vertex as usize], inc.point)) < inc.glint_mm {
                continue;
            }
            let Some(v) = bilinear(img, w, h, vv.px[0], vv.px[1]) else { continue };
            if v <= floor || floor <= 0.0 && v <= 0.0 {
                continue;
            }
            let to_rd = f64::from(vv.factor) * scale;
            let y = (f64::from(v) * to_rd).ln() as f32;
            let floor_rd = (f64::from(floor) * to_rd) as f32;
            taken += 1;
            for (j, &col) in tri.iter().enumerate() {
                let b = inc.hit.bary[j].max(0.0) * vv.confidence;
                if b <= 0.0 {
                    continue;
                }
                let e = &mut self.sums[col as usize * self.n + vv.vertex as usize][channel];
                e[0] += b;
                e[1] += b * y;
                e[2] += b * offsets[j][0];
                e[3] += b * offsets[j][1];
                e[4] += b * floor_rd;
                if let Some(slot) = near_slot(mesh, vv.vertex as usize, col as usize) {
                    let e = &mut self.near[col as usize * NEAR_SLOTS + slot][channel];
                    e[0] += b;
                    e[1] += b * (f64::from(v) * to_rd) as f32;
                }
            }
        }
        taken
    }

    /// Each entry's value at the vertices themselves: the log mean moved from its spots'
    /// weighted centroid back to vertex `k` along the gradient `g` of `ln F(r, ·)` in `k`'s
    /// tangent plane. With `rates` (a fall-off `e^(−s·d)/d²` per channel, [`super::falloff`]),
    /// `g` is the fall-off's; without, a plane fitted (weighted least squares) through the
    /// centroids of `k` and its one-ring (with fewer than three usable points, none). The beam's width
    /// taken out: a Gaussian beam of `beam_sigma_mm` measures `F·(1 + ½σ²|g|²)` to first order
    /// (the fall-off is convex). Entries seen in all three channels at [`MIN_FLOOR_RATIO`] ×
    /// their noise floor are measured; their weight is the least channel's Σw. The near field
    /// (the diagonal and each one-ring) is the plain weighted mean instead (see inside).
    pub fn nodal(
        &self,
        mesh: &SurfaceMesh,
        beam_sigma_mm: f64,
        rates: Option<[f64; 3]>,
    ) -> (Vec<[f32; 3]>, Vec<f32>) {
        use rayon::prelude::*;
        let n = self.n;
        let mean = |i: usize, c: usize| -> Option<(f64, [f64; 2], f64)> {
            let e = &self.sums[i][c];
            (e[0] > 0.0).then(|| {
                let w = f64::from(e[0]);
                (f64::from(e[1]) / w, [f64::from(e[2]) / w, f64::from(e[3]) / w], w)
            })
        };
        // The plane through k's and its ring's centroids of row r (k's tangent coordinates),
        // `own` being k's: its gradient. `pts` is room for the points, reused.
        let ring_gradient = |k: usize, r: usize, c: usize, own, pts: &mut Vec<([f64; 2], f64, f64)>| {
            let (xk, tk) = (mesh.vertices[k], &self.tangents[k]);
            pts.clear();
            pts.push(own);
            for &(j, _) in &mesh.rings[k] {
                let j = j as usize;
                if let Some((yj, uj, wj)) = mean(j * n + r, c) {
                    let tj = &self.tangents[j];
                    let p = crate::vec3::add(
                        sub(mesh.vertices[j], xk),
                        crate::vec3::add(crate::vec3::scale(tj[0], uj[0]), crate::vec3::scale(tj[1], uj[1])),
                    );
                    pts.push(([dot(p, tk[0]), dot(p, tk[1])], yj, wj));
                }
            }
            plane_gradient(pts).unwrap_or([0.0, 0.0])
        };
        let half_edge = 0.5 * mesh.mean_edge(); // a sum over every edge: once, not per entry
        let mut values: Vec<[f32; 3]> = vec![[0.0; 3]; n * n];
        let mut weights: Vec<f32> = vec![0.0; n * n];
        values.par_chunks_mut(n).zip(weights.par_chunks_mut(n)).enumerate().for_each(|(k, (vcol, wcol))| {
            let xk = mesh.vertices[k];
            let tk = &self.tangents[k];
            let mut pts = Vec::with_capacity(16);
            let mut entry = |r: usize| -> ([f32; 3], f32) {
                if let Some(ns) = near_slot(mesh, r, k) {
                    // The near field: the barycentric split's plain mean, as the paper resamples.
                    // It estimates `Rd` averaged over `k`'s hat function (blurred by the beam),
                    // which is what carries the right energy when `F` is lit by a broad light
                    // (Σk F(r, k)·Ak is then ∫ Rd(x, xr) dx); no single point value would.
                    let e = &self.near[k * NEAR_SLOTS + ns];
                    return if e.iter().all(|c| c[0] > 0.0) {
                        (e.map(|c| c[1] / c[0]), e.iter().map(|c| c[0]).fold(f32::MAX, f32::min))
                    } else {
                        ([0.0; 3], 0.0)
                    };
                }
                let mut v = [0.0f32; 3];
                let mut ok = true;
                let mut weight = f32::MAX;
                for c in 0..3 {
                    let e = &self.sums[k * n + r][c];
                    let Some((y, u, w)) = mean(k * n + r, c) else {
                        ok = false;
                        break;
                    };
                    if (y.exp() as f32) < MIN_FLOOR_RATIO * e[4] / e[0] {
                        ok = false;
                        break;
                    }
                    let g = match rates {
                        Some(rates) => {
                            let xr = mesh.vertices[r];
                            let dv = sub(xk, xr);
                            let d = norm(dv).max(half_edge);
                            let k_ = -(rates[c] + 2.0 / d) / d;
                            [k_ * dot(dv, tk[0]), k_ * dot(dv, tk[1])]
                        }
                        None => ring_gradient(k, r, c, (u, y, w), &mut pts),
                    };
                    let blur = 1.0 + 0.5 * beam_sigma_mm * beam_sigma_mm * (g[0] * g[0] + g[1] * g[1]);
                    v[c] = ((y - g[0] * u[0] - g[1] * u[1]).exp() / blur) as f32;
                    weight = weight.min(w as f32);
                }
                if ok {
                    (v, weight)
                } else {
                    ([0.0; 3], 0.0)
                }
            };
            for (r, (v, w)) in vcol.iter_mut().zip(wcol.iter_mut()).enumerate() {
                (*v, *w) = entry(r);
            }
        });
        (values, weights)
    }
}

/// The gradient of the weighted least-squares plane `y = a + g·q` through `(q, y, w)`; `None`
/// with fewer than three points or when they are (nearly) collinear.
pub fn plane_gradient(pts: &[([f64; 2], f64, f64)]) -> Option<[f64; 2]> {
    if pts.len() < 3 {
        return None;
    }
    // Weights capped relative to the largest, so one well-sampled point cannot make the others
    // irrelevant; the plane through the weighted centroid: a 2 × 2 system.
    let wmax = pts.iter().map(|p| p.2).fold(0.0, f64::max);
    let w = |p: &([f64; 2], f64, f64)| (p.2 / wmax).max(0.1);
    let sw: f64 = pts.iter().map(w).sum();
    let c = pts.iter().fold([0.0; 3], |a, p| {
        let k = w(p) / sw;
        [a[0] + k * p.0[0], a[1] + k * p.0[1], a[2] + k * p.1]
    });
    let (mut sxx, mut sxy, mut syy, mut bx, mut by) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in pts {
        let k = w(p);
        let (dx, dy, dz) = (p.0[0] - c[0], p.0[1] - c[1], p.1 - c[2]);
        sxx += k * dx * dx;
        sxy += k * dx * dy;
        syy += k * dy * dy;
        bx += k * dx * dz;
        by += k * dy * dz;
    }
    let det = sxx * syy - sxy * sxy;
    // (Nearly) collinear points leave one direction of the gradient undetermined.
    if det.is_nan() || det <= 0.05 * (sxx + syy).powi(2) {
        return None;
    }
    Some([(syy * bx - sxy * by) / det, (sxx * by - sxy * bx) / det])
}

/// A flat, white, Lambertian calibration target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WhiteTarget {
    /// A point on it, world mm.
    pub point: V3,
    /// Its unit normal, towards the camera.
    pub normal: V3,
    /// Its albedo.
    pub albedo: f64,
}

/// Section 4.4's white balance, made absolute: a laser spot on the white target reflects
/// `albedo·Φ`, so the radiance integrated over the target's area is `albedo·Φ/π`. Summing each
/// pixel's value times the area it sees on the target (within `radius_mm` of `centre`) gives
/// the camera's gain times the laser's flux, `Φ`, in pixel-value·mm² units.
pub fn flux_scale(img: &[f32], cam: &Pinhole, target: &WhiteTarget, centre: V3, radius_mm: f64) -> f64 {
    let sum: f64 =
        target_pixels(cam, target, centre, radius_mm).map(|(i, _, area)| f64::from(img[i]) * area).sum();
    std::f64::consts::PI * sum / target.albedo
}

/// The pixels that see `target` within `radius_mm` of `centre`: index, the point seen, and the
/// area the pixel covers there (its solid angle `cos³α / f²` times `t² / |cos|` on the plane).
fn target_pixels<'a>(
    cam: &'a Pinhole,
    target: &'a WhiteTarget,
    centre: V3,
    radius_mm: f64,
) -> impl Iterator<Item = (usize, V3, f64)> + 'a {
    let (w, h) = (cam.width as usize, cam.height as usize);
    (0..w * h).filter_map(move |i| {
        let d = cam.ray((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let dn = dot(d, target.normal);
        if dn.abs() < 1e-9 {
            return None;
        }
        let t = dot(sub(target.point, cam.eye), target.normal) / dn;
        let p = crate::vec3::add(cam.eye, crate::vec3::scale(d, t));
        if t <= 0.0 || norm(sub(p, centre)) > radius_mm {
            return None;
        }
        let cos_a = dot(d, cam.axes[2]);
        Some((i, p, t * t * cos_a.powi(3) / (cam.focal_px * cam.focal_px * dn.abs())))
    })
}

/// The beam's width from its spot on the white target: the σ of its cross-section (the second
/// moment of the spot's light on the target's plane, within `radius_mm` of `centre`, across
/// the beam's direction `beam`), mm. `None` if nothing is lit.
pub fn beam_sigma(
    img: &[f32],
    cam: &Pinhole,
    target: &WhiteTarget,
    beam: V3,
    centre: V3,
    radius_mm: f64,
) -> Option<f64> {
    let pts: Vec<(V3, f64)> = target_pixels(cam, target, centre, radius_mm)
        .map(|(i, p, area)| (p, f64::from(img[i]).max(0.0) * area))
        .collect();
    let sw: f64 = pts.iter().map(|p| p.1).sum();
    if sw.is_nan() || sw <= 0.0 {
        return None;
    }
    let c = pts.iter().fold([0.0; 3], |a, p| crate::vec3::add(a, crate::vec3::scale(p.0, p.1 / sw)));
    let m2: f64 = pts
        .iter()
        .map(|(p, wt)| {
            let q = sub(*p, c);
            let across = sub(q, crate::vec3::scale(beam, dot(q, beam)));
            wt * dot(across, across)
        })
        .sum::<f64>()
        / sw;
    Some((m2 / 2.0).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;
    use crate::disco::optics::Projector;

    #[test]
    fn plane_gradient_recovers_a_plane_and_refuses_a_line() {
        let pts: Vec<([f64; 2], f64, f64)> = [[0.0, 0.0], [3.0, 0.5], [-1.0, 2.0], [0.5, -3.0]]
            .iter()
            .map(|&q| (q, 1.0 + 0.2 * q[0] - 0.7 * q[1], 1.0))
            .collect();
        let g = plane_gradient(&pts).unwrap();
        assert!((g[0] - 0.2).abs() < 1e-12 && (g[1] + 0.7).abs() < 1e-12, "{g:?}");
        let line: Vec<([f64; 2], f64, f64)> =
            (0..4).map(|i| ([f64::from(i), 2.0 * f64::from(i)], 0.0, 1.0)).collect();
        assert_eq!(plane_gradient(&line), None);
        assert_eq!(plane_gradient(&pts[..2]), None);
    }

    #[test]
    fn bilinear_interpolates_between_pixel_centres() {
        let img = [0.0, 1.0, 2.0, 3.0];
        assert_eq!(bilinear(&img, 2, 2, 0.5, 0.5), Some(0.0));
        assert_eq!(bilinear(&img, 2, 2, 1.0, 0.5), Some(0.5));
        assert_eq!(bilinear(&img, 2, 2, 1.0, 1.0), Some(1.5));
        assert_eq!(bilinear(&img, 2, 2, 1.6, 1.0), None);
    }

    #[test]
    fn the_spot_peak_is_found_to_a_hundredth_of_a_pixel() {
        let (w, h) = (40, 30);
        let (sx, sy) = (17.3, 12.8);
        let img: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
                (-((x - sx).powi(2) + (y - sy).powi(2)) / (2.0 * 1.5f64.powi(2))).exp() as f32
            })
            .collect();
        let p = spot_peak(&img, w, h, [18.0, 12.0], 5, 0.01).unwrap();
        assert!((p[0] - sx).abs() < 0.01 && (p[1] - sy).abs() < 0.01, "{p:?}");
        // Nothing above the floor, or a peak outside the window: no spot.
        assert_eq!(spot_peak(&img, w, h, [18.0, 12.0], 5, 2.0), None);
        assert_eq!(spot_peak(&img, w, h, [30.0, 12.0], 4, 0.0), None);
    }

    #[test]
    fn a_uniform_target_integrates_to_its_flux() {
        // A camera square on a target 200 mm away, whose radiance albedo·Φ/(π·A) is uniform
        // over a disc of area A: the sum gives Φ back.
        let cam = Pinhole::looking(200, 200, 400.0, [0.0, -200.0, 30.0], [0.0, 0.0, 30.0]);
        let target = WhiteTarget { point: [0.0, 0.0, 30.0], normal: [0.0, -1.0, 0.0], albedo: 0.9 };
        let (phi, r) = (5.0, 20.0);
        let radiance = target.albedo * phi / (std::f64::consts::PI * std::f64::consts::PI * r * r);
        let mut img = vec![0.0f32; 200 * 200];
        for y in 0..200 {
            for x in 0..200 {
                let d = cam.ray(x as f64 + 0.5, y as f64 + 0.5);
                let t = 200.0 / d[1];
                let p = crate::vec3::add(cam.eye, crate::vec3::scale(d, t));
                if (p[0].powi(2) + (p[2] - 30.0).powi(2)).sqrt() < r {
                    img[y * 200 + x] = radiance as f32;
                }
            }
        }
        let got = flux_scale(&img, &cam, &target, [0.0, 0.0, 30.0], 30.0);
        assert!((got / phi - 1.0).abs() < 0.01, "{got}");
    }

    #[test]
    fn the_beam_width_comes_back_from_a_slanted_spot() {
        // A beam of σ 1.2 mm meets the target 40° off its normal: the footprint is stretched
        // along one axis, the σ across the beam is what comes back.
        let cam = Pinhole::looking(200, 200, 400.0, [0.0, -200.0, 30.0], [0.0, 0.0, 30.0]);
        let target = WhiteTarget { point: [0.0, 0.0, 30.0], normal: [0.0, -1.0, 0.0], albedo: 0.9 };
        let beam = normalize([40f64.to_radians().sin(), 40f64.to_radians().cos(), 0.0]);
        let centre = [0.0, 0.0, 30.0];
        let sigma = 1.2;
        let img: Vec<f32> = (0..200 * 200)
            .map(|i| {
                let d = cam.ray((i % 200) as f64 + 0.5, (i / 200) as f64 + 0.5);
                let p = crate::vec3::add(cam.eye, crate::vec3::scale(d, 200.0 / d[1]));
                let q = sub(p, centre);
                let across = sub(q, crate::vec3::scale(beam, dot(q, beam)));
                (-dot(across, across) / (2.0 * sigma * sigma)).exp() as f32
            })
            .collect();
        let got = beam_sigma(&img, &cam, &target, beam, centre, 10.0).unwrap();
        assert!((got / sigma - 1.0).abs() < 0.02, "{got}");
        assert_eq!(beam_sigma(&vec![0.0; 200 * 200], &cam, &target, beam, centre, 10.0), None);
    }

    #[test]
    fn a_views_points_are_point_of_at_its_turntable_angle() {
        let mesh = SurfaceMesh::new(&pebble(2, [20.0, 20.0, 30.0]));
        let cam = Pinhole::looking(320, 240, 500.0, [200.0, 0.0, 30.0], [0.0, 0.0, 30.0]);
        let view = ViewMap::new(&mesh, &cam, 37.0, &ViewLimits::default());
        let hits: Vec<&Hit> = view.surface.iter().flatten().collect();
        assert!(hits.len() > 1000, "{}", hits.len());
        for hit in hits {
            let (p, n) = view.point(&mesh, hit);
            let (q, m) = point_of(&mesh, &view.world, 37.0, hit);
            assert!(norm(sub(p, q)) < 1e-9 && norm(sub(n, m)) < 1e-9, "{p:?} {q:?} {n:?} {m:?}");
        }
    }

    #[test]
    fn a_frame_of_known_rd_resamples_to_it() {
        // Paint each visible vertex's pixel with the radiance an Rd of 1e-3 gives and check the
        // column comes back as 1e-3, split over the incident triangle.
        let mesh = SurfaceMesh::new(&pebble(2, [20.0, 20.0, 30.0]));
        let cam = Pinhole::looking(320, 240, 500.0, [200.0, 0.0, 30.0], [0.0, 0.0, 30.0]);
        let limits = ViewLimits::default();
        let view = ViewMap::new(&mesh, &cam, 0.0, &limits);
        assert!(view.vertices.len() > 40, "{}", view.vertices.len());
        let proj = Projector::aimed([220.0, 30.0, 35.0], [0.0, 0.0, 30.0], [32768.0, 32768.0], [1e-5, 1e-5]);
        let inc =
            incidence(&mesh, &view.world, 0.0, proj.eye, proj.ray([32768.0, 32768.0]), &limits).unwrap();
        let flux = 2.0;
        let mut img = vec![0.0f32; 320 * 240];
        // Constant Lo = Rd·Ft_o·Ft_i·Φ/π per pixel region: paint every pixel with its own
        // surface point's factor.
        for (i, s) in view.surface.iter().enumerate() {
            if let Some(hit) = s {
                let (p, n) = point_of(&mesh, &view.world, 0.0, hit);
                let cos_o = dot(n, normalize(sub(cam.eye, p)));
                let ft = fresnel_transmittance(1.3, cos_o);
                img[i] = (1e-3 * ft * inc.fresnel * flux / std::f64::consts::PI) as f32;
            }
        }
        let mut acc = Accumulator::new(&mesh);
        for c in 0..3 {
            acc.add(&mesh, &view, &inc, &img, c, flux, 0.0);
        }
        let (means, weights) = acc.nodal(&mesh, 0.0, None);
        let tri = mesh.triangles[inc.hit.triangle as usize];
        let mut n = 0;
        for &k in &tri {
            for vv in &view.vertices {
                let i = k as usize * mesh.vertices.len() + vv.vertex as usize;
                if weights[i] > 0.0 {
                    n += 1;
                    // The vertex normal differs from the pixels' interpolated ones by a little.
                    assert!((means[i][1] / 1e-3 - 1.0).abs() < 0.03, "{:?}", means[i]);
                }
            }
        }
        assert!(n > 40);
    }

    /// A camera near the beam's mirror direction (11° here) may see the surface reflect the
    /// beam: the vertices within the glint radius of the entry point take no sample from the
    /// frame, the others do; a camera over 40° off sees no glint.
    #[test]
    fn a_spot_seen_near_its_mirror_direction_leaves_its_glint_out() {
        let mesh = SurfaceMesh::new(&pebble(3, [20.0, 20.0, 30.0]));
        let limits = ViewLimits::default();
        let proj = Projector::aimed([220.0, 30.0, 35.0], [0.0, 0.0, 30.0], [32768.0, 32768.0], [1e-5, 1e-5]);
        let dir = proj.ray([32768.0, 32768.0]);
        let mirrored = ViewMap::new(
            &mesh,
            &Pinhole::looking(320, 240, 500.0, [200.0, 0.0, 30.0], [0.0, 0.0, 30.0]),
            0.0,
            &limits,
        );
        let inc = mirrored.incidence(&mesh, proj.eye, dir, &limits).unwrap();
        let to_eye = normalize(sub(mirrored.camera.eye, inc.point));
        let a = glint_angle_deg(inc.mirror, to_eye);
        assert!(a > 8.0 && a < 14.0 && inc.glint_mm == limits.glint_radius_mm, "{a}° {}", inc.glint_mm);
        // The mirror direction is the beam reflected: equal angles either side of the normal.
        let (_, n) = point_of(&mesh, &mirrored.world, 0.0, &inc.hit);
        assert!((dot(inc.mirror, n) + dot(dir, n)).abs() < 1e-12 && (norm(inc.mirror) - 1.0).abs() < 1e-12);
        let plain = incidence(&mesh, &mirrored.world, 0.0, proj.eye, dir, &limits).unwrap();
        assert_eq!(plain.glint_mm, 0.0);
        let img = vec![1.0f32; 320 * 240];
        let taken = |inc: &Incidence| {
            let mut acc = Accumulator::new(&mesh);
            acc.add(&mesh, &mirrored, inc, &img, 0, 1.0, 0.5);
            let k = mesh.triangles[inc.hit.triangle as usize][0] as usize;
            let n = mesh.vertices.len();
            (0..n).filter(|&v| acc.sums[k * n + v][0][0] > 0.0).collect::<Vec<usize>>()
        };
        let (all, kept) = (taken(&plain), taken(&inc));
        let near: Vec<usize> =
            all.iter().copied().filter(|&v| norm(sub(mirrored.world[v], inc.point)) < inc.glint_mm).collect();
        assert!(
            near.len() >= 3 && kept.len() + near.len() == all.len(),
            "{} {} {}",
            all.len(),
            kept.len(),
            near.len()
        );
        assert!(kept.iter().all(|v| !near.contains(v)));
        let aside = ViewMap::new(
            &mesh,
            &Pinhole::looking(320, 240, 500.0, [150.0, 150.0, 30.0], [0.0, 0.0, 30.0]),
            0.0,
            &limits,
        );
        let inc = aside.incidence(&mesh, proj.eye, dir, &limits).unwrap();
        let a = glint_angle_deg(inc.mirror, normalize(sub(aside.camera.eye, inc.point)));
        assert!(a > 40.0 && inc.glint_mm == 0.0, "{a}°");
    }
}
