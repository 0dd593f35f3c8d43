//! From per-pixel candidates to one cut-off per pixel: 8-neighbour softening, the choice of the
//! first or strongest cut-off, and the segment-size filter. All on image-sized arrays.

use std::collections::VecDeque;

use super::{Cands, SurfaceParams};

/// The 8-neighbours of `i` in a `w × h` grid.
fn neighbours(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, y) = ((i % w) as i64, (i / w) as i64);
    (-1i64..=1)
        .flat_map(move |dy| (-1i64..=1).map(move |dx| (x + dx, y + dy)))
        .filter(move |&(nx, ny)| (nx, ny) != (x, y) && nx >= 0 && ny >= 0 && nx < w as i64 && ny < h as i64)
        .map(move |(nx, ny)| ny as usize * w + nx as usize)
}

/// One cut-off per pixel from the candidate lists (see the module steps 5–7).
pub(crate) fn resolve(cands: &[Cands], w: usize, h: usize, p: &SurfaceParams) -> Vec<Option<f64>> {
    let step = p.max_step as f32;
    // Softening: accepted[i] bit k for candidate k of pixel i; strong ones seed a flood fill
    // that takes in weak candidates of 8-neighbours at about the same t.
    let mut accepted = vec![0u8; cands.len()];
    let mut queue = VecDeque::new();
    for (i, c) in cands.iter().enumerate() {
        for (k, x) in c.as_slice().iter().enumerate() {
            if f64::from(x.strength) >= p.strong {
                accepted[i] |= 1 << k;
                queue.push_back((i, x.t));
            }
        }
    }
    while let Some((i, t)) = queue.pop_front() {
        for j in neighbours(i, w, h) {
            for (k, x) in cands[j].as_slice().iter().enumerate() {
                if accepted[j] & (1 << k) == 0 && (x.t - t).abs() <= step {
                    accepted[j] |= 1 << k;
                    queue.push_back((j, x.t));
                }
            }
        }
    }
    // One per pixel: the first (lists are in t order) or the strongest accepted.
    let mut t: Vec<Option<f32>> = cands
        .iter()
        .zip(&accepted)
        .map(|(c, &a)| {
            let acc = c.as_slice().iter().enumerate().filter(|(k, _)| a & (1 << k) != 0).map(|(_, x)| x);
            if p.first_surface {
                acc.map(|x| x.t).next()
            } else {
                acc.fold(None::<&super::Cand>, |b, x| match b {
                    Some(b) if b.strength >= x.strength => Some(b),
                    _ => Some(x),
                })
                .map(|x| x.t)
            }
        })
        .collect();
    // Segments: 8-connected, neighbouring cut-offs within max_step; small ones go.
    let mut label = vec![u32::MAX; t.len()];
    let mut members = Vec::new();
    for seed in 0..t.len() {
        if t[seed].is_none() || label[seed] != u32::MAX {
            continue;
        }
        members.clear();
        label[seed] = seed as u32;
        members.push(seed);
        let mut head = 0;
        while head < members.len() {
            let i = members[head];
            head += 1;
            let Some(ti) = t[i] else { continue };
            for j in neighbours(i, w, h) {
                if label[j] == u32::MAX {
                    if let Some(tj) = t[j] {
                        if (tj - ti).abs() <= step {
                            label[j] = seed as u32;
                            members.push(j);
                        }
                    }
                }
            }
        }
        if members.len() < p.min_segment {
            for &i in &members {
                t[i] = None;
            }
        }
    }
    // Trim: drop pixels on a segment's rim (a neighbour missing, in another segment, or
    // outside the image) or on a kink of the depth map (a second difference through the pixel
    // above `max_kink`): there the median mixes in neighbours that do not continue the
    // pixel's surface linearly, which pulls its cut-off. The first pass sees both; later
    // passes widen the rim.
    let kink = p.max_kink as f32;
    for pass in 0..p.trim {
        let rim: Vec<bool> = (0..t.len())
            .map(|i| {
                let Some(ti) = t[i] else { return false };
                let (x, y) = (i % w, i / w);
                if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    return true;
                }
                if neighbours(i, w, h).any(|j| t[j].is_none() || label[j] != label[i]) {
                    return true;
                }
                // Opposite neighbours: left-right, up-down, and the two diagonals.
                pass == 0
                    && [(i - 1, i + 1), (i - w, i + w), (i - w - 1, i + w + 1), (i - w + 1, i + w - 1)].iter().any(|&(a, b)| {
                        matches!((t[a], t[b]), (Some(ta), Some(tb)) if (ta - 2.0 * ti + tb).abs() > kink)
                    })
            })
            .collect();
        for (ti, r) in t.iter_mut().zip(rim) {
            if r {
                *ti = None;
            }
        }
    }
    t.into_iter().map(|x| x.map(f64::from)).collect()
}

#[cfg(test)]
mod tests {
    use super::super::Cand;
    use super::*;

    fn grid(w: usize, h: usize, f: impl Fn(usize, usize) -> Vec<(f32, f32)>) -> Vec<Cands> {
        (0..w * h)
            .map(|i| {
                let mut c = Cands::default();
                for (t, s) in f(i % w, i / w) {
                    c.push(Cand { t, strength: s }, true);
                }
                c
            })
            .collect()
    }

    #[test]
    fn softening_grows_from_strong_into_weak_and_segments_filter() {
        let p = SurfaceParams {
            strong: 0.3,
            weak: 0.1,
            max_step: 1.0,
            min_segment: 5,
            trim: 0,
            ..Default::default()
        };
        let (w, h) = (10, 6);
        // Left half: one strong pixel then weak ones on a smooth ramp; right half: weak only.
        let c = grid(w, h, |x, y| {
            let t = 10.0 + 0.3 * x as f32;
            if x < 5 {
                vec![(t, if (x, y) == (0, 0) { 0.5 } else { 0.15 })]
            } else if x > 5 {
                vec![(t + 20.0, 0.15)]
            } else {
                vec![]
            }
        });
        let out = resolve(&c, w, h, &p);
        for y in 0..h {
            for x in 0..w {
                let got = out[y * w + x];
                if x < 5 {
                    assert_eq!(got, Some(f64::from(10.0 + 0.3 * x as f32)), "({x},{y})");
                } else {
                    assert_eq!(got, None, "({x},{y})");
                }
            }
        }
        // An isolated strong pixel is a segment of one: dropped; with min_segment 1 it stays.
        let c = grid(w, h, |x, y| if (x, y) == (3, 3) { vec![(5.0, 0.9)] } else { vec![] });
        assert!(resolve(&c, w, h, &p).iter().all(|t| t.is_none()));
        let p1 = SurfaceParams { min_segment: 1, ..p };
        assert_eq!(resolve(&c, w, h, &p1)[33], Some(5.0));
    }

    #[test]
    fn first_or_strongest() {
        let p = SurfaceParams { strong: 0.3, weak: 0.1, min_segment: 1, trim: 0, ..Default::default() };
        let c = grid(1, 1, |_, _| vec![(4.0, 0.4), (9.0, 0.8)]);
        assert_eq!(resolve(&c, 1, 1, &SurfaceParams { first_surface: true, ..p })[0], Some(4.0));
        assert_eq!(resolve(&c, 1, 1, &SurfaceParams { first_surface: false, ..p })[0], Some(9.0));
    }
}
