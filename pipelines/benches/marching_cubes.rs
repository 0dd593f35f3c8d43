//! Marching cubes throughput in voxels per second on a fixed 256³ volume: a sphere of radius
//! 100 voxels, its signed distance perturbed by a smooth ripple and a little white noise (so
//! the surface is bumpy and some cells are ambiguous).
//!
//! `cargo bench -p lightrig-pipelines --bench marching_cubes`
//!
//! Set `LIGHTRIG_MC_DUMP=/some/dir` to also write the volume there (`volume.f32`, raw
//! little-endian float32, x fastest, then y, then z; `dims.txt`: `nx ny nz`) for
//! `pipelines/benches/skimage_marching_cubes.py`.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_pipelines::firs::mesh::{marching_cubes, Grid, MarchingCubes, Solid};

const N: usize = 256;

fn hash(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn volume() -> Vec<f32> {
    let c = (N as f64 - 1.0) / 2.0;
    let mut v = Vec::with_capacity(N * N * N);
    for k in 0..N {
        for j in 0..N {
            for i in 0..N {
                let (x, y, z) = (i as f64 - c, j as f64 - c, k as f64 - c);
                let ripple = 4.0 * (x / 7.0).sin() * (y / 9.0).sin() * (z / 11.0).sin();
                let noise =
                    (hash((k * N + j) as u64 * N as u64 + i as u64) >> 11) as f64 / (1u64 << 53) as f64;
                v.push(((x * x + y * y + z * z).sqrt() - 100.0 + ripple + 0.3 * (noise - 0.5)) as f32);
            }
        }
    }
    v
}

fn dump(dir: &str, v: &[f32]) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(format!("{dir}/volume.f32"), bytes)?;
    std::fs::write(format!("{dir}/dims.txt"), format!("{N} {N} {N}\n"))
}

fn bench(c: &mut Criterion) {
    let v = volume();
    if let Ok(dir) = std::env::var("LIGHTRIG_MC_DUMP") {
        dump(&dir, &v).expect("writing the volume");
        eprintln!("volume written to {dir}");
    }
    let grid = Grid { dims: [N; 3], voxel: [1.0; 3], origin: [0.0; 3] };
    let voxels = (N * N * N) as f64;
    let m = marching_cubes(&v, &grid, 0.0, Solid::Below).expect("marching cubes");
    eprintln!("{} vertices, {} triangles", m.vertices.len(), m.triangles.len());
    // Plain best-of-10 figures besides criterion's estimate (the machine is shared).
    let stream = |v: &[f32]| {
        let mut mc = MarchingCubes::new(grid, 0.0, Solid::Below).expect("grid");
        for s in v.chunks_exact(N * N) {
            mc.push(s).expect("slice");
        }
        mc.finish().expect("mesh")
    };
    for (name, threads) in [("whole array, all threads", 0), ("streamed slices, 1 thread", 1)] {
        let best = (0..10)
            .map(|_| {
                let t0 = Instant::now();
                if threads == 0 {
                    black_box(marching_cubes(&v, &grid, 0.0, Solid::Below).expect("mc"));
                } else {
                    black_box(stream(&v));
                }
                t0.elapsed().as_secs_f64()
            })
            .fold(f64::MAX, f64::min);
        eprintln!(
            "marching cubes {name} ({} threads): best of 10 {:.1} ms, {:.0} Mvoxel/s",
            if threads == 0 { rayon::current_num_threads() } else { 1 },
            best * 1e3,
            voxels / best / 1e6
        );
    }
    let mut g = c.benchmark_group("marching_cubes");
    g.throughput(Throughput::Elements(voxels as u64));
    g.sample_size(10);
    g.bench_function("256^3 bumpy sphere, all threads", |b| {
        b.iter(|| marching_cubes(black_box(&v), &grid, 0.0, Solid::Below))
    });
    g.bench_function("256^3 bumpy sphere, streamed, 1 thread", |b| b.iter(|| stream(black_box(&v))));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
