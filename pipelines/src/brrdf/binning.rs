//! Binning (thesis §4.4.3): each wavelength pair's samples discretised in `(θo, θi, φd)`, 32³
//! bins (64³ for strongly specular materials); bins the turntable's coarse steps leave empty
//! are filled by diffusion.
//!
//! `θo`, `θi` ∈ [0, π/2) and `φd` ∈ [0, π], `n` bins each. A bin holds the mean of its samples.
//! The fill diffuses the observed bins' values into the empty ones: started from a pyramid of
//! coarser bins (so that a hole far from every observation starts from its region's mean, not
//! from zero), then Jacobi steps of the discrete Laplace equation over the empty bins with the
//! observed ones held.

/// Samples being binned.
#[derive(Debug, Clone)]
pub struct Binner {
    /// Bins per dimension.
    pub n: usize,
    /// Values per sample (wavelength pairs).
    pub k: usize,
    sum: Vec<f64>,
    count: Vec<u32>,
}

/// A binned BRRDF: `values[bin · k + pair]`, bin `(io · n + ii) · n + ip`.
#[derive(Debug, Clone, PartialEq)]
pub struct Binned {
    pub n: usize,
    pub k: usize,
    pub values: Vec<f32>,
    /// Samples per bin (0: filled by diffusion).
    pub count: Vec<u32>,
}

impl Binner {
    /// `n` bins per dimension (a power of two), `k` values a sample.
    pub fn new(n: usize, k: usize) -> Binner {
        assert!(n.is_power_of_two(), "bins per dimension must be a power of two");
        Binner { n, k, sum: vec![0.0; n * n * n * k], count: vec![0; n * n * n] }
    }

    /// The bin of `(θo, θi, φd)` (radians), if inside the domain.
    pub fn bin(&self, theta_o: f64, theta_i: f64, phi_d: f64) -> Option<usize> {
        let half = std::f64::consts::FRAC_PI_2;
        let idx = |v: f64, top: f64| -> Option<usize> {
            if !(0.0..=top).contains(&v) {
                return None;
            }
            Some(((v / top * self.n as f64) as usize).min(self.n - 1))
        };
        let (o, i, p) = (idx(theta_o, half)?, idx(theta_i, half)?, idx(phi_d, std::f64::consts::PI)?);
        Some((o * self.n + i) * self.n + p)
    }

    /// Adds a sample's `values` at `(θo, θi, φd)`; false if outside the domain.
    pub fn add(&mut self, theta_o: f64, theta_i: f64, phi_d: f64, values: &[f64]) -> bool {
        let Some(b) = self.bin(theta_o, theta_i, phi_d) else { return false };
        self.count[b] += 1;
        for (s, v) in self.sum[b * self.k..(b + 1) * self.k].iter_mut().zip(values) {
            *s += v;
        }
        true
    }

    /// The bins' means, empty bins filled by diffusion (`iterations` Jacobi steps after the
    /// pyramid start).
    pub fn finish(self, iterations: usize) -> Binned {
        let (n, k) = (self.n, self.k);
        let mut values = vec![0.0f64; n * n * n * k];
        for b in 0..n * n * n {
            if self.count[b] > 0 {
                let c = f64::from(self.count[b]);
                for j in 0..k {
                    values[b * k + j] = self.sum[b * k + j] / c;
                }
            }
        }
        // The pyramid: level L has n >> L bins a side; means of the observed bins below.
        let mut levels: Vec<(usize, Vec<f64>, Vec<u32>)> = vec![(n, self.sum.clone(), self.count.clone())];
        while levels.last().is_some_and(|l| l.0 > 1) {
            let (m, sum, count) = levels.last().cloned().unwrap_or_default();
            let h = m / 2;
            let (mut s2, mut c2) = (vec![0.0; h * h * h * k], vec![0u32; h * h * h]);
            for o in 0..m {
                for i in 0..m {
                    for p in 0..m {
                        let (b, b2) = ((o * m + i) * m + p, ((o / 2) * h + i / 2) * h + p / 2);
                        c2[b2] += count[b];
                        for j in 0..k {
                            s2[b2 * k + j] += sum[b * k + j];
                        }
                    }
                }
            }
            levels.push((h, s2, c2));
        }
        // Top down: an empty bin starts from its parent's mean.
        let mut parent: Vec<f64> = Vec::new();
        for (m, sum, count) in levels.iter().rev() {
            let m = *m;
            let mut mean = vec![0.0; m * m * m * k];
            for o in 0..m {
                for i in 0..m {
                    for p in 0..m {
                        let b = (o * m + i) * m + p;
                        if count[b] > 0 {
                            for j in 0..k {
                                mean[b * k + j] = sum[b * k + j] / f64::from(count[b]);
                            }
                        } else if !parent.is_empty() {
                            let h = m / 2;
                            let pb = ((o / 2) * h + i / 2) * h + p / 2;
                            mean[b * k..(b + 1) * k].copy_from_slice(&parent[pb * k..(pb + 1) * k]);
                        }
                    }
                }
            }
            parent = mean;
        }
        for b in 0..n * n * n {
            if self.count[b] == 0 {
                values[b * k..(b + 1) * k].copy_from_slice(&parent[b * k..(b + 1) * k]);
            }
        }
        // Jacobi steps over the empty bins.
        let empty: Vec<usize> = (0..n * n * n).filter(|&b| self.count[b] == 0).collect();
        let mut next = values.clone();
        for _ in 0..iterations {
            for &b in &empty {
                let (o, i, p) = (b / (n * n), (b / n) % n, b % n);
                let mut nb = [usize::MAX; 6];
                let mut c = 0;
                for (d, (oo, ii, pp)) in [
                    (o.wrapping_sub(1), i, p),
                    (o + 1, i, p),
                    (o, i.wrapping_sub(1), p),
                    (o, i + 1, p),
                    (o, i, p.wrapping_sub(1)),
                    (o, i, p + 1),
                ]
                .into_iter()
                .enumerate()
                {
                    if oo < n && ii < n && pp < n {
                        nb[d] = (oo * n + ii) * n + pp;
                        c += 1;
                    }
                }
                for j in 0..k {
                    let s: f64 = nb.iter().filter(|&&x| x != usize::MAX).map(|&x| values[x * k + j]).sum();
                    next[b * k + j] = s / f64::from(c);
                }
            }
            std::mem::swap(&mut values, &mut next);
            for &b in &empty {
                next[b * k..(b + 1) * k].copy_from_slice(&values[b * k..(b + 1) * k]);
            }
        }
        Binned { n, k, values: values.into_iter().map(|v| v as f32).collect(), count: self.count }
    }
}

impl Binned {
    /// Bins that held samples.
    pub fn observed(&self) -> usize {
        self.count.iter().filter(|&&c| c > 0).count()
    }

    /// The value of pair `j` at the bin of `(θo, θi, φd)` (nearest bin).
    pub fn at(&self, theta_o: f64, theta_i: f64, phi_d: f64, j: usize) -> Option<f32> {
        let b = Binner { n: self.n, k: self.k, sum: Vec::new(), count: Vec::new() }
            .bin(theta_o, theta_i, phi_d)?;
        self.values.get(b * self.k + j).copied()
    }

    /// The bin centre's angles `(θo, θi, φd)` of bin `b`.
    pub fn centre(&self, b: usize) -> (f64, f64, f64) {
        let n = self.n;
        let (o, i, p) = (b / (n * n), (b / n) % n, b % n);
        let half = std::f64::consts::FRAC_PI_2;
        let f = |x: usize| (x as f64 + 0.5) / n as f64;
        (f(o) * half, f(i) * half, f(p) * std::f64::consts::PI)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth BRRDF-like function of the three angles, two "pairs".
    fn truth(o: f64, i: f64, p: f64) -> [f64; 2] {
        [0.3 + 0.2 * o.cos() * i.cos(), 0.1 + 0.05 * (p / 2.0).cos() + 0.1 * i]
    }

    #[test]
    fn observed_bins_hold_their_mean_and_empty_ones_are_diffused_from_their_neighbours() {
        let n = 16;
        let mut b = Binner::new(n, 2);
        // Samples on every other slab of θi and the last (as a coarse turntable leaves them), two
        // per bin.
        let mut expect = std::collections::HashMap::new();
        for o in 0..n {
            for i in (0..n).filter(|i| i % 2 == 0 || *i == n - 1) {
                for p in 0..n {
                    let probe = Binned { n, k: 2, values: Vec::new(), count: Vec::new() };
                    let (co, ci, cp) = probe.centre((o * n + i) * n + p);
                    let (d1, d2) = (0.2 / n as f64, -0.2 / n as f64);
                    let (v1, v2) = (truth(co + d1, ci, cp), truth(co + d2, ci, cp));
                    b.add(co + d1, ci, cp, &v1);
                    b.add(co + d2, ci, cp, &v2);
                    expect.insert((o * n + i) * n + p, [(v1[0] + v2[0]) / 2.0, (v1[1] + v2[1]) / 2.0]);
                }
            }
        }
        let out = b.finish(50);
        assert_eq!(out.observed(), n * n * (n / 2 + 1));
        for (&bin, v) in &expect {
            for (j, want) in v.iter().enumerate() {
                assert!(
                    (f64::from(out.values[bin * 2 + j]) - want).abs() < 1e-6,
                    "bin {bin}: kept as observed"
                );
            }
        }
        // The filled slabs: close to the smooth truth at their centres.
        let mut worst = 0.0f64;
        for bin in 0..n * n * n {
            if out.count[bin] == 0 {
                let (o, i, p) = out.centre(bin);
                let t = truth(o, i, p);
                for (j, want) in t.iter().enumerate() {
                    worst = worst.max((f64::from(out.values[bin * 2 + j]) - want).abs() / want);
                }
            }
        }
        assert!(worst < 0.03, "worst relative error of a filled bin {worst}");
    }

    #[test]
    fn a_region_far_from_every_sample_starts_from_the_nearest_means() {
        let mut b = Binner::new(8, 1);
        // One corner observed at 1, the opposite one at 3: nothing is left at zero.
        b.add(0.01, 0.01, 0.01, &[1.0]);
        b.add(1.55, 1.55, 3.1, &[3.0]);
        let out = b.finish(30);
        assert!(out.values.iter().all(|&v| (0.99..=3.01).contains(&v)), "all between the observations");
        assert!(b_out_bin(&out, 0.01) < b_out_bin(&out, 1.55));
        assert!(Binner::new(8, 1).bin(1.6, 0.1, 0.1).is_none(), "θo beyond π/2 is outside");
    }

    fn b_out_bin(out: &Binned, a: f64) -> f32 {
        out.at(a, a, a * 2.0, 0).unwrap()
    }
}
