//! Camera calibration: synthetic boards with known truth, rendered chessboards, and OpenCV's sample
//! photographs.

use lightrig_imaging::calib::*;

/// Deterministic noise: a small LCG and Box–Muller.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
    }
}

fn truth() -> Intrinsics {
    Intrinsics {
        fx: 800.0,
        fy: 790.0,
        cx: 322.0,
        cy: 238.0,
        k1: -0.21,
        k2: 0.08,
        p1: 0.001,
        p2: -0.0007,
        k3: 0.0,
    }
}

/// Board 9×6, square 25 mm, seen from varied poses at ~400–600 mm.
fn poses() -> Vec<Pose> {
    let raw = [
        ([0.1, -0.2, 0.05], [-100.0, -60.0, 450.0]),
        ([-0.3, 0.1, 0.1], [-90.0, -70.0, 500.0]),
        ([0.25, 0.35, -0.1], [-120.0, -50.0, 520.0]),
        ([-0.2, -0.4, 0.3], [-80.0, -80.0, 480.0]),
        ([0.4, 0.0, -0.2], [-110.0, -40.0, 550.0]),
        ([0.0, 0.45, 0.15], [-100.0, -65.0, 600.0]),
        ([0.15, 0.2, 1.2], [-20.0, -120.0, 470.0]),
        ([-0.35, -0.1, -0.3], [-95.0, -55.0, 430.0]),
    ];
    raw.iter().map(|&(rvec, tvec)| Pose { rvec, tvec }).collect()
}

fn synthetic_views(
    k: &Intrinsics,
    board: &Board,
    poses: &[Pose],
    sigma: f64,
    seed: u64,
) -> Vec<Vec<(f64, f64)>> {
    let mut rng = Rng(seed);
    poses
        .iter()
        .map(|p| {
            board
                .points
                .iter()
                .map(|b| {
                    let (u, v) = project(k, p, [b[0], b[1], 0.0]).unwrap();
                    (u + sigma * rng.gauss(), v + sigma * rng.gauss())
                })
                .collect()
        })
        .collect()
}

#[test]
fn calibrates_synthetic_boards_with_noise() {
    let k = truth();
    let board = Board::chessboard(9, 6, 25.0);
    let views = synthetic_views(&k, &board, &poses(), 0.1, 7);
    let c = calibrate(&board, &views).unwrap();
    let e = c.intrinsics;
    eprintln!("recovered {e:?}, rms {}", c.rms);
    assert!((e.fx / k.fx - 1.0).abs() < 0.002, "fx {}", e.fx);
    assert!((e.fy / k.fy - 1.0).abs() < 0.002, "fy {}", e.fy);
    assert!((e.cx - k.cx).abs() < 2.0 && (e.cy - k.cy).abs() < 2.0, "{e:?}");
    assert!((e.k1 - k.k1).abs() < 0.02, "k1 {}", e.k1);
    // RMS per point of 2-D noise with σ = 0.1 per axis is ≈ 0.1·√2, less the fitted parameters.
    assert!(c.rms > 0.1 && c.rms < 0.16, "rms {}", c.rms);
    for (p, q) in c.views.iter().zip(poses()) {
        for i in 0..3 {
            assert!((p.tvec[i] - q.tvec[i]).abs() < 2.0, "{p:?} vs {q:?}");
            assert!((p.rvec[i] - q.rvec[i]).abs() < 0.01, "{p:?} vs {q:?}");
        }
    }
}

#[test]
fn exact_data_gives_exact_parameters() {
    let k = truth();
    let board = Board::chessboard(9, 6, 25.0);
    let views = synthetic_views(&k, &board, &poses(), 0.0, 1);
    let c = calibrate(&board, &views).unwrap();
    assert!(c.rms < 1e-6, "rms {}", c.rms);
    assert!(
        (c.intrinsics.fx - k.fx).abs() < 1e-4 && (c.intrinsics.k2 - k.k2).abs() < 1e-5,
        "{:?}",
        c.intrinsics
    );
}

#[test]
fn calibration_errors_are_typed() {
    let board = Board::chessboard(9, 6, 25.0);
    let views = synthetic_views(&truth(), &board, &poses()[..2], 0.0, 1);
    assert_eq!(calibrate(&board, &views), Err(CalibError::TooFewViews { got: 2, need: 3 }));
    // Three copies of one view: no information on the intrinsics.
    let same = vec![views[0].clone(), views[0].clone(), views[0].clone()];
    assert!(
        matches!(calibrate(&board, &same), Err(CalibError::Degenerate(_))),
        "{:?}",
        calibrate(&board, &same)
    );
    // Collinear board points.
    let line = Board { points: (0..10).map(|i| [i as f64, 0.0]).collect() };
    let lv: Vec<Vec<(f64, f64)>> =
        (0..3).map(|j| (0..10).map(|i| (i as f64 * 10.0, j as f64)).collect()).collect();
    assert!(matches!(calibrate(&line, &lv), Err(CalibError::Degenerate(_))));
    let short = vec![views[0][..10].to_vec(); 3];
    assert!(matches!(calibrate(&board, &short), Err(CalibError::InvalidInput(_))));
    let mut nan = views[0].clone();
    nan[3].0 = f64::NAN;
    assert!(matches!(pose_from_board(&truth(), &nan, &board), Err(CalibError::InvalidInput(_))));
}

#[test]
fn undistort_inverts_distortion() {
    let k = truth();
    for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.4, 0.3), (0.1, 0.35)] {
        let (xd, yd) = k.distort(x, y);
        let (u, v) = (k.fx * xd + k.cx, k.fy * yd + k.cy);
        let (bx, by) = undistort_point(&k, (u, v)).unwrap();
        assert!((bx - x).abs() < 1e-10 && (by - y).abs() < 1e-10);
    }
}

#[test]
fn pose_from_one_board_and_rays() {
    let k = truth();
    let board = Board::chessboard(9, 6, 25.0);
    let truth_pose = Pose { rvec: [2.6, 0.3, -0.2], tvec: [-90.0, 50.0, 700.0] };
    let view = synthetic_views(&k, &board, &[truth_pose], 0.1, 3).pop().unwrap();
    let (pose, rms) = pose_from_board(&k, &view, &board).unwrap();
    assert!(rms < 0.2, "rms {rms}");
    for i in 0..3 {
        assert!((pose.tvec[i] - truth_pose.tvec[i]).abs() < 1.0, "{pose:?}");
        assert!((pose.rvec[i] - truth_pose.rvec[i]).abs() < 0.005, "{pose:?}");
    }
    // The ray through a board corner's exact projection passes through the corner (Z = 0).
    for b in [board.points[0], board.points[31], board.points[53]] {
        let uv = project(&k, &truth_pose, [b[0], b[1], 0.0]).unwrap();
        let (o, d) = pixel_ray(&k, &truth_pose, uv).unwrap();
        assert!((d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - 1.0).abs() < 1e-12);
        let s = -o[2] / d[2];
        let hit = [o[0] + s * d[0], o[1] + s * d[1]];
        assert!((hit[0] - b[0]).abs() < 1e-6 && (hit[1] - b[1]).abs() < 1e-6, "{hit:?} vs {b:?}");
        assert!(s > 0.0);
    }
    let c = truth_pose.camera_centre();
    // rvec ≈ 2.6 rad about X: the board is seen from its +Z side.
    assert!(c[2] > 0.0, "{c:?}");
}
