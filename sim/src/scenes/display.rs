//! The BRDF display's liquid (thesis chapter 5): two voice coils, one per axis, each driving a
//! paddle whose motion launches plane waves across a liquid layer towards the displayed spot;
//! a laser beam arriving at incidence `β` is reflected by the spot onto a flat screen the
//! camera views. What the camera integrates over its exposure is the time-averaged
//! distribution of reflection directions: the displayed lobe.
//!
//! The scene reads each coil's **samples as the simulated controller played them**
//! ([`RigState::coils`], with [`RigState::coils_before`] for the waves already under way), not
//! the partials a plan asked for. A coil's drive `u(t)` (fraction of full scale) moves its
//! paddle through a damped resonance, `P(f) = G·f₀² / (f₀² − f² + i·f·f₀/Q)` (m per full
//! scale); the wave it launches reaches the spot `d` away with the phase `e^(−i·k·d)` and the
//! viscous decay `e^(−κ·d)` of [`Liquid`]. So the true response is
//! `H(f) = P(f)·e^(−(κ + i·k)·d)` (surface amplitude at the spot per unit drive), and the slope
//! there along the axis is `s(t) = ℱ⁻¹[−i·k(f)·H(f)·ℱ[u]]`, done with one FFT per coil per
//! frame. The waves on the two axes cross at right angles and add: the surface's gradient is
//! `(sx, sy)`.
//!
//! The optics are exact: each sample's facet (normal `∝ (−sx, −sy, 1)`) mirrors the beam, and
//! the reflected ray is intersected with the screen's plane ([`ScreenView`]: a flat screen at
//! a distance, facing the mirror direction or turned from it, a camera pixel per square patch
//! of it). The picture is a histogram of where the rays land over the exposure's samples
//! (each ray the beam's Gaussian spot, `beam_sigma` rad at the screen's distance, integrated
//! over every pixel it touches), normalised so that a still beam on a pixel's centre peaks at
//! radiance [`DisplayScene::peak`].
//!
//! A lab's tank and coils are not ideal: [`Faults`] adds a surfactant film's damping, the
//! far wall's and the paddle's reflections, the coils' saturation and harmonics and the
//! crosstalk between them, each switchable ([`scene_for`](crate::scenes::scene_for) turns
//! all on).
//!
//! Shared with the fit it scores (`host::fit::display`, `pipelines::display`): the screen's
//! numbers (the rig file's `[plan.screen]`, exact), a Gaussian beam (the fit blurs its lobe by
//! one), [`Liquid`] (so the calibration's wave number is the truth's) and the coils' sample
//! rate. Not shared: the faults (the fit measures `|H|` at small drive and learns the rest
//! from what the camera saw), the reflection and the ray–plane intersection (the fit maps pixels to
//! facet tilts by half vectors), the paddle and the path (the fit measures only `|H|`), and
//! the lobe's shape (the fit fits Ward's lobe; the scene makes what the controller played).

use std::sync::{Arc, Mutex};

use lightrig_pipelines::display::slopes::erf;
use lightrig_pipelines::display::Liquid;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

use crate::camera::{RigState, Scene};

/// One coil's actuator and the path of its waves to the displayed spot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Actuator {
    /// Paddle amplitude per full-scale drive well below resonance, m.
    pub gain_m: f64,
    /// Resonance of the paddle in contact with the liquid, Hz.
    pub resonance_hz: f64,
    /// Quality factor of that resonance.
    pub q: f64,
    /// Distance from the paddle to the displayed spot, m.
    pub distance_m: f64,
    /// Distance from the paddle to the tank's far wall behind the spot, m.
    pub tank_m: f64,
}

impl Actuator {
    /// The actuator's numbers, bit for bit (a cache key).
    fn to_bits(self) -> [u64; 5] {
        [self.gain_m, self.resonance_hz, self.q, self.distance_m, self.tank_m].map(f64::to_bits)
    }

    /// The paddle's complex response at `f` Hz, m per full scale.
    pub fn paddle(&self, f: f64) -> Complex<f64> {
        let f0 = self.resonance_hz;
        self.gain_m * f0 * f0 / Complex::new(f0 * f0 - f * f, f * f0 / self.q)
    }

    /// The true response `H(f)`: surface amplitude at the spot per full-scale drive, complex.
    pub fn response(&self, liquid: &Liquid, f: f64) -> Complex<f64> {
        if f <= 0.0 {
            return Complex::new(0.0, 0.0);
        }
        let k = liquid.wave_number(f);
        let travel = Complex::new(-liquid.spatial_damping(k) * self.distance_m, -k * self.distance_m).exp();
        self.paddle(f) * travel
    }

    /// The slope along the axis at the spot per full-scale drive at `f` Hz, complex, with the
    /// liquid's surface as `faults` has it (clean or filmed) and the waves the walls send
    /// back when `faults.walls`: the paddle's wave `e^(−q·d)` (`q = κ + i·k`), minus the far
    /// wall's reflection `R_w·e^(−q·(2L − d))` (a wave running back has the opposite slope),
    /// both bounced between wall and paddle `1 / (1 − R_w·R_p·e^(−2·q·L))`.
    pub fn slope_response(&self, liquid: &Liquid, f: f64, faults: Faults) -> Complex<f64> {
        if f <= 0.0 {
            return Complex::new(0.0, 0.0);
        }
        let k = liquid.wave_number(f);
        let q = Complex::new(damping(liquid, k, f, faults.film), k);
        let (d, l) = (self.distance_m, self.tank_m.max(self.distance_m));
        let mut path = (-q * d).exp();
        if faults.walls {
            let back = WALL_REFLECTION * (-q * (2.0 * l - d)).exp();
            path = (path - back) / (1.0 - WALL_REFLECTION * PADDLE_REFLECTION * (-q * 2.0 * l).exp());
        }
        // ∂/∂x of a·e^(i(ωt − kx)) is −i·k times it.
        Complex::new(0.0, -k) * self.paddle(f) * path
    }
}

/// Amplitude decay over distance of a wave of wave number `k` at `f` Hz, 1/m: Lamb's clean
/// surface ([`Liquid::spatial_damping`], temporal rate `2ν·k²`), or under an inextensible
/// surfactant film, whose rate `k·√(ν·ω/8)` (Lamb §351) is 2.3 times the clean one for water
/// at 200 Hz.
fn damping(liquid: &Liquid, k: f64, f: f64, film: bool) -> f64 {
    let clean = liquid.spatial_damping(k);
    if !film {
        return clean;
    }
    let nu = liquid.kinematic_viscosity;
    let w = 2.0 * std::f64::consts::PI * f;
    clean * (k * (nu * w / 8.0).sqrt()) / (2.0 * nu * k * k)
}

/// What a tank and coils as labs have them add to the ideal display, each switchable
/// ([`scene_for`](crate::scenes::scene_for) turns all on; [`DisplayScene::small_water`] is
/// ideal). The values each uses are the constants beside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Faults {
    /// A surfactant film on the water (any tank left open for an hour): the surface damps waves
    /// as an inextensible film ([`damping`]).
    pub film: bool,
    /// The far wall ([`WALL_REFLECTION`]) and the paddle ([`PADDLE_REFLECTION`]) send waves
    /// back across the spot: a standing-wave ripple in the response, a period of 25–40 Hz in
    /// the 2 cm tank.
    pub walls: bool,
    /// Each coil's excursion saturates ([`SATURATION`]) and its suspension is asymmetric
    /// ([`SECOND_ORDER`]): harmonics, intermodulation and compression at large drive.
    pub harmonics: bool,
    /// Each coil's drive leaks into the other's ([`CROSSTALK`]): the frame couples the arms.
    pub crosstalk: bool,
}

/// Reflection coefficient of the tank's far wall for capillary waves (a plain wall with a
/// strip of foam at the waterline, no beach).
pub const WALL_REFLECTION: f64 = 0.35;
/// Reflection coefficient of the paddle for waves coming back to it.
pub const PADDLE_REFLECTION: f64 = 0.5;
/// The drive (fraction of full scale) at which a coil's excursion bends over: it moves as
/// `S·tanh(u/S)`, a sine of 0.3's fundamental 3.5 % short.
pub const SATURATION: f64 = 0.8;
/// The asymmetric suspension's second-order term: the excursion gains `c·u²` (a 1.2 % second
/// harmonic at u = 0.3).
pub const SECOND_ORDER: f64 = 0.08;
/// The share of each coil's drive that reaches the other coil (−28 dB).
pub const CROSSTALK: f64 = 0.04;

impl Faults {
    /// The ideal display.
    pub const NONE: Faults = Faults { film: false, walls: false, harmonics: false, crosstalk: false };
    /// Every fault on.
    pub const ALL: Faults = Faults { film: true, walls: true, harmonics: true, crosstalk: true };
    /// Each fault's name, as reports and `only` spell them.
    pub const NAMES: [&'static str; 4] = ["film", "walls", "harmonics", "crosstalk"];

    /// Only the fault named `name` on.
    pub fn only(name: &str) -> Option<Faults> {
        let mut f = Faults::NONE;
        match name {
            "film" => f.film = true,
            "walls" => f.walls = true,
            "harmonics" => f.harmonics = true,
            "crosstalk" => f.crosstalk = true,
            _ => return None,
        }
        Some(f)
    }

    /// The names of the faults on, or `["none"]`.
    pub fn names(&self) -> Vec<&'static str> {
        let on = [self.film, self.walls, self.harmonics, self.crosstalk];
        let v: Vec<&'static str> = Self::NAMES.iter().zip(on).filter(|(_, o)| *o).map(|(n, _)| *n).collect();
        if v.is_empty() {
            vec!["none"]
        } else {
            v
        }
    }
}

/// A coil's excursion for the drive `u` (fraction of full scale) with `faults.harmonics`.
fn excursion(u: f64, faults: Faults) -> f64 {
    if faults.harmonics {
        SATURATION * (u / SATURATION).tanh() + SECOND_ORDER * u * u
    } else {
        u
    }
}

/// The screen picture's side, pixels (`scene_for`'s).
pub const SCREEN_PIXELS: u32 = 192;

/// Where the screen stands, as the scene draws it (the rig file's `[plan.screen]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScreenView {
    /// From the spot to the screen along the mirror direction, m.
    pub distance_m: f64,
    /// Side of the patch of screen one pixel sees, m.
    pub pitch_m: f64,
    /// The beam's incidence on the still liquid, in the x–z plane, coming from −x, rad.
    pub incidence_rad: f64,
    /// The screen turned from facing the mirror direction, about its vertical, rad.
    pub tilt_rad: f64,
    /// Image position (pixels from the top-left corner) of the mirror direction.
    pub centre_px: [f64; 2],
}

impl ScreenView {
    /// The screen of the demo's rig file: 50 mm from the spot, 0.6 mm per pixel of a `side`
    /// pixel picture centred on the mirror direction, the beam 10° off the normal.
    pub fn demo(side: u32) -> Self {
        ScreenView {
            distance_m: 0.05,
            pitch_m: 0.6e-3 * f64::from(SCREEN_PIXELS) / f64::from(side.max(1)),
            incidence_rad: 10f64.to_radians(),
            tilt_rad: 0.0,
            centre_px: [f64::from(side) / 2.0; 2],
        }
    }

    /// Where a ray leaving the spot along `r` meets the screen, in image pixels (continuous),
    /// if it does (in front of the spot).
    pub fn land(&self, r: [f64; 3]) -> Option<(f64, f64)> {
        let (sb, cb) = self.incidence_rad.sin_cos();
        // The screen's frame: its normal starts on the mirror direction (sin β, 0, cos β) and
        // is turned by the tilt about the vertical y; image x lies in the x–z plane.
        let (st, ct) = self.tilt_rad.sin_cos();
        let normal = [sb * ct + cb * st, 0.0, cb * ct - sb * st];
        let across = [cb * ct - sb * st, 0.0, -(sb * ct + cb * st)];
        let centre = [self.distance_m * sb, 0.0, self.distance_m * cb];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let along = dot(r, normal);
        if along <= 0.0 {
            return None;
        }
        let t = dot(centre, normal) / along;
        let hit = [r[0] * t - centre[0], r[1] * t - centre[1], r[2] * t - centre[2]];
        Some((self.centre_px[0] + dot(hit, across) / self.pitch_m, self.centre_px[1] + hit[1] / self.pitch_m))
    }
}

/// The display scene.
pub struct DisplayScene {
    /// The liquid.
    pub liquid: Liquid,
    /// The coil on voice-coil channel 0 makes waves along x; channel 1's along y.
    pub actuators: [Actuator; 2],
    /// Image size, pixels.
    pub size: (u32, u32),
    /// The screen.
    pub screen: ScreenView,
    /// The beam's Gaussian spot, σ as an angle from the spot, rad.
    pub beam_sigma: f64,
    /// Radiance of a still beam's peak.
    pub peak: f64,
    /// Each coil's sample rate, Hz (the rig file's `sample_rate_hz`).
    pub rates_hz: [f64; 2],
    /// What a real tank and coils add ([`Faults::NONE`] in [`DisplayScene::small_water`]).
    pub faults: Faults,
    /// The last exposure's picture, by the samples it came from (pixels render in parallel).
    cache: Mutex<Option<(u64, Arc<Vec<f64>>)>>,
    /// Each coil's response at the FFT bins of the sizes used (`bins`).
    responses: Mutex<Vec<(ResponseKey, Bins)>>,
}

/// What a coil's response at the FFT's bins depends on: axis, rate, size, faults, actuator,
/// liquid.
type ResponseKey = (usize, u64, usize, Faults, [u64; 5], [u64; 4]);
/// A coil's response at each FFT bin up to half the size.
type Bins = Arc<Vec<Complex<f64>>>;

impl DisplayScene {
    /// The thesis's small setup 2 on water: efficiency peak near 200 Hz (coils of slightly
    /// different make, so each needs its own calibration) at the sides of a 2 × 2 cm tank, the
    /// spot 10 and 12 mm from them; ideal ([`Faults::NONE`]);
    /// a `width × height` view of the demo's screen ([`ScreenView::demo`]: ±49° about the
    /// mirror direction on the wider side, where α = 0.14 reflects with σ ≈ 0.2 rad).
    pub fn small_water(width: u32, height: u32) -> Self {
        // A 2 cm tank: each paddle at one side, the spot 10 and 12 mm from them.
        let a = Actuator { gain_m: 5.0e-4, resonance_hz: 190.0, q: 2.0, distance_m: 0.010, tank_m: 0.020 };
        let b = Actuator { gain_m: 4.0e-4, resonance_hz: 215.0, q: 2.5, distance_m: 0.012, tank_m: 0.020 };
        let mut screen = ScreenView::demo(width.max(height));
        screen.centre_px = [f64::from(width) / 2.0, f64::from(height) / 2.0];
        DisplayScene {
            liquid: Liquid::WATER,
            actuators: [a, b],
            size: (width, height),
            screen,
            beam_sigma: 0.018,
            peak: 1.0,
            rates_hz: [48_000.0; 2],
            faults: Faults::NONE,
            cache: Mutex::new(None),
            responses: Mutex::new(Vec::new()),
        }
    }

    /// The slope along the coil's axis at the spot, at each of `now`'s samples, from the
    /// coil's drive: `before` (played earlier, for the waves already under way) then `now`
    /// (this coil alone: no crosstalk).
    pub fn slopes(&self, axis: usize, rate_hz: f64, before: &[i16], now: &[i16]) -> Vec<f64> {
        let drive: Vec<f64> = before.iter().chain(now).map(|&s| full_scale(s)).collect();
        self.slopes_of(axis, rate_hz, &drive, before.len())
    }

    /// The slope at the spot from coil `axis`'s drive `drive` (fractions of full scale, the
    /// first `skip` of them played before the exposure), at each sample after `skip`.
    fn slopes_of(&self, axis: usize, rate_hz: f64, drive: &[f64], skip: usize) -> Vec<f64> {
        let n_total = drive.len();
        if n_total <= skip {
            return Vec::new();
        }
        // Zero padding to twice the length: the circular convolution of the FFT never wraps
        // the response of the last samples onto the first.
        let n = (2 * n_total).next_power_of_two();
        let mut buf: Vec<Complex<f64>> = drive
            .iter()
            .map(|&u| Complex::new(excursion(u, self.faults), 0.0))
            .chain(std::iter::repeat(Complex::new(0.0, 0.0)))
            .take(n)
            .collect();
        let mut planner = FftPlanner::new();
        planner.plan_fft_forward(n).process(&mut buf);
        let g = self.bins(axis, rate_hz, n);
        for j in 1..=n / 2 {
            buf[j] *= g[j];
            if j != n - j {
                buf[n - j] *= g[j].conj();
            }
        }
        buf[0] = Complex::new(0.0, 0.0);
        planner.plan_fft_inverse(n).process(&mut buf);
        buf[skip..n_total].iter().map(|c| c.re / n as f64).collect()
    }

    /// Coil `axis`'s slope response at each bin `0..=n/2` of an `n`-point FFT at `rate_hz`,
    /// computed once per size (each bin's wave number takes a root search).
    fn bins(&self, axis: usize, rate_hz: f64, n: usize) -> Bins {
        let l = &self.liquid;
        let liquid = [l.density, l.surface_tension, l.kinematic_viscosity, l.depth].map(f64::to_bits);
        let key = (axis, rate_hz.to_bits(), n, self.faults, self.actuators[axis].to_bits(), liquid);
        let mut cache = self.responses.lock().expect("not poisoned");
        if let Some((_, g)) = cache.iter().find(|(k, _)| *k == key) {
            return g.clone();
        }
        let act = self.actuators[axis];
        let g: Bins = Arc::new(
            (0..=n / 2)
                .map(|j| act.slope_response(&self.liquid, j as f64 * rate_hz / n as f64, self.faults))
                .collect(),
        );
        cache.push((key, g.clone()));
        g
    }

    /// `|H(f)|` as a calibration by one small sine measures it on coil `axis`: the slope's
    /// amplitude at the spot per full-scale drive over the wave number, walls and film as
    /// [`DisplayScene::faults`] has them (the coils' nonlinearity vanishes at small drive).
    pub fn effective_response(&self, axis: usize, f: f64) -> f64 {
        let k = self.liquid.wave_number(f);
        self.actuators[axis].slope_response(&self.liquid, f, self.faults).norm() / k
    }

    /// The surface's gradient `(∂h/∂x, ∂h/∂y)` at the spot over the exposure, one per sample
    /// (a silent axis stays level). With crosstalk each coil also plays [`CROSSTALK`] of the
    /// other's drive (the two at the same rate; at different rates they cannot couple
    /// sample by sample and the scene keeps them apart).
    pub fn gradients(&self, state: &RigState) -> Vec<(f64, f64)> {
        fn part(v: &[Vec<i16>], a: usize) -> &[i16] {
            v.get(a).map_or(&[][..], Vec::as_slice)
        }
        self.gradients_of(
            [part(&state.coils_before, 0), part(&state.coils_before, 1)],
            [part(&state.coils, 0), part(&state.coils, 1)],
        )
    }

    /// [`DisplayScene::gradients`] of each coil's samples played `before` the exposure and
    /// during it (`now`).
    pub fn gradients_of(&self, before: [&[i16]; 2], now: [&[i16]; 2]) -> Vec<(f64, f64)> {
        // Both coils' drives on one time line: `lead` samples before the exposure, `len` in it.
        let lead = before[0].len().max(before[1].len());
        let len = now[0].len().max(now[1].len());
        let mut drives = [vec![0.0; lead + len], vec![0.0; lead + len]];
        for (a, d) in drives.iter_mut().enumerate() {
            let (before, now) = (before[a], now[a]);
            for (i, &s) in before.iter().enumerate() {
                d[lead - before.len() + i] = full_scale(s);
            }
            for (i, &s) in now.iter().enumerate() {
                d[lead + i] = full_scale(s);
            }
        }
        if self.faults.crosstalk && self.rates_hz[0] == self.rates_hz[1] {
            let [x, y] = &drives;
            let mixed = |a: &[f64], b: &[f64]| -> Vec<f64> {
                a.iter().zip(b).map(|(&a, &b)| a + CROSSTALK * b).collect()
            };
            drives = [mixed(x, y), mixed(y, x)];
        }
        let silent = |a: usize| now[a].is_empty() && !self.faults.crosstalk;
        let axis = |a: usize| {
            if silent(a) {
                Vec::new()
            } else {
                self.slopes_of(a, self.rates_hz[a], &drives[a], lead)
            }
        };
        let (sx, sy) = (axis(0), axis(1));
        let n = sx.len().max(sy.len());
        (0..n)
            .map(|i| {
                let s = |v: &[f64]| v.get(i).copied().unwrap_or(0.0);
                (s(&sx), s(&sy))
            })
            .collect()
    }

    fn picture(&self, state: &RigState) -> Arc<Vec<f64>> {
        let key = coil_key(state);
        let mut cache = self.cache.lock().expect("not poisoned");
        if let Some((k, pic)) = cache.as_ref() {
            if *k == key {
                return pic.clone();
            }
        }
        let pic = Arc::new(self.draw(state));
        *cache = Some((key, pic.clone()));
        pic
    }

    /// The screen over the exposure.
    fn draw(&self, state: &RigState) -> Vec<f64> {
        let mut gradients = self.gradients(state);
        if gradients.is_empty() {
            // Silent coils: a still surface, the beam straight back.
            gradients.push((0.0, 0.0));
        }
        self.picture_of(&gradients)
    }

    /// The screen's picture when the spot's gradient runs through `gradients` `(∂h/∂x, ∂h/∂y)`
    /// over the exposure.
    pub fn picture_of(&self, gradients: &[(f64, f64)]) -> Vec<f64> {
        let (w, h) = (self.size.0 as usize, self.size.1 as usize);
        let (sb, cb) = self.screen.incidence_rad.sin_cos();
        // Towards the light.
        let wi = [-sb, 0.0, cb];
        let mut hist = vec![0.0; w * h];
        let weight = 1.0 / gradients.len().max(1) as f64;
        // The spot's σ on the screen, pixels.
        let sigma = (self.beam_sigma * self.screen.distance_m / self.screen.pitch_m).max(1e-6);
        for &(gx, gy) in gradients {
            let norm = (gx * gx + gy * gy + 1.0).sqrt();
            let n = [-gx / norm, -gy / norm, 1.0 / norm];
            let c = 2.0 * (wi[0] * n[0] + wi[1] * n[1] + wi[2] * n[2]);
            let r = [c * n[0] - wi[0], c * n[1] - wi[1], c * n[2] - wi[2]];
            let Some((px, py)) = self.screen.land(r) else { continue };
            // The beam's Gaussian spot about where the ray lands, integrated over each pixel.
            let (wx, x0) = spot_weights(px, sigma, w);
            let (wy, y0) = spot_weights(py, sigma, h);
            for (j, vy) in wy.iter().enumerate() {
                let row = (y0 + j) * w + x0;
                for (i, vx) in wx.iter().enumerate() {
                    hist[row + i] += weight * vx * vy;
                }
            }
        }
        // A still beam landing on a pixel's centre peaks at `peak`.
        let centre = erf(0.5 / (sigma * std::f64::consts::SQRT_2));
        let norm = self.peak / (centre * centre);
        hist.into_iter().map(|v| v * norm).collect()
    }
}

/// A sample as a fraction of full scale.
fn full_scale(s: i16) -> f64 {
    f64::from(s) / f64::from(i16::MAX)
}

/// The share of a Gaussian of `sigma` pixels about `at` (pixels, continuous) that falls in
/// each pixel of a line `n` long, from the first pixel within 5σ: `(shares, first)`.
fn spot_weights(at: f64, sigma: f64, n: usize) -> (Vec<f64>, usize) {
    let lo = (at - 5.0 * sigma).floor().clamp(0.0, n as f64) as usize;
    let hi = (at + 5.0 * sigma).ceil().clamp(0.0, n as f64) as usize;
    let cdf = |x: f64| 0.5 * (1.0 + erf((x - at) / (sigma * std::f64::consts::SQRT_2)));
    ((lo..hi).map(|i| cdf(i as f64 + 1.0) - cdf(i as f64)).collect(), lo)
}

/// A key for an exposure's coil samples, cheap enough to take per pixel: where they lie, how
/// many, and 32 of them spread over each (two exposures of waves never agree on all of those).
fn coil_key(state: &RigState) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for c in state.coils.iter().chain(&state.coils_before) {
        (c.as_ptr() as usize, c.len()).hash(&mut h);
        c.iter().step_by(c.len() / 32 + 1).for_each(|s| s.hash(&mut h));
    }
    state.exposure_s.to_bits().hash(&mut h);
    h.finish()
}

impl Scene for DisplayScene {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        let pic = self.picture(state);
        let v = pic[y as usize * self.size.0 as usize + x as usize];
        [v, v, v]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lightrig_firmware::synth::Synth;
    use lightrig_pipelines::display::mapping::{
        golden_phase, ward_of_slope_roughness, Axis, Response, X_FREQUENCIES, Y_FREQUENCIES,
    };
    use lightrig_pipelines::display::slopes::{arcsine_cdf, fitted_gaussian_sd, ks_distance, ks_to_gaussian};
    use lightrig_protocol::sequence::Partial;

    const RATE: u32 = 48_000;

    /// What the controller's synthesiser plays for `partials` `(Hz, drive, phase turns)`:
    /// `lead` seconds of settling (not returned as `now`), then `secs`.
    fn played(partials: &[(f64, f64, f64)], lead: f64, secs: f64) -> (Vec<i16>, Vec<i16>) {
        let mut synth = Synth::new(RATE);
        let p: Vec<Partial> = partials
            .iter()
            .map(|&(f, d, ph)| Partial {
                freq_mhz: (f * 1000.0).round() as u32,
                amplitude: (d * f64::from(u16::MAX)).round() as u16,
                phase: (ph * 65536.0) as u16,
            })
            .collect();
        synth.set(&p, 0).unwrap();
        let mut before = vec![0i16; (lead * f64::from(RATE)) as usize];
        synth.fill(&mut before);
        let mut now = vec![0i16; (secs * f64::from(RATE)) as usize];
        synth.fill(&mut now);
        (before, now)
    }

    fn true_response(scene: &DisplayScene, axis: usize) -> Response {
        let points = (10..=80)
            .map(|i| f64::from(i) * 5.0)
            .map(|f| (f, scene.actuators[axis].response(&scene.liquid, f).norm()))
            .collect();
        Response { points }
    }

    #[test]
    fn a_surfactant_film_damps_water_waves_at_200_hz_about_twice_as_fast() {
        // Clean water's damping 2ν·k² against an inextensible film's, the ratio the literature
        // gives for water at 200 Hz (about 2.3).
        let w = Liquid::WATER;
        let k = w.wave_number(200.0);
        let ratio = damping(&w, k, 200.0, true) / damping(&w, k, 200.0, false);
        assert!((2.1..2.4).contains(&ratio), "{ratio}");
        // So the wave reaching the spot 10 mm away keeps less of its amplitude.
        let mut scene = DisplayScene::small_water(16, 16);
        let clean = scene.effective_response(0, 200.0);
        scene.faults = Faults::only("film").unwrap();
        let filmed = scene.effective_response(0, 200.0);
        let kappa = w.spatial_damping(k);
        assert!((filmed / clean - (-(ratio - 1.0) * kappa * 0.010).exp()).abs() < 1e-12);
    }

    #[test]
    fn walls_reflect_waves_back_across_the_spot_and_the_slope_vanishes_at_a_wall() {
        let w = Liquid::WATER;
        let all = Faults::only("walls").unwrap();
        // At the wall itself the incident and reflected slopes cancel but for what the wall
        // lets through: (1 − R_w), bounced between wall and paddle.
        let a = Actuator { gain_m: 5.0e-4, resonance_hz: 190.0, q: 2.0, distance_m: 0.02, tank_m: 0.02 };
        for f in [120.0, 200.0, 310.0] {
            let k = w.wave_number(f);
            let q = Complex::new(damping(&w, k, f, false), k);
            let bounce = 1.0 - WALL_REFLECTION * PADDLE_REFLECTION * (-q * 0.04).exp();
            let ratio = a.slope_response(&w, f, all) * bounce / a.slope_response(&w, f, Faults::NONE);
            assert!((ratio - Complex::new(1.0 - WALL_REFLECTION, 0.0)).norm() < 1e-12, "{f} Hz: {ratio}");
        }
        // At the spot, 10 mm before the wall, a ripple: |H| rises and falls against the
        // ideal tank's as the round trip's phase turns, by about the reflection coefficient.
        let scene = DisplayScene::small_water(16, 16);
        let mut walled = DisplayScene::small_water(16, 16);
        walled.faults = all;
        let ratios: Vec<f64> = (90..=340)
            .map(f64::from)
            .map(|f| walled.effective_response(0, f) / scene.effective_response(0, f))
            .collect();
        let (lo, hi) = ratios.iter().fold((f64::MAX, 0.0f64), |(l, h), &r| (l.min(r), h.max(r)));
        assert!(lo < 0.85 && hi > 1.15 && hi < 1.6, "{lo}..{hi}");
        // Its maxima lie where a round trip of the spot's 20 mm to the wall and back turns the
        // phase by an odd multiple of π (there the two slopes add), give or take the bounce.
        let peaks: Vec<f64> = (1..ratios.len() - 1)
            .filter(|&i| ratios[i] > ratios[i - 1] && ratios[i] > ratios[i + 1])
            .map(|i| 90.0 + i as f64)
            .collect();
        assert!(peaks.len() >= 6, "{peaks:?}");
        for &f in &peaks {
            let turns = w.wave_number(f) * 0.020 / std::f64::consts::TAU;
            let off = (turns - turns.floor() - 0.5).abs();
            assert!(off < 0.2, "{f} Hz: {turns} turns");
        }
    }

    #[test]
    fn saturating_coils_compress_large_sines_and_add_harmonics_but_not_small_ones() {
        let mut scene = DisplayScene::small_water(16, 16);
        let f = 211.0;
        let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        // The slope's amplitude at 2f, by its projection on that frequency over 1 s.
        let at = |v: &[f64], g: f64| {
            let (mut c, mut s) = (0.0, 0.0);
            for (i, x) in v.iter().enumerate() {
                let t = std::f64::consts::TAU * g * i as f64 / f64::from(RATE);
                c += x * t.cos();
                s += x * t.sin();
            }
            2.0 * (c * c + s * s).sqrt() / v.len() as f64
        };
        for (drive, compressed) in [(0.01, 1.0), (0.3, 1.0 - 0.3f64.powi(2) / (4.0 * SATURATION.powi(2)))] {
            let (before, now) = played(&[(f, drive, 0.0)], 0.1, 1.0);
            scene.faults = Faults::NONE;
            let ideal = scene.slopes(0, f64::from(RATE), &before, &now);
            scene.faults = Faults::only("harmonics").unwrap();
            let real = scene.slopes(0, f64::from(RATE), &before, &now);
            // The fundamental shrinks as tanh's cubic term says, −u²/(4S²).
            let ratio = at(&real, f) / at(&ideal, f);
            assert!((ratio - compressed).abs() < 0.002, "drive {drive}: {ratio} against {compressed}");
            // The suspension's c·u² adds a second harmonic of c·u/2 in excursion, which the
            // liquid carries at 2f's response.
            let g = |x: f64| scene.effective_response(0, x) * scene.liquid.wave_number(x);
            let want = SECOND_ORDER * drive * drive / 2.0 * g(2.0 * f);
            assert!(
                (at(&real, 2.0 * f) / want - 1.0).abs() < 0.02,
                "drive {drive}: 2f {}",
                at(&real, 2.0 * f)
            );
            assert!(rms(&real) < rms(&ideal) * 1.0001, "drive {drive}");
        }
    }

    #[test]
    fn crosstalk_moves_the_silent_coils_axis_by_its_share_of_the_other_drive() {
        let mut scene = DisplayScene::small_water(16, 16);
        scene.faults = Faults::only("crosstalk").unwrap();
        let f = 193.0;
        let (before, now) = played(&[(f, 0.1, 0.0)], 0.1, 1.0);
        let g = scene.gradients_of([&before, &[]], [&now, &[]]);
        let rms = |v: &mut dyn Iterator<Item = f64>| {
            let v: Vec<f64> = v.collect();
            (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
        };
        let (x, y) = (rms(&mut g.iter().map(|p| p.0)), rms(&mut g.iter().map(|p| p.1)));
        // The y coil plays CROSSTALK of the x drive through its own response at f.
        let want = CROSSTALK * scene.effective_response(1, f) / scene.effective_response(0, f);
        assert!((y / x / want - 1.0).abs() < 0.01, "{} against {want}", y / x);
        // Without it the y axis stays level.
        scene.faults = Faults::NONE;
        let g = scene.gradients_of([&before, &[]], [&now, &[]]);
        assert!(g.iter().all(|p| p.1 == 0.0));
    }

    #[test]
    fn the_actuators_are_most_efficient_near_200_hz_as_the_small_setup() {
        let scene = DisplayScene::small_water(64, 64);
        for axis in 0..2 {
            // Slope per unit drive: what the display spends drive on.
            let eff = |f: f64| {
                scene.actuators[axis].response(&scene.liquid, f).norm() * scene.liquid.wave_number(f)
            };
            let best =
                (20..=160).map(|i| f64::from(i) * 5.0).max_by(|a, b| eff(*a).total_cmp(&eff(*b))).unwrap();
            assert!((150.0..260.0).contains(&best), "axis {axis}: {best} Hz");
        }
    }

    #[test]
    fn a_tilted_surface_sends_the_beam_where_the_mirror_law_says() {
        // Beam straight down, screen square on 50 mm up, 0.5 mm per pixel, centre (32, 32):
        // a gradient g along x turns the normal by atan g towards −x, the reflection by twice
        // that, so the spot lands D·tan(2·atan g) from the centre towards −x.
        let mut scene = DisplayScene::small_water(64, 64);
        scene.screen = ScreenView {
            distance_m: 0.05,
            pitch_m: 0.5e-3,
            incidence_rad: 0.0,
            tilt_rad: 0.0,
            centre_px: [32.0, 32.0],
        };
        // A spot of 2 px: its pixel-integrated centroid is where it landed, to 1e-4 px (the
        // error function's approximation errs by 1.5e-7).
        scene.beam_sigma = 0.02;
        for (g, axis) in [(0.1, 0), (-0.05, 1)] {
            let grad = if axis == 0 { (g, 0.0) } else { (0.0, g) };
            let pic = scene.picture_of(&[grad]);
            let off = 0.05 * (2.0 * f64::atan(g)).tan() / 0.5e-3;
            let (mut m0, mut mx, mut my) = (0.0, 0.0, 0.0);
            for (i, v) in pic.iter().enumerate() {
                m0 += v;
                mx += v * ((i % 64) as f64 + 0.5);
                my += v * ((i / 64) as f64 + 0.5);
            }
            let (x, y) = (mx / m0, my / m0);
            let want = if axis == 0 { (32.0 - off, 32.0) } else { (32.0, 32.0 - off) };
            assert!((x - want.0).abs() < 1e-4 && (y - want.1).abs() < 1e-4, "{g}: ({x}, {y}) vs {want:?}");
        }
        // At incidence β the still surface mirrors the beam onto the centre of a screen that
        // faces the mirror direction, and a ray away from the screen misses it.
        scene.screen.incidence_rad = 0.3;
        assert_eq!(scene.screen.land([0.3f64.sin(), 0.0, 0.3f64.cos()]), Some((32.0, 32.0)));
        assert_eq!(scene.screen.land([-0.3f64.sin(), 0.0, -0.3f64.cos()]), None);
    }

    #[test]
    fn one_sine_played_by_the_synthesiser_gives_the_arcsine_law_of_eq_5_6() {
        let scene = DisplayScene::small_water(64, 64);
        let (f, drive) = (167.0, 0.2);
        let (before, now) = played(&[(f, drive, 0.0)], 0.1, 0.5);
        let s = scene.slopes(0, f64::from(RATE), &before, &now);
        // ρ = k·|H|·drive: the wave's slope amplitude.
        let rho = scene.liquid.wave_number(f) * scene.actuators[0].response(&scene.liquid, f).norm() * drive;
        let deltas: Vec<f64> = s.iter().map(|s| 2.0 * s).collect();
        let ks = ks_distance(&deltas, |d| arcsine_cdf(d, rho, 0.0));
        assert!(ks < 0.01, "KS distance to Eq. 5.6: {ks}");
        assert!(ks_to_gaussian(&deltas) > 0.05);
    }

    #[test]
    fn seven_partials_solved_with_the_true_response_show_the_asked_alpha_as_a_bell() {
        let scene = DisplayScene::small_water(64, 64);
        for (axis, freqs) in [(0, &X_FREQUENCIES), (1, &Y_FREQUENCIES)] {
            let a = Axis {
                name: "x",
                frequencies: freqs.to_vec(),
                response: true_response(&scene, axis),
                max_drive: 0.5,
                max_slope: 6f64.to_radians(),
            };
            for alpha in [0.02, 0.08, 0.14] {
                let p = a.solve(alpha, &scene.liquid).unwrap();
                let partials: Vec<_> =
                    p.iter().enumerate().map(|(i, q)| (q.frequency, q.drive, golden_phase(i))).collect();
                let (before, now) = played(&partials, 0.1, 1.0);
                // The facet tilt is the slope: the bell fitted to it has the standard deviation
                // α_s/√2 of the tilts Ward's lobe shows as α (over the partials' whole period).
                let slopes = scene.slopes(axis, f64::from(RATE), &before, &now);
                let shown = ward_of_slope_roughness(fitted_gaussian_sd(&slopes) * 2f64.sqrt());
                assert!((shown / alpha - 1.0).abs() < 0.01, "axis {axis} α {alpha}: shown {shown}");
                let ks = ks_to_gaussian(&slopes);
                assert!(ks < 0.03, "axis {axis} α {alpha}: KS to a Gaussian {ks}");
            }
        }
    }
}
