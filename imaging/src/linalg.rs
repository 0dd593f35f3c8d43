//! Small dense linear algebra on row-major `f64` matrices: a symmetric eigen-decomposition by
//! cyclic Jacobi rotations (exact to rounding for the sizes here: calibration's 9×9 normal
//! equations, a bispectral PCA's few hundred wavelength pairs), singular values, the condition
//! number and the pseudoinverse from it.

/// Eigenvalues (descending) and eigenvectors (as columns of a row-major `n × n` matrix) of the
/// symmetric row-major `n × n` matrix `a`.
pub fn sym_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let norm: f64 = m.iter().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i * n + j].powi(2))
            .sum();
        if off.sqrt() <= 1e-15 * norm.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = m[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let (app, aqq) = (m[p * n + p], m[q * n + q]);
                // The rotation that zeroes m[p][q] (Golub & Van Loan 8.5.2).
                let tau = (aqq - app) / (2.0 * apq);
                let t = tau.signum() / (tau.abs() + (1.0 + tau * tau).sqrt());
                let t = if tau == 0.0 { 1.0 } else { t };
                let c = 1.0 / (1.0 + t * t).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (mkp, mkq) = (m[k * n + p], m[k * n + q]);
                    m[k * n + p] = c * mkp - s * mkq;
                    m[k * n + q] = s * mkp + c * mkq;
                }
                for k in 0..n {
                    let (mpk, mqk) = (m[p * n + k], m[q * n + k]);
                    m[p * n + k] = c * mpk - s * mqk;
                    m[q * n + k] = s * mpk + c * mqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| m[j * n + j].total_cmp(&m[i * n + i]));
    let values = order.iter().map(|&i| m[i * n + i]).collect();
    let mut vectors = vec![0.0; n * n];
    for (col, &i) in order.iter().enumerate() {
        for k in 0..n {
            vectors[k * n + col] = v[k * n + i];
        }
    }
    (values, vectors)
}

/// `AᵀA` of the row-major `rows × cols` matrix `a`.
pub fn gram(a: &[f64], rows: usize, cols: usize) -> Vec<f64> {
    let mut g = vec![0.0; cols * cols];
    for r in 0..rows {
        let row = &a[r * cols..(r + 1) * cols];
        for i in 0..cols {
            if row[i] == 0.0 {
                continue;
            }
            for j in i..cols {
                g[i * cols + j] += row[i] * row[j];
            }
        }
    }
    for i in 0..cols {
        for j in 0..i {
            g[i * cols + j] = g[j * cols + i];
        }
    }
    g
}

/// The singular values of the row-major `rows × cols` matrix `a`, descending (`min(rows, cols)`
/// of them).
pub fn singular_values(a: &[f64], rows: usize, cols: usize) -> Vec<f64> {
    let (values, _) = if rows >= cols {
        sym_eigen(&gram(a, rows, cols), cols)
    } else {
        sym_eigen(&gram(&transpose(a, rows, cols), cols, rows), rows)
    };
    values.into_iter().map(|l| l.max(0.0).sqrt()).collect()
}

/// The condition number `σ_max / σ_min` (infinite when singular).
pub fn cond(a: &[f64], rows: usize, cols: usize) -> f64 {
    let s = singular_values(a, rows, cols);
    match (s.first(), s.last()) {
        (Some(&hi), Some(&lo)) if lo > hi * 1e-13 => hi / lo,
        _ => f64::INFINITY,
    }
}

/// The transpose of the row-major `rows × cols` matrix `a`.
pub fn transpose(a: &[f64], rows: usize, cols: usize) -> Vec<f64> {
    let mut t = vec![0.0; a.len()];
    for r in 0..rows {
        for c in 0..cols {
            t[c * rows + r] = a[r * cols + c];
        }
    }
    t
}

/// The Moore–Penrose pseudoinverse (`cols × rows`, row-major) of the row-major `rows × cols`
/// matrix `a`: `V Σ⁺ Vᵀ Aᵀ` from the eigen-decomposition of `AᵀA`, singular values below
/// `1e-12·σ_max` dropped.
pub fn pinv(a: &[f64], rows: usize, cols: usize) -> Vec<f64> {
    let (lambda, v) = sym_eigen(&gram(a, rows, cols), cols);
    let top = lambda.first().copied().unwrap_or(0.0).max(0.0);
    // (AᵀA)⁺ = V Λ⁺ Vᵀ
    let mut inv = vec![0.0; cols * cols];
    for (k, &l) in lambda.iter().enumerate() {
        if l <= top * 1e-24 || l <= 0.0 {
            continue;
        }
        for i in 0..cols {
            for j in 0..cols {
                inv[i * cols + j] += v[i * cols + k] * v[j * cols + k] / l;
            }
        }
    }
    // (AᵀA)⁺ Aᵀ
    let mut out = vec![0.0; cols * rows];
    for i in 0..cols {
        for r in 0..rows {
            out[i * rows + r] = (0..cols).map(|j| inv[i * cols + j] * a[r * cols + j]).sum();
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_symmetric_matrix_is_its_eigenvectors_times_its_eigenvalues() {
        let a = [4.0, 1.0, 2.0, 1.0, 3.0, 0.5, 2.0, 0.5, 5.0];
        let (l, v) = sym_eigen(&a, 3);
        assert!(l.windows(2).all(|w| w[0] >= w[1]));
        for i in 0..3 {
            for j in 0..3 {
                let back: f64 = (0..3).map(|k| v[i * 3 + k] * l[k] * v[j * 3 + k]).sum();
                assert!((back - a[i * 3 + j]).abs() < 1e-12, "({i},{j})");
                let dot: f64 = (0..3).map(|k| v[k * 3 + i] * v[k * 3 + j]).sum();
                assert!((dot - f64::from(u8::from(i == j))).abs() < 1e-12, "orthonormal");
            }
        }
        assert!((l.iter().sum::<f64>() - 12.0).abs() < 1e-12, "the trace");
    }

    #[test]
    fn singular_values_condition_and_pseudoinverse() {
        // A 3×2 matrix with singular values 3 and 1 (orthonormal columns scaled).
        let (c, s) = (0.6, 0.8);
        let a = [3.0 * c, -s, 3.0 * s, c, 0.0, 0.0];
        let sv = singular_values(&a, 3, 2);
        assert!((sv[0] - 3.0).abs() < 1e-12 && (sv[1] - 1.0).abs() < 1e-12, "{sv:?}");
        assert!((singular_values(&transpose(&a, 3, 2), 2, 3)[1] - 1.0).abs() < 1e-12);
        assert!((cond(&a, 3, 2) - 3.0).abs() < 1e-12);
        assert_eq!(cond(&[1.0, 2.0, 2.0, 4.0], 2, 2), f64::INFINITY);
        // A⁺A = I for full column rank.
        let p = pinv(&a, 3, 2);
        for i in 0..2 {
            for j in 0..2 {
                let v: f64 = (0..3).map(|k| p[i * 3 + k] * a[k * 2 + j]).sum();
                assert!((v - f64::from(u8::from(i == j))).abs() < 1e-12);
            }
        }
    }
}
