//! HDR merge throughput: a 16-exposure 8-bit RGB stack of 1024×768, merged with a given
//! response (the fast path of `hdr::merge`), in input pixels per second (`width·height·16`).
//!
//! Set `LIGHTRIG_HDR_DUMP=/some/dir` to also write the stack (`stack_NN.rgb`, raw interleaved
//! RGB), `times.txt` and `response.f32` (256×3 linear f⁻¹, float32, level-major) there, for
//! `imaging/benches/opencv_merge.py`.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_imaging::hdr::{merge, MergeOptions, Response, Stack, WeightShape, Weights};

const W: usize = 1024;
const H: usize = 768;
const P: usize = 16;

fn hash(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Radiance gradient over 5 decades with texture, gamma-2.2 response, 1-stop exposures.
fn stack() -> (Vec<Vec<u8>>, Vec<f32>, Vec<Response>) {
    let times: Vec<f32> = (0..P).map(|j| (0.9e-5 * 2f64.powi(j as i32)) as f32).collect();
    let mut imgs: Vec<Vec<u8>> = (0..P).map(|_| Vec::with_capacity(W * H * 3)).collect();
    for y in 0..H {
        for x in 0..W {
            for c in 0..3 {
                let tex = (hash(((y * W + x) * 3 + c) as u64) >> 11) as f64 / (1u64 << 53) as f64;
                let e = 10f64.powf(5.0 * x as f64 / (W - 1) as f64 + 0.1 * (tex - 0.5)) * [1.0, 0.8, 0.6][c];
                for (img, &t) in imgs.iter_mut().zip(&times) {
                    let s = (e * t as f64).clamp(0.0, 1.0).powf(1.0 / 2.2);
                    img.push((255.0 * s).round() as u8);
                }
            }
        }
    }
    let r = Response::from_inverse(256, |z| (z as f64 / 255.0).powf(2.2));
    (imgs, times, vec![r; 3])
}

fn dump(dir: &str, imgs: &[Vec<u8>], times: &[f32], r: &[Response]) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    for (j, img) in imgs.iter().enumerate() {
        std::fs::write(format!("{dir}/stack_{j:02}.rgb"), img)?;
    }
    let t: String = times.iter().map(|t| format!("{t:e}\n")).collect();
    std::fs::write(format!("{dir}/times.txt"), t)?;
    let mut resp = Vec::with_capacity(256 * 3 * 4);
    for z in 0..256 {
        for rc in r {
            resp.extend_from_slice(&rc.inverse(z).to_le_bytes());
        }
    }
    std::fs::write(format!("{dir}/response.f32"), resp)?;
    std::fs::write(format!("{dir}/size.txt"), format!("{W} {H} {P}\n"))
}

fn bench(c: &mut Criterion) {
    let (imgs, times, r) = stack();
    if let Ok(dir) = std::env::var("LIGHTRIG_HDR_DUMP") {
        dump(&dir, &imgs, &times, &r).expect("writing the stack");
        eprintln!("stack written to {dir}");
    }
    let st = Stack::new(W, H, 3, imgs.iter().map(|v| v.as_slice()).collect(), times).unwrap();
    let mut g = c.benchmark_group("hdr_merge");
    g.throughput(Throughput::Elements((W * H * P) as u64));
    for (name, shape, threads) in [
        ("hat_2_threads", WeightShape::Hat, 2),
        ("hat_1_thread", WeightShape::Hat, 1),
        ("snr_2_threads", WeightShape::Snr, 2),
    ] {
        let o = MergeOptions { weights: Weights { shape, ..Weights::full(256) }, threads };
        // A plain figure in input Mpx/s besides criterion's estimate.
        let runs = 10;
        let t0 = Instant::now();
        for _ in 0..runs {
            black_box(merge(&st, &r, &o).unwrap());
        }
        let dt = t0.elapsed().as_secs_f64() / runs as f64;
        eprintln!("{name}: {:.1} ms per merge, {:.0} input Mpx/s", dt * 1e3, (W * H * P) as f64 / dt / 1e6);
        g.bench_function(name, |b| b.iter(|| merge(black_box(&st), &r, &o).unwrap()));
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
