//! FIRS surface detection throughput: space-time voxels per second of the streaming detector
//! (median, gradients, candidates, softening, segments) on a generated 512×512×400 stack.
//!
//! `cargo bench -p lightrig-pipelines --bench firs_surface`
//!
//! The stack: a sphere of radius 200 px in front of a wall; the cut-off of pixel `(u, v)` at
//! frame `t*(u, v)` (the sphere's depth, 0.5 frame per pixel of depth), intensity
//! `4 + 200·Φ((t* − t)/1.2)` plus uniform noise of ±3. Generated once as scanline slabs, so
//! the timing is the detector's alone.

use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_pipelines::firs::surface::{SurfaceDetector, SurfaceParams};

const W: usize = 512;
const H: usize = 512;
const F: usize = 400;

/// The standard normal distribution function (logistic approximation, ample for a bench).
fn phi(x: f64) -> f64 {
    1.0 / (1.0 + (-1.702 * x).exp())
}

fn slabs() -> Vec<Vec<f32>> {
    let mut seed = 0x2545_F491_4F6C_DD1Du64;
    (0..H)
        .map(|v| {
            let mut slab = vec![0f32; W * F];
            for u in 0..W {
                let (x, y) = (u as f64 - 256.0, v as f64 - 256.0);
                let r2 = x * x + y * y;
                let tstar = if r2 < 200.0 * 200.0 {
                    60.0 + 0.5 * (200.0 - (200.0f64 * 200.0 - r2).sqrt())
                } else {
                    360.0
                };
                for t in 0..F {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    let noise = ((seed >> 40) as f64 / (1u64 << 24) as f64 - 0.5) * 6.0;
                    slab[u * F + t] = (4.0 + 200.0 * phi((tstar - t as f64) / 1.2) + noise) as f32;
                }
            }
            slab
        })
        .collect()
}

fn run(slabs: &[Vec<f32>], params: SurfaceParams) -> usize {
    let mut det = SurfaceDetector::new(W, H, F, params).expect("dims");
    for s in slabs {
        det.push_scanline(s).expect("slab");
    }
    det.finish().expect("finish").t.iter().filter(|t| t.is_some()).count()
}

fn bench(c: &mut Criterion) {
    let slabs = slabs();
    let params = SurfaceParams { laser_dir: Some([-1.0, 0.0]), ..Default::default() };
    let voxels = (W * H * F) as u64;
    // A plain figure first, printed: criterion's own report gives the same as elements/s.
    let t0 = Instant::now();
    let found = run(&slabs, params);
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "firs_surface: {W}×{H}×{F} = {voxels} voxels in {dt:.3} s, {:.1} Mvoxel/s, {} threads, {found} pixels with a surface",
        voxels as f64 / dt / 1e6,
        rayon::current_num_threads()
    );
    let mut g = c.benchmark_group("firs_surface");
    g.throughput(Throughput::Elements(voxels));
    g.sample_size(10);
    g.bench_function("detect 512x512x400", |b| b.iter(|| run(&slabs, params)));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
