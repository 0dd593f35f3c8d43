//! DISCO's per-frame work against reading the frames: a 2 562-vertex pebble seen at 768 × 496
//! (the paper's camera), each frame's entry point found (the projector's ray cast on the
//! mesh), its noise floor measured, and every visible vertex resampled into the entry
//! triangle's columns — the fit's per-frame work on a decoded frame, one thread — beside
//! decoding the same frame from a half-float EXR (what reading a session costs per frame).
//! Prints frames per second of each, the best of 3 runs.
//!
//! `cargo bench -p lightrig-pipelines --bench disco_resample`
//!
//! The paper resampled 50 frames/s on a 3 GHz Xeon; the target here is 500 frames/s.

use std::hint::black_box;
use std::time::Instant;

use lightrig_imaging::io::{read, write_exr, ExrPrecision, Image};
use lightrig_pipelines::disco::mesh::{pebble, SurfaceMesh};
use lightrig_pipelines::disco::optics::{point_of, Pinhole, Projector};
use lightrig_pipelines::disco::resample::{background_sigma, incidence, Accumulator, ViewLimits, ViewMap};
use lightrig_pipelines::vec3::{norm, sub};

const FRAMES: usize = 300;

fn best_of(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut best = f64::INFINITY;
    for _ in 0..runs {
        let t = Instant::now();
        f();
        best = best.min(t.elapsed().as_secs_f64());
    }
    best
}

fn main() {
    let mesh = SurfaceMesh::new(&pebble(4, [24.0, 20.0, 30.0]));
    let cam = Pinhole::looking(768, 496, 1800.0, [300.0, 0.0, 90.0], [0.0, 0.0, 30.0]);
    let proj = Projector::aimed(
        [260.0, -150.0, 60.0],
        [0.0, 0.0, 30.0],
        [32768.0, 32768.0],
        [10.6526e-6, -10.6526e-6],
    );
    let limits = ViewLimits::default();
    let t = Instant::now();
    let view = ViewMap::new(&mesh, &cam, 0.0, &limits);
    let view_s = t.elapsed().as_secs_f64();
    // Spots over the object; a frame per spot with a smooth fall-off from the entry point.
    let codes: Vec<[f64; 2]> = (0..FRAMES)
        .map(|k| {
            let (i, j) = ((k % 20) as f64, (k / 20) as f64);
            [32768.0 + (i - 10.0) * 600.0, 32768.0 + (j - 7.0) * 600.0]
        })
        .collect();
    let frame = |code: [f64; 2]| -> Vec<f32> {
        let Some(inc) = incidence(
            &mesh,
            &view.world,
            0.0,
            proj.eye,
            proj.ray(code),
            &ViewLimits { max_incidence_deg: 90.0, ..limits },
        ) else {
            return vec![1e-4; 768 * 496];
        };
        view.surface
            .iter()
            .map(|h| match h {
                Some(h) => {
                    let (p, _) = point_of(&mesh, &view.world, 0.0, h);
                    let d = norm(sub(p, inc.point));
                    (100.0 * (-0.2 * d).exp() / (1.0 + d * d)) as f32
                }
                None => 1e-4,
            })
            .collect()
    };
    let frames: Vec<Vec<f32>> = codes.iter().map(|&c| frame(c)).collect();
    let mut acc = Accumulator::new(&mesh);
    let mut used = 0;
    let resample_s = best_of(3, || {
        used = 0;
        for (f, &code) in frames.iter().zip(&codes) {
            let Some(inc) = incidence(&mesh, &view.world, 0.0, proj.eye, proj.ray(code), &limits) else {
                continue;
            };
            let floor = 5.0 * background_sigma(f, &view.surface, 7);
            black_box(acc.add(&mesh, &view, &inc, f, used % 3, 1.0, floor));
            used += 1;
        }
    });
    // Decoding: the same frames as a camera's half-float EXR files.
    let dir = std::env::temp_dir().join(format!("lightrig-disco-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let n_files = 30;
    for (k, f) in frames.iter().take(n_files).enumerate() {
        let mut img = Image::new(768, 496, 1);
        img.data.copy_from_slice(f);
        write_exr(dir.join(format!("{k}.exr")), &img, ExrPrecision::Half).expect("write");
    }
    let decode_s = best_of(3, || {
        for k in 0..n_files {
            black_box(read(dir.join(format!("{k}.exr"))).expect("read"));
        }
    });
    std::fs::remove_dir_all(&dir).ok();
    println!(
        "disco: {} vertices, 768×496, {} visible; per view once {:.1} ms",
        mesh.vertices.len(),
        view.vertices.len(),
        1e3 * view_s
    );
    println!(
        "  resampling (entry point, noise floor, columns): {:.0} frames/s ({} frames with the spot on the object, one thread)",
        used as f64 / resample_s,
        used
    );
    println!(
        "  decoding a half-float EXR frame:                 {:.0} frames/s (one thread)",
        n_files as f64 / decode_s
    );
}
