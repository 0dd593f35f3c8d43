//! Section 7: the local term on the texture atlas — per spot, the frame resampled at the atlas
//! texels around the entry point and `m(d)` fitted ([`kernel::fit`]); the fits put on the
//! texels next to each entry point, the remainder `data / m` kept as the multiplicative
//! correction texture `C`; both filled over the atlas where no spot fell (section 7.2); and a
//! texel's 7 × 7 kernel evaluated from them.
//!
//! **Choices:** the data of a spot are all texels within [`LocalParams::radius_mm`] of the
//! entry point (the paper's 8 × 8 texels; at our 0.5 mm texels those would not reach its
//! δ1 = 3 mm); the correction is kept per texel (averaged over the spots that saw it — the
//! paper's 8 × 8 textures "overlap" the same way); the parameters are filled by
//! nearest-observed propagation over the atlas's 4-neighbourhood (boundary texels through their
//! links), then smoothed with the observed texels held — the filtering framework of 6.2 with a
//! least-squares ψ.

use std::collections::VecDeque;

use super::atlas::Atlas;
use super::dipole::fresnel_transmittance;
use super::kernel::{self, Blur, Profile, Sample, Stages};
use super::mesh::SurfaceMesh;
use super::optics::turn;
use super::resample::{bilinear, Incidence, ViewMap};
use crate::vec3::{dot, norm, normalize, sub, V3};

/// The local term's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalParams {
    /// Texel pitch, mm.
    pub texel_mm: f64,
    /// Data of a spot: texels within this distance of the entry point, mm.
    pub radius_mm: f64,
    pub stages: Stages,
    /// Pixels seen more grazing than this are not data, degrees.
    pub max_view_deg: f64,
    /// Spots entering more obliquely than this are not fitted, degrees: the footprint is then
    /// an ellipse (σ × σ/cos θ) that no radial blur model matches (at 30° the axes differ by
    /// 15 %; at 45°, where the fits scattered by 30 %, by 41 %).
    pub max_incidence_deg: f64,
    /// A spot's fit is kept when its relative RMS misfit is at most this (the dipole's own fit
    /// has 8 %; spots across a boundary between media, or whose fast term ran to the largest
    /// rate the fit considers, miss it).
    pub max_misfit: f64,
    /// Kept spots of one view within this distance of each other share their rates
    /// ([`pool`]), mm; 0 fits each spot alone (the paper).
    pub pool_mm: f64,
    /// At most this many spots (the nearest) in one spot's pool.
    pub pool_max: usize,
}

impl LocalParams {
    /// Whether a spot's fit goes into the textures (see [`LocalParams::max_misfit`]).
    pub fn accepts(&self, p: &Profile) -> bool {
        p.misfit <= self.max_misfit && p.sigma[1] < 0.9 * kernel::RATES.1
    }
}

impl Default for LocalParams {
    fn default() -> Self {
        LocalParams {
            texel_mm: 0.5,
            radius_mm: 5.0,
            stages: Stages::default(),
            max_view_deg: 70.0,
            max_incidence_deg: 30.0,
            max_misfit: 0.08,
            pool_mm: 6.0,
            pool_max: 8,
        }
    }
}

/// The kernels' size in texels (the paper's 7 × 7).
pub const KERNEL: usize = 7;

/// The beam's σ as the surface sees it at `angle_deg` incidence: the footprint is σ × σ/cos θ;
/// the isotropic Gaussian with the same second moment has `σ·√((1 + 1/cos²θ)/2)`.
pub fn footprint_sigma(beam_sigma: f64, angle_deg: f64) -> f64 {
    let c = angle_deg.to_radians().cos().max(0.2);
    beam_sigma * ((1.0 + 1.0 / (c * c)) / 2.0).sqrt()
}

/// The blur a spot's data show, σ in mm: the beam's footprint ([`footprint_sigma`]) and the
/// bilinear look-up between pixels (a tent of the pixel's footprint `s` on the surface, variance
/// `s²/6` per axis; the pixel's own area is not added: the virtual camera samples at pixel
/// centres, and a real lens's blur would add to both alike).
pub fn spot_sigma(beam_sigma: f64, mesh: &SurfaceMesh, view: &ViewMap, inc: &Incidence) -> f64 {
    let beam = footprint_sigma(beam_sigma, inc.angle_deg);
    let cam = &view.camera;
    let dist = norm(sub(inc.point, cam.eye));
    let n = turn(mesh.face_normal(inc.hit.triangle as usize), view.turntable_deg);
    let cos_o = dot(n, normalize(sub(cam.eye, inc.point))).max(0.2);
    let s = dist / cam.focal_px;
    let pixel_var = s * s * (1.0 + 1.0 / (cos_o * cos_o)) / 2.0 / 6.0;
    (beam * beam + pixel_var).sqrt()
}

/// Blur tables by σ, built when first asked for: log-spaced bins 2 % apart.
pub struct Blurs {
    tables: std::sync::Mutex<std::collections::HashMap<i32, std::sync::Arc<Blur>>>,
    d_max: f64,
}

const BIN: f64 = 0.02;

impl Blurs {
    pub fn new(d_max: f64) -> Self {
        Blurs { tables: std::sync::Mutex::new(std::collections::HashMap::new()), d_max }
    }

    /// The table for a blur of `sigma` mm (within 1 %).
    pub fn at(&self, sigma: f64) -> std::sync::Arc<Blur> {
        let bin = (sigma.max(1e-3).ln() / BIN).round() as i32;
        if let Some(b) = self.tables.lock().ok().and_then(|t| t.get(&bin).cloned()) {
            return b;
        }
        let b = std::sync::Arc::new(Blur::new((f64::from(bin) * BIN).exp(), self.d_max));
        if let Ok(mut t) = self.tables.lock() {
            t.insert(bin, std::sync::Arc::clone(&b));
        }
        b
    }
}

/// One laser frame's data near its spot: `(texel, sample)`, the value as `Rd` (mm⁻²: the same
/// normalisation as `F`'s columns).
#[allow(clippy::too_many_arguments)]
pub fn spot_samples(
    mesh: &SurfaceMesh,
    atlas: &Atlas,
    view: &ViewMap,
    inc: &Incidence,
    img: &[f32],
    channel: u8,
    flux: f64,
    floor: f32,
    eta: f64,
    params: &LocalParams,
) -> Vec<(u32, Sample)> {
    let cam = &view.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let cos_max = params.max_view_deg.to_radians().cos();
    let scale = std::f64::consts::PI / (inc.fresnel * flux);
    let mut out = Vec::new();
    for t in atlas.texels_near(inc.object, params.radius_mm) {
        let Some(tx) = atlas.texels[t as usize].as_ref() else { continue };
        let p = turn(tx.point, view.turntable_deg);
        let Some((px, _)) = cam.project(p) else { continue };
        // Seen: the pixel under it looks at this part of the surface.
        let (x, y) = (px[0].floor(), px[1].floor());
        if x < 0.0 || y < 0.0 || x as usize >= w || y as usize >= h {
            continue;
        }
        let Some(hit) = view.surface[y as usize * w + x as usize] else { continue };
        let dist = norm(sub(p, cam.eye));
        if (f64::from(hit.t) - dist).abs() > atlas.texel_mm + dist * 1e-3 {
            continue;
        }
        let n = turn(mesh.face_normal(tx.triangle as usize), view.turntable_deg);
        let cos_o = dot(n, normalize(sub(cam.eye, p)));
        if cos_o < cos_max {
            continue;
        }
        let Some(v) = bilinear(img, w, h, px[0] as f32, px[1] as f32) else { continue };
        // Well above the noise: near the floor only the samples noise lifted would pass.
        if v <= super::resample::MIN_FLOOR_RATIO * floor || v <= 0.0 {
            continue;
        }
        let rd = f64::from(v) * scale / fresnel_transmittance(eta, cos_o);
        out.push((t, Sample { d: norm(sub(tx.point, inc.object)), channel, value: rd }));
    }
    out
}

/// A profile as the vector the atlas holds and fills.
pub fn to_params(p: &Profile) -> [f64; 8] {
    let e = |c: f64, s: f64| 2.0 * std::f64::consts::PI * c / (s * s);
    let (s1, s2) = (p.sigma[0], p.sigma[1]);
    [
        s1.ln(),
        s2.ln(),
        e(p.c1[0], s1),
        e(p.c1[1], s1),
        e(p.c1[2], s1),
        e(p.c2[0], s2),
        e(p.c2[1], s2),
        e(p.c2[2], s2),
    ]
}

/// [`to_params`] undone.
pub fn from_params(v: &[f64; 8]) -> Profile {
    let (s1, s2) = (v[0].exp(), v[1].exp());
    let c = |e: f64, s: f64| e * s * s / (2.0 * std::f64::consts::PI);
    Profile {
        sigma: [s1, s2],
        c1: [c(v[2], s1), c(v[3], s1), c(v[4], s1)],
        c2: [c(v[5], s2), c(v[6], s2), c(v[7], s2)],
        misfit: 0.0,
    }
}

/// One spot's fitted kernel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpotKernel {
    pub view: usize,
    pub code: [u16; 2],
    /// The entry point, object frame.
    pub point: V3,
    pub angle_deg: f64,
    /// The blur the fit took out ([`spot_sigma`]), mm.
    pub sigma_mm: f64,
    pub profile: Profile,
    /// Data points used (all channels).
    pub samples: usize,
    /// Spots whose data fixed this one's rates, itself included ([`pool`]; 1: its own fit).
    pub pooled: usize,
}

/// One spot's data for [`pool`]: its entry point, its data (divided by the detail texture),
/// the blur it shows and its own fit.
pub struct PoolSpot<'a> {
    pub point: V3,
    pub samples: &'a [Sample],
    pub blur: &'a Blur,
    pub own: Profile,
}

/// **Choice (beyond the paper):** each spot's rates fitted together with its neighbours'
/// ([`kernel::fit_shared`]: σ1, σ2 shared, each spot's own c1, c2), the spots of one view
/// within [`LocalParams::pool_mm`] of it (at most [`LocalParams::pool_max`], the nearest;
/// all of them kept spots, whose own fits passed). Alone, a spot's σ2 rests on the dozen
/// texels within δ2 through a blur as wide as the fast term, and trades off against c2 (over
/// the virtual pebble's spots, correlated 0.98: σ2 scattered by 23 % where `c2/σ2²` did by
/// 7 %). The pooled profile replaces the spot's own where it too passes
/// [`LocalParams::accepts`] (across a change of medium it does not): `(profile, spots
/// pooled)` per spot, in order.
pub fn pool(spots: &[PoolSpot], params: &LocalParams) -> Vec<(Profile, usize)> {
    use rayon::prelude::*;
    (0..spots.len())
        .into_par_iter()
        .map(|i| {
            let mut near: Vec<(f64, usize)> = spots
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(j, s)| (norm(sub(s.point, spots[i].point)), j))
                .filter(|&(d, _)| d <= params.pool_mm)
                .collect();
            near.sort_by(|a, b| a.0.total_cmp(&b.0));
            near.truncate(params.pool_max.saturating_sub(1));
            if near.is_empty() {
                return (spots[i].own, 1);
            }
            let set: Vec<(&[Sample], &Blur)> = std::iter::once(i)
                .chain(near.iter().map(|&(_, j)| j))
                .map(|j| (spots[j].samples, spots[j].blur))
                .collect();
            match kernel::fit_shared(&set, &params.stages) {
                Some(p) if params.accepts(&p[0]) => (p[0], set.len()),
                _ => (spots[i].own, 1),
            }
        })
        .collect()
}

/// What the spots leave on the atlas: the kernels' parameters on the texels next to each entry
/// point, and the correction `data / m` on every texel a spot's data reached.
#[derive(Debug, Clone)]
pub struct LocalAccumulator {
    /// Per texel: Σw·(ln σ1, ln σ2, e1 ×3, e2 ×3), Σw; `e = 2π·c/σ²`, each term's energy (what
    /// the fill averages: c2 and σ2 alone trade off against each other).
    params: Vec<([f64; 8], f64)>,
    /// Per texel and channel: Σ ln ratio, count (a geometric mean: a few spots' outliers do not
    /// carry it).
    correction: Vec<[(f64, u32); 3]>,
}

impl LocalAccumulator {
    pub fn new(atlas: &Atlas) -> Self {
        let n = atlas.texels.len();
        LocalAccumulator { params: vec![([0.0; 8], 0.0); n], correction: vec![[(0.0, 0); 3]; n] }
    }

    /// Fits a spot's data (all three channels) and records it; `None` when the fit fails.
    pub fn add(
        &mut self,
        atlas: &Atlas,
        blur: &Blur,
        samples: &[(u32, Sample)],
        point: V3,
        stages: &Stages,
    ) -> Option<Profile> {
        let data: Vec<Sample> = samples.iter().map(|s| s.1).collect();
        let p = kernel::fit(&data, blur, stages)?;
        self.record(atlas, blur, samples, point, &p);
        Some(p)
    }

    /// Records a spot fitted elsewhere (in parallel): its parameters on the texels next to the
    /// entry point (the paper's four neighbours of the peak), `data / m` on its texels.
    pub fn record(&mut self, atlas: &Atlas, blur: &Blur, samples: &[(u32, Sample)], point: V3, p: &Profile) {
        let v = [p.sigma[0].ln(), p.sigma[1].ln(), p.c1[0], p.c1[1], p.c1[2], p.c2[0], p.c2[1], p.c2[2]];
        for t in atlas.texels_near(point, atlas.texel_mm * std::f64::consts::FRAC_1_SQRT_2 + 1e-9) {
            let e = &mut self.params[t as usize];
            for (a, b) in e.0.iter_mut().zip(v) {
                *a += b;
            }
            e.1 += 1.0;
        }
        for &(t, s) in samples {
            let m = p.eval_blurred(blur, usize::from(s.channel), s.d);
            if m > 0.0 {
                let e = &mut self.correction[t as usize][usize::from(s.channel)];
                e.0 += (s.value / m).ln();
                e.1 += 1;
            }
        }
    }

    /// The filled textures (section 7.2).
    pub fn finish(&self, atlas: &Atlas) -> LocalTextures {
        let n = atlas.texels.len();
        let mut params: Vec<Option<[f64; 8]>> =
            self.params.iter().map(|(s, w)| (*w > 0.0).then(|| s.map(|x| x / w))).collect();
        let observed: Vec<bool> = params.iter().map(Option::is_some).collect();
        fill(atlas, &mut params, &observed);
        let mut corr: Vec<Option<[f64; 3]>> = self
            .correction
            .iter()
            .map(|c| (c.iter().all(|e| e.1 > 0)).then(|| c.map(|(s, k)| (s / f64::from(k)).exp())))
            .collect();
        let corr_observed: Vec<bool> = corr.iter().map(Option::is_some).collect();
        fill(atlas, &mut corr, &corr_observed);
        LocalTextures {
            params: params.into_iter().map(|p| p.map(|v| v.map(|x| x as f32))).collect(),
            correction: corr.into_iter().map(|c| c.map(|v| v.map(|x| x as f32))).collect(),
            observed,
            texels: n,
        }
    }
}

/// Fills `values` over the atlas's inside texels: each unobserved texel first takes its nearest
/// observed texel's value (breadth first over the 4-neighbourhood), then 64 sweeps average each
/// with its neighbours, observed texels held.
pub fn fill<const K: usize>(atlas: &Atlas, values: &mut [Option<[f64; K]>], observed: &[bool]) {
    let mut queue: VecDeque<u32> =
        (0..values.len() as u32).filter(|&i| values[i as usize].is_some()).collect();
    while let Some(i) = queue.pop_front() {
        let v = values[i as usize];
        for j in atlas.neighbours(i).into_iter().flatten() {
            if values[j as usize].is_none() && atlas.texels[j as usize].is_some() {
                values[j as usize] = v;
                queue.push_back(j);
            }
        }
    }
    for _ in 0..64 {
        for i in 0..values.len() {
            if observed[i] || values[i].is_none() {
                continue;
            }
            let mut sum = [0.0; K];
            let mut k = 0.0;
            for j in atlas.neighbours(i as u32).into_iter().flatten() {
                if let Some(v) = values[j as usize] {
                    for (s, x) in sum.iter_mut().zip(v) {
                        *s += x;
                    }
                    k += 1.0;
                }
            }
            if k > 0.0 {
                values[i] = Some(sum.map(|s| s / k));
            }
        }
    }
}

/// The local term on the atlas.
#[derive(Debug, Clone)]
pub struct LocalTextures {
    /// Per texel: ln σ1, ln σ2, each term's energy `2π·c/σ²` (RGB, RGB); `None` off the
    /// charts.
    pub params: Vec<Option<[f32; 8]>>,
    /// Per texel: the multiplicative correction (RGB).
    pub correction: Vec<Option<[f32; 3]>>,
    /// Texels whose parameters a spot gave (the rest are filled).
    pub observed: Vec<bool>,
    pub texels: usize,
}

impl LocalTextures {
    /// Texel `t`'s `m(d)`.
    pub fn profile(&self, t: u32) -> Option<Profile> {
        let v = self.params.get(t as usize)?.as_ref()?.map(f64::from);
        Some(Profile {
            sigma: [v[0].exp(), v[1].exp()],
            c1: [v[2], v[3], v[4]],
            c2: [v[5], v[6], v[7]],
            misfit: 0.0,
        })
    }

    /// Texel `t`'s 7 × 7 kernel (row-major, RGB): at each texel of its neighbourhood (walked on the
    /// atlas, across charts through the boundary links) `m(d)` at their 3D distance times that
    /// texel's correction, times its area (texel²) so that it multiplies irradiance. Cells off
    /// the surface are zero.
    pub fn kernel(&self, atlas: &Atlas, t: u32) -> Option<[[f32; 3]; KERNEL * KERNEL]> {
        let p = self.profile(t)?;
        let centre = atlas.texels.get(t as usize)?.as_ref()?.point;
        let h = (KERNEL / 2) as i32;
        let mut out = [[0.0f32; 3]; KERNEL * KERNEL];
        let area = atlas.texel_mm * atlas.texel_mm;
        for dy in -h..=h {
            // Walk vertically first, then horizontally (left, right, up, down = 0..4).
            let mut row = Some(t);
            for _ in 0..dy.unsigned_abs() {
                row = row.and_then(|r| atlas.neighbours(r)[if dy < 0 { 2 } else { 3 }]);
            }
            for dx in -h..=h {
                let mut cell = row;
                for _ in 0..dx.unsigned_abs() {
                    cell = cell.and_then(|r| atlas.neighbours(r)[if dx < 0 { 0 } else { 1 }]);
                }
                let Some(c) = cell else { continue };
                let Some(tx) = atlas.texels[c as usize].as_ref() else { continue };
                let d = norm(sub(tx.point, centre));
                let corr = self.correction[c as usize].unwrap_or([1.0; 3]);
                let k = ((dy + h) * KERNEL as i32 + dx + h) as usize;
                for ch in 0..3 {
                    out[k][ch] = (p.eval(ch, d) * f64::from(corr[ch]) * area) as f32;
                }
            }
        }
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;
    use crate::disco::optics::{point_of, Pinhole};
    use crate::disco::resample::{incidence, ViewLimits};

    #[test]
    fn neighbouring_spots_share_their_rates_and_distant_ones_do_not() {
        // Two media 30 mm apart, four spots each within 3 mm, 3 % noise; one spot 60 mm away.
        let blur = Blur::new(0.85, 6.0);
        let stages = Stages::default();
        let media = [
            Profile { sigma: [0.73, 3.4], c1: [0.02, 0.015, 0.01], c2: [0.3, 0.35, 0.4], misfit: 0.0 },
            Profile { sigma: [0.5, 2.2], c1: [0.03, 0.02, 0.02], c2: [0.2, 0.2, 0.25], misfit: 0.0 },
        ];
        let offsets = [[0.0, 0.0], [0.4, 0.1], [-0.3, 0.45], [0.2, -0.35]];
        let mut spots: Vec<(V3, Vec<Sample>)> = Vec::new();
        for (m, truth) in media.iter().enumerate() {
            for (i, &o) in offsets.iter().enumerate() {
                let point = [30.0 * m as f64 + i as f64, 0.5 * i as f64, 0.0];
                spots.push((point, kernel::tests::spot_data(truth, &blur, o, 0.03, (m * 4 + i) as u64 + 1)));
            }
        }
        spots.push(([90.0, 0.0, 0.0], kernel::tests::spot_data(&media[0], &blur, [0.1, 0.2], 0.03, 99)));
        let own: Vec<Profile> = spots.iter().map(|(_, d)| kernel::fit(d, &blur, &stages).unwrap()).collect();
        let input: Vec<PoolSpot> = spots
            .iter()
            .zip(&own)
            .map(|((point, d), &own)| PoolSpot { point: *point, samples: d, blur: &blur, own })
            .collect();
        let params = LocalParams::default();
        let out = pool(&input, &params);
        for (i, (p, n)) in out.iter().enumerate().take(8) {
            let truth = &media[i / 4];
            assert_eq!(*n, 4, "spot {i}");
            // One pool, one pair of rates (summed in another order from each spot).
            let first = out[i / 4 * 4].0.sigma;
            assert!((0..2).all(|k| (p.sigma[k] / first[k] - 1.0).abs() < 1e-6), "{p:?} {first:?}");
            assert!((p.sigma[0] / truth.sigma[0] - 1.0).abs() < 0.05, "spot {i}: {p:?}");
            assert!((p.sigma[1] / truth.sigma[1] - 1.0).abs() < 0.10, "spot {i}: {p:?}");
        }
        assert_eq!(out[8], (own[8], 1), "alone: its own fit");
        // Pooling off: every spot its own fit.
        let alone = pool(&input, &LocalParams { pool_mm: 0.0, ..params });
        assert!(alone.iter().zip(&own).all(|(a, o)| *a == (*o, 1)));
    }

    fn pebble_atlas() -> (SurfaceMesh, Atlas) {
        let mesh = SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]));
        let atlas = Atlas::build(&mesh, 0.5, 3);
        (mesh, atlas)
    }

    #[test]
    fn filling_reaches_every_inside_texel_and_holds_the_observed() {
        let (_, atlas) = pebble_atlas();
        let inside: Vec<usize> = (0..atlas.texels.len()).filter(|&i| atlas.texels[i].is_some()).collect();
        let mut v: Vec<Option<[f64; 1]>> = vec![None; atlas.texels.len()];
        let mut observed = vec![false; v.len()];
        // Two observed texels far apart, values 1 and 3.
        let (a, b) = (inside[0], inside[inside.len() - 1]);
        v[a] = Some([1.0]);
        v[b] = Some([3.0]);
        observed[a] = true;
        observed[b] = true;
        fill(&atlas, &mut v, &observed);
        assert_eq!((v[a], v[b]), (Some([1.0]), Some([3.0])));
        let filled = inside.iter().filter(|&&i| v[i].is_some()).count();
        assert_eq!(filled, inside.len(), "every inside texel reached through neighbours and links");
        assert!(inside.iter().all(|&i| v[i].unwrap()[0] >= 1.0 && v[i].unwrap()[0] <= 3.0));
        // Nothing off the charts.
        assert!((0..v.len()).all(|i| atlas.texels[i].is_some() || v[i].is_none()));
    }

    /// A frame of the pebble lit at `entry` whose exitant Rd is `rd(d)` (3D distance), seen by a
    /// camera with 0.1 mm pixels.
    fn frame(mesh: &SurfaceMesh, rd: &dyn Fn(f64) -> f64) -> (ViewMap, Incidence, Vec<f32>) {
        let cam = Pinhole::looking(400, 400, 3000.0, [300.0, 0.0, 30.0], [0.0, 0.0, 30.0]);
        let limits = ViewLimits::default();
        let view = ViewMap::new(mesh, &cam, 0.0, &limits);
        let inc =
            incidence(mesh, &view.world, 0.0, [300.0, 10.0, 30.0], normalize([-1.0, -0.02, 0.0]), &limits)
                .unwrap();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut img = vec![0.0f32; w * h];
        for (i, hit) in view.surface.iter().enumerate() {
            let Some(hit) = hit else { continue };
            let (p, n) = point_of(mesh, &view.world, 0.0, hit);
            let cos_o = dot(n, normalize(sub(cam.eye, p)));
            // Flux 2, through both boundaries, radiance = M·Ft_o/π.
            let m = 2.0 * inc.fresnel * rd(norm(sub(p, inc.point)));
            img[i] = (m * fresnel_transmittance(1.3, cos_o) / std::f64::consts::PI) as f32;
        }
        (view, inc, img)
    }

    #[test]
    fn a_spot_frame_resamples_to_its_rd_at_the_texels_and_fits_back() {
        let (mesh, atlas) = pebble_atlas();
        let truth = Profile { sigma: [0.7, 3.0], c1: [0.04, 0.03, 0.02], c2: [0.5, 0.6, 0.7], misfit: 0.0 };
        let mut all = Vec::new();
        let mut view_inc = None;
        for c in 0..3u8 {
            let (view, inc, img) = frame(&mesh, &|d| truth.eval(usize::from(c), d));
            let s = spot_samples(&mesh, &atlas, &view, &inc, &img, c, 2.0, 0.0, 1.3, &LocalParams::default());
            assert!(s.len() > 200, "{}", s.len());
            // Each sample is the truth at its texel to the bilinear look-up's error (0.1 mm pixels).
            let mut errs: Vec<f64> =
                s.iter().map(|(_, x)| (x.value / truth.eval(usize::from(c), x.d) - 1.0).abs()).collect();
            errs.sort_by(f64::total_cmp);
            assert!(errs[errs.len() / 2] < 0.01, "median {}", errs[errs.len() / 2]);
            all.extend(s);
            view_inc = Some(inc);
        }
        let inc = view_inc.unwrap();
        let mut acc = LocalAccumulator::new(&atlas);
        let p = acc.add(&atlas, &Blur::new(0.0, 8.0), &all, inc.object, &Stages::default()).unwrap();
        assert!((p.sigma[0] / 0.7 - 1.0).abs() < 0.03 && (p.sigma[1] / 3.0 - 1.0).abs() < 0.05, "{p:?}");
        let tex = acc.finish(&atlas);
        let near = atlas.texels_near(inc.object, 0.36);
        assert!(!near.is_empty() && near.iter().all(|&t| tex.observed[t as usize]));
        // The correction is 1 where the model is exact; every inside texel has parameters.
        let t = near[0];
        let corr = tex.correction[t as usize].unwrap();
        assert!(corr.iter().all(|&c| (c - 1.0).abs() < 0.05), "{corr:?}");
        assert!((0..atlas.texels.len()).all(|i| atlas.texels[i].is_none() || tex.params[i].is_some()));
        // The kernel: m(0)·texel² at the centre, falling off, every cell on the surface.
        let k = tex.kernel(&atlas, t).unwrap();
        let centre = k[KERNEL * KERNEL / 2];
        assert!((f64::from(centre[0]) / (p.eval(0, 0.0) * 0.25 * f64::from(corr[0])) - 1.0).abs() < 1e-4);
        assert!(k.iter().all(|c| c[0] > 0.0 && c[0] <= centre[0]));
    }

    #[test]
    fn the_footprint_widens_with_incidence() {
        assert_eq!(footprint_sigma(0.85, 0.0), 0.85);
        let s60 = footprint_sigma(0.85, 60.0);
        assert!((s60 - 0.85 * 2.5f64.sqrt()).abs() < 1e-9);
        let blurs = Blurs::new(8.0);
        assert!((blurs.at(0.85).beam / 0.85 - 1.0).abs() < 0.011);
        assert!((blurs.at(s60).beam / s60 - 1.0).abs() < 0.011);
    }
}
