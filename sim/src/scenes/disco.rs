//! The DISCO scene: a translucent pebble on the turntable, lit by the galvo's laser spot and
//! seen by a grey HDR camera from the rig file's camera positions.
//!
//! Physics (the paper's equation 1 with a beam): the object is marble (Jensen et al. 2001's
//! measured σs′, σa; η = 1.3) with a vein of skin-like material through it, so it is
//! inhomogeneous. Between an entry point `xi` and an exit point `xo` the diffuse reflectance
//! `Rd(xi, xo)` is the mean of the two points' dipoles at their 3D distance (symmetric, as light
//! transport is). The beam has a Gaussian profile of `beam_sigma_mm` (0.85 mm: the paper's
//! ≈ 2 mm spot at half maximum), integrated with 3 × 3 Gauss–Hermite rays; each ray's flux
//! enters through `Ft(η, ωi)`. A pixel sees the surface point its centre's ray hits:
//! `Lo = Ft(η, ωo)/π · Σ_rays Φ_ray·Ft(η, ωi)·Rd(xi, xo)`. Each laser (635, 532, 476 nm) drives
//! the dipole's red, green or blue channel; the grey camera sees it with its own sensitivity
//! times the laser's power (`flux`, unknown to the fit: the white balance measures it).
//!
//!
//! Surface detail ([`Veining`]): thin dark lines in the marble's skin, finer than the mesh. The
//! skin's transmittance `T(x)` (per colour) takes its share of the light where it enters and
//! where it leaves, so `Rd` seen through the skin is `T(xi)·Rd(xi, xo)·T(xo)`, symmetric as
//! before. This is what the paper's detail texture `T_ρ` (section 6.3) models: a modulation of
//! the response that no illumination changes.
//!
//! The white balance step (`meta.kind = "white"`) shows the white target instead: a Lambertian
//! plane of the rig file's albedo, lit by the beam (`E = I(s)·cos θ`).
//!
//! The registration frame (the `[plan] registration` output on, the paper's section 4): two
//! spotlights 120 mm either side of the camera light the whole object; a broad light's
//! response is the total diffuse reflectance (the dipole's integral) entering and leaving
//! through the Fresnel terms and the skin, `Lo = Ft(ωo)/π·T·Rd_total·T·Σ E_s·Ft(ωi,s)` per
//! colour, the grey camera taking their mean, with the entering irradiance spread over some
//! 8 mm of surface (light under a translucent surface travels), so the object glows out to its
//! outline. Only its silhouette matters to the fit; the room is
//! dark. The object stands on the turntable where [`DiscoScene::scan_pose`] says the scanned mesh
//! is *not*: `object.ply` ([`DiscoScene::scanned_mesh`]) is the mesh in the scanner's frame.
//!
//! The glint: the surface reflects `1 − Ft(η, θi)` of the beam (1.7 % head on) into a
//! Gaussian lobe of [`GLINT_LOBE_RAD`] about the mirror direction, so a camera near the mirror
//! direction sees a bright point at the spot's centre, as on polished marble; the fit must
//! leave those pixels out (the paper's section 5).

use std::collections::HashMap;
use std::sync::{Arc, RwLock};

use lightrig_host::disco::DiscoSetup;
use lightrig_host::rigfile::RigFile;
use lightrig_pipelines::disco::dipole::{fresnel_transmittance, rd_between, Dipole, Medium, MARBLE, SKIN1};

use lightrig_pipelines::disco::mesh::{pebble, SurfaceMesh};
use lightrig_pipelines::disco::optics::{cast, point_of, surface_map, turn, turned, Hit};
use lightrig_pipelines::disco::register::Pose;
use lightrig_pipelines::disco::relight::{sub_centroids, DistantLight};
use lightrig_pipelines::firs::mesh::Mesh;
use lightrig_pipelines::vec3::{add, cross, dot, norm, normalize, scale, sub, V3};
use lightrig_protocol::config::AxisKind;

use crate::camera::{RigState, Scene};

/// The vein: the object-frame points within `half_width_mm` of a plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vein {
    pub normal: V3,
    pub offset_mm: f64,
    pub half_width_mm: f64,
}

/// Surface detail: dark lines where warped planes cut the surface. Line `i` is the level set
/// `dot(p, n) − offset + A·sin(2π·dot(p, w)/λ) = 0` with a Gaussian cross-section of
/// `sigma_mm`; the skin's transmittance is `1 − depth_c·Σ_i g_i` (brownish: it takes more blue).
#[derive(Debug, Clone, PartialEq)]
pub struct Veining {
    /// `(n, offset_mm, w, amplitude_mm, wavelength_mm)` per line.
    pub lines: Vec<(V3, f64, V3, f64, f64)>,
    pub sigma_mm: f64,
    pub depth: [f64; 3],
}

impl Veining {
    /// The skin's transmittance at object-frame point `p`, per colour.
    pub fn at(&self, p: V3) -> [f64; 3] {
        let g: f64 = self
            .lines
            .iter()
            .map(|&(n, o, w, a, l)| {
                let s = dot(p, n) - o + a * (std::f64::consts::TAU * dot(p, w) / l).sin();
                (-s * s / (2.0 * self.sigma_mm * self.sigma_mm)).exp()
            })
            .sum();
        self.depth.map(|d| (1.0 - d * g).max(0.2))
    }
}

/// A pixel's surface point in a view.
#[derive(Debug, Clone, Copy)]
struct Seen {
    point: V3,
    material: u8,
    /// `Ft(η, ωo)/π` times the skin's transmittance, per colour.
    out: [f64; 3],
    /// The radiance under the registration spotlights (grey).
    lit: f64,
    /// World point, its normal, the unit direction to the camera: where the surface's own
    /// reflection of the beam (the glint) is seen.
    world: V3,
    normal: V3,
    to_eye: V3,
}

/// One beam ray inside the object.
#[derive(Debug, Clone, Copy)]
struct Entry {
    point: V3,
    material: u8,
    /// Share of the flux times `Ft(η, ωi)` times the skin's transmittance, per colour.
    weight: [f64; 3],
}

/// The beam at one spot: its rays by two quadratures. Within [`FINE_MM`] of the centre's entry
/// point `Rd` changes over a fraction of the beam's width (its scale there is the dipole's
/// source depth, 0.45 mm in marble), which 3 × 3 Gauss–Hermite rays 1.5 mm apart cannot
/// resolve: pixels there sum the fine grid.
struct Beam {
    centre: Option<V3>,
    coarse: Vec<Entry>,
    fine: Vec<Entry>,
}

/// The registration spotlights: this far either side of the camera (mm), each of this intensity
/// (flux per steradian: about 0.05 of irradiance at 300 mm).
const SPOTLIGHT_OFFSET_MM: f64 = 120.0;
const SPOTLIGHT_INTENSITY: f64 = 2_000.0;

/// Pixels within this distance of the beam's centre (mm) use the fine quadrature.
pub const FINE_MM: f64 = 4.5;
/// The fine quadrature: a square grid of this pitch (in σ) over the disc of radius
/// [`FINE_REACH`] σ: on a plane, within 0.3 % of the dipole's exact convolution with the beam
/// out to 5 mm. The kernel fit's rates follow the beam's shape steeply: cut at 3σ with a σ/3
/// pitch (4.5 % off), they came out 3.5 % (σ1) and 5 % (σ2) low.
const FINE_PITCH: f64 = 1.0 / 4.0;
const FINE_REACH: f64 = 4.0;

/// The fine quadrature's rays across the beam: `(a, b, weight)`, offsets in σ, weights summing
/// to 1.
fn fine_grid() -> Vec<(f64, f64, f64)> {
    let steps = (FINE_REACH / FINE_PITCH).round() as i32;
    let mut grid = Vec::new();
    for i in -steps..=steps {
        for j in -steps..=steps {
            let (a, b) = (f64::from(i) * FINE_PITCH, f64::from(j) * FINE_PITCH);
            if a * a + b * b <= FINE_REACH * FINE_REACH {
                grid.push((a, b, (-(a * a + b * b) / 2.0).exp()));
            }
        }
    }
    let total: f64 = grid.iter().map(|g| g.2).sum();
    grid.into_iter().map(|(a, b, w)| (a, b, w / total)).collect()
}

type ViewKey = (usize, i64);
/// A view's beam at a galvo code.
type BeamKey = (ViewKey, [u16; 2]);

/// The DISCO scene.
pub struct DiscoScene {
    pub setup: DiscoSetup,
    pub mesh: SurfaceMesh,
    /// Body, vein.
    pub media: [Medium; 2],
    pub vein: Vein,
    pub veining: Veining,
    pub beam_sigma_mm: f64,
    /// Per laser channel: the dipole channel it drives and its flux as the camera sees it.
    pub lasers: Vec<(u8, usize, f64)>,
    /// The registration spotlights' output channel (`[plan] registration`), if any.
    pub spotlights: Option<u8>,
    /// The scanner's frame: `object.ply` is the object's mesh placed by this pose (the
    /// turntable frame → the scan's); the fit's registration must find its inverse.
    pub scan_pose: Pose,
    turntable: Option<u8>,
    dipoles: [[Dipole; 3]; 2],
    /// Per vertex: the skin's transmittance averaged over its hat function.
    hat_skin: Vec<[f64; 3]>,
    views: RwLock<HashMap<ViewKey, Arc<Vec<Option<Seen>>>>>,
    beams: RwLock<HashMap<BeamKey, Arc<Beam>>>,
}

/// The dipole channel a laser wavelength drives.
pub fn channel_of(nm: u16) -> usize {
    match nm {
        600.. => 0,
        500..=599 => 1,
        _ => 2,
    }
}

/// 3-point Gauss–Hermite nodes (in σ) and weights.
const GH: [(f64, f64); 3] =
    [(-1.732_050_807_568_877_2, 1.0 / 6.0), (0.0, 2.0 / 3.0), (1.732_050_807_568_877_2, 1.0 / 6.0)];

impl DiscoScene {
    /// The scene for `rig` (its `[plan.fit]` geometry), the pebble from an icosphere of `level`
    /// (3: 642 vertices, 4: 2 562).
    pub fn new(rig: &RigFile, level: u32) -> Result<Self, String> {
        let setup = DiscoSetup::from_rig(rig).map_err(|e| e.to_string())?;
        let mesh = SurfaceMesh::new(&pebble(level, [24.0, 20.0, 30.0]));
        let spotlights = rig
            .plan
            .get("registration")
            .and_then(|v| v.as_str())
            .and_then(|n| rig.lasers.iter().find(|l| l.name.as_deref() == Some(n)))
            .map(|l| l.channel);
        // A grey camera's sensitivity falls towards the blue; the lasers are all 10 mW.
        let lasers = rig
            .lasers
            .iter()
            .filter(|l| Some(l.channel) != spotlights)
            .map(|l| {
                let c = channel_of(l.wavelength_nm);
                (l.channel, c, [1.0, 0.85, 0.6][c])
            })
            .collect();
        let media = [MARBLE, SKIN1];
        let mut scene = DiscoScene {
            setup,
            mesh,
            media,
            vein: Vein { normal: normalize([1.0, 0.4, 0.8]), offset_mm: 24.0, half_width_mm: 3.0 },
            veining: Veining {
                lines: vec![
                    (normalize([0.3, 1.0, 0.2]), 2.0, normalize([1.0, -0.3, 0.0]), 3.0, 23.0),
                    (normalize([-0.7, 0.2, 1.0]), -12.0, normalize([0.0, 1.0, -0.2]), 2.5, 17.0),
                    (normalize([1.0, -0.5, -0.3]), -6.0, normalize([0.0, 0.5, 1.0]), 3.5, 29.0),
                ],
                sigma_mm: 0.8,
                depth: [0.3, 0.36, 0.42],
            },
            beam_sigma_mm: 0.85,
            lasers,
            spotlights,
            // 12° about the vertical and a few degrees' tilt, 6 mm off: a scan as a lab's
            // geometry tools leave it, roughly upright.
            scan_pose: Pose { rotation: [0.04, -0.03, 0.21], translation: [3.0, -4.0, 2.5] },
            turntable: rig.steppers.iter().find(|s| s.kind == AxisKind::Rotary).map(|s| s.axis),
            dipoles: [media[0].dipoles(), media[1].dipoles()],
            views: RwLock::new(HashMap::new()),
            beams: RwLock::new(HashMap::new()),
            hat_skin: Vec::new(),
        };
        scene.hat_skin =
            (0..scene.mesh.vertices.len()).map(|k| scene.hat_mean(k, &|x| scene.detail(x))).collect();
        Ok(scene)
    }

    /// `∫ φk(x)·g(x) dx / ∫ φk` over vertex `k`'s hat function (per colour): each
    /// triangle of `k`'s fan split 12 × 12, evaluated at the sub-triangles' centroids.
    fn hat_mean(&self, k: usize, g: &dyn Fn(V3) -> [f64; 3]) -> [f64; 3] {
        let (mut sum, mut wsum) = ([0.0; 3], 0.0);
        let split = 12u32;
        for t in self.mesh.triangles.iter().filter(|t| t.contains(&(k as u32))) {
            let rot = t.iter().position(|&i| i as usize == k).unwrap_or(0);
            let [a, b, c] = [0, 1, 2].map(|j| self.mesh.vertices[t[(rot + j) % 3] as usize]);
            let area = 0.5 * norm(cross(sub(b, a), sub(c, a)));
            for (u, v) in sub_centroids(split) {
                let wa = 1.0 - u - v;
                let x = add(add(scale(a, wa), scale(b, u)), scale(c, v));
                let w = wa * area;
                let gx = g(x);
                for (ch, s) in sum.iter_mut().enumerate() {
                    *s += w * gx[ch];
                }
                wsum += w;
            }
        }
        sum.map(|s| if wsum > 0.0 { s / wsum } else { 0.0 })
    }

    /// The mesh as the scanner delivers it (`object.ply`): placed by [`Self::scan_pose`].
    pub fn scanned_mesh(&self) -> Mesh {
        self.scan_pose.place(&self.mesh.mesh())
    }

    /// The medium at object-frame point `p`: 0 body, 1 vein.
    pub fn material_at(&self, p: V3) -> u8 {
        u8::from((dot(p, self.vein.normal) - self.vein.offset_mm).abs() < self.vein.half_width_mm)
    }

    /// Each vertex's medium.
    pub fn vertex_materials(&self) -> Vec<u8> {
        self.mesh.vertices.iter().map(|&p| self.material_at(p)).collect()
    }

    /// The skin's transmittance at object-frame point `p` ([`Veining`]), per colour.
    pub fn detail(&self, p: V3) -> [f64; 3] {
        self.veining.at(p)
    }

    /// The true `Rd` between object-frame points `a` and `b` seen through the skin, channel `c`,
    /// mm⁻²: the dipole, times the skin's transmittance at both ends.
    pub fn rd(&self, a: V3, b: V3, c: usize) -> f64 {
        self.rd_below(a, b, c) * self.detail(a)[c] * self.detail(b)[c]
    }

    /// `Rd` under the skin (the dipole alone).
    fn rd_below(&self, a: V3, b: V3, c: usize) -> f64 {
        let (ma, mb) = (self.material_at(a), self.material_at(b));
        rd_between(&self.dipoles[usize::from(ma)][c], &self.dipoles[usize::from(mb)][c], norm(sub(a, b)))
    }

    /// Whether vertex `r`'s fan is clear of the skin's lines: its skin and its hat function's
    /// mean both within 2 % of 1 in every colour.
    pub fn skin_clear(&self, r: usize) -> bool {
        let (t, h) = (self.detail(self.mesh.vertices[r]), self.hat_skin[r]);
        (0..3).all(|c| t[c] >= 0.98 && h[c] >= 0.98)
    }

    /// The true throughput factor `F(r, k)` (beyond the near field), per channel, symmetric:
    /// `Rd` under the skin between the two vertices, times the skin at both ends as `F` holds
    /// it — light leaves through the skin at vertex `r` and enters through vertex `k`'s hat
    /// function (the spots split over its fan), so the entry's skin is its hat mean `T̄k` —
    /// made symmetric as the fit's `F` is: `Rd·½(T_r·T̄k + T_k·T̄r)`. Under a broad light this
    /// `F` gives each vertex its exitance (the entering light is integrated over the hats).
    pub fn truth(&self, r: usize, k: usize) -> [f64; 3] {
        let (a, b) = (self.mesh.vertices[r], self.mesh.vertices[k]);
        let (ta, tb) = (self.detail(a), self.detail(b));
        let (ha, hb) = (self.hat_skin[r], self.hat_skin[k]);
        [0, 1, 2].map(|c| self.rd_below(a, b, c) * 0.5 * (ta[c] * hb[c] + tb[c] * ha[c]))
    }

    /// What the near field's entries of `F` estimate (the diagonal and one-ring: the paper's
    /// barycentric split, a mean over `k`'s hat function), symmetric as the fit's `F` is: the
    /// mean of [`DiscoScene::hat_response`] both ways.
    pub fn hat_truth(&self, r: usize, k: usize) -> [f64; 3] {
        let (a, b) = (self.hat_response(r, k), self.hat_response(k, r));
        [0, 1, 2].map(|c| 0.5 * (a[c] + b[c]))
    }

    /// The response at vertex `r` to light entering by vertex `k`'s hat function,
    /// `∫ φk(x) Rd(x, xr) dx / ∫ φk`: each triangle of `k`'s fan split 12 × 12, evaluated at the
    /// sub-triangles' centroids.
    pub fn hat_response(&self, r: usize, k: usize) -> [f64; 3] {
        let xr = self.mesh.vertices[r];
        self.hat_mean(k, &|x| [0, 1, 2].map(|c| self.rd(x, xr, c)))
    }

    /// Each vertex's radiant exitance under `light` (object frame) computed from the object's
    /// physics, independently of any `F`: `M(xr) = ∫ Rd(x, xr)·E·max(0, n(x)·l)·Ft(η, θ(x)) dx`
    /// over the whole surface, each triangle split into sub-triangles (3 × 3; 24 × 24 within
    /// 8 mm of `xr`, where `Rd` peaks within a millimetre) evaluated at their centroids.
    pub fn exitance(&self, light: &DistantLight) -> Vec<[f64; 3]> {
        let below = self.exitance_below_skin(light);
        below
            .iter()
            .zip(&self.mesh.vertices)
            .map(|(m, &p)| {
                let t = self.detail(p);
                [0, 1, 2].map(|c| m[c] * t[c])
            })
            .collect()
    }

    /// [`DiscoScene::exitance`] before the skin at the vertex lets it out: smooth under a broad
    /// light, so interpolating it between vertices and multiplying by the skin's transmittance
    /// at a surface point gives that point's exitance ([`DiscoScene::detail`]).
    pub fn exitance_below_skin(&self, light: &DistantLight) -> Vec<[f64; 3]> {
        use rayon::prelude::*;
        let l = normalize(light.towards);
        let eta = self.setup.eta;
        (0..self.mesh.vertices.len())
            .into_par_iter()
            .map(|r| {
                let xr = self.mesh.vertices[r];
                let mr = usize::from(self.material_at(xr));
                let mut m = [0.0; 3];
                for t in &self.mesh.triangles {
                    let [a, b, c] = t.map(|i| self.mesh.vertices[i as usize]);
                    let [na, nb, nc] = t.map(|i| self.mesh.normals[i as usize]);
                    let area = 0.5 * norm(cross(sub(b, a), sub(c, a)));
                    let near = [a, b, c].iter().any(|&v| norm(sub(v, xr)) < 8.0);
                    let split = if near { 24 } else { 3 };
                    let w = area / f64::from(split * split);
                    for (u, v) in sub_centroids(split) {
                        let wa = 1.0 - u - v;
                        let n = normalize(add(add(scale(na, wa), scale(nb, u)), scale(nc, v)));
                        let cos = dot(n, l);
                        if cos <= 0.0 {
                            continue;
                        }
                        let x = add(add(scale(a, wa), scale(b, u)), scale(c, v));
                        let e = light.irradiance * cos * fresnel_transmittance(eta, cos) * w;
                        let mx = usize::from(self.material_at(x));
                        let d = norm(sub(x, xr));
                        let skin = self.detail(x);
                        for (ch, mc) in m.iter_mut().enumerate() {
                            *mc += e * skin[ch] * rd_between(&self.dipoles[mr][ch], &self.dipoles[mx][ch], d);
                        }
                    }
                }
                m
            })
            .collect()
    }

    fn view_key(state: &RigState, deg: f64) -> ViewKey {
        let pos = state.meta.get("camera_position").and_then(|v| v.as_u64()).unwrap_or(0) as usize;
        (pos, (deg * 1000.0).round() as i64)
    }

    fn view(&self, key: ViewKey, deg: f64) -> Option<Arc<Vec<Option<Seen>>>> {
        if let Some(v) = self.views.read().ok()?.get(&key) {
            return Some(Arc::clone(v));
        }
        let cam = self.setup.cameras.get(key.0)?.1;
        let world = turned(&self.mesh, deg);
        // The registration spotlights: the irradiance entering at each vertex, E = I·cos θ / d²
        // through `Ft`, spread over the surface as light under a translucent surface spreads
        // (three rounds of one-ring averaging, some 8 mm: marble's diffusion length), so the
        // object glows out to its outline.
        let spots = [-1.0, 1.0].map(|s| add(cam.eye, scale(cam.axes[0], s * SPOTLIGHT_OFFSET_MM)));
        let mut entering: Vec<f64> = world
            .iter()
            .zip(&self.mesh.normals)
            .map(|(&p, &n)| {
                let n = turn(n, deg);
                spots
                    .iter()
                    .map(|&s| {
                        let to = sub(s, p);
                        let cos_i = dot(n, normalize(to));
                        if cos_i <= 0.0 {
                            0.0
                        } else {
                            SPOTLIGHT_INTENSITY * cos_i / dot(to, to)
                                * fresnel_transmittance(self.setup.eta, cos_i)
                        }
                    })
                    .sum()
            })
            .collect();
        for _ in 0..3 {
            entering = self
                .mesh
                .rings
                .iter()
                .enumerate()
                .map(|(v, ring)| {
                    (entering[v] + ring.iter().map(|&(j, _)| entering[j as usize]).sum::<f64>())
                        / (1 + ring.len()) as f64
                })
                .collect();
        }
        let map: Vec<Option<Seen>> = surface_map(&self.mesh, &world, &cam)
            .iter()
            .map(|h| {
                h.map(|hit| {
                    let (p, n) = point_of(&self.mesh, &world, deg, &hit);
                    let obj = self.object_point(&hit);
                    let to_eye = normalize(sub(cam.eye, p));
                    let cos_o = dot(n, to_eye);
                    let out = fresnel_transmittance(self.setup.eta, cos_o) / std::f64::consts::PI;
                    let material = self.material_at(obj);
                    let skin = self.detail(obj);
                    let out = skin.map(|t| out * t);
                    // Under the spotlights: the surface the camera sees faces it (the face's
                    // own normal; the interpolated one may turn away at the outline).
                    let tri = self.mesh.triangles[hit.triangle as usize];
                    let e: f64 = (0..3).map(|k| f64::from(hit.bary[k]) * entering[tri[k] as usize]).sum();
                    let face = turn(self.mesh.face_normal(hit.triangle as usize), deg);
                    let leaving =
                        fresnel_transmittance(self.setup.eta, dot(face, to_eye)) / std::f64::consts::PI;
                    let d = &self.dipoles[usize::from(material)];
                    let lit = (0..3)
                        .map(|c| e * skin[c] * d[c].total_reflectance() * leaving * skin[c])
                        .sum::<f64>()
                        / 3.0;
                    Seen { point: obj, material, out, lit, world: p, normal: n, to_eye }
                })
            })
            .collect();
        let map = Arc::new(map);
        self.views.write().ok()?.insert(key, Arc::clone(&map));
        Some(map)
    }

    fn object_point(&self, hit: &Hit) -> V3 {
        let t = self.mesh.triangles[hit.triangle as usize];
        (0..3).fold([0.0; 3], |p, k| add(p, scale(self.mesh.vertices[t[k] as usize], f64::from(hit.bary[k]))))
    }

    /// The beam's rays for galvo code `code` with the turntable at `deg`: where each enters
    /// (object frame) and with what weight.
    fn beam(&self, key: ViewKey, code: [u16; 2], deg: f64) -> Arc<Beam> {
        if let Some(b) = self.beams.read().ok().and_then(|m| m.get(&(key, code)).cloned()) {
            return b;
        }
        let proj = &self.setup.projector;
        let d = proj.ray([f64::from(code[0]), f64::from(code[1])]);
        let u = normalize(cross(d, [0.0, 0.0, 1.0]));
        let v = cross(u, d);
        let world = turned(&self.mesh, deg);
        let sigma = self.beam_sigma_mm;
        let entry = |hit: &Hit, weight: f64| -> Option<Entry> {
            let (_, n) = point_of(&self.mesh, &world, deg, hit);
            let cos_i = -dot(n, d);
            if cos_i <= 0.0 {
                return None;
            }
            let obj = self.object_point(hit);
            let w = weight * fresnel_transmittance(self.setup.eta, cos_i);
            Some(Entry {
                point: obj,
                material: self.material_at(obj),
                weight: self.detail(obj).map(|t| w * t),
            })
        };
        let origin = |a: f64, b: f64| add(proj.eye, add(scale(u, a * sigma), scale(v, b * sigma)));
        let mut coarse = Vec::new();
        for &(a, wa) in &GH {
            for &(b, wb) in &GH {
                let Some(hit) = cast(&self.mesh, &world, origin(a, b), d) else { continue };
                coarse.extend(entry(&hit, wa * wb));
            }
        }
        // The fine grid: only the triangles near the centre's hit can be hit.
        let centre_hit = cast(&self.mesh, &world, proj.eye, d);
        let mut fine = Vec::new();
        if let Some(c) = &centre_hit {
            let (cw, _) = point_of(&self.mesh, &world, deg, c);
            let reach = (FINE_REACH + 1.0) * sigma + 2.0 * self.mesh.mean_edge();
            let near: Vec<usize> = (0..self.mesh.triangles.len())
                .filter(|&t| self.mesh.triangles[t].iter().any(|&i| norm(sub(world[i as usize], cw)) < reach))
                .collect();
            for (a, b, w) in fine_grid() {
                let o = origin(a, b);
                let mut best: Option<Hit> = None;
                for &k in &near {
                    let [p, q, r] = self.mesh.triangles[k].map(|i| world[i as usize]);
                    if let Some((dist, bu, bv)) =
                        lightrig_pipelines::disco::optics::ray_triangle(o, d, p, q, r)
                    {
                        if best.is_none_or(|h| dist < f64::from(h.t)) {
                            best = Some(Hit {
                                triangle: k as u32,
                                bary: [(1.0 - bu - bv) as f32, bu as f32, bv as f32],
                                t: dist as f32,
                            });
                        }
                    }
                }
                if let Some(hit) = best {
                    fine.extend(entry(&hit, w));
                }
            }
        }
        let b = Arc::new(Beam { centre: centre_hit.map(|h| self.object_point(&h)), coarse, fine });
        if let Ok(mut m) = self.beams.write() {
            // Frames come spot by spot: keep the cache small.
            if m.len() > 64 {
                m.clear();
            }
            m.insert((key, code), Arc::clone(&b));
        }
        b
    }

    /// The white target's radiance at pixel `(x, y)` of camera position `pos` with `flux` on
    /// at code `code`.
    fn white(&self, pos: usize, x: u32, y: u32, code: [u16; 2], flux: f64) -> f64 {
        let Some(&(_, cam)) = self.setup.cameras.get(pos) else { return 0.0 };
        let t = &self.setup.white;
        let d = cam.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
        let dn = dot(d, t.normal);
        if dn.abs() < 1e-9 {
            return 0.0;
        }
        let s = dot(sub(t.point, cam.eye), t.normal) / dn;
        if s <= 0.0 {
            return 0.0;
        }
        let p = add(cam.eye, scale(d, s));
        let proj = &self.setup.projector;
        let b = proj.ray([f64::from(code[0]), f64::from(code[1])]);
        let rel = sub(p, proj.eye);
        let perp = norm(sub(rel, scale(b, dot(rel, b))));
        let sigma2 = self.beam_sigma_mm * self.beam_sigma_mm;
        let intensity = flux / (2.0 * std::f64::consts::PI * sigma2) * (-perp * perp / (2.0 * sigma2)).exp();
        t.albedo * intensity * dot(b, t.normal).abs() / std::f64::consts::PI
    }
}

impl Scene for DiscoScene {
    fn size(&self) -> (u32, u32) {
        self.setup.cameras.first().map_or((1, 1), |(_, c)| (c.width, c.height))
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        self.pixel(&self.frame(state), x, y)
    }

    fn radiance_row(&self, y: u32, state: &RigState, out: &mut [[f64; 3]]) {
        let frame = self.frame(state);
        for (x, o) in out.iter_mut().enumerate() {
            *o = self.pixel(&frame, x as u32, y);
        }
    }
}

/// What a frame's pixels share: which lights are on, the view of the object, the beam.
enum Frame {
    Dark,
    /// The registration spotlights alone.
    Spotlit(Arc<Vec<Option<Seen>>>),
    /// The white target under the beam: camera position, galvo code, each laser's flux.
    White(usize, [u16; 2], Vec<(usize, f64)>),
    /// The object under the beam: the view, the beam, its direction, each laser's channel and
    /// flux.
    Beam(Arc<Vec<Option<Seen>>>, Arc<Beam>, V3, Vec<(usize, f64)>),
}

impl DiscoScene {
    fn frame(&self, state: &RigState) -> Frame {
        let on: Vec<(usize, f64)> =
            self.lasers.iter().filter(|l| state.lasers & (1 << l.0) != 0).map(|l| (l.1, l.2)).collect();
        let deg = self.turntable.and_then(|a| state.axes.get(usize::from(a))).copied().unwrap_or(0.0);
        let key = Self::view_key(state, deg);
        let spotlit = self.spotlights.is_some_and(|c| state.lasers & (1 << c) != 0);
        if spotlit && on.is_empty() {
            return self.view(key, deg).map_or(Frame::Dark, Frame::Spotlit);
        }
        let Some(&code) = state.galvos.first() else { return Frame::Dark };
        if on.is_empty() {
            return Frame::Dark;
        }
        if state.meta.get("kind").and_then(|k| k.as_str()) == Some("white") {
            return Frame::White(key.0, code, on);
        }
        let Some(view) = self.view(key, deg) else { return Frame::Dark };
        let d = self.setup.projector.ray([f64::from(code[0]), f64::from(code[1])]);
        Frame::Beam(view, self.beam(key, code, deg), d, on)
    }

    fn pixel(&self, frame: &Frame, x: u32, y: u32) -> [f64; 3] {
        let w = self.size().0;
        let (view, beam, d, on) = match frame {
            Frame::Dark => return [0.0; 3],
            Frame::Spotlit(view) => return [view[(y * w + x) as usize].map_or(0.0, |seen| seen.lit); 3],
            Frame::White(pos, code, on) => {
                let v: f64 = on.iter().map(|&(_, f)| self.white(*pos, x, y, *code, f)).sum();
                return [v; 3];
            }
            Frame::Beam(view, beam, d, on) => (view, beam, *d, on),
        };
        let Some(seen) = view[(y * w + x) as usize] else { return [0.0; 3] };
        let rays = match beam.centre {
            Some(c) if norm(sub(c, seen.point)) < FINE_MM => &beam.fine,
            _ => &beam.coarse,
        };
        let glint = self.glint(&seen, d);
        let mut l = 0.0;
        for &(c, flux) in on {
            let mo = &self.dipoles[usize::from(seen.material)][c];
            let mut s = 0.0;
            for e in rays.iter() {
                s += e.weight[c]
                    * rd_between(
                        mo,
                        &self.dipoles[usize::from(e.material)][c],
                        norm(sub(e.point, seen.point)),
                    );
            }
            l += flux * s * seen.out[c] + flux * glint;
        }
        [l; 3]
    }
}

/// The glint's lobe: the surface's reflection spreads about the mirror direction as a Gaussian
/// of this σ, rad (polished marble).
pub const GLINT_LOBE_RAD: f64 = 0.1;

impl DiscoScene {
    /// The surface's own reflection of the beam along `d` (a galvo code's ray) seen at `seen`,
    /// per unit flux: the beam's irradiance there (its Gaussian profile across the beam) reflected by
    /// Fresnel's `1 − Ft(η, θi)` into a lobe of [`GLINT_LOBE_RAD`] about the mirror direction
    /// (normalised over the lobe's solid angle), the radiance the camera sees.
    fn glint(&self, seen: &Seen, d: V3) -> f64 {
        let proj = &self.setup.projector;
        let cos_i = -dot(d, seen.normal);
        if cos_i <= 0.0 {
            return 0.0;
        }
        let v = sub(seen.world, proj.eye);
        let across = sub(v, scale(d, dot(v, d)));
        let s2 = self.beam_sigma_mm * self.beam_sigma_mm;
        let e = (-dot(across, across) / (2.0 * s2)).exp() / (2.0 * std::f64::consts::PI * s2);
        let mirror = add(d, scale(seen.normal, 2.0 * cos_i));
        let a = lightrig_pipelines::vec3::angle(mirror, seen.to_eye);
        let lobe = (-a * a / (2.0 * GLINT_LOBE_RAD * GLINT_LOBE_RAD)).exp()
            / (2.0 * std::f64::consts::PI * GLINT_LOBE_RAD * GLINT_LOBE_RAD);
        (1.0 - fresnel_transmittance(self.setup.eta, cos_i)) * e * lobe
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rig() -> RigFile {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/disco.toml");
        RigFile::load(&path).unwrap()
    }

    #[test]
    fn the_spotlights_light_the_whole_object_seen_and_nothing_else() {
        let scene = DiscoScene::new(&rig(), 2).unwrap();
        // The shipped rig's fourth output is the spotlights, not a laser driving the dipole.
        assert_eq!((scene.spotlights, scene.lasers.len()), (Some(3), 3));
        let state = RigState {
            lasers: 1 << 3,
            galvos: vec![[8192, 8192]],
            axes: vec![30.0, 0.0],
            meta: serde_json::json!({ "kind": "view", "camera_position": 1 }),
            ..RigState::default()
        };
        let (_, cam) = scene.setup.cameras[1];
        let world = turned(&scene.mesh, 30.0);
        let seen = surface_map(&scene.mesh, &world, &cam);
        let (w, _) = scene.size();
        let (mut lit, mut dark) = (f64::INFINITY, 0.0f64);
        for (i, s) in seen.iter().enumerate() {
            let v = scene.radiance(i as u32 % w, i as u32 / w, &state)[0];
            match s {
                Some(_) => lit = lit.min(v),
                None => dark = dark.max(v),
            }
        }
        // Every pixel on the object is lit (to its outline, through the Fresnel terms), none
        // beside it.
        assert!(lit > 1e-5 && dark == 0.0, "{lit} {dark}");
        // The scan is the object moved by the scan pose.
        let scan = scene.scanned_mesh();
        let back = scene.scan_pose.inverse().apply(scan.vertices[7]);
        assert!(norm(sub(back, scene.mesh.vertices[7])) < 1e-9);
        assert!(norm(sub(scan.vertices[7], scene.mesh.vertices[7])) > 1.0);
    }

    #[test]
    fn the_spot_glows_where_the_projector_points_and_falls_off_through_the_object() {
        let scene = DiscoScene::new(&rig(), 2).unwrap();
        let (_, cam) = scene.setup.cameras[0];
        // Aim at the pebble's surface point facing between camera and projector.
        let target = [22.0, -4.0, 30.0];
        let code = scene.setup.projector.code_of(target).map(|c| c.round() as u16);
        let red = rig().lasers.iter().find(|l| l.wavelength_nm == 635).unwrap().channel;
        let state = RigState {
            lasers: 1 << red,
            galvos: vec![code],
            axes: vec![0.0, 0.0],
            meta: serde_json::json!({ "kind": "view", "camera_position": 0 }),
            ..RigState::default()
        };
        let (px, _) = cam.project(target).unwrap();
        let at = scene.radiance(px[0] as u32, px[1] as u32, &state)[0];
        let (far, _) = cam.project([20.0, 8.0, 45.0]).unwrap();
        let far = scene.radiance(far[0] as u32, far[1] as u32, &state)[0];
        assert!(at > 1e-3 && far > 0.0 && far < at * 1e-2, "{at} {far}");
        // The background is dark; the white step shows the target instead.
        assert_eq!(scene.radiance(0, 0, &state), [0.0; 3]);
        let white = RigState { meta: serde_json::json!({ "kind": "white" }), ..state };
        let zero = scene.setup.projector.code_of(scene.setup.white.point).map(|c| c.round() as u16);
        let white = RigState { galvos: vec![zero], ..white };
        let (c, _) = cam.project(scene.setup.white.point).unwrap();
        assert!(scene.radiance(c[0] as u32, c[1] as u32, &white)[0] > 0.01);
    }

    /// The glint: `(1 − Ft)·E·lobe`, brightest on the beam's axis seen along the mirror
    /// direction, falling off as Gaussians across the beam and away from the mirror direction;
    /// none where the beam meets the surface from behind.
    #[test]
    fn the_glint_is_the_beam_reflected_into_its_lobe() {
        let scene = DiscoScene::new(&rig(), 2).unwrap();
        let p = &scene.setup.projector;
        let d = p.ray([30_000.0, 33_000.0]);
        let n = normalize([1.0, -0.3, 0.2]);
        let cos_i = -dot(d, n);
        let mirror = add(d, scale(n, 2.0 * cos_i));
        let on_axis = add(p.eye, scale(d, 250.0));
        let seen = |world: V3, to_eye: V3| Seen {
            point: [0.0; 3],
            material: 0,
            out: [0.0; 3],
            lit: 0.0,
            world,
            normal: n,
            to_eye,
        };
        let s = scene.beam_sigma_mm;
        let peak = (1.0 - fresnel_transmittance(1.3, cos_i))
            / (2.0 * std::f64::consts::PI * s * s)
            / (2.0 * std::f64::consts::PI * GLINT_LOBE_RAD * GLINT_LOBE_RAD);
        let g = scene.glint(&seen(on_axis, mirror), d);
        assert!(cos_i > 0.5 && (g / peak - 1.0).abs() < 1e-12, "{g} {peak}");
        // Two beam σ across the beam: e^(−2).
        let across = normalize(cross(d, [0.0, 0.0, 1.0]));
        let g2 = scene.glint(&seen(add(on_axis, scale(across, 2.0 * s)), mirror), d);
        assert!((g2 / peak - (-2.0f64).exp()).abs() < 1e-9, "{}", g2 / peak);
        // Three lobe σ from the mirror direction: e^(−4.5).
        let off = turned_about(mirror, normalize(cross(mirror, [0.0, 0.0, 1.0])), 3.0 * GLINT_LOBE_RAD);
        let g3 = scene.glint(&seen(on_axis, off), d);
        assert!((g3 / peak - (-4.5f64).exp()).abs() < 1e-9, "{}", g3 / peak);
        // The beam meeting the surface from behind reflects nothing.
        let back = Seen { normal: scale(n, -1.0), ..seen(on_axis, mirror) };
        assert_eq!(scene.glint(&back, d), 0.0);
    }

    /// `v` turned by `angle` rad about the axis `u` (unit, perpendicular to `v`).
    fn turned_about(v: V3, u: V3, angle: f64) -> V3 {
        add(scale(v, angle.cos()), scale(cross(u, v), angle.sin()))
    }

    #[test]
    fn the_exitance_under_a_broad_light_is_the_total_diffuse_reflectance() {
        // Lit head-on, a point on a large smooth marble surface returns the irradiance entering
        // times Rd's integral (Jensen et al.'s total diffuse reflectance) — the pebble is not a
        // half-space, so within a few percent, where the surface faces the light squarely.
        let scene = DiscoScene::new(&rig(), 3).unwrap();
        let light = DistantLight { towards: [1.0, 0.0, 0.0], irradiance: 1.0 };
        let m = scene.exitance(&light);
        let mats = scene.vertex_materials();
        let r = (0..scene.mesh.vertices.len())
            .filter(|&v| mats[v] == 0 && scene.detail(scene.mesh.vertices[v])[2] > 0.999)
            .max_by(|&a, &b| scene.mesh.normals[a][0].total_cmp(&scene.mesh.normals[b][0]))
            .unwrap();
        for (c, d) in MARBLE.dipoles().iter().enumerate() {
            let want = d.total_reflectance() * fresnel_transmittance(1.3, 1.0);
            assert!((m[r][c] / want - 1.0).abs() < 0.1, "channel {c}: {} vs {want}", m[r][c]);
        }
    }

    #[test]
    fn the_truth_is_symmetric_and_decays_faster_in_blue() {
        let scene = DiscoScene::new(&rig(), 2).unwrap();
        let mats = scene.vertex_materials();
        assert!(mats.contains(&1) && mats.contains(&0), "both media on the surface");
        let a = scene.truth(3, 40);
        assert_eq!(a, scene.truth(40, 3));
        let near = scene.truth(3, scene.mesh.rings[3][0].0 as usize);
        assert!(near[0] > a[0] && a[0] > a[1] && a[1] > a[2], "{near:?} {a:?}");
        // Between two body vertices it is marble's dipole.
        let (i, j) = (0..mats.len())
            .flat_map(|i| (0..mats.len()).map(move |j| (i, j)))
            .find(|&(i, j)| i != j && mats[i] == 0 && mats[j] == 0)
            .unwrap();
        let (a, b) = (scene.mesh.vertices[i], scene.mesh.vertices[j]);
        let skin =
            0.5 * (scene.detail(a)[1] * scene.hat_skin[j][1] + scene.detail(b)[1] * scene.hat_skin[i][1]);
        assert_eq!(scene.truth(i, j)[1], MARBLE.dipoles()[1].rd(norm(sub(a, b))) * skin);
    }

    #[test]
    fn the_skins_lines_are_finer_than_the_mesh_and_take_light_at_both_ends() {
        let scene = DiscoScene::new(&rig(), 3).unwrap();
        let (v, t) = (&scene.mesh.vertices, &scene.mesh.triangles);
        let dark = v.iter().filter(|&&p| scene.detail(p)[2] < 0.9).count() as f64 / v.len() as f64;
        assert!(dark > 0.03 && dark < 0.35, "{dark}");
        // Lines pass between vertices: triangles dark inside with bright corners.
        let between = t
            .iter()
            .filter(|tri| {
                let c = tri.iter().fold([0.0; 3], |c, &i| add(c, scale(v[i as usize], 1.0 / 3.0)));
                scene.detail(c)[1] < 0.8 && tri.iter().all(|&i| scene.detail(v[i as usize])[1] > 0.95)
            })
            .count();
        assert!(between >= 2, "{between}");
        // Rd through the skin: the dipole times the skin at both ends, either way round.
        let (a, b) = (v[10], v[200]);
        for c in 0..3 {
            let want = scene.rd_below(a, b, c) * scene.detail(a)[c] * scene.detail(b)[c];
            assert_eq!(scene.rd(a, b, c), want);
            assert_eq!(scene.rd(b, a, c), scene.rd(a, b, c));
        }
        // A vertex's exitance leaves through its skin.
        let light = DistantLight { towards: [1.0, 0.0, 0.3], irradiance: 1.0 };
        let (m, below) = (scene.exitance(&light), scene.exitance_below_skin(&light));
        for r in [0, 50, 300] {
            let skin = scene.detail(v[r]);
            assert_eq!(m[r], [0, 1, 2].map(|c| below[r][c] * skin[c]));
        }
    }

    #[test]
    fn the_fine_beam_agrees_with_the_coarse_one_where_pixels_switch_between_them() {
        // At FINE_MM from the centre the two quadratures of the beam agree (no seam in the
        // frames); at 0.5 mm the 3 × 3 rays, 1.5 mm apart, are off by far more.
        let scene = DiscoScene::new(&rig(), 3).unwrap();
        let code = scene.setup.projector.code_of([22.0, -4.0, 30.0]).map(|c| c.round() as u16);
        let beam = scene.beam((0, 0), code, 0.0);
        let c = beam.centre.unwrap();
        assert!(beam.fine.len() > 200 && beam.coarse.len() == 9);
        let d = MARBLE.dipoles()[0];
        let sum = |rays: &[Entry], p: V3| {
            rays.iter().map(|e| e.weight[0] * d.rd(norm(sub(e.point, p)))).sum::<f64>()
        };
        let t = normalize(cross(
            scene.setup.projector.ray([f64::from(code[0]), f64::from(code[1])]),
            [0.0, 0.0, 1.0],
        ));
        let rel = |r: f64| {
            let p = add(c, scale(t, r));
            sum(&beam.coarse, p) / sum(&beam.fine, p) - 1.0
        };
        eprintln!("coarse/fine − 1: {:?}", [0.5, 1.0, 2.0, 3.0, 4.0, 4.5, 5.0].map(rel));
        assert!(rel(FINE_MM).abs() < 0.01, "{}", rel(FINE_MM));
        assert!(rel(0.5).abs() > 0.05, "{}", rel(0.5));
    }

    #[test]
    fn the_fine_beam_has_the_gaussians_width() {
        // The kernel fit's σ2 follows the blur's width steeply (told 1 % too wide, ~5 % high):
        // the rendered beam must have the σ the fit is told. Cut at 3σ the grid's variance was
        // 0.949 σ² per axis.
        let g = fine_grid();
        let m = |f: &dyn Fn(f64, f64) -> f64| g.iter().map(|&(a, b, w)| w * f(a, b)).sum::<f64>();
        assert!((m(&|_, _| 1.0) - 1.0).abs() < 1e-12);
        assert!(m(&|a, _| a).abs() < 1e-12 && m(&|_, b| b).abs() < 1e-12);
        for var in [m(&|a, _| a * a), m(&|_, b| b * b)] {
            assert!((var - 1.0).abs() < 0.003, "variance {var} σ²");
        }
        // The fourth moment: 3σ⁴ for a Gaussian, 1.4 % less cut at 4σ (at 3σ: 17 % less).
        let kurt = m(&|a, _| a.powi(4));
        assert!((kurt / 3.0 - 1.0).abs() < 0.02, "{kurt}");
        assert!(g.iter().all(|&(a, b, _)| (a * a + b * b).sqrt() <= FINE_REACH + 1e-12));
        // On a plane, marble's dipole under the grid's rays against its exact convolution with
        // the beam (the radial integral with the Bessel kernel), out to 5 mm.
        let (d, s) = (MARBLE.dipoles()[0], 0.85f64);
        let worst = (1..=50)
            .map(|k| {
                let r = 0.1 * f64::from(k) + 0.013;
                let quad: f64 =
                    g.iter().map(|&(a, b, w)| w * d.rd(((r - a * s).powi(2) + (b * s).powi(2)).sqrt())).sum();
                let (lo, hi, n) = ((r - 8.0 * s).max(0.0), r + 8.0 * s, 4000);
                let h = (hi - lo) / f64::from(n);
                let exact: f64 = (0..n)
                    .map(|i| {
                        let x = lo + (f64::from(i) + 0.5) * h;
                        d.rd(x) * x / (s * s)
                            * (-(x - r) * (x - r) / (2.0 * s * s)).exp()
                            * lightrig_pipelines::disco::kernel::i0e(x * r / (s * s))
                            * h
                    })
                    .sum();
                (quad / exact - 1.0).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 0.005, "{worst}");
    }
}
