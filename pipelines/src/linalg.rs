//! Small dense linear systems: the normal equations of the Gauss–Newton and
//! Levenberg–Marquardt steps and the least-squares fits, a few unknowns each.

/// Solves the `N × N` system `a·x = b` by Gaussian elimination with partial pivoting; `None`
/// where `a` is singular to working precision (a pivot below `N·ε` of its column's largest
/// entry: unknowns in different units keep their own scale) or holds a non-finite number.
pub fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    if a.iter().flatten().chain(&b).any(|v| !v.is_finite()) {
        return None;
    }
    let tiny: [f64; N] =
        std::array::from_fn(|c| a.iter().fold(0.0f64, |m, r| m.max(r[c].abs())) * N as f64 * f64::EPSILON);
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[p][c].abs() <= tiny[c] || a[p][c] == 0.0 {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let (pivot, pb) = (a[c], b[c]);
        for (row, br) in a.iter_mut().zip(b.iter_mut()).skip(c + 1) {
            let f = row[c] / pivot[c];
            for (v, pv) in row.iter_mut().zip(pivot.iter()).skip(c) {
                *v -= f * pv;
            }
            *br -= f * pb;
        }
    }
    let mut x = [0.0; N];
    for c in (0..N).rev() {
        let s: f64 = (c + 1..N).map(|k| a[c][k] * x[k]).sum();
        x[c] = (b[c] - s) / a[c][c];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_system_needing_a_row_swap_is_solved_exactly() {
        // The first pivot is zero: without pivoting this fails.
        let a = [[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]];
        let x = solve(a, [4.5, 3.0, 6.0]).unwrap();
        // x = (1.5, 1.5, 1.5): 3 + 1.5 = 4.5, 1.5 + 1.5 = 3, 4.5 + 1.5 = 6.
        for (got, want) in x.iter().zip([1.5, 1.5, 1.5]) {
            assert!((got - want).abs() < 1e-12, "{x:?}");
        }
    }

    #[test]
    fn singular_and_non_finite_systems_are_refused() {
        assert_eq!(solve([[1.0, 2.0], [2.0, 4.0]], [1.0, 2.0]), None);
        assert_eq!(solve([[0.0; 4]; 4], [1.0; 4]), None);
        assert_eq!(solve([[f64::NAN, 0.0], [0.0, 1.0]], [1.0, 1.0]), None);
        // Badly scaled but regular: kept (each column's threshold is its own).
        let x = solve([[1e-9, 0.0], [0.0, 1e9]], [1e-9, 1e9]).unwrap();
        assert!((x[0] - 1.0).abs() < 1e-12 && (x[1] - 1.0).abs() < 1e-12);
    }
}
