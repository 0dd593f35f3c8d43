//! The 3×3×3 median of a scanline slab.
//!
//! Slab layout: `u × t` with `t` contiguous (`slab[u·frames + t]`). The 27 neighbours of voxel
//! `(u, v, t)` are nine `t`-lines (`u ± 1`, `v ± 1`) at `t − 1, t, t + 1`, so the median of a
//! run of `t` is a selection over 27 shifted slices, done lane-wise on fixed-size chunks the
//! compiler vectorises.

/// Lanes per chunk: 15 working rows of this many floats stay in L1.
const CH: usize = 32;

/// Orders `a[j]`, `b[j]` per lane so that `a` holds the smaller.
#[inline(always)]
fn cmpswap(a: &mut [f32; CH], b: &mut [f32; CH]) {
    for (x, y) in a.iter_mut().zip(b.iter_mut()) {
        let (p, q) = (*x, *y);
        *x = p.min(q);
        *y = p.max(q);
    }
}

/// Lane-wise median of 27 rows (forgetful selection): keep 15 rows, move the smallest and the
/// largest to the ends and forget both, take in the next row, until the three left hold the
/// median in the middle. With 15 = ⌈27/2⌉ + 1 rows the median is never among the forgotten.
/// 195 compare-exchanges per lane instead of a full sort.
#[inline(always)]
fn median27(src: &[[f32; CH]; 27], out: &mut [f32; CH]) {
    let mut b = [[0f32; CH]; 15];
    b.copy_from_slice(&src[..15]);
    let mut m = 15;
    let mut next = 15;
    loop {
        for i in 1..m {
            let (first, rest) = b.split_at_mut(i);
            cmpswap(&mut first[0], &mut rest[0]);
        }
        for i in 1..m - 1 {
            let (lower, upper) = b.split_at_mut(m - 1);
            cmpswap(&mut lower[i], &mut upper[0]);
        }
        if next == 27 {
            break;
        }
        b[0] = src[next];
        next += 1;
        m -= 1;
    }
    *out = b[1];
}

/// The 3×3×3 median of row `v` of the stack into `out` (`width × frames`), from raw rows
/// `rows = [v − 1, v, v + 1]` (the caller repeats the edge row at the image's top and bottom).
/// Outside the stack the nearest voxel is repeated (`u`, `t` clamped).
pub(crate) fn median_row(rows: [&[f32]; 3], width: usize, frames: usize, out: &mut [f32]) {
    let mut src = [[0f32; CH]; 27];
    let mut res = [0f32; CH];
    for u in 0..width {
        let cols = [u.saturating_sub(1), u, (u + 1).min(width - 1)];
        let mut t0 = 0;
        while t0 < frames {
            let n = CH.min(frames - t0);
            let mut k = 0;
            for row in rows {
                for &c in &cols {
                    let line = &row[c * frames..(c + 1) * frames];
                    for dt in 0..3usize {
                        let dst = &mut src[k];
                        if t0 + dt >= 1 && t0 + dt + CH <= frames {
                            // Interior: a straight copy.
                            dst.copy_from_slice(&line[t0 + dt - 1..t0 + dt - 1 + CH]);
                        } else {
                            // The first and last chunks clamp t to the stack.
                            for (j, d) in dst.iter_mut().enumerate().take(n) {
                                *d = line[(t0 + j + dt).saturating_sub(1).min(frames - 1)];
                            }
                        }
                        k += 1;
                    }
                }
            }
            median27(&src, &mut res);
            out[u * frames + t0..u * frames + t0 + n].copy_from_slice(&res[..n]);
            t0 += n;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median27_matches_sorting() {
        let mut x = 12345u64;
        let mut src = [[0f32; CH]; 27];
        for _ in 0..50 {
            for row in src.iter_mut() {
                for v in row.iter_mut() {
                    x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    // Few levels, so ties are common.
                    *v = ((x >> 59) as f32) * 0.5;
                }
            }
            let mut out = [0f32; CH];
            median27(&src, &mut out);
            for j in 0..CH {
                let mut col: Vec<f32> = src.iter().map(|r| r[j]).collect();
                col.sort_by(f32::total_cmp);
                assert_eq!(out[j], col[13]);
            }
        }
    }

    #[test]
    fn median_row_matches_a_direct_median() {
        let (w, f) = (5usize, 70usize);
        let rows: Vec<Vec<f32>> = (0..3)
            .map(|r| (0..w * f).map(|i| (((i * 7919 + r * 104729) % 97) as f32).sin()).collect())
            .collect();
        let mut out = vec![0f32; w * f];
        median_row([&rows[0], &rows[1], &rows[2]], w, f, &mut out);
        for u in 0..w {
            for t in 0..f {
                let mut v = Vec::new();
                for row in &rows {
                    for du in [-1i64, 0, 1] {
                        for dt in [-1i64, 0, 1] {
                            let uu = (u as i64 + du).clamp(0, w as i64 - 1) as usize;
                            let tt = (t as i64 + dt).clamp(0, f as i64 - 1) as usize;
                            v.push(row[uu * f + tt]);
                        }
                    }
                }
                v.sort_by(f32::total_cmp);
                assert_eq!(out[u * f + t], v[13], "u {u} t {t}");
            }
        }
    }
}
