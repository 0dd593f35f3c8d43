//! The BRDF display's liquid (thesis chapter 5): two voice coils, one per axis, each driving a
//! paddle whose motion launches plane waves across a liquid layer towards the displayed spot;
//! a laser beam (or a distant point light) at normal incidence is reflected by the spot onto a
//! screen the camera views. What the camera integrates over its exposure is the time-averaged
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
//! frame. A ray reflects to `δ = 2·atan(s)` on each axis (the waves on the two axes cross at
//! right angles and, being small, add).
//!
//! The screen: pixel `(x, y)` sees the reflection angles `δ = ((x + ½ − w/2)·p, (y + ½ − h/2)·p)`
//! with `p` the angular pitch; the beam has a Gaussian profile of `beam_sigma` rad. The
//! picture is a histogram of `δ(t)` over the exposure's samples (bilinear splats), blurred by
//! the beam, normalised so that a still beam's peak has radiance [`DisplayScene::peak`].

use std::sync::{Arc, Mutex};

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
}

impl Actuator {
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
}

/// The screen picture's side, pixels (`scene_for`'s).
pub const SCREEN_PIXELS: u32 = 192;

/// The display scene.
pub struct DisplayScene {
    /// The liquid.
    pub liquid: Liquid,
    /// The coil on voice-coil channel 0 makes waves along x; channel 1's along y.
    pub actuators: [Actuator; 2],
    /// Image size, pixels.
    pub size: (u32, u32),
    /// Angle one pixel spans on the screen, rad.
    pub pitch: f64,
    /// The beam's Gaussian σ on the screen, rad.
    pub beam_sigma: f64,
    /// Radiance of a still beam's peak.
    pub peak: f64,
    /// Each coil's sample rate, Hz (the rig file's `sample_rate_hz`).
    pub rates_hz: [f64; 2],
    /// The last exposure's picture, by the samples it came from (pixels render in parallel).
    cache: Mutex<Option<(u64, Arc<Vec<f64>>)>>,
}

impl DisplayScene {
    /// The thesis's small setup 2 on water: efficiency peak near 200 Hz (coils of slightly
    /// different make, so each needs its own calibration), the spot 10 mm from each paddle;
    /// a `width × height` view of the screen spanning ±1.2 rad on its wider side (α = 0.14
    /// spreads reflections with σ = 0.28 rad: the screen holds ±4σ of it).
    pub fn small_water(width: u32, height: u32) -> Self {
        let a = Actuator { gain_m: 5.0e-4, resonance_hz: 190.0, q: 2.0, distance_m: 0.010 };
        let b = Actuator { gain_m: 4.0e-4, resonance_hz: 215.0, q: 2.5, distance_m: 0.012 };
        let pitch = 2.4 / f64::from(width.max(height));
        DisplayScene {
            liquid: Liquid::WATER,
            actuators: [a, b],
            size: (width, height),
            pitch,
            beam_sigma: 1.5 * pitch,
            peak: 1.0,
            rates_hz: [48_000.0; 2],
            cache: Mutex::new(None),
        }
    }

    /// The slope along the coil's axis at the spot, at each of `now`'s samples, from the
    /// coil's drive: `before` (played earlier, for the waves already under way) then `now`.
    pub fn slopes(&self, axis: usize, rate_hz: f64, before: &[i16], now: &[i16]) -> Vec<f64> {
        let n_total = before.len() + now.len();
        if now.is_empty() {
            return Vec::new();
        }
        // Zero padding to twice the length: the circular convolution of the FFT never wraps
        // the response of the last samples onto the first.
        let n = (2 * n_total).next_power_of_two();
        let mut buf: Vec<Complex<f64>> = before
            .iter()
            .chain(now)
            .map(|&s| Complex::new(f64::from(s) / f64::from(i16::MAX), 0.0))
            .chain(std::iter::repeat(Complex::new(0.0, 0.0)))
            .take(n)
            .collect();
        let mut planner = FftPlanner::new();
        planner.plan_fft_forward(n).process(&mut buf);
        let act = self.actuators[axis];
        for j in 1..=n / 2 {
            let f = j as f64 * rate_hz / n as f64;
            let k = self.liquid.wave_number(f);
            // ∂/∂x of a·e^(i(ωt − kx)) is −i·k times it.
            let g = Complex::new(0.0, -k) * act.response(&self.liquid, f);
            buf[j] *= g;
            if j != n - j {
                buf[n - j] *= g.conj();
            }
        }
        buf[0] = Complex::new(0.0, 0.0);
        planner.plan_fft_inverse(n).process(&mut buf);
        buf[before.len()..n_total].iter().map(|c| c.re / n as f64).collect()
    }

    /// Reflection angles `(δx, δy)` over the exposure, one per sample (both coils run at the
    /// same rate; a silent axis stays level).
    pub fn reflections(&self, state: &RigState) -> Vec<(f64, f64)> {
        let axis = |a: usize| {
            let now = state.coils.get(a).map_or(&[][..], Vec::as_slice);
            let before = state.coils_before.get(a).map_or(&[][..], Vec::as_slice);
            self.slopes(a, self.rates_hz[a], before, now)
        };
        let (sx, sy) = (axis(0), axis(1));
        let n = sx.len().max(sy.len());
        (0..n)
            .map(|i| {
                let s = |v: &[f64]| v.get(i).copied().unwrap_or(0.0);
                (2.0 * s(&sx).atan(), 2.0 * s(&sy).atan())
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
        let (w, h) = (self.size.0 as usize, self.size.1 as usize);
        let mut rays = self.reflections(state);
        if rays.is_empty() {
            // Silent coils: a still surface, the beam straight back.
            rays.push((0.0, 0.0));
        }
        let mut hist = vec![0.0; w * h];
        let weight = 1.0 / rays.len() as f64;
        for (dx, dy) in rays {
            let fx = dx / self.pitch + w as f64 / 2.0 - 0.5;
            let fy = dy / self.pitch + h as f64 / 2.0 - 0.5;
            let (x0, y0) = (fx.floor(), fy.floor());
            let (tx, ty) = (fx - x0, fy - y0);
            for (ox, oy, wgt) in [
                (0, 0, (1.0 - tx) * (1.0 - ty)),
                (1, 0, tx * (1.0 - ty)),
                (0, 1, (1.0 - tx) * ty),
                (1, 1, tx * ty),
            ] {
                let (x, y) = (x0 as i64 + ox, y0 as i64 + oy);
                if (0..w as i64).contains(&x) && (0..h as i64).contains(&y) {
                    hist[y as usize * w + x as usize] += weight * wgt;
                }
            }
        }
        // The beam's profile, separable; a still beam's peak becomes `peak`.
        let s = self.beam_sigma / self.pitch;
        let r = (4.0 * s).ceil() as i64;
        let kernel: Vec<f64> = (-r..=r).map(|i| (-(i as f64).powi(2) / (2.0 * s * s)).exp()).collect();
        let blur = |src: &[f64], stride: usize, len: usize, lines: usize, line_stride: usize| {
            let mut out = vec![0.0; src.len()];
            for l in 0..lines {
                for i in 0..len {
                    let mut acc = 0.0;
                    for (t, kv) in kernel.iter().enumerate() {
                        let j = i as i64 + t as i64 - r;
                        if (0..len as i64).contains(&j) {
                            acc += kv * src[l * line_stride + j as usize * stride];
                        }
                    }
                    out[l * line_stride + i * stride] = acc;
                }
            }
            out
        };
        let along_x = blur(&hist, 1, w, h, w);
        let both = blur(&along_x, w, h, w, 1);
        both.into_iter().map(|v| v * self.peak).collect()
    }
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
    use lightrig_pipelines::display::mapping::{golden_phase, Axis, Response, X_FREQUENCIES, Y_FREQUENCIES};
    use lightrig_pipelines::display::slopes::{arcsine_cdf, ks_distance, ks_to_gaussian, moments};
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
        let points = (20..=80)
            .map(|i| f64::from(i) * 5.0)
            .map(|f| (f, scene.actuators[axis].response(&scene.liquid, f).norm()))
            .collect();
        Response { points }
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
            };
            for alpha in [0.02, 0.08, 0.14] {
                let p = a.solve(alpha, &scene.liquid).unwrap();
                let partials: Vec<_> =
                    p.iter().enumerate().map(|(i, q)| (q.frequency, q.drive, golden_phase(i))).collect();
                let (before, now) = played(&partials, 0.1, 0.5);
                let deltas: Vec<f64> = scene
                    .slopes(axis, f64::from(RATE), &before, &now)
                    .iter()
                    .map(|s| 2.0 * s.atan())
                    .collect();
                let (_, var) = moments(&deltas);
                let shown = var.sqrt() / 2.0;
                assert!((shown / alpha - 1.0).abs() < 0.03, "axis {axis} α {alpha}: shown {shown}");
                let ks = ks_to_gaussian(&deltas);
                assert!(ks < 0.03, "axis {axis} α {alpha}: KS to a Gaussian {ks}");
            }
        }
    }
}
