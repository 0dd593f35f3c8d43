//! HDR: response recovery and merging on synthetic stacks of known radiance and response.
//!
//! Scene: 256×256×3, radiance a horizontal gradient over 5 decades times a random texture
//! (±0.05 decades), channel gains 1, 0.8, 0.6. Response (truth): `s = X^(1/2.2)` on
//! normalised exposure `X = E·Δt` (clipped at 1), quantised to 8 bits as `round(255·s)`.
//! Noise before the response: shot noise for a 10⁶ e⁻ full well and read noise 10⁻⁴ of full
//! scale (seeded Gaussian). 16 exposures, 1 stop apart, the shortest putting the brightest
//! gradient value at `X = 0.9`.
//!
//! The recovery tests also use a second response shape (`Curve::Filmic`, a shoulder) and
//! 12- and 16-bit quantisation of the same scene.
//!
//! Run with `--nocapture` to see the figures.

use lightrig_imaging::hdr::{
    debevec, merge, merge_linear, robertson, DebevecOptions, Hdr, HdrError, MergeOptions, Response,
    RobertsonOptions, Stack, WeightShape, Weights,
};

const W: usize = 256;
const H: usize = 256;
const C: usize = 3;
const GAMMA: f64 = 2.2;

/// SplitMix64 with Box–Muller normals.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// Radiance per sample (interleaved) and the exposure times.
fn scene(seed: u64) -> (Vec<f64>, Vec<f32>) {
    let mut rng = Rng(seed);
    let gains = [1.0, 0.8, 0.6];
    let mut e = Vec::with_capacity(W * H * C);
    for y in 0..H {
        for x in 0..W {
            let base = 5.0 * x as f64 / (W - 1) as f64 + 0.02 * (y as f64 * 0.1).sin();
            for g in gains {
                let tex = 0.1 * (rng.uniform() - 0.5);
                e.push(g * 10f64.powf(base + tex));
            }
        }
    }
    let e_max = 10f64.powf(5.02);
    let t0 = 0.9 / e_max;
    let times = (0..16).map(|j| (t0 * 2f64.powi(j)) as f32).collect();
    (e, times)
}

/// Known response: level → normalised exposure, `X = (z/(levels−1))^γ`.
fn truth_inverse(z: usize, levels: usize, gamma: f64) -> f64 {
    (z as f64 / (levels - 1) as f64).powf(gamma)
}

/// The stack: `levels`-level quantisation of `X^(1/γ)` with noise.
fn expose(e: &[f64], times: &[f32], levels: usize, gamma: f64, seed: u64) -> Vec<Vec<u16>> {
    let mut rng = Rng(seed);
    let full_well = 1e6;
    let read = 1e-4;
    let top = (levels - 1) as f64;
    times
        .iter()
        .map(|&t| {
            e.iter()
                .map(|&e| {
                    let x = e * t as f64;
                    let x = x + (x / full_well).sqrt() * rng.normal() + read * rng.normal();
                    let s = x.clamp(0.0, 1.0).powf(1.0 / gamma);
                    (top * s).round() as u16
                })
                .collect()
        })
        .collect()
}

fn to_u8(v: &[Vec<u16>]) -> Vec<Vec<u8>> {
    v.iter().map(|i| i.iter().map(|&z| z as u8).collect()).collect()
}

/// Relative errors where the sample is not clipped (or black) in every exposure.
fn errors(hdr: &Hdr, e: &[f64], scale: f64) -> Vec<f64> {
    let mut errs: Vec<f64> = hdr
        .radiance
        .iter()
        .zip(e)
        .zip(&hdr.unreliable)
        .filter(|(_, &u)| !u)
        .map(|((&r, &e), _)| (r as f64 * scale / e - 1.0).abs())
        .collect();
    errs.sort_by(|a, b| a.partial_cmp(b).unwrap());
    errs
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Best scale (median ratio) between the merged radiance and the truth; the recovered
/// responses are only defined up to a constant factor.
fn scale_to_truth(hdr: &Hdr, e: &[f64]) -> f64 {
    let mut ratios: Vec<f64> = hdr
        .radiance
        .iter()
        .zip(e)
        .zip(&hdr.unreliable)
        .filter(|(_, &u)| !u)
        .map(|((&r, &e), _)| e / r as f64)
        .collect();
    ratios.sort_by(|a, b| a.partial_cmp(b).unwrap());
    ratios[ratios.len() / 2]
}

fn known(levels: usize) -> Response {
    Response::from_inverse(levels, |z| truth_inverse(z, levels, GAMMA))
}

fn opts(levels: usize, shape: WeightShape) -> MergeOptions {
    MergeOptions { weights: Weights { shape, ..Weights::full(levels) }, threads: 2 }
}

/// The target (median ≤ 0.1 %, p99 ≤ 0.5 %) with the known response. 12-bit data
/// meet it; 8-bit gamma-2.2 data cannot with 1-stop spacing (quantisation alone is ≈ 0.3 %
/// per exposure at the top of the range), so 8-bit gets a looser bound; see the figures.
#[test]
fn merge_with_known_response_meets_accuracy_target() {
    let (e, times) = scene(1);
    for levels in [256, 4096] {
        let raw = expose(&e, &times, levels, GAMMA, 2);
        let r = vec![known(levels); 3];
        for shape in [WeightShape::Hat, WeightShape::Snr] {
            let hdr = if levels == 256 {
                let imgs = to_u8(&raw);
                let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times.clone());
                merge(&stack.unwrap(), &r, &opts(levels, shape)).unwrap()
            } else {
                let stack = Stack::new(W, H, C, raw.iter().map(|v| v.as_slice()).collect(), times.clone());
                merge(&stack.unwrap(), &r, &opts(levels, shape)).unwrap()
            };
            let errs = errors(&hdr, &e, 1.0);
            let (med, p99) = (percentile(&errs, 0.5), percentile(&errs, 0.99));
            let excluded = hdr.unreliable.iter().filter(|&&u| u).count();
            eprintln!(
                "{levels} levels, known response, {shape:?}: median {:.4} %, p99 {:.4} %, \
                 {excluded} samples clipped in all",
                med * 100.0,
                p99 * 100.0
            );
            match (levels, shape) {
                (4096, WeightShape::Snr) => assert!(med <= 0.001 && p99 <= 0.005, "{med} {p99}"),
                (256, WeightShape::Snr) => assert!(med <= 0.002 && p99 <= 0.008, "{med} {p99}"),
                _ => {}
            }
        }
    }
}

#[test]
fn linear_12_and_16_bit_merge() {
    let (e, times) = scene(3);
    for (levels, bound_med, bound_p99) in [(4096, 0.001, 0.005), (65536, 0.001, 0.005)] {
        let imgs = expose(&e, &times, levels, 1.0, 4);
        let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times.clone()).unwrap();
        let o = MergeOptions {
            weights: Weights { black: 0, saturation: levels as u32 - 1, shape: WeightShape::Snr },
            threads: 0,
        };
        let hdr = merge_linear(&stack, levels, &o).unwrap();
        // Linear: radiance in levels per unit time, truth X = z/(levels−1).
        let errs = errors(&hdr, &e, 1.0 / (levels - 1) as f64);
        let (med, p99) = (percentile(&errs, 0.5), percentile(&errs, 0.99));
        eprintln!("linear {levels} levels: median {:.4} %, p99 {:.4} %", med * 100.0, p99 * 100.0);
        assert!(med <= bound_med && p99 <= bound_p99, "{levels}: {med} {p99}");
    }
}

/// `max |g − g_true − offset|` over the levels `lo..=hi`, the offset being the mean difference.
fn curve_error(r: &Response, lo: usize, hi: usize) -> f64 {
    let d: Vec<f64> = (lo..=hi).map(|z| r.g[z] as f64 - truth_inverse(z, r.levels, GAMMA).ln()).collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.iter().map(|v| (v - mean).abs()).fold(0.0, f64::max)
}

fn recovered_check(
    name: &str,
    responses: &[Response],
    stack: &Stack<u8>,
    e: &[f64],
    bound: f64,
) -> (f64, f64) {
    for (c, r) in responses.iter().enumerate() {
        let d: Vec<String> = [10, 20, 50, 128, 200, 250]
            .iter()
            .map(|&z| format!("{z}:{:.3}", r.g[z] as f64 - truth_inverse(z, 256, GAMMA).ln()))
            .collect();
        eprintln!("{name} channel {c}: g − g_true at {}", d.join(" "));
        let err = curve_error(r, 20, 250);
        eprintln!("{name} channel {c}: max |Δg| over levels 20..=250: {err:.4}");
        assert!(err < bound, "{name} channel {c} curve error {err}");
    }
    let hdr = merge(stack, responses, &opts(256, WeightShape::Snr)).unwrap();
    let s = scale_to_truth(&hdr, e);
    let errs = errors(&hdr, e, s);
    let (med, p99) = (percentile(&errs, 0.5), percentile(&errs, 0.99));
    eprintln!("8-bit, {name} response: median {:.4} %, p99 {:.4} %", med * 100.0, p99 * 100.0);
    (med, p99)
}

#[test]
fn debevec_recovers_the_response() {
    let (e, times) = scene(5);
    let imgs = to_u8(&expose(&e, &times, 256, GAMMA, 6));
    let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let r = debevec(&stack, 256, &DebevecOptions::new(256)).unwrap();
    assert_eq!(r.len(), 3);
    assert!(r.iter().all(|r| r.g[128] == 0.0));
    let (med, p99) = recovered_check("Debevec", &r, &stack, &e, 0.005);
    // 8-bit: the quantisation bound (≈ 0.16 % median with the known response), not 0.1 %.
    assert!(med <= 0.002 && p99 <= 0.01, "{med} {p99}");
}

#[test]
fn robertson_recovers_the_response() {
    let (e, times) = scene(7);
    let imgs = to_u8(&expose(&e, &times, 256, GAMMA, 8));
    let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let r = robertson(&stack, 256, &RobertsonOptions::new(256)).unwrap();
    assert!(r.iter().all(|r| r.g[128].abs() < 1e-6));
    let (med, p99) = recovered_check("Robertson", &r, &stack, &e, 0.005);
    // The plain iteration was off by ≈ 6 % here (the 1-stop ambiguity, see `robertson`).
    assert!(med <= 0.002 && p99 <= 0.01, "{med} {p99}");
}

#[test]
fn debevec_bins_16_bit_input() {
    let (e, times) = scene(9);
    let imgs = expose(&e, &times, 65536, GAMMA, 10);
    let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let o = DebevecOptions { max_bins: 512, ..DebevecOptions::new(65536) };
    let r = debevec(&stack, 65536, &o).unwrap();
    for r in &r {
        let err = curve_error(r, 4000, 65000);
        eprintln!("Debevec 16-bit (512 bins): max |Δg| over 4000..=65000: {err:.4}");
        assert!(err < 0.01, "{err}");
    }
}

#[test]
fn clipped_and_black_samples_have_zero_weight() {
    let (e, times) = scene(11);
    let imgs = to_u8(&expose(&e, &times, 256, GAMMA, 12));
    let weights = Weights { black: 8, saturation: 240, shape: WeightShape::Snr };
    let o = MergeOptions { weights, threads: 2 };
    let r = vec![known(256); 3];
    let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times.clone()).unwrap();
    let a = merge(&stack, &r, &o).unwrap();
    // Perturb every clipped/black sample within its clipped range, except in the shortest and
    // longest exposures (those define the fallback of all-clipped pixels).
    let mut rng = Rng(99);
    let mut changed = 0;
    let mut pert = imgs.clone();
    for img in pert.iter_mut().skip(1).take(14) {
        for z in img.iter_mut() {
            if *z >= 240 {
                *z = 240 + (rng.next_u64() % 16) as u8;
                changed += 1;
            } else if *z <= 8 {
                *z = (rng.next_u64() % 9) as u8;
                changed += 1;
            }
        }
    }
    assert!(changed > 10_000);
    let stack = Stack::new(W, H, C, pert.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let b = merge(&stack, &r, &o).unwrap();
    assert_eq!(a, b);
    assert!(a.unreliable.iter().any(|&u| u), "the scene has samples clipped in every exposure");
}

#[test]
fn all_clipped_pixels_are_flagged_with_defined_values() {
    let sat = [255u8, 255, 0, 0];
    let short = [255u8, 0, 0, 128];
    let stack = Stack::new(2, 2, 1, vec![&short[..], &sat[..]], vec![1.0, 4.0]).unwrap();
    let r = [Response::linear(256, 0)];
    let hdr = merge(&stack, &r, &opts(256, WeightShape::Hat)).unwrap();
    assert_eq!(hdr.unreliable, [true, true, true, false]);
    let close = |a: f32, b: f32| (a - b).abs() <= 1e-4 * b.abs();
    assert!(close(hdr.radiance[0], 255.0)); // saturated everywhere: shortest exposure, lower bound
    assert!(close(hdr.radiance[1], 255.0 / 4.0)); // black in the shortest: longest exposure
    assert_eq!(hdr.radiance[2], 0.0); // black everywhere
    assert!(close(hdr.radiance[3], 128.0));
    assert!(hdr.radiance.iter().all(|v| v.is_finite()));
}

#[test]
fn single_thread_and_threads_agree() {
    let (e, times) = scene(13);
    let imgs = to_u8(&expose(&e, &times, 256, GAMMA, 14));
    let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let r = vec![known(256); 3];
    let mut o = opts(256, WeightShape::Hat);
    o.threads = 1;
    let a = merge(&stack, &r, &o).unwrap();
    o.threads = 7;
    let b = merge(&stack, &r, &o).unwrap();
    assert_eq!(a, b);
}

#[test]
fn bad_input_gives_typed_errors() {
    let a = [0u8; 12];
    let b = [0u8; 11];
    assert_eq!(
        Stack::new(2, 2, 3, vec![&a[..], &b[..]], vec![1.0, 2.0]).unwrap_err(),
        HdrError::SizeMismatch { index: 1, expected: 12, found: 11 }
    );
    assert_eq!(
        Stack::new(2, 2, 3, vec![&a[..]], vec![1.0]).unwrap_err(),
        HdrError::TooFewExposures { found: 1, needed: 2 }
    );
    assert_eq!(
        Stack::new(2, 2, 3, vec![&a[..], &a[..]], vec![1.0]).unwrap_err(),
        HdrError::CountMismatch { images: 2, times: 1 }
    );
    for t in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        assert!(matches!(
            Stack::new(2, 2, 3, vec![&a[..], &a[..]], vec![1.0, t]).unwrap_err(),
            HdrError::NonPositiveTime { index: 1, .. }
        ));
    }
    assert!(matches!(
        Stack::new(0, 2, 3, vec![&a[..], &a[..]], vec![1.0, 2.0]).unwrap_err(),
        HdrError::InvalidParameter(_)
    ));
    // All black: nothing to fit.
    let s = Stack::new(2, 2, 3, vec![&a[..], &a[..]], vec![1.0, 2.0]).unwrap();
    assert_eq!(debevec(&s, 256, &DebevecOptions::new(256)).unwrap_err(), HdrError::NoUsablePixels);
    assert_eq!(robertson(&s, 256, &RobertsonOptions::new(256)).unwrap_err(), HdrError::NoUsablePixels);
    // Responses that do not fit.
    let o = opts(256, WeightShape::Hat);
    assert!(matches!(
        merge(&s, &[Response::linear(256, 0)], &o).unwrap_err(),
        HdrError::ResponseMismatch { expected: 3, found: 1 }
    ));
    let bad = Response { levels: 256, g: vec![0.0; 10] };
    assert!(matches!(merge(&s, &vec![bad; 3], &o).unwrap_err(), HdrError::ResponseMismatch { .. }));
    assert!(matches!(
        merge_linear(&s, 1000, &o).unwrap_err(),
        HdrError::InvalidParameter(_) // 1000 levels do not fit u8
    ));
    let o = MergeOptions {
        weights: Weights { black: 100, saturation: 100, shape: WeightShape::Hat },
        threads: 1,
    };
    assert!(matches!(merge_linear(&s, 256, &o).unwrap_err(), HdrError::InvalidParameter(_)));
    let d = DebevecOptions { lambda: f64::NAN, ..DebevecOptions::new(256) };
    assert!(matches!(debevec(&s, 256, &d).unwrap_err(), HdrError::InvalidParameter(_)));
}

#[derive(Clone, Copy, Debug)]
enum Curve {
    Gamma,
    Filmic,
}

impl Curve {
    /// Normalised exposure → normalised signal.
    fn forward(self, x: f64) -> f64 {
        match self {
            Curve::Gamma => x.powf(1.0 / GAMMA),
            // Reinhard-style shoulder then a 1/1.5 power: s = ((1+k)X/(X+k))^(1/1.5).
            Curve::Filmic => ((1.0 + FK) * x / (x + FK)).powf(1.0 / 1.5),
        }
    }
    fn inverse(self, s: f64) -> f64 {
        match self {
            Curve::Gamma => s.powf(GAMMA),
            Curve::Filmic => {
                let y = s.powf(1.5);
                FK * y / (1.0 + FK - y)
            }
        }
    }
}
const FK: f64 = 0.5;
const FULL_WELL: f64 = 1e6;
const READ_NOISE: f64 = 1e-4;

fn expose_curve(e: &[f64], times: &[f32], levels: usize, curve: Curve, seed: u64) -> Vec<Vec<u16>> {
    let mut rng = Rng(seed);
    let top = (levels - 1) as f64;
    times
        .iter()
        .map(|&t| {
            e.iter()
                .map(|&e| {
                    let x = e * t as f64;
                    let x = x + (x / FULL_WELL).sqrt() * rng.normal() + READ_NOISE * rng.normal();
                    (top * curve.forward(x.clamp(0.0, 1.0))).round() as u16
                })
                .collect()
        })
        .collect()
}

/// Merge black level for a recovery test: the level a dark frame reaches at 3σ of read noise.
/// Below it samples carry no radiance information (their `f⁻¹` cannot be recovered either),
/// so they get zero weight, as a camera's measured black level would give them.
fn noise_floor(curve: Curve, levels: usize) -> u32 {
    (((levels - 1) as f64) * curve.forward(3.0 * READ_NOISE)).ceil() as u32
}

/// Median and p99 of the relative radiance error (after the global scale) of a merge with
/// `r`, black level at the noise floor.
fn merged_error<T: lightrig_imaging::hdr::Sample>(
    stack: &Stack<T>,
    r: &[Response],
    e: &[f64],
    black: u32,
) -> (f64, f64) {
    let levels = r[0].levels;
    let o = MergeOptions { weights: Weights { black, ..Weights::snr(levels) }, threads: 2 };
    let hdr = merge(stack, r, &o).unwrap();
    let errs = errors(&hdr, e, scale_to_truth(&hdr, e));
    (percentile(&errs, 0.5), percentile(&errs, 0.99))
}

/// The target with the response recovered from the stack itself, on 12- and 16-bit
/// stacks of two response shapes. Seeds 100–102 were checked when this was written (all
/// within 0.081 % median and 0.32 % p99); the test runs one.
#[test]
fn recovered_responses_meet_accuracy_target_at_12_and_16_bit() {
    let (e, times) = scene(100);
    for curve in [Curve::Gamma, Curve::Filmic] {
        for levels in [4096usize, 65536] {
            let imgs = expose_curve(&e, &times, levels, curve, 200);
            let stack =
                Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times.clone()).unwrap();
            let black = noise_floor(curve, levels);
            let weights = Weights { black, ..Weights::full(levels) };
            let known = Response::from_inverse(levels, |z| curve.inverse(z as f64 / (levels - 1) as f64));
            let rd =
                debevec(&stack, levels, &DebevecOptions { weights, ..DebevecOptions::new(levels) }).unwrap();
            let rr =
                robertson(&stack, levels, &RobertsonOptions { weights, ..RobertsonOptions::new(levels) })
                    .unwrap();
            for (name, r) in [("known", vec![known; 3]), ("Debevec", rd), ("Robertson", rr)] {
                assert!(name == "known" || r.iter().all(|r| r.g[levels / 2].abs() < 1e-6), "gauge");
                let (med, p99) = merged_error(&stack, &r, &e, black);
                eprintln!(
                    "{levels} levels, {curve:?}, {name} response: median {:.4} %, p99 {:.4} % (black {black})",
                    med * 100.0,
                    p99 * 100.0
                );
                assert!(med <= 0.001 && p99 <= 0.005, "{levels} {curve:?} {name}: {med} {p99}");
            }
        }
    }
}

/// 8-bit gamma-2.2 data with half-stop instead of 1-stop spacing (32 exposures over the
/// same range): twice the samples per pixel, so quantisation error averages down by ≈ √2.
#[test]
fn eight_bit_half_stop_spacing() {
    let (e, times) = scene(15);
    let t0 = times[0] as f64;
    for (label, times) in [
        ("1 stop", times.clone()),
        ("1/2 stop", (0..31).map(|j| (t0 * 2f64.powf(j as f64 / 2.0)) as f32).collect::<Vec<_>>()),
    ] {
        let imgs = to_u8(&expose_curve(&e, &times, 256, Curve::Gamma, 16));
        let stack = Stack::new(W, H, C, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
        let black = noise_floor(Curve::Gamma, 256);
        let weights = Weights { black, ..Weights::full(256) };
        let rd = debevec(&stack, 256, &DebevecOptions { weights, ..DebevecOptions::new(256) }).unwrap();
        let rr = robertson(&stack, 256, &RobertsonOptions { weights, ..RobertsonOptions::new(256) }).unwrap();
        for (name, r) in [("known", vec![known(256); 3]), ("Debevec", rd), ("Robertson", rr)] {
            let (med, p99) = merged_error(&stack, &r, &e, black);
            eprintln!(
                "8-bit, {label}, {name} response: median {:.4} %, p99 {:.4} %",
                med * 100.0,
                p99 * 100.0
            );
            assert!(med <= 0.002 && p99 <= 0.01, "{label} {name}: {med} {p99}");
        }
    }
}
