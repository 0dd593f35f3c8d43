//! The laser projector's pose from laser hit points (section 4.4): "given a set of laser hit
//! points on the object's surface and the corresponding deflection settings of the laser
//! projector, we are able to recover the position of the laser projector relative to the
//! setup". A rig file's projector pose is measured by hand to a few millimetres and a degree,
//! which at 30 cm puts the computed entry point several millimetres from the spot: F's columns
//! would be filed under the wrong vertices. The spots themselves say where the beam went: each
//! seen spot's sub-pixel peak, cast onto the registered mesh, is a point its code's beam passes
//! through. The galvo's own calibration (zero codes, radians per code) is kept; the scanner's
//! pivot and orientation (six parameters) are fitted by damped Gauss–Newton to the points'
//! distances from their beams, with points far off the fit (a spot seen through the object, or
//! at the silhouette) dropped and the fit repeated.

use super::mesh::SurfaceMesh;
use super::optics::{cast, point_of, turned, Projector};
use super::register::Pose;
use crate::vec3::{add, dot, norm, scale, sub, V3};

/// A spot seen on the object: the galvo code it was shot at and where it entered, world mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HitPoint {
    pub code: [f64; 2],
    pub point: V3,
}

/// The fitted projector and how well its beams pass through the hit points.
#[derive(Debug, Clone, PartialEq)]
pub struct ProjectorFit {
    pub projector: Projector,
    /// The correction to the starting projector: its pivot moved by `translation` (mm), its
    /// axes turned by `rotation` about the pivot.
    pub correction: Pose,
    /// Hit points used, and dropped as outliers.
    pub used: usize,
    pub dropped: usize,
    /// Root mean square and largest distance of the used points from their beams, mm.
    pub rms_mm: f64,
    pub max_mm: f64,
}

/// The projector `start` corrected by `c`: pivot moved by `c.translation`, axes turned.
pub fn corrected(start: &Projector, c: &Pose) -> Projector {
    Projector { eye: add(start.eye, c.translation), axes: start.axes.map(|a| c.rotate(a)), ..*start }
}

/// How far `h.point` lies from the beam `p` shoots at `h.code`: the component across the beam.
pub fn miss(p: &Projector, h: &HitPoint) -> V3 {
    let d = p.ray(h.code);
    let q = sub(h.point, p.eye);
    sub(q, scale(d, dot(q, d)))
}

/// Fits the projector's pivot and orientation to `hits`, starting from `start` (the rig file's
/// measured pose; within some 10 mm and 3°). Robust to a minority of wrong points (a spot seen
/// through the object, or glow at the silhouette taken for it): the fit is first made to the
/// half of the points nearest their beams, four times over; then points within
/// `max(3 × the median distance, floor_mm)` are kept and the fit repeated until they settle.
/// `None` with fewer than 12 points, or fewer than 6 left.
pub fn fit_projector(start: &Projector, hits: &[HitPoint], floor_mm: f64) -> Option<ProjectorFit> {
    if hits.len() < 12 {
        return None;
    }
    let distances = |x: &[f64; 6]| -> Vec<f64> {
        let p = corrected(start, &pose_of(x));
        hits.iter().map(|h| norm(miss(&p, h))).collect()
    };
    let median = |d: &[f64]| {
        let mut v = d.to_vec();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut x = [0.0f64; 6];
    let mut keep: Vec<bool> = vec![true; hits.len()];
    for round in 0..10 {
        let d = distances(&x);
        let limit = if round < 4 { median(&d) } else { (3.0 * median(&d)).max(floor_mm) };
        let next: Vec<bool> = d.iter().map(|&d| d <= limit).collect();
        if round > 4 && next == keep {
            break;
        }
        keep = next;
        let used: Vec<&HitPoint> = hits.iter().zip(&keep).filter(|(_, k)| **k).map(|(h, _)| h).collect();
        // Two equations per point, six unknowns: a few points more than three.
        if used.len() < 6 {
            return None;
        }
        x = gauss_newton(start, &used, x)?;
    }
    let c = pose_of(&x);
    let projector = corrected(start, &c);
    let d: Vec<f64> =
        hits.iter().zip(&keep).filter(|(_, k)| **k).map(|(h, _)| norm(miss(&projector, h))).collect();
    Some(ProjectorFit {
        projector,
        correction: c,
        used: d.len(),
        dropped: hits.len() - d.len(),
        rms_mm: (d.iter().map(|d| d * d).sum::<f64>() / d.len() as f64).sqrt(),
        max_mm: d.iter().copied().fold(0.0, f64::max),
    })
}

fn pose_of(x: &[f64; 6]) -> Pose {
    Pose { translation: [x[0], x[1], x[2]], rotation: [x[3], x[4], x[5]] }
}

/// Levenberg–Marquardt on the stacked miss vectors, numerical Jacobian (the model is a handful
/// of trigonometric functions; 6 parameters).
fn gauss_newton(start: &Projector, hits: &[&HitPoint], mut x: [f64; 6]) -> Option<[f64; 6]> {
    let residuals = |x: &[f64; 6]| -> Vec<f64> {
        let p = corrected(start, &pose_of(x));
        hits.iter().flat_map(|h| miss(&p, h)).collect()
    };
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut r = residuals(&x);
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    // Steps: 1 µm in the pivot, 1 µrad in the rotation.
    let h = [1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6];
    for _ in 0..50 {
        let mut jac = vec![[0.0; 6]; r.len()];
        for k in 0..6 {
            let mut xp = x;
            xp[k] += h[k];
            let rp = residuals(&xp);
            for (row, (a, b)) in jac.iter_mut().zip(rp.iter().zip(&r)) {
                row[k] = (a - b) / h[k];
            }
        }
        let mut jtj = [[0.0; 6]; 6];
        let mut jtr = [0.0; 6];
        for (row, res) in jac.iter().zip(&r) {
            for i in 0..6 {
                jtr[i] += row[i] * res;
                for j in 0..6 {
                    jtj[i][j] += row[i] * row[j];
                }
            }
        }
        let mut improved = false;
        while lambda < 1e9 {
            let mut a = jtj;
            for (i, row) in a.iter_mut().enumerate() {
                row[i] += lambda * jtj[i][i].max(1e-12);
            }
            let step = crate::linalg::solve(a, jtr.map(|v| -v))?;
            let mut xn = x;
            for i in 0..6 {
                xn[i] += step[i];
            }
            let rn = residuals(&xn);
            let cn = cost(&rn);
            if cn < c {
                let small = step.iter().zip(&h).all(|(s, h)| s.abs() < 1e-3 * h);
                (x, r, c) = (xn, rn, cn);
                lambda = (lambda * 0.3).max(1e-9);
                improved = true;
                if small {
                    return Some(x);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Some(x)
}

/// How far the entry points of `a`'s beams lie from `b`'s beams, the farthest over the mesh:
/// `a`'s beam aimed at each vertex of `mesh` turned to each of `angles_deg`, cast on the mesh
/// (the first surface it meets), and that entry point's distance from `b`'s beam of the same
/// code, mm. With `a` a projector and `b` another estimate of it, how far F's columns would
/// move between the two.
pub fn entry_shift(a: &Projector, b: &Projector, mesh: &SurfaceMesh, angles_deg: &[f64]) -> f64 {
    use rayon::prelude::*;
    let mut worst = 0.0f64;
    for &deg in angles_deg {
        let world = turned(mesh, deg);
        // A cast per vertex against every triangle: in parallel.
        let shift = world
            .par_iter()
            .filter_map(|&v| {
                let code = a.code_of(v);
                let hit = cast(mesh, &world, a.eye, a.ray(code))?;
                let (point, _) = point_of(mesh, &world, deg, &hit);
                Some(norm(miss(b, &HitPoint { code, point })))
            })
            .reduce(|| 0.0, f64::max);
        worst = worst.max(shift);
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::pebble;

    fn truth() -> Projector {
        Projector::aimed([260.0, -150.0, 60.0], [0.0, 0.0, 30.0], [32768.0; 2], [10.65e-6, -10.65e-6])
    }

    /// Hit points of `p`'s beams on the pebble turned to 0°, 90°, 180°, 270°, a grid of codes.
    fn hits(p: &Projector, noise_mm: f64) -> Vec<HitPoint> {
        let mesh = mesh();
        let mut out = Vec::new();
        let mut k = 0u32;
        for deg in ANGLES {
            let world = turned(&mesh, deg);
            for i in -7..=7 {
                for j in -7..=7 {
                    let code = [32768.0 + f64::from(i) * 1000.0, 32768.0 + f64::from(j) * 1000.0];
                    let Some(hit) = cast(&mesh, &world, p.eye, p.ray(code)) else { continue };
                    let (pt, _) = point_of(&mesh, &world, deg, &hit);
                    // Deterministic noise, uniform in ±noise.
                    k = k.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                    let u = |s: u32| f64::from((k >> s) & 1023) / 1023.0 * 2.0 - 1.0;
                    let n = [u(0) * noise_mm, u(10) * noise_mm, u(20) * noise_mm];
                    out.push(HitPoint { code, point: add(pt, n) });
                }
            }
        }
        out
    }

    fn mesh() -> SurfaceMesh {
        SurfaceMesh::new(&pebble(3, [24.0, 20.0, 30.0]))
    }

    const ANGLES: [f64; 4] = [0.0, 90.0, 180.0, 270.0];

    #[test]
    fn a_projector_placed_by_hand_is_found_from_its_spots() {
        let t = truth();
        let mut hits = hits(&t, 0.05);
        assert!(hits.len() > 200, "{}", hits.len());
        // A third of the spots seen wrong (through the object, or glow at the silhouette taken
        // for the spot): 2-16 mm off their beams.
        let mut wrong = 0;
        for (i, h) in hits.iter_mut().enumerate().filter(|(i, _)| i % 3 == 1) {
            let off = 2.0 + (i % 15) as f64;
            h.point = add(h.point, [0.0, off, -0.5 * off]);
            wrong += usize::from(norm(miss(&t, h)) > 1.0);
        }
        assert!(wrong > 60, "{wrong}");
        // Measured by hand: 5.8 mm and 1.5° off (entry points 3.7 mm off: the two partly cancel).
        let measured = corrected(&t, &Pose { translation: [4.0, -3.0, 3.0], rotation: [0.012, -0.02, 0.01] });
        let before = entry_shift(&t, &measured, &mesh(), &ANGLES);
        assert!(before > 3.0, "the hand-measured projector is only {before} mm off");
        let fit = fit_projector(&measured, &hits, 0.5).unwrap();
        let after = entry_shift(&t, &fit.projector, &mesh(), &ANGLES);
        assert!(after < 0.05, "{after} mm off after the fit: {fit:?}");
        assert!(fit.dropped >= wrong && fit.dropped < wrong + 5, "{wrong} wrong: {fit:?}");
        assert!(fit.rms_mm < 0.05 && fit.max_mm < 0.1, "{fit:?}");
    }

    #[test]
    fn too_few_points_fix_nothing_and_an_exact_start_stays() {
        let t = truth();
        let hits = hits(&t, 0.0);
        assert!(fit_projector(&t, &hits[..11], 0.5).is_none());
        // An exact start stays put.
        let fit = fit_projector(&t, &hits, 0.5).unwrap();
        assert!(entry_shift(&t, &fit.projector, &mesh(), &ANGLES) < 1e-5);
        assert_eq!(fit.dropped, 0);
    }

    #[test]
    fn entry_shift_is_the_distance_across_the_beams() {
        let t = truth();
        // The same projector: nothing but the hits' f32 barycentric weights (a few nm).
        assert!(entry_shift(&t, &t, &mesh(), &ANGLES) < 1e-5);
        // The pivot raised 2 mm: every beam moves 2 mm less the part along itself; the farthest,
        // a level beam (the pivot is as high as the pebble's top), the whole 2 mm.
        let raised = corrected(&t, &Pose { translation: [0.0, 0.0, 2.0], rotation: [0.0; 3] });
        let s = entry_shift(&t, &raised, &mesh(), &ANGLES);
        assert!((s - 2.0).abs() < 1e-4, "{s}");
        // Turned 0.5° about the pivot: about 300 mm × 0.0087 at the object.
        let turned =
            corrected(&t, &Pose { translation: [0.0; 3], rotation: [0.0, 0.0, 0.5f64.to_radians()] });
        let s = entry_shift(&t, &turned, &mesh(), &ANGLES);
        assert!(s > 2.2 && s < 3.0, "{s}");
    }
}
