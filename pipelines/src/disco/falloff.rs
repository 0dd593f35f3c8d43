//! The object's overall fall-off with distance, taken out of `F` before the mesh filter and put
//! back after.
//!
//! The paper's filter (section 6.2) is an averaging one: an entry it fills lies between the
//! measured ones around it. Where the camera's dynamic range ends — far through the object,
//! where `Rd` is 10⁻⁶ of the spot's and below — there is nothing beyond to interpolate towards,
//! and the fill holds the last measured level, hundreds of times too bright. Dividing `F` by
//! the fall-off every diffusing object shares, `e^(−s·d)/d²` (the dipole's far field) with `s`
//! per channel fitted to the measured entries, leaves a residual that varies slowly over the
//! surface; the filter fills that, and the fall-off goes back on, so unmeasured far entries
//! continue the measured decay. Measured entries are unchanged (the factor is divided out
//! exactly as it was multiplied in) and symmetry is kept (it depends only on the distance).

use rayon::prelude::*;

use crate::vec3::{norm, sub};

use super::interpolate::Matrix;
use super::mesh::SurfaceMesh;

/// A channel's fall-off `ln F ≈ a − s·d − p·ln d`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Falloff {
    /// Rate, mm⁻¹.
    pub s: f64,
    /// Power of the distance.
    pub p: f64,
}

/// The power of the distance: the dipole's far field, `e^(−σtr·d)/d²`. (Fitting it too
/// extrapolates worse: over the few centimetres the camera measures, `s` and `p` trade off.)
pub const POWER: f64 = 2.0;

/// Per channel, the rate `s` fitted by least squares to the measured entries (weight > 0) at
/// least `min_d` mm apart, with `p` = [`POWER`]; `s` kept ≥ 0 (a diffuser does not brighten
/// with distance); `None` with fewer than 10 entries in a channel.
pub fn fit(mesh: &SurfaceMesh, m: &Matrix, min_d: f64) -> Option<[Falloff; 3]> {
    let n = m.n;
    let mut acc = [[0.0f64; 5]; 3]; // Σ1, Σd, Σd², Σy, Σd·y with y = ln F + p·ln d
    for k in 0..n {
        for r in 0..n {
            let i = k * n + r;
            if m.weight[i] <= 0.0 {
                continue;
            }
            let d = norm(sub(mesh.vertices[r], mesh.vertices[k]));
            if d < min_d {
                continue;
            }
            for (c, a) in acc.iter_mut().enumerate() {
                let v = f64::from(m.values[i][c]);
                if v > 0.0 {
                    let y = v.ln() + POWER * d.ln();
                    *a = [a[0] + 1.0, a[1] + d, a[2] + d * d, a[3] + y, a[4] + d * y];
                }
            }
        }
    }
    let mut out = [Falloff { s: 0.0, p: POWER }; 3];
    for c in 0..3 {
        let [n1, sd, sdd, sy, sdy] = acc[c];
        let det = n1 * sdd - sd * sd;
        if n1 < 10.0 || det <= 0.0 {
            return None;
        }
        out[c].s = (-(n1 * sdy - sd * sy) / det).max(0.0);
    }
    Some(out)
}

/// Multiplies `F(r, k)` by `e^(s·d)·max(d, d_min)^p` (`forward`) or divides by it.
pub fn apply(mesh: &SurfaceMesh, m: &mut Matrix, f: [Falloff; 3], d_min: f64, forward: bool) {
    let n = m.n;
    m.values.par_chunks_mut(n.max(1)).enumerate().for_each(|(k, col)| {
        for (r, v) in col.iter_mut().enumerate() {
            let d = norm(sub(mesh.vertices[r], mesh.vertices[k]));
            let dd = d.max(d_min);
            for c in 0..3 {
                let g = (f[c].s * d).exp() * dd.powf(f[c].p);
                let x = f64::from(v[c]);
                v[c] = if forward { x * g } else { x / g } as f32;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;

    #[test]
    fn the_fall_off_is_recovered_and_undone_exactly() {
        let mesh = SurfaceMesh::new(&pebble(1, [20.0, 20.0, 30.0]));
        let n = mesh.vertices.len();
        let rates = [0.1, 0.2, 0.3];
        let values: Vec<[f32; 3]> = (0..n * n)
            .map(|i| {
                let d = norm(sub(mesh.vertices[i % n], mesh.vertices[i / n])).max(1.0);
                rates.map(|s| (2.0 * (-s * d).exp() / (d * d)) as f32)
            })
            .collect();
        let m0 = Matrix { n, values, weight: vec![1.0; n * n] };
        let s = fit(&mesh, &m0, 5.0).unwrap();
        for c in 0..3 {
            assert!((s[c].s - rates[c]).abs() < 1e-4 && (s[c].p - 2.0).abs() < 1e-3, "{s:?}");
        }
        let mut m = m0.clone();
        apply(&mesh, &mut m, s, 1.0, true);
        // Detrended, the far entries are all about the same.
        let far: Vec<f32> = (0..n * n)
            .filter(|&i| norm(sub(mesh.vertices[i % n], mesh.vertices[i / n])) > 5.0)
            .map(|i| m.values[i][2])
            .collect();
        let (lo, hi) = far.iter().fold((f32::MAX, 0.0f32), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(hi / lo < 1.01, "{lo} {hi}");
        apply(&mesh, &mut m, s, 1.0, false);
        for (a, b) in m.values.iter().zip(&m0.values) {
            for c in 0..3 {
                assert!((a[c] / b[c] - 1.0).abs() < 1e-5);
            }
        }
        assert_eq!(fit(&mesh, &Matrix { n, values: m0.values.clone(), weight: vec![0.0; n * n] }, 5.0), None);
    }
}
