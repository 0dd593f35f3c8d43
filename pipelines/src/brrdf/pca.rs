//! PCA-steered acquisition (thesis section 4.5): the bispectral samples of a few dense
//! turntable angles, mean removed, decomposed into principal components; wavelength pairs
//! chosen greedily so that the components' rows at those pairs stay well conditioned; any
//! sample's full bispectral vector reconstructed from its values at the chosen pairs through
//! the pseudoinverse; and the saturated variant of figure 4.10, which keeps a strong specular
//! highlight from taking the first components.
//!
//! A sample is one vectorised reradiation matrix: its value at each of the `K` wavelength pairs.

use lightrig_imaging::linalg::{cond, gram, pinv, sym_eigen};
use rayon::prelude::*;

/// The principal components of a set of bispectral samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Pca {
    /// The mean sample (`K` values).
    pub mean: Vec<f64>,
    /// The components, strongest first, each `K` values of unit length.
    pub basis: Vec<Vec<f64>>,
    /// Each component's energy (eigenvalue of `FᵀF`), then those of the components not kept.
    pub energy: Vec<f64>,
}

impl Pca {
    /// The principal components of `samples` (each `K` values), keeping `n`.
    pub fn new(samples: &[Vec<f64>], n: usize) -> Pca {
        let k = samples.first().map_or(0, Vec::len);
        let count = samples.len().max(1) as f64;
        let mut mean = vec![0.0; k];
        for s in samples {
            for (m, v) in mean.iter_mut().zip(s) {
                *m += v / count;
            }
        }
        let f: Vec<f64> = samples.iter().flat_map(|s| s.iter().zip(&mean).map(|(v, m)| v - m)).collect();
        // FᵀF, its rows shared out over the cores in blocks (summed after).
        let block = 2048 * k.max(1);
        let g = f.par_chunks(block).map(|rows| gram(rows, rows.len() / k.max(1), k)).reduce(
            || vec![0.0; k * k],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            },
        );
        let (energy, vectors) = sym_eigen(&g, k);
        let basis = (0..n.min(k)).map(|c| (0..k).map(|i| vectors[i * k + c]).collect()).collect();
        Pca { mean, basis, energy: energy.into_iter().map(|e| e.max(0.0)).collect() }
    }

    /// The fraction of the samples' energy (about the mean) the first `n` components leave out
    /// (the thesis's residual energy).
    pub fn residual(&self, n: usize) -> f64 {
        let total: f64 = self.energy.iter().sum();
        if total <= 0.0 {
            return 0.0;
        }
        self.energy.iter().skip(n).sum::<f64>() / total
    }

    /// `R`: the basis' rows at `pairs` (row-major, `pairs.len() × n`).
    fn rows(&self, pairs: &[usize]) -> Vec<f64> {
        pairs.iter().flat_map(|&p| self.basis.iter().map(move |b| b[p])).collect()
    }

    /// Greedy choice of `count` wavelength pairs (indices into the `K`): first the pair of the
    /// basis' largest entry, then each time the pair whose row added keeps `cond(R)` smallest.
    pub fn select_pairs(&self, count: usize) -> Vec<usize> {
        let k = self.mean.len();
        let n = self.basis.len();
        let Some(first) = (0..k).max_by(|&a, &b| {
            let m = |p: usize| self.basis.iter().map(|v| v[p].abs()).fold(0.0, f64::max);
            m(a).total_cmp(&m(b))
        }) else {
            return Vec::new();
        };
        let mut chosen = vec![first];
        while chosen.len() < count.min(k) {
            let best = (0..k)
                .filter(|p| !chosen.contains(p))
                .map(|p| {
                    let mut with = chosen.clone();
                    with.push(p);
                    (p, cond(&self.rows(&with), with.len(), n))
                })
                .min_by(|a, b| a.1.total_cmp(&b.1));
            match best {
                Some((p, _)) => chosen.push(p),
                None => break,
            }
        }
        chosen
    }

    /// `cond(R)` of a choice of pairs.
    pub fn condition(&self, pairs: &[usize]) -> f64 {
        cond(&self.rows(pairs), pairs.len(), self.basis.len())
    }

    /// The full sample (`K` values) from its values `measured` at `pairs`: the mixture
    /// `x = R⁺·(m − mean)` of the components, plus the mean.
    pub fn reconstruct(&self, pairs: &[usize], measured: &[f64]) -> Vec<f64> {
        let n = self.basis.len();
        let r_plus = pinv(&self.rows(pairs), pairs.len(), n);
        let centred: Vec<f64> = pairs.iter().zip(measured).map(|(&p, m)| m - self.mean[p]).collect();
        let x: Vec<f64> = (0..n)
            .map(|i| (0..pairs.len()).map(|j| r_plus[i * pairs.len() + j] * centred[j]).sum())
            .collect();
        (0..self.mean.len())
            .map(|p| self.mean[p] + (0..n).map(|i| self.basis[i][p] * x[i]).sum::<f64>())
            .collect()
    }
}

/// Figure 4.10's saturation `x̃ = sat(x)`: the inverse of `x = sign(x̃)(x̃² + |x̃|)`, linear for
/// small `|x|` and `O(√x)` for large; `scale` is where it bends (values are divided by it first).
pub fn saturate(x: f64, scale: f64) -> f64 {
    let u = (x / scale).abs();
    scale * x.signum() * ((1.0 + 4.0 * u).sqrt() - 1.0) / 2.0
}

/// The inverse of [`saturate`].
pub fn desaturate(x: f64, scale: f64) -> f64 {
    let u = x / scale;
    scale * u.signum() * (u * u + u.abs())
}

/// The saturated PCA: the components of the samples' saturated values (a strong highlight
/// weighs as its square root); reconstructions are desaturated.
#[derive(Debug, Clone, PartialEq)]
pub struct SaturatedPca {
    /// The components of the saturated samples.
    pub pca: Pca,
    /// [`saturate`]'s scale.
    pub scale: f64,
}

impl SaturatedPca {
    /// The saturated samples' principal components, keeping `n`.
    pub fn new(samples: &[Vec<f64>], n: usize, scale: f64) -> Self {
        let sat: Vec<Vec<f64>> =
            samples.iter().map(|s| s.iter().map(|&v| saturate(v, scale)).collect()).collect();
        SaturatedPca { pca: Pca::new(&sat, n), scale }
    }

    /// [`Pca::reconstruct`] on saturated measurements, desaturated.
    pub fn reconstruct(&self, pairs: &[usize], measured: &[f64]) -> Vec<f64> {
        let sat: Vec<f64> = measured.iter().map(|&v| saturate(v, self.scale)).collect();
        self.pca.reconstruct(pairs, &sat).into_iter().map(|v| desaturate(v, self.scale)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A seeded generator.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// Samples of a rank-2 bispectral family over `k` pairs: mean + a·u + b·v.
    fn family(k: usize, count: usize, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>, Vec<f64>) {
        let u: Vec<f64> = (0..k).map(|i| (i as f64 * 0.3).sin() + 1.0).collect();
        let v: Vec<f64> = (0..k).map(|i| if i % 5 == 0 { 2.0 } else { (i as f64 * 0.11).cos() }).collect();
        let mut r = Rng(seed);
        let samples = (0..count)
            .map(|_| {
                let (a, b) = (r.next() * 2.0, r.next() - 0.5);
                (0..k).map(|i| 0.5 + a * u[i] + b * v[i]).collect()
            })
            .collect();
        (samples, u, v)
    }

    #[test]
    fn two_components_hold_a_rank_two_family_and_two_pairs_reconstruct_it() {
        let (samples, u, v) = family(40, 60, 3);
        let pca = Pca::new(&samples, 2);
        assert!(pca.residual(2) < 1e-12, "{}", pca.residual(2));
        assert!(pca.residual(1) > 1e-3);
        // The components span u and v (the family varies along both about its mean): each is
        // its own projection on them.
        for w in [&u, &v] {
            let c: Vec<f64> =
                pca.basis.iter().map(|b| b.iter().zip(w.iter()).map(|(x, y)| x * y).sum()).collect();
            let off: f64 =
                (0..40).map(|i| (w[i] - c[0] * pca.basis[0][i] - c[1] * pca.basis[1][i]).powi(2)).sum();
            let len: f64 = w.iter().map(|x| x * x).sum();
            assert!(off < 1e-20 * len, "{off}");
        }
        let pairs = pca.select_pairs(2);
        assert_eq!(pairs.len(), 2);
        let largest = (0..40).max_by(|&a, &b| {
            let m = |p: usize| pca.basis.iter().map(|x| x[p].abs()).fold(0.0, f64::max);
            m(a).total_cmp(&m(b))
        });
        assert_eq!(Some(pairs[0]), largest, "the greedy choice starts at the largest entry");
        // A new sample of the family, measured at two pairs only, comes back whole.
        let (new, _, _) = family(40, 1, 99);
        let measured: Vec<f64> = pairs.iter().map(|&p| new[0][p]).collect();
        let full = pca.reconstruct(&pairs, &measured);
        let err = full.iter().zip(&new[0]).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err < 1e-9, "{err}");
    }

    #[test]
    fn the_greedy_choice_is_better_conditioned_than_neighbouring_pairs() {
        let (samples, _, _) = family(40, 60, 5);
        let mut r = Rng(11);
        // Some noise: a full-rank set, four components kept.
        let noisy: Vec<Vec<f64>> =
            samples.iter().map(|s| s.iter().map(|v| v + 0.01 * r.next()).collect()).collect();
        let pca = Pca::new(&noisy, 4);
        let greedy = pca.select_pairs(4);
        let naive: Vec<usize> = (0..4).collect();
        assert!(
            pca.condition(&greedy) < pca.condition(&naive),
            "{} vs {}",
            pca.condition(&greedy),
            pca.condition(&naive)
        );
        assert!(pca.condition(&greedy).is_finite());
    }

    #[test]
    fn saturation_is_linear_near_zero_and_a_square_root_far_out_and_inverts() {
        for x in [-50.0, -1.0, -0.01, 0.0, 0.01, 1.0, 50.0, 1e4] {
            assert!((desaturate(saturate(x, 2.0), 2.0) - x).abs() < 1e-9 * x.abs().max(1.0), "{x}");
        }
        assert!((saturate(1e-4, 1.0) - 1e-4).abs() < 1e-7, "linear for small values");
        assert!((saturate(1e6, 1.0) / 1e3 - 1.0).abs() < 1e-2, "√x for large ones");
    }

    #[test]
    fn a_saturated_pca_gives_a_strong_highlight_less_of_its_energy() {
        // Diffuse samples of a rank-2 family, one in ten with a strong highlight on three pairs.
        let (mut samples, _, _) = family(30, 80, 7);
        for s in samples.iter_mut().step_by(10) {
            for v in s.iter_mut().take(3) {
                *v += 30.0;
            }
        }
        // The first component's share of the energy: the highlight's, in the plain PCA.
        let share = |p: &Pca| p.energy[0] / p.energy.iter().sum::<f64>();
        let plain = Pca::new(&samples, 3);
        let sat = SaturatedPca::new(&samples, 3, 0.5);
        let (a, b) = (share(&plain), share(&sat.pca));
        assert!(a > 0.9, "the highlight holds nearly all of the plain PCA's energy: {a}");
        assert!(b < a - 0.1, "less of the saturated one's: {b} against {a}");
        // The saturated PCA still reconstructs: a sample from its own three components' pairs.
        let pairs = sat.pca.select_pairs(3);
        for i in [0, 1] {
            let m: Vec<f64> = pairs.iter().map(|&p| samples[i][p]).collect();
            let full = sat.reconstruct(&pairs, &m);
            for &p in &pairs {
                assert!((full[p] - samples[i][p]).abs() < 1e-9, "a measured pair comes back as measured");
            }
        }
    }
}
