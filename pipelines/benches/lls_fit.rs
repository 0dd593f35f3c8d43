//! LLS fit throughput: pixel traces of 400 frames per second, one thread.
//!
//! `cargo bench -p lightrig-pipelines --bench lls_fit`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_pipelines::linear_light::{response, Quadrature, Tube};
use lightrig_pipelines::lls::fit_trace;
use lightrig_pipelines::vec3::normalize;

fn bench(c: &mut Criterion) {
    let (p, n, v) = ([1.0, 2.0, 0.3], normalize([0.02, -0.03, 1.0]), normalize([-0.5, 0.02, 0.866]));
    // 400 frames at 0.6 mm: the pass of a 240 mm gantry travel.
    let tubes: Vec<Tube> = (0..400)
        .map(|k| Tube { x: -140.0 + 0.6 * k as f64, z: 50.0, radius: 6.0, y0: -150.0, y1: 150.0, yaw: 0.0 })
        .collect();
    let q = Quadrature::fit();
    let mut g = c.benchmark_group("lls_fit");
    g.throughput(Throughput::Elements(1));
    g.sample_size(10);
    for alpha in [0.04, 0.3] {
        let mut obs: [Vec<f64>; 3] = Default::default();
        let valid: [Vec<bool>; 3] = std::array::from_fn(|_| vec![true; tubes.len()]);
        for t in &tubes {
            let r = response(p, n, v, t, Some(alpha), &q);
            for (c, o) in obs.iter_mut().enumerate() {
                o.push(0.3 / (c + 1) as f64 * r.diffuse + 0.06 * r.specular);
            }
        }
        g.bench_function(format!("trace of 400 frames, alpha {alpha}"), |b| {
            b.iter(|| fit_trace(&obs, &valid, &tubes, p, n, v, &q))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
