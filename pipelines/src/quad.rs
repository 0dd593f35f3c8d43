//! Gauss–Legendre quadrature: `n` nodes integrate polynomials of degree `2n − 1` exactly.

/// Nodes and weights of the `n`-point rule on `[−1, 1]`, by Newton's iteration on the Legendre
/// polynomial from the Chebyshev guesses.
pub fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // P_n(x) and its derivative by the three-term recurrence.
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let pn = if n == 0 {
                1.0
            } else if n == 1 {
                x
            } else {
                p1
            };
            let pm = if n == 1 { 1.0 } else { p0 };
            dp = n as f64 * (x * pn - pm) / (x * x - 1.0);
            let dx = pn / dp;
            x -= dx;
            if dx.abs() < 1e-15 {
                break;
            }
        }
        out.push((x, 2.0 / ((1.0 - x * x) * dp * dp)));
    }
    out
}

/// `rule` mapped onto `[a, b]`: `(x, w)` pairs with `Σ w·f(x) ≈ ∫_a^b f`.
pub fn on_interval(rule: &[(f64, f64)], a: f64, b: f64) -> impl Iterator<Item = (f64, f64)> + '_ {
    let (m, h) = ((a + b) / 2.0, (b - a) / 2.0);
    rule.iter().map(move |&(x, w)| (m + h * x, h * w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integrates_polynomials_of_degree_2n_minus_1_exactly() {
        for n in 1..=16 {
            let rule = gauss_legendre(n);
            let w: f64 = rule.iter().map(|r| r.1).sum();
            assert!((w - 2.0).abs() < 1e-13, "n={n}: weights sum to {w}");
            let d = 2 * n - 1;
            let got: f64 = on_interval(&rule, 0.0, 2.0).map(|(x, w)| w * x.powi(d as i32)).sum();
            let want = 2f64.powi(d as i32 + 1) / (d as f64 + 1.0);
            assert!((got / want - 1.0).abs() < 1e-12, "n={n}: {got} vs {want}");
        }
    }
}
