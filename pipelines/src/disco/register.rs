//! Silhouette registration (section 4.4, after Lensch et al. 2001): the object's pose on the
//! turntable from the registration frames, one per view, taken with the spotlights lighting the
//! whole object. A translucent object shows few features, but light carried under its surface
//! makes it glow out to its outline, so its silhouette is easy to find. The scanned mesh's
//! silhouette, projected at a candidate pose into every registration view, is compared with the
//! frames' silhouettes; a downhill simplex over the pose's six parameters minimises the mismatch.
//!
//! Two stages. First the mismatch, on the views at a quarter of their resolution: the pixels
//! where the two silhouettes disagree, each weighted by one plus its distance to the frame's
//! outline, so a pose far off still feels which way to go. A pixel count moves in steps,
//! though, and stalls a pixel or so short; so then, at full resolution, the mesh's
//! contour (its edges between a triangle facing the camera and one facing away, sampled every
//! half pixel) is drawn onto the frame's outline: the mean squared signed distance from the
//! contour to the outline (interpolated between pixel centres, so it moves smoothly with the
//! pose; capped at 2 pixels, so a hidden fold of the contour cannot pull) is minimised the same
//! way. Thousands of contour points over several views place the mesh to a fraction of a pixel.

use lightrig_imaging::calib::{rodrigues, rodrigues_inv};
use rayon::prelude::*;

use super::hull;
use super::optics::{turn, Pinhole};
use crate::firs::mesh::Mesh;
use crate::vec3::{add, norm, scale, sub, V3};

/// A rigid placement: `p ↦ R(rotation)·p + translation` (rotation vector in rad, mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: V3,
    pub translation: V3,
}

impl Pose {
    pub const IDENTITY: Pose = Pose { rotation: [0.0; 3], translation: [0.0; 3] };

    /// The rotation matrix.
    pub fn matrix(&self) -> [[f64; 3]; 3] {
        rodrigues(self.rotation)
    }

    /// A direction turned by the rotation.
    pub fn rotate(&self, d: V3) -> V3 {
        let m = self.matrix();
        [0, 1, 2].map(|i| m[i][0] * d[0] + m[i][1] * d[1] + m[i][2] * d[2])
    }

    /// A point placed.
    pub fn apply(&self, p: V3) -> V3 {
        add(self.rotate(p), self.translation)
    }

    /// The pose undoing this one.
    pub fn inverse(&self) -> Pose {
        let inv = Pose { rotation: scale(self.rotation, -1.0), translation: [0.0; 3] };
        Pose { translation: scale(inv.rotate(self.translation), -1.0), ..inv }
    }

    /// This pose, then `next`.
    pub fn then(&self, next: &Pose) -> Pose {
        let (a, b) = (self.matrix(), next.matrix());
        let mut m = [[0.0; 3]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = (0..3).map(|k| b[i][k] * a[k][j]).sum();
            }
        }
        Pose { rotation: rodrigues_inv(&m), translation: next.apply(self.translation) }
    }

    /// The rotation's angle, degrees.
    pub fn angle_deg(&self) -> f64 {
        norm(self.rotation).to_degrees()
    }

    /// `mesh` placed (same vertex order).
    pub fn place(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: mesh.vertices.iter().map(|&v| self.apply(v)).collect(),
            triangles: mesh.triangles.clone(),
        }
    }
}

/// The farthest any of `points` lands between placements `a` and `b`, mm.
pub fn max_displacement(a: &Pose, b: &Pose, points: &[V3]) -> f64 {
    points.iter().map(|&p| norm(sub(a.apply(p), b.apply(p)))).fold(0.0, f64::max)
}

/// The silhouette in a registration frame (row-major, `width` wide): pixels brighter than the
/// background by `sigmas` of its noise. The background is read from the frame's border,
/// `border` pixels wide, which the object must not touch: its median and robust σ (1.4826 ×
/// the median absolute deviation). `None` when nothing stands out, or when over half the
/// border would count as object (the border is not background).
pub fn silhouette(img: &[f32], width: usize, border: usize, sigmas: f32) -> Option<Vec<bool>> {
    let height = img.len() / width.max(1);
    if width <= 2 * border || height <= 2 * border {
        return None;
    }
    let mut edge: Vec<f32> = Vec::with_capacity(2 * border * (width + height));
    for y in 0..height {
        for x in 0..width {
            if x < border || y < border || x >= width - border || y >= height - border {
                edge.push(img[y * width + x]);
            }
        }
    }
    let median = |v: &mut Vec<f32>| {
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f32::total_cmp).1
    };
    let bg = median(&mut edge);
    let mut dev: Vec<f32> = edge.iter().map(|&v| (v - bg).abs()).collect();
    let sigma = 1.4826 * median(&mut dev);
    let threshold = bg + sigmas * sigma.max(f32::MIN_POSITIVE);
    let above = edge.iter().filter(|&&v| v > threshold).count();
    let mask: Vec<bool> = img.iter().map(|&v| v > threshold).collect();
    (2 * above <= edge.len() && mask.contains(&true)).then_some(mask)
}

/// Pixels (centres at +0.5, row-major) covered by any triangle of the surface with vertices
/// `world`, as `cam` sees it: the mesh's silhouette, written into `out`.
pub fn mask_of(world: &[V3], triangles: &[[u32; 3]], cam: &Pinhole, out: &mut Vec<bool>) {
    let (w, h) = (cam.width as usize, cam.height as usize);
    out.clear();
    out.resize(w * h, false);
    let px: Vec<Option<[f64; 2]>> = world.iter().map(|&p| cam.project(p).map(|(q, _)| q)).collect();
    for t in triangles {
        let (Some(a), Some(b), Some(c)) = (px[t[0] as usize], px[t[1] as usize], px[t[2] as usize]) else {
            continue;
        };
        let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if area == 0.0 {
            continue;
        }
        let s = area.signum();
        let x0 = (a[0].min(b[0]).min(c[0]) - 0.5).ceil().max(0.0) as usize;
        let y0 = (a[1].min(b[1]).min(c[1]) - 0.5).ceil().max(0.0) as usize;
        let x1 = ((a[0].max(b[0]).max(c[0]) - 0.5).floor() + 1.0).clamp(0.0, w as f64) as usize;
        let y1 = ((a[1].max(b[1]).max(c[1]) - 0.5).floor() + 1.0).clamp(0.0, h as f64) as usize;
        let edge = |p: [f64; 2], q: [f64; 2], x: f64, y: f64| {
            s * ((q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0]))
        };
        for y in y0..y1 {
            let yc = y as f64 + 0.5;
            for x in x0..x1 {
                let xc = x as f64 + 0.5;
                if edge(a, b, xc, yc) >= 0.0 && edge(b, c, xc, yc) >= 0.0 && edge(c, a, xc, yc) >= 0.0 {
                    out[y * w + x] = true;
                }
            }
        }
    }
}

/// Each pixel's distance (pixels, chamfer 1 / √2) to the nearest pixel of the other class.
pub fn outline_distance(mask: &[bool], width: usize) -> Vec<f32> {
    let height = mask.len() / width.max(1);
    let far = (width + height) as f32;
    let pass = |target: bool| -> Vec<f32> {
        let mut d: Vec<f32> = mask.iter().map(|&m| if m == target { 0.0 } else { far }).collect();
        let s2 = std::f32::consts::SQRT_2;
        for y in 0..height {
            for x in 0..width {
                let i = y * width + x;
                let mut v = d[i];
                if x > 0 {
                    v = v.min(d[i - 1] + 1.0);
                }
                if y > 0 {
                    v = v.min(d[i - width] + 1.0);
                    if x > 0 {
                        v = v.min(d[i - width - 1] + s2);
                    }
                    if x + 1 < width {
                        v = v.min(d[i - width + 1] + s2);
                    }
                }
                d[i] = v;
            }
        }
        for y in (0..height).rev() {
            for x in (0..width).rev() {
                let i = y * width + x;
                let mut v = d[i];
                if x + 1 < width {
                    v = v.min(d[i + 1] + 1.0);
                }
                if y + 1 < height {
                    v = v.min(d[i + width] + 1.0);
                    if x + 1 < width {
                        v = v.min(d[i + width + 1] + s2);
                    }
                    if x > 0 {
                        v = v.min(d[i + width - 1] + s2);
                    }
                }
                d[i] = v;
            }
        }
        d
    };
    let (to_in, to_out) = (pass(true), pass(false));
    to_in.iter().zip(&to_out).map(|(a, b)| a + b).collect()
}

/// One registration view: its camera, the turntable's angle, the frame's silhouette.
#[derive(Debug, Clone)]
pub struct SilhouetteView {
    pub camera: Pinhole,
    pub turntable_deg: f64,
    pub mask: Vec<bool>,
    /// Signed distance to the outline (pixels; positive inside), zero between the last pixel
    /// in and the first out: `|signed| + 0.5` is the distance to the other class.
    signed: Vec<f32>,
}

impl SilhouetteView {
    pub fn new(camera: Pinhole, turntable_deg: f64, mask: Vec<bool>) -> Self {
        let distance = outline_distance(&mask, camera.width as usize);
        let signed = distance.iter().zip(&mask).map(|(&d, &m)| if m { d - 0.5 } else { 0.5 - d }).collect();
        SilhouetteView { camera, turntable_deg, mask, signed }
    }

    /// This view at a `k`-th of its resolution: a pixel is the object where at least half of
    /// the `k × k` pixels it covers are (the frame's last `width mod k` columns and rows
    /// dropped).
    pub fn coarse(&self, k: usize) -> SilhouetteView {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (cw, ch) = (w / k, h / k);
        let mut mask = vec![false; cw * ch];
        for (j, m) in mask.iter_mut().enumerate() {
            let (cx, cy) = (j % cw, j / cw);
            let inside: usize = (0..k)
                .map(|dy| self.mask[(cy * k + dy) * w + cx * k..][..k].iter().filter(|&&b| b).count())
                .sum();
            *m = 2 * inside >= k * k;
        }
        let kf = k as f64;
        let camera = Pinhole {
            width: cw as u32,
            height: ch as u32,
            focal_px: self.camera.focal_px / kf,
            centre: self.camera.centre.map(|c| c / kf),
            ..self.camera
        };
        SilhouetteView::new(camera, self.turntable_deg, mask)
    }

    /// The signed outline distance at continuous pixel position `(x, y)`, bilinear between the
    /// pixel centres (clamped at the frame's edge).
    fn signed_at(&self, x: f64, y: f64) -> f64 {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let fx = (x - 0.5).clamp(0.0, (w - 1) as f64);
        let fy = (y - 0.5).clamp(0.0, (h - 1) as f64);
        let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let v = |x: usize, y: usize| f64::from(self.signed[y * w + x]);
        (1.0 - ty) * ((1.0 - tx) * v(x0, y0) + tx * v(x1, y0))
            + ty * ((1.0 - tx) * v(x0, y1) + tx * v(x1, y1))
    }

    /// The mesh's contour at `pose` against the frame's outline: (Σ length·min(d², cap²), Σ
    /// length) over the contour sampled every half pixel.
    fn contour_misfit(&self, mesh: &Mesh, edges: &[([u32; 2], [u32; 2])], pose: &Pose) -> (f64, f64) {
        const CAP: f64 = 2.0;
        let px: Vec<Option<[f64; 2]>> = mesh
            .vertices
            .iter()
            .map(|&v| self.camera.project(turn(pose.apply(v), self.turntable_deg)).map(|(q, _)| q))
            .collect();
        let facing = |t: u32| -> Option<bool> {
            let tri = mesh.triangles[t as usize];
            let [a, b, c] = [px[tri[0] as usize]?, px[tri[1] as usize]?, px[tri[2] as usize]?];
            Some((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0.0)
        };
        let (mut sum, mut len) = (0.0, 0.0);
        for &(e, tris) in edges {
            let (Some(fa), Some(fb)) = (facing(tris[0]), facing(tris[1])) else { continue };
            if fa == fb {
                continue;
            }
            let (Some(a), Some(b)) = (px[e[0] as usize], px[e[1] as usize]) else { continue };
            let l = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            let k = (2.0 * l).ceil().max(1.0) as usize;
            let w = l / k as f64;
            for i in 0..k {
                let t = (i as f64 + 0.5) / k as f64;
                let d = self.signed_at(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
                sum += w * (d * d).min(CAP * CAP);
                len += w;
            }
        }
        (sum, len)
    }

    /// The mesh's silhouette with the object placed by `pose` (mesh frame → turntable frame).
    pub fn render(&self, mesh: &Mesh, pose: &Pose, out: &mut Vec<bool>) {
        render(mesh, pose, &self.camera, self.turntable_deg, out);
    }

    /// Pixels where `rendered` and the frame disagree, each weighted by 1 + its distance to the
    /// frame's outline.
    fn weighted_mismatch(&self, rendered: &[bool]) -> f64 {
        rendered
            .iter()
            .zip(&self.mask)
            .zip(&self.signed)
            .filter(|((r, m), _)| r != m)
            .map(|(_, &d)| 1.5 + f64::from(d.abs()))
            .sum()
    }

    /// How well `rendered` matches the frame's silhouette ([`agreement`]).
    pub fn agreement(&self, rendered: &[bool]) -> ViewAgreement {
        agreement(&self.mask, rendered)
    }
}

/// The mesh's silhouette as `camera` sees it with the object placed by `pose` (mesh frame →
/// turntable frame) and the turntable at `turntable_deg`, into `out`.
pub fn render(mesh: &Mesh, pose: &Pose, camera: &Pinhole, turntable_deg: f64, out: &mut Vec<bool>) {
    let world: Vec<V3> = mesh.vertices.iter().map(|&v| turn(pose.apply(v), turntable_deg)).collect();
    mask_of(&world, &mesh.triangles, camera, out);
}

/// How well two silhouettes match: (pixels in one but not the other, intersection over union).
pub fn agreement(mask: &[bool], rendered: &[bool]) -> ViewAgreement {
    let (mut both, mut either) = (0usize, 0usize);
    for (&r, &m) in rendered.iter().zip(mask) {
        both += usize::from(r && m);
        either += usize::from(r || m);
    }
    ViewAgreement {
        mismatched: either - both,
        iou: if either == 0 { 0.0 } else { both as f64 / either as f64 },
    }
}

/// A view's silhouettes compared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewAgreement {
    /// Pixels in one silhouette but not the other.
    pub mismatched: usize,
    /// Intersection over union.
    pub iou: f64,
}

/// The registration's result.
#[derive(Debug, Clone)]
pub struct Registration {
    /// Mesh frame → turntable frame.
    pub pose: Pose,
    /// Per view, at `pose`.
    pub views: Vec<ViewAgreement>,
    /// Mismatch evaluations the search took.
    pub evaluations: usize,
}

impl Registration {
    /// The worst view's intersection over union (0 without views).
    pub fn min_iou(&self) -> f64 {
        self.views.iter().map(|v| v.iou).reduce(f64::min).unwrap_or(0.0)
    }

    /// Pixels mismatched over all views.
    pub fn mismatched(&self) -> usize {
        self.views.iter().map(|v| v.mismatched).sum()
    }
}

/// The pose (mesh frame → turntable frame) whose silhouettes best match `views`, searched from
/// `guess`: a downhill simplex over the rotation (about the mesh's centroid) and the
/// translation, restarted from its best point with a smaller simplex until a restart gains
/// nothing, first on the weighted pixel mismatch, then on the contour's distance to the
/// outline (see the module's docs). The search reaches some 20° and 10 mm from the guess; the
/// result is a local optimum, so a symmetric object is registered up to its symmetry.
pub fn register(mesh: &Mesh, views: &[SilhouetteView], guess: Pose) -> Registration {
    let n = mesh.vertices.len().max(1) as f64;
    let centroid = scale(mesh.vertices.iter().fold([0.0; 3], |s, &v| add(s, v)), 1.0 / n);
    // x: rotation vector about the centroid (rad), then the centroid's move (mm).
    let pose_of = |x: &[f64; 6]| -> Pose {
        let about = Pose { rotation: [x[0], x[1], x[2]], translation: [0.0; 3] };
        let to_origin = Pose { rotation: [0.0; 3], translation: scale(centroid, -1.0) };
        let back = Pose { rotation: [0.0; 3], translation: add(centroid, [x[3], x[4], x[5]]) };
        guess.then(&to_origin).then(&about).then(&back)
    };
    let mismatch = |views: &[SilhouetteView], x: &[f64; 6]| -> f64 {
        let pose = pose_of(x);
        views
            .par_iter()
            .map_init(Vec::new, |buf, v| {
                v.render(mesh, &pose, buf);
                v.weighted_mismatch(buf)
            })
            .sum()
    };
    // The pixel mismatch only brings the pose within a pixel or so: at a quarter of the
    // resolution it does so at a sixteenth of the cost, and the contour takes it from there.
    let coarse: Vec<SilhouetteView> = views.par_iter().map(|v| v.coarse(COARSE)).collect();
    let (x, e1) =
        descend(&|x| mismatch(&coarse, x), [0.0; 6], [0.1, 0.1, 0.2, 4.0, 4.0, 4.0], 0.5 * COARSE as f64);
    let edges = contour_edges(mesh);
    let contour = |x: &[f64; 6]| -> f64 {
        let pose = pose_of(x);
        let (s, l) = views
            .par_iter()
            .map(|v| v.contour_misfit(mesh, &edges, &pose))
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        if l > 0.0 {
            s / l
        } else {
            f64::INFINITY
        }
    };
    let (x, e2) = descend(&contour, x, [0.01, 0.01, 0.01, 0.3, 0.3, 0.3], 0.01);
    let evaluations = e1 + e2;
    let pose = pose_of(&x);
    let mut buf = Vec::new();
    let agreement = views
        .iter()
        .map(|v| {
            v.render(mesh, &pose, &mut buf);
            v.agreement(&buf)
        })
        .collect();
    Registration { pose, views: agreement, evaluations }
}

/// [`register`] from `guess`; where that leaves some view's silhouettes agreeing below
/// `accept` (intersection over union) — the scan's frame too far from how the object stands —
/// again from the visual hull's guesses ([`hull::guesses`]) whose silhouettes disagree least,
/// in that order until one settles at `accept`, the best kept (fewest pixels mismatched over
/// the views). The second field says whether the hull's guesses were needed.
pub fn register_global(
    mesh: &Mesh,
    views: &[SilhouetteView],
    guess: Pose,
    accept: f64,
) -> (Registration, bool) {
    let first = register(mesh, views, guess);
    if first.min_iou() >= accept {
        return (first, false);
    }
    let hv: Vec<hull::HullView> = views
        .iter()
        .map(|v| hull::HullView { camera: &v.camera, turntable_deg: v.turntable_deg, mask: &v.mask })
        .collect();
    let mut scored: Vec<(f64, Pose)> = hull::guesses(mesh, &hv)
        .into_iter()
        .map(|p| {
            let mut buf = Vec::new();
            let cost: f64 = views
                .iter()
                .map(|v| {
                    v.render(mesh, &p, &mut buf);
                    v.weighted_mismatch(&buf)
                })
                .sum();
            (cost, p)
        })
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut best = first;
    for (_, p) in scored.into_iter().take(HULL_TRIES) {
        let r = register(mesh, views, p);
        if r.mismatched() < best.mismatched() {
            best = Registration { evaluations: best.evaluations + r.evaluations, ..r };
        } else {
            best.evaluations += r.evaluations;
        }
        if best.min_iou() >= accept {
            break;
        }
    }
    (best, true)
}

/// The mismatch stage runs on the views at this fraction of their resolution (16 times fewer
/// pixels to render and compare); the contour stage at full resolution.
const COARSE: usize = 4;

/// The hull's guesses registered from, best first by their silhouettes' mismatch, until one
/// settles at `accept` (the egg's first two are the same pose up to its symmetry; a third
/// covers a close call).
pub const HULL_TRIES: usize = 3;

/// Downhill simplex from `x0`, restarted from its best point with a third of the steps until a
/// restart gains nothing once the translation step is below `fine` mm: (best point,
/// evaluations).
fn descend(
    f: &(dyn Fn(&[f64; 6]) -> f64 + Sync),
    x0: [f64; 6],
    mut step: [f64; 6],
    fine: f64,
) -> ([f64; 6], usize) {
    let (mut x, mut best) = (x0, f(&x0));
    let mut evaluations = 1;
    for _ in 0..12 {
        let (nx, nf, e) = nelder_mead(f, x, step, 400);
        evaluations += e;
        let gained = best - nf;
        if nf < best {
            (x, best) = (nx, nf);
        }
        // Gains below 10⁻⁵ of the misfit move the mesh by thousandths of a millimetre.
        if gained <= 1e-5 * best.max(1e-12) && step[3] < fine {
            break;
        }
        step = step.map(|s| s / 3.0);
    }
    (x, evaluations)
}

/// Each edge shared by two triangles: its vertices and the two triangles.
fn contour_edges(mesh: &Mesh) -> Vec<([u32; 2], [u32; 2])> {
    let mut first: std::collections::HashMap<[u32; 2], u32> = std::collections::HashMap::new();
    let mut out = Vec::new();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let key = [a.min(b), a.max(b)];
            match first.remove(&key) {
                Some(o) => out.push((key, [o, t as u32])),
                None => {
                    first.insert(key, t as u32);
                }
            }
        }
    }
    out
}

/// Nelder–Mead downhill simplex from `x0` with initial steps `step`, at most `max_evals`
/// evaluations: (best point, its value, evaluations).
fn nelder_mead<const D: usize>(
    f: &dyn Fn(&[f64; D]) -> f64,
    x0: [f64; D],
    step: [f64; D],
    max_evals: usize,
) -> ([f64; D], f64, usize) {
    let mut pts: Vec<([f64; D], f64)> = Vec::with_capacity(D + 1);
    pts.push((x0, f(&x0)));
    for i in 0..D {
        let mut x = x0;
        x[i] += step[i];
        pts.push((x, f(&x)));
    }
    let mut evals = D + 1;
    let lerp = |a: &[f64; D], b: &[f64; D], t: f64| -> [f64; D] {
        std::array::from_fn(|i| a[i] + t * (b[i] - a[i]))
    };
    while evals < max_evals {
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        if pts[D].1 - pts[0].1 <= 1e-7 * pts[0].1.abs().max(1e-300) {
            break;
        }
        let centroid: [f64; D] =
            std::array::from_fn(|i| pts[..D].iter().map(|p| p.0[i]).sum::<f64>() / D as f64);
        let worst = pts[D];
        let reflected = lerp(&centroid, &worst.0, -1.0);
        let fr = f(&reflected);
        evals += 1;
        if fr < pts[0].1 {
            let expanded = lerp(&centroid, &worst.0, -2.0);
            let fe = f(&expanded);
            evals += 1;
            pts[D] = if fe < fr { (expanded, fe) } else { (reflected, fr) };
        } else if fr < pts[D - 1].1 {
            pts[D] = (reflected, fr);
        } else {
            let contracted =
                if fr < worst.1 { lerp(&centroid, &reflected, 0.5) } else { lerp(&centroid, &worst.0, 0.5) };
            let fc = f(&contracted);
            evals += 1;
            if fc < worst.1.min(fr) {
                pts[D] = (contracted, fc);
            } else {
                let best = pts[0].0;
                for p in pts.iter_mut().skip(1) {
                    p.0 = lerp(&best, &p.0, 0.5);
                    p.1 = f(&p.0);
                }
                evals += D;
            }
        }
    }
    pts.sort_by(|a, b| a.1.total_cmp(&b.1));
    (pts[0].0, pts[0].1, evals)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::disco::mesh::pebble;

    pub(crate) fn rig_views(mesh: &Mesh, truth: &Pose) -> Vec<SilhouetteView> {
        let cams = [
            Pinhole::looking(384, 248, 900.0, [300.0, 0.0, 90.0], [0.0, 0.0, 30.0]),
            Pinhole::looking(384, 248, 900.0, [200.0, 220.0, 150.0], [0.0, 0.0, 30.0]),
        ];
        let mut views = Vec::new();
        for cam in cams {
            for deg in [0.0, 90.0, 180.0, 270.0] {
                let probe = SilhouetteView::new(cam, deg, vec![false; 384 * 248]);
                let mut mask = Vec::new();
                probe.render(mesh, truth, &mut mask);
                views.push(SilhouetteView::new(cam, deg, mask));
            }
        }
        views
    }

    /// The egg turned by `rotation` about its middle (30 mm up) and moved by `shift`: it stays
    /// in the test cameras' frames.
    pub(crate) fn about_centre(rotation: V3, shift: V3) -> Pose {
        let c = [0.0, 0.0, 30.0];
        let turned = Pose { rotation, translation: [0.0; 3] };
        Pose { rotation, translation: add(sub(c, turned.apply(c)), shift) }
    }

    #[test]
    fn poses_compose_and_invert() {
        let a = Pose { rotation: [0.1, -0.2, 0.3], translation: [1.0, 2.0, -3.0] };
        let b = Pose { rotation: [-0.3, 0.05, 0.2], translation: [-4.0, 0.5, 2.0] };
        let p = [3.0, -1.0, 7.0];
        let ab = a.then(&b);
        assert!(norm(sub(ab.apply(p), b.apply(a.apply(p)))) < 1e-12);
        assert!(norm(sub(a.inverse().apply(a.apply(p)), p)) < 1e-12);
        assert!(max_displacement(&a.then(&a.inverse()), &Pose::IDENTITY, &[p]) < 1e-12);
    }

    #[test]
    fn the_rasterised_silhouette_is_the_surface_maps() {
        use crate::disco::mesh::SurfaceMesh;
        use crate::disco::optics::{surface_map, turned};
        let mesh = SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]));
        let cam = Pinhole::looking(384, 248, 900.0, [300.0, 0.0, 90.0], [0.0, 0.0, 30.0]);
        let world = turned(&mesh, 35.0);
        let hits = surface_map(&mesh, &world, &cam);
        let mut mask = Vec::new();
        mask_of(&world, &mesh.triangles, &cam, &mut mask);
        let differ = hits.iter().zip(&mask).filter(|(h, &m)| h.is_some() != m).count();
        let inside = mask.iter().filter(|&&m| m).count();
        // Only pixel centres on a shared edge may fall either way.
        assert!(inside > 15_000 && differ <= inside / 1000, "{differ} of {inside}");
    }

    #[test]
    fn a_coarse_view_is_the_frame_seen_by_a_camera_with_pixels_k_times_larger() {
        // A 40 × 28 frame with an 18 × 10 block in it, at offsets that split coarse pixels.
        let cam = Pinhole::looking(41, 29, 50.0, [100.0, 0.0, 0.0], [0.0; 3]);
        let mask: Vec<bool> =
            (0..41 * 29).map(|i| (6..24).contains(&(i % 41)) && (5..15).contains(&(i / 41))).collect();
        let c = SilhouetteView::new(cam, 30.0, mask).coarse(4);
        assert_eq!((c.camera.width, c.camera.height, c.turntable_deg), (10, 7, 30.0));
        for (j, &m) in c.mask.iter().enumerate() {
            let (x, y) = (j % 10, j / 10);
            // Columns 6..24 cover coarse columns 2..6 wholly and half of column 1; rows 5..15
            // cover row 2 wholly and three quarters of rows 1 and 3: column 1 is in at half
            // (row 2), out at three eighths.
            let inside = (2..6).contains(&x) && (1..4).contains(&y) || (x, y) == (1, 2);
            assert_eq!(m, inside, "({x}, {y})");
        }
        // A point lands at a k-th of its pixel position.
        let p = [3.0, -4.0, 2.5];
        let (fine, _) = cam.project(p).unwrap();
        let (coarse, _) = c.camera.project(p).unwrap();
        assert!((coarse[0] - fine[0] / 4.0).abs() < 1e-12 && (coarse[1] - fine[1] / 4.0).abs() < 1e-12);
    }

    #[test]
    fn the_outline_distance_is_zero_only_where_the_class_changes_next_door() {
        let w = 9;
        let mask: Vec<bool> =
            (0..81).map(|i| (2..7).contains(&(i % w)) && (2..7).contains(&(i / w))).collect();
        let d = outline_distance(&mask, w);
        // The centre of the 5 × 5 square is 3 steps from the outside; a corner pixel outside,
        // one diagonal step from the square.
        assert_eq!(d[4 * w + 4], 3.0);
        assert!((d[w + 1] - std::f32::consts::SQRT_2).abs() < 1e-6);
        assert_eq!(d[2 * w + 2], 1.0);
    }

    #[test]
    fn the_silhouette_is_what_stands_above_the_borders_noise() {
        let (w, h) = (40usize, 30usize);
        let mut img = vec![0.0f32; w * h];
        let mut state = 7u32;
        for (i, v) in img.iter_mut().enumerate() {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5;
            let (x, y) = (i % w, i / w);
            let inside = (10..30).contains(&x) && (8..22).contains(&y);
            *v = 1.0 + 0.1 * noise + if inside { 5.0 } else { 0.0 };
        }
        let mask = silhouette(&img, w, 3, 8.0).unwrap();
        for (i, &m) in mask.iter().enumerate() {
            let (x, y) = (i % w, i / w);
            assert_eq!(m, (10..30).contains(&x) && (8..22).contains(&y), "({x}, {y})");
        }
        // A frame with nothing in it (the spotlights dark, or the object missing) is refused.
        assert!(silhouette(&vec![1.0f32; w * h], w, 3, 8.0).is_none());
    }

    /// The egg placed 12° and 6 mm off the guess is found to within 0.03 mm at every vertex (a
    /// tenth of a pixel; 0.014 mm when written) from eight views' silhouettes.
    #[test]
    fn the_pose_is_recovered_from_the_views_silhouettes() {
        let mesh = pebble(3, [24.0, 20.0, 30.0]);
        let truth = Pose { rotation: [0.03, -0.05, 0.21], translation: [3.0, -4.0, 2.5] };
        let views = rig_views(&mesh, &truth);
        let r = register(&mesh, &views, Pose::IDENTITY);
        let err = max_displacement(&r.pose, &truth, &mesh.vertices);
        assert!(err < 0.03, "vertices up to {err} mm off; pose {:?}", r.pose);
        for v in &r.views {
            assert!(v.iou > 0.995, "{v:?}");
        }
        // Far off, some view disagrees by thousands of pixels.
        let mut buf = Vec::new();
        views[0].render(&mesh, &Pose::IDENTITY, &mut buf);
        assert!(views[0].agreement(&buf).mismatched > 2_000);
    }

    /// A scan far from how the egg stands (turned 119° about a tilted axis, 25 mm aside): the
    /// descent from its own frame stalls, the visual hull's guesses find it, up to the egg's
    /// symmetry (a half turn about its own axis).
    #[test]
    fn a_scan_far_from_upright_is_placed_from_the_visual_hull() {
        let mesh = pebble(3, [24.0, 20.0, 30.0]);
        let truth = about_centre([1.5, -1.2, 0.8], [20.0, -15.0, 0.0]);
        let views = rig_views(&mesh, &truth);
        let (plain, used) = register_global(&mesh, &views, Pose::IDENTITY, 0.95);
        assert!(used, "the descent from the scan's own frame found it");
        let half_turn = Pose { rotation: [0.0, 0.0, std::f64::consts::PI], translation: [0.0; 3] };
        let err = max_displacement(&plain.pose, &truth, &mesh.vertices).min(max_displacement(
            &plain.pose,
            &half_turn.then(&truth),
            &mesh.vertices,
        ));
        assert!(err < 0.03, "vertices up to {err} mm off; pose {:?}", plain.pose);
        assert!(plain.min_iou() > 0.995, "{:?}", plain.views);
        // Near its own frame, the hull is not consulted.
        let close = Pose { rotation: [0.03, -0.05, 0.21], translation: [3.0, -4.0, 2.5] };
        let (r, used) = register_global(&mesh, &rig_views(&mesh, &close), Pose::IDENTITY, 0.95);
        assert!(!used && max_displacement(&r.pose, &close, &mesh.vertices) < 0.03);
    }
}
