//! The bispectral PCA of thesis §4.5 on a 32 768 × 170 matrix (32 768 samples, the thesis's 170
//! wavelength pairs): `Pca::new` (mean removed, `FᵀF`, its eigen-decomposition), then the
//! greedy choice of 5 pairs by `cond(R)`. Prints the best of 5 runs of each.
//!
//! `cargo bench -p lightrig-pipelines --bench brrdf_pca`
//!
//! With `LIGHTRIG_PCA_DUMP=/some/dir` it also writes the matrix there (`f.f64`: raw
//! little-endian float64, row-major; `shape.txt`: `rows cols`) for
//! `pipelines/benches/numpy_pca.py`, which times NumPy's SVD of the same matrix.

use std::hint::black_box;
use std::time::Instant;

use lightrig_pipelines::brrdf::pca::Pca;

const ROWS: usize = 32_768;
const COLS: usize = 170;

fn hash(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn unit(k: u64) -> f64 {
    (hash(k) >> 11) as f64 / (1u64 << 53) as f64
}

/// Six smooth spectral components mixed with per-sample weights, plus 1 % noise: a bispectral
/// material's samples as the PCA sees them.
fn matrix() -> Vec<f64> {
    let comps: Vec<Vec<f64>> = (0..6)
        .map(|c| (0..COLS).map(|j| ((j as f64 + 1.0) * (0.05 + 0.03 * c as f64)).sin() + 1.2).collect())
        .collect();
    let mut f = Vec::with_capacity(ROWS * COLS);
    for r in 0..ROWS {
        let w: Vec<f64> = (0..6).map(|c| unit((r * 8 + c) as u64) / (1.0 + c as f64)).collect();
        for j in 0..COLS {
            let v: f64 = comps.iter().zip(&w).map(|(comp, w)| comp[j] * w).sum();
            f.push(v + 0.01 * (unit((r * COLS + j) as u64 ^ 0xABCD) - 0.5));
        }
    }
    f
}

fn best_of<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..runs {
        let t = Instant::now();
        let r = black_box(f());
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("at least one run"))
}

fn main() {
    let f = matrix();
    if let Ok(dir) = std::env::var("LIGHTRIG_PCA_DUMP") {
        std::fs::create_dir_all(&dir).expect("dump directory");
        let bytes: Vec<u8> = f.iter().flat_map(|x| x.to_le_bytes()).collect();
        std::fs::write(format!("{dir}/f.f64"), bytes).expect("writing the matrix");
        std::fs::write(format!("{dir}/shape.txt"), format!("{ROWS} {COLS}\n")).expect("writing the shape");
        eprintln!("matrix written to {dir}");
    }
    let samples: Vec<Vec<f64>> = f.chunks_exact(COLS).map(<[f64]>::to_vec).collect();
    let (t_pca, pca) = best_of(5, || Pca::new(&samples, 10));
    let (t_select, pairs) = best_of(5, || pca.select_pairs(5));
    let top: f64 = pca.energy.iter().take(6).sum::<f64>() / pca.energy.iter().sum::<f64>();
    println!(
        "lightrig Pca::new {ROWS}x{COLS}, 10 components: best of 5 {:.1} ms ({:.4} of the energy in 6; \
         rayon threads {})",
        t_pca * 1e3,
        top,
        rayon::current_num_threads()
    );
    println!(
        "lightrig select_pairs(5): best of 5 {:.2} ms, pairs {pairs:?}, cond(R) {:.2}",
        t_select * 1e3,
        pca.condition(&pairs)
    );
    println!("lightrig PCA + selection: {:.1} ms", (t_pca + t_select) * 1e3);
}
