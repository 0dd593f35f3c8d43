//! Section 6.3: the detail texture `T_ρ` — surface detail finer than the mesh, as a modulation
//! of the global response that no illumination changes.
//!
//! For a texel that a frame shows smoothly lit (far from the spot, every value above the
//! noise), the texel's own value `t_uv` is divided by `t_int`, the same frame interpolated from
//! the texel's triangle's three vertices; `T_ρ` is the confidence-weighted mean of the ratio
//! over all such frames. At rendering the global response is multiplied by it, so the response
//! at the vertices stays as `F` has it and everything between is modulated consistently.
//!
//! **Choices:** `t_int` interpolates in log (`Π v_i^{b_i}`), as [`super::relight::render`]
//! interpolates the response: a spot's light falls off exponentially, which linear
//! interpolation over a triangle overestimates by up to `(κh)²/8` (8 % at κ = 0.4 mm⁻¹ and
//! 1.8 mm edges) and so would bias `T_ρ` low; in log only the distance's own curvature over a
//! triangle is left, at most `κh²/(8d)` (a bias of 1-2 % high at 8 mm). "Smoothly lit" is at least [`DetailParams::min_distance_mm`] from the
//! entry point (the local kernels' domain is within 5 mm). Texels no frame showed are 1 (no
//! detail known).

use crate::vec3::{dot, norm, normalize, sub, V3};

use super::atlas::Atlas;
use super::dipole::fresnel_transmittance;
use super::mesh::SurfaceMesh;
use super::optics::turn;
use super::resample::{bilinear, seen_at, ViewMap};

/// The detail texture's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetailParams {
    /// Texels nearer the spot's entry point than this are not smoothly lit, mm.
    pub min_distance_mm: f64,
    /// The texel's and its vertices' values must be at least this many times the frame's noise
    /// floor.
    pub min_snr: f32,
    /// Texels seen more grazing than this are left out, degrees.
    pub max_view_deg: f64,
    /// Relative index of refraction, for the texel's Fresnel factor.
    pub eta: f64,
}

impl Default for DetailParams {
    fn default() -> Self {
        DetailParams { min_distance_mm: 8.0, min_snr: 4.0, max_view_deg: 70.0, eta: 1.3 }
    }
}

/// A texel as one view sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TexelView {
    pub texel: u32,
    pub px: [f32; 2],
    /// `π / Ft(η, ωo)` at the texel.
    pub factor: f32,
    /// `cos θo`.
    pub confidence: f32,
    /// The texel's triangle's vertices as indices into the view's [`ViewMap::vertices`].
    pub slots: [u32; 3],
    pub bary: [f32; 3],
}

/// The texels a view sees whose triangle's three vertices it also sees.
#[derive(Debug, Clone, Default)]
pub struct DetailView {
    pub texels: Vec<TexelView>,
}

impl DetailView {
    /// A texel is seen when the four pixels of its bilinear look-up see the surface at its depth
    /// (within a fifth of a mesh edge, as [`ViewMap::new`] has it for vertices) and it faces the
    /// camera within `params.max_view_deg`.
    pub fn new(mesh: &SurfaceMesh, atlas: &Atlas, view: &ViewMap, params: &DetailParams) -> Self {
        let cam = &view.camera;
        let mut slot = vec![u32::MAX; mesh.vertices.len()];
        for (i, v) in view.vertices.iter().enumerate() {
            slot[v.vertex as usize] = i as u32;
        }
        let tol = 0.2 * mesh.mean_edge();
        let cos_max = params.max_view_deg.to_radians().cos();
        let mut texels = Vec::new();
        for (i, t) in atlas.texels.iter().enumerate() {
            let Some(t) = t else { continue };
            let tri = mesh.triangles[t.triangle as usize];
            let slots = tri.map(|v| slot[v as usize]);
            if slots.contains(&u32::MAX) {
                continue;
            }
            let p = turn(t.point, view.turntable_deg);
            let Some((px, _)) = cam.project(p) else { continue };
            if !seen_at(&view.surface, cam, px, p, tol) {
                continue;
            }
            let n = (0..3).fold([0.0; 3], |n, k| {
                crate::vec3::add(n, crate::vec3::scale(mesh.normals[tri[k] as usize], f64::from(t.bary[k])))
            });
            let cos_o = dot(turn(normalize(n), view.turntable_deg), normalize(sub(cam.eye, p)));
            if cos_o < cos_max {
                continue;
            }
            let ft = fresnel_transmittance(params.eta, cos_o);
            texels.push(TexelView {
                texel: i as u32,
                px: [px[0] as f32, px[1] as f32],
                factor: (std::f64::consts::PI / ft) as f32,
                confidence: cos_o as f32,
                slots,
                bary: t.bary,
            });
        }
        DetailView { texels }
    }
}

/// One frame's ratios `t_uv / t_int` with their weights, for the texels it shows smoothly lit:
/// `(texel, ratio, weight)`. `entry` is the spot's entry point (object frame), `floor` the
/// frame's noise floor.
pub fn frame_ratios(
    atlas: &Atlas,
    dv: &DetailView,
    view: &ViewMap,
    img: &[f32],
    entry: V3,
    floor: f32,
    params: &DetailParams,
) -> Vec<(u32, f32, f32)> {
    let (w, h) = (view.camera.width as usize, view.camera.height as usize);
    let min = params.min_snr * floor.max(f32::MIN_POSITIVE);
    // The vertices' values in log (NaN where too dark to use).
    let logs: Vec<f32> = view
        .vertices
        .iter()
        .map(|v| match bilinear(img, w, h, v.px[0], v.px[1]) {
            Some(x) if x >= min => (x * v.factor).ln(),
            _ => f32::NAN,
        })
        .collect();
    let mut out = Vec::new();
    for tv in &dv.texels {
        let Some(t) = atlas.texels[tv.texel as usize] else { continue };
        if norm(sub(t.point, entry)) < params.min_distance_mm {
            continue;
        }
        let l = tv.slots.map(|s| logs[s as usize]);
        if l.iter().any(|x| x.is_nan()) {
            continue;
        }
        let Some(x) = bilinear(img, w, h, tv.px[0], tv.px[1]).filter(|&x| x >= min) else { continue };
        let int = (0..3).map(|k| tv.bary[k] * l[k]).sum::<f32>();
        out.push((tv.texel, (x * tv.factor).ln() - int, tv.confidence));
    }
    for o in &mut out {
        o.1 = o.1.exp();
    }
    out
}

/// The ratios summed per texel and colour.
#[derive(Debug, Clone)]
pub struct DetailAccumulator {
    sum: Vec<[f64; 3]>,
    weight: Vec<[f64; 3]>,
}

impl DetailAccumulator {
    pub fn new(atlas: &Atlas) -> Self {
        let n = atlas.texels.len();
        DetailAccumulator { sum: vec![[0.0; 3]; n], weight: vec![[0.0; 3]; n] }
    }

    /// Adds one frame's [`frame_ratios`] for colour `channel`.
    pub fn add(&mut self, channel: usize, ratios: &[(u32, f32, f32)]) {
        for &(t, r, w) in ratios {
            let (t, w) = (t as usize, f64::from(w));
            self.sum[t][channel] += w * f64::from(r);
            self.weight[t][channel] += w;
        }
    }

    /// `T_ρ` at texel `t` in colour `channel` from the frames added so far (none: no frame yet).
    pub fn current(&self, t: u32, channel: usize) -> Option<f64> {
        let (s, w) = (self.sum.get(t as usize)?, self.weight.get(t as usize)?);
        (w[channel] > 0.0).then(|| s[channel] / w[channel])
    }

    /// `T_ρ`: the weighted mean per texel and colour; 1 where no frame showed the texel.
    pub fn finish(&self) -> DetailTexture {
        let values = self
            .sum
            .iter()
            .zip(&self.weight)
            .map(|(s, w)| [0, 1, 2].map(|c| if w[c] > 0.0 { (s[c] / w[c]) as f32 } else { 1.0 }))
            .collect();
        let observed = self.weight.iter().map(|w| w.iter().all(|&x| x > 0.0)).collect();
        DetailTexture { values, observed }
    }
}

/// The detail texture `T_ρ` on the atlas.
#[derive(Debug, Clone, Default)]
pub struct DetailTexture {
    /// Per texel (the atlas's order), per colour.
    pub values: Vec<[f32; 3]>,
    /// Whether frames showed the texel in every colour.
    pub observed: Vec<bool>,
}

impl DetailTexture {
    /// `T_ρ` at the surface point on `triangle` at `bary`: bilinear between the four texels
    /// around it on its triangle's chart (a gutter texel stands for the texel its link names,
    /// where the surface goes on in the next chart; texels of other charts or off the atlas are
    /// left out), else its texel's value; 1 off the atlas.
    pub fn at(&self, atlas: &Atlas, mesh: &SurfaceMesh, triangle: u32, bary: [f64; 3]) -> [f64; 3] {
        let value = |t: u32| self.values.get(t as usize).map(|v| v.map(f64::from));
        let nearest = || atlas.texel_of(mesh, triangle, bary).and_then(value).unwrap_or([1.0; 3]);
        let Some(tri) = mesh.triangles.get(triangle as usize) else { return [1.0; 3] };
        let chart = atlas.triangle_chart.get(triangle as usize).copied().unwrap_or(u32::MAX);
        let p = (0..3).fold([0.0; 3], |p, k| {
            crate::vec3::add(p, crate::vec3::scale(mesh.vertices[tri[k] as usize], bary[k]))
        });
        let Some(xy) = atlas.to_atlas(chart, p) else { return nearest() };
        let (fx, fy) = (xy[0] - 0.5, xy[1] - 0.5);
        let (x0, y0) = (fx.floor(), fy.floor());
        let (ax, ay) = (fx - x0, fy - y0);
        let (mut sum, mut wsum) = ([0.0; 3], 0.0);
        for (dx, dy, w) in [
            (0, 0, (1.0 - ax) * (1.0 - ay)),
            (1, 0, ax * (1.0 - ay)),
            (0, 1, (1.0 - ax) * ay),
            (1, 1, ax * ay),
        ] {
            let (x, y) = (x0 as i64 + dx, y0 as i64 + dy);
            if x < 0 || y < 0 || x >= i64::from(atlas.width) || y >= i64::from(atlas.height) || w <= 0.0 {
                continue;
            }
            let j = (y * i64::from(atlas.width) + x) as usize;
            let t = match atlas.texels[j] {
                Some(t) if t.chart == chart => Some(j as u32),
                Some(_) => None,
                None => atlas.links[j],
            };
            if let Some(v) = t.and_then(value) {
                for c in 0..3 {
                    sum[c] += w * v[c];
                }
                wsum += w;
            }
        }
        if wsum > 0.0 {
            sum.map(|s| s / wsum)
        } else {
            nearest()
        }
    }
}

/// The skin at each vertex relative to its one-ring, per colour: what the local term's light
/// leaves through at the vertex (`T_ρ` is relative to the vertices' own values, so the model's
/// vertices must carry it; the local kernels' correction `C` holds it only where a spot's fit
/// was kept).
///
/// From `F`'s measured entries before they are made symmetric (`values[k·n + r]` is the light
/// leaving at `r`): for every column `k` at least `min_d` mm from `r` and measured at `r` and at
/// three or more of its ring, `ln F(r, k)` less the mean of its ring's, each first divided by the
/// fall-off `e^(−s·d)/d^p` (else the fall-off's curvature over the ring, `ρ²/4·Δ ln F`, would
/// read as detail: 10 % at 10 mm); the median over the columns. 1 with fewer than 5 columns.
pub fn vertex_detail(
    mesh: &SurfaceMesh,
    values: &[[f32; 3]],
    measured: &[bool],
    falloff: &[super::falloff::Falloff; 3],
    min_d: f64,
) -> Vec<[f32; 3]> {
    use rayon::prelude::*;
    let n = mesh.vertices.len();
    let flat = |r: usize, k: usize, c: usize| -> Option<f64> {
        let i = k * n + r;
        let v = f64::from(values[i][c]);
        let d = norm(sub(mesh.vertices[r], mesh.vertices[k]));
        (measured[i] && v > 0.0 && d >= min_d).then(|| v.ln() + falloff[c].s * d + falloff[c].p * d.ln())
    };
    (0..n)
        .into_par_iter()
        .map(|r| {
            [0, 1, 2].map(|c| {
                let mut res: Vec<f64> = (0..n)
                    .filter_map(|k| {
                        let own = flat(r, k, c)?;
                        let ring: Vec<f64> =
                            mesh.rings[r].iter().filter_map(|&(j, _)| flat(j as usize, k, c)).collect();
                        (ring.len() >= 3).then(|| own - ring.iter().sum::<f64>() / ring.len() as f64)
                    })
                    .collect();
                if res.len() < 5 {
                    return 1.0;
                }
                let mid = res.len() / 2;
                let (_, m, _) = res.select_nth_unstable_by(mid, f64::total_cmp);
                m.exp() as f32
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;
    use crate::disco::optics::Pinhole;
    use crate::disco::resample::ViewLimits;

    /// A frame of an object whose response is a smooth exponential fall-off from `entry` times a
    /// detail `skin(p)`, rendered per pixel from the surface point it sees.
    fn frame(mesh: &SurfaceMesh, view: &ViewMap, entry: V3, skin: &dyn Fn(V3) -> f64) -> Vec<f32> {
        view.surface
            .iter()
            .map(|h| {
                h.map_or(0.0, |hit| {
                    let t = mesh.triangles[hit.triangle as usize];
                    let p = (0..3).fold([0.0; 3], |p, k| {
                        crate::vec3::add(
                            p,
                            crate::vec3::scale(mesh.vertices[t[k] as usize], f64::from(hit.bary[k])),
                        )
                    });
                    ((-0.3 * norm(sub(p, entry))).exp() * skin(p)) as f32
                })
            })
            .collect()
    }

    #[test]
    fn a_vertex_darker_than_its_ring_is_found_through_the_fall_off() {
        // F(r, k) = T_r·T̄_k·e^(−0.2·d)/d², with vertex 7's skin at 0.7 and the rest 1.
        let mesh = SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]));
        let n = mesh.vertices.len();
        let skin = |v: usize| if v == 7 { 0.7 } else { 1.0 };
        let mut values = vec![[0.0f32; 3]; n * n];
        for k in 0..n {
            for r in 0..n {
                let d = norm(sub(mesh.vertices[r], mesh.vertices[k])).max(0.1);
                let f = skin(r) * skin(k) * (-0.2 * d).exp() / (d * d);
                values[k * n + r] = [f as f32; 3];
            }
        }
        let measured = vec![true; n * n];
        let falloff = [super::super::falloff::Falloff { s: 0.2, p: 2.0 }; 3];
        let d = vertex_detail(&mesh, &values, &measured, &falloff, 8.0);
        assert!((d[7][0] - 0.7).abs() < 0.005, "{:?}", d[7]);
        // Its ring sees it as one of theirs: a sixth or so of the difference, brighter.
        let j = mesh.rings[7][0].0 as usize;
        assert!(d[j][1] > 1.0 && d[j][1] < 1.1, "{:?}", d[j]);
        let far = (0..n)
            .find(|&v| {
                v != 7
                    && !mesh.rings[7].iter().any(|e| e.0 as usize == v)
                    && !mesh.rings[v].iter().any(|e| mesh.rings[e.0 as usize].iter().any(|f| f.0 == 7))
            })
            .unwrap();
        assert!((d[far][2] - 1.0).abs() < 1e-3, "{:?}", d[far]);
        // Without the fall-off taken out, its curvature over the ring reads as detail.
        let none = [super::super::falloff::Falloff { s: 0.0, p: 0.0 }; 3];
        let biased = vertex_detail(&mesh, &values, &measured, &none, 8.0);
        assert!((biased[far][0] - 1.0).abs() > 0.01, "{:?}", biased[far]);
        // Nothing measured: 1.
        assert_eq!(vertex_detail(&mesh, &values, &vec![false; n * n], &falloff, 8.0)[7], [1.0; 3]);
    }

    #[test]
    fn a_smooth_fall_off_gives_no_detail_and_a_stripe_is_recovered() {
        let mesh = SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]));
        let atlas = Atlas::build(&mesh, 0.5, 3);
        let cam = Pinhole::looking(400, 260, 900.0, [300.0, 0.0, 90.0], [0.0, 0.0, 30.0]);
        // The test frames are exitance already: η = 1 makes every Fresnel factor the same π.
        let view = ViewMap::new(&mesh, &cam, 0.0, &ViewLimits { eta: 1.0, ..ViewLimits::default() });
        let params = DetailParams { eta: 1.0, ..DetailParams::default() };
        let dv = DetailView::new(&mesh, &atlas, &view, &params);
        assert!(dv.texels.len() > 3000, "{}", dv.texels.len());
        let entries = [[24.0, 0.0, 30.0], [20.0, 10.0, 45.0], [18.0, -12.0, 15.0]];
        // No detail: T_ρ is 1 but for the curvature of the distance over a triangle, which log
        // interpolation does not follow (at most `κ·h²/(8d)`: 6 % at 8 mm, κ = 0.3 mm⁻¹).
        // What it does not know is what a real frame shows: a smooth fall-off stays near 1.
        let mut acc = DetailAccumulator::new(&atlas);
        for e in entries {
            let img = frame(&mesh, &view, e, &|_| 1.0);
            let r = frame_ratios(&atlas, &dv, &view, &img, e, 1e-4, &params);
            assert!(r.iter().all(|&(t, _, _)| norm(sub(atlas.texels[t as usize].unwrap().point, e)) >= 8.0));
            acc.add(0, &r);
        }
        let flat = acc.finish();
        let seen: Vec<f32> = (0..atlas.texels.len())
            .filter(|&t| flat.values[t][0] != 1.0 || acc.weight[t][0] > 0.0)
            .map(|t| flat.values[t][0])
            .collect();
        assert!(seen.len() > 2000, "{}", seen.len());
        let mut dev: Vec<f32> = seen.iter().map(|v| (v - 1.0).abs()).collect();
        dev.sort_by(f32::total_cmp);
        let q = |p: usize| dev[dev.len() * p / 100];
        eprintln!("|T_ρ − 1| 50/90/99th percentile {} {} {}", q(50), q(90), q(99));
        assert!(q(50) < 0.025 && q(99) < 0.06, "{} {}", q(50), q(99));
        // A dark stripe (z within 1 mm of 30, 40 % darker), finer than the mesh: recovered on
        // texels well inside it, relative to the vertices' own values.
        let stripe = |p: V3| if (p[2] - 30.0).abs() < 1.0 { 0.6 } else { 1.0 };
        let mut acc = DetailAccumulator::new(&atlas);
        for e in entries {
            let img = frame(&mesh, &view, e, &stripe);
            acc.add(1, &frame_ratios(&atlas, &dv, &view, &img, e, 1e-4, &params));
        }
        let d = acc.finish();
        let (mut inside, mut errors) = (0, Vec::new());
        for tv in &dv.texels {
            let t = atlas.texels[tv.texel as usize].unwrap();
            if acc.weight[tv.texel as usize][1] == 0.0 || (t.point[2] - 30.0).abs() > 0.6 {
                continue;
            }
            // The truth: the texel's detail over its vertices' (log-interpolated).
            let tri = mesh.triangles[t.triangle as usize];
            let vs: f64 =
                (0..3).map(|k| f64::from(t.bary[k]) * stripe(mesh.vertices[tri[k] as usize]).ln()).sum();
            let want = 0.6 / vs.exp();
            let got = f64::from(d.values[tv.texel as usize][1]);
            // The curvature above, and pixels that straddle the stripe's hard edge.
            assert!((got / want - 1.0).abs() < 0.1, "texel {}: {got} vs {want}", tv.texel);
            errors.push((got / want - 1.0).abs());
            inside += usize::from(got < 0.9);
        }
        errors.sort_by(f64::total_cmp);
        let checked = errors.len();
        assert!(checked > 50 && inside > checked / 2, "{checked} {inside}");
        assert!(errors[checked / 2] < 0.04, "median {}", errors[checked / 2]);
        // Channels no frame had stay 1, and no texel is observed in every colour.
        assert!(d.values.iter().all(|v| v[0] == 1.0 && v[2] == 1.0));
        assert!(!d.observed.iter().any(|&o| o));
    }
}
