//! LLS fit throughput against the time to read the same stack, both in pixel traces of 400
//! frames per second on one thread:
//!
//! - `lls_fit`: one pixel's trace fitted (its [`TraceModel`] built, then ρd, ρs, α), each
//!   trial integrating the lobe for the pixel (`fit_trace`) or looking it up in the shared
//!   tables (`fit_trace_tabled`; warm: the nodes this pixel needs already built, as for all
//!   but the first pixels of an image; cold: built in the iteration, an upper bound), and
//!   refitted from that fit with α 1 % off (a session's refit with the blended normals);
//!   and the normal search on one pixel's two diagonal passes (`fit_normal`), about a
//!   quarter of a session's fit on one thread (docs/pipelines/lls.md, "Speed").
//! - `lls_read`: a stack of 400 16-bit RGB PNG frames (what the virtual camera writes) read
//!   from disk into memory, per pixel of the frame: the rate at which traces arrive.
//!
//! The target is fit time ≤ 3 × read time, i.e. `lls_fit` throughput ≥ ⅓ of
//! `lls_read`'s. `cargo bench -p lightrig-pipelines --bench lls_fit`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_imaging::io::{read_with, write_png, BitDepth, Encoding, Image, ReadOptions};
use lightrig_pipelines::lls::linear_light::{response, Quadrature, Tube};
use lightrig_pipelines::lls::{
    fit_normal, fit_trace, fit_trace_tabled, LobeTables, PassTrace, Sweep, TraceFit, TraceModel,
};
use lightrig_pipelines::vec3::normalize;

const FRAMES: usize = 400;

fn fit(c: &mut Criterion) {
    let (p, n, v) = ([1.0, 2.0, 0.3], normalize([0.02, -0.03, 1.0]), normalize([-0.5, 0.02, 0.866]));
    // 400 frames at 0.6 mm: the pass of a 240 mm gantry travel.
    let tubes: Vec<Tube> = (0..FRAMES)
        .map(|k| Tube { x: -140.0 + 0.6 * k as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 })
        .collect();
    let q = Quadrature::render();
    let mut g = c.benchmark_group("lls_fit");
    g.throughput(Throughput::Elements(1));
    g.sample_size(20);
    // Its parts: the pixel's bands, and one trial of (n, α) (a fit makes 4 to 7). The pass'
    // sweep is made once for every pixel, as the session's fit does.
    let sweep = Sweep::new(&tubes);
    g.bench_function(format!("model of {FRAMES} frames"), |b| b.iter(|| TraceModel::of(p, v, &sweep)));
    let model = TraceModel::of(p, v, &sweep);
    g.bench_function("diffuse trace", |b| b.iter(|| model.diffuse(n)));
    let tables = LobeTables::new();
    for alpha in [0.04, 0.3] {
        g.bench_function(format!("specular trace, alpha {alpha}"), |b| b.iter(|| model.specular(n, alpha)));
        let _ = model.specular_tabled(n, alpha, &tables);
        g.bench_function(format!("tabled specular trace, alpha {alpha}"), |b| {
            b.iter(|| model.specular_tabled(n, alpha, &tables))
        });
    }
    for alpha in [0.04, 0.3] {
        let mut obs: [Vec<f64>; 3] = Default::default();
        let valid: [Vec<bool>; 3] = std::array::from_fn(|_| vec![true; tubes.len()]);
        for t in &tubes {
            let r = response(p, n, v, t, Some(alpha), &q);
            for (c, o) in obs.iter_mut().enumerate() {
                o.push(0.3 / (c + 1) as f64 * r.diffuse + 0.06 * r.specular);
            }
        }
        g.bench_function(format!("trace of {FRAMES} frames, alpha {alpha}"), |b| {
            b.iter(|| fit_trace(&obs, &valid, &TraceModel::of(p, v, &sweep), n, None))
        });
        let _ = fit_trace_tabled(&obs, &valid, &model, n, None, &tables);
        g.bench_function(format!("tabled trace of {FRAMES} frames, alpha {alpha}"), |b| {
            b.iter(|| fit_trace_tabled(&obs, &valid, &TraceModel::of(p, v, &sweep), n, None, &tables))
        });
        // The session's refit: the same trace from its first fit with α 1 % off (the
        // blended normal moves α a little): two trials where the minimum is within 2.5 %.
        let first = fit_trace_tabled(&obs, &valid, &model, n, None, &tables);
        let prior = TraceFit { alpha: first.alpha * 1.01, ..first };
        g.bench_function(format!("tabled refit of {FRAMES} frames, alpha {alpha}, 1 % off"), |b| {
            b.iter(|| fit_trace_tabled(&obs, &valid, &TraceModel::of(p, v, &sweep), n, Some(&prior), &tables))
        });
        g.bench_function(format!("tabled trace of {FRAMES} frames, alpha {alpha}, cold tables"), |b| {
            b.iter(|| {
                fit_trace_tabled(&obs, &valid, &TraceModel::of(p, v, &sweep), n, None, &LobeTables::new())
            })
        });
    }
    // The session's normal search: the two diagonal passes (±15° mounts, 400 frames each) of
    // one pixel, α known from the straight pass, from a start 0.3° off (a neighbour's normal)
    // and 2° off; the passes' models built outside (`model of 400 frames` above).
    let truth = normalize([0.03, -0.02, 1.0]);
    for alpha in [0.04, 0.3] {
        let passes: Vec<_> = [15f64, -15.0]
            .iter()
            .map(|yaw| {
                let tubes: Vec<Tube> = (0..FRAMES)
                    .map(|k| {
                        Tube::through([-140.0 + 0.6 * k as f64, 0.0, 50.0], yaw.to_radians(), 6.0, 300.0)
                    })
                    .collect();
                let mut obs: [Vec<f64>; 3] = Default::default();
                for t in &tubes {
                    let r = response(p, truth, v, t, Some(alpha), &q);
                    for (c, o) in obs.iter_mut().enumerate() {
                        o.push(0.3 / (c + 1) as f64 * r.diffuse + 0.06 * r.specular);
                    }
                }
                let valid: [Vec<bool>; 3] = std::array::from_fn(|_| vec![true; tubes.len()]);
                (obs, valid, TraceModel::of(p, v, &Sweep::new(&tubes)))
            })
            .collect();
        let passes: Vec<PassTrace> =
            passes.iter().map(|(obs, valid, model)| PassTrace { obs, valid, model }).collect();
        for off_deg in [0.3f64, 2.0] {
            let t = off_deg.to_radians().tan();
            let n0 = normalize([truth[0] / truth[2] + t, truth[1] / truth[2], 1.0]);
            let _ = fit_normal(&passes, n0, alpha, Some(&tables));
            g.bench_function(
                format!("normal search, 2 x {FRAMES} frames, alpha {alpha}, {off_deg} deg off"),
                |b| b.iter(|| fit_normal(&passes, n0, alpha, Some(&tables))),
            );
        }
    }
    g.finish();
}

fn read(c: &mut Criterion) {
    let (w, h) = (160u32, 120u32);
    let dir = std::env::temp_dir().join("lightrig-bench-lls-read");
    let _ = std::fs::create_dir_all(&dir);
    // A bright band moving across a shaded sample, with noise (a fixed LCG): compresses like a
    // real frame, not like a flat one.
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let paths: Vec<_> = (0..FRAMES)
        .map(|k| {
            let path = dir.join(format!("frame-{k:04}.png"));
            let img = Image::from_fn(w, h, 3, |x, y, ch| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let noise = ((seed >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.004;
                let band = (-((x as f32 - k as f32 * 0.4).powi(2)) / 200.0).exp();
                (0.2 + 0.1 * (y as f32 / h as f32) + 0.6 * band) / (1.0 + ch as f32 * 0.3) + noise
            });
            if !path.exists() {
                write_png(&path, &img, BitDepth::Sixteen).expect("write a bench frame");
            }
            path
        })
        .collect();
    let mut g = c.benchmark_group("lls_read");
    // Per pixel of the frame: one trace of FRAMES frames arrives per pixel.
    g.throughput(Throughput::Elements(u64::from(w * h)));
    g.sample_size(10);
    g.bench_function(format!("{FRAMES} frames of {w}x{h} RGB16 PNG"), |b| {
        b.iter(|| {
            paths
                .iter()
                .map(|p| {
                    read_with(p, ReadOptions { assume: Encoding::Linear, expect_depth: None })
                        .expect("read a bench frame")
                })
                .collect::<Vec<_>>()
        })
    });
    g.finish();
}

criterion_group!(benches, fit, read);
criterion_main!(benches);
