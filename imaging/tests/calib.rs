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

/// Renders a chessboard of `(cols+1) × (rows+1)` squares (`square` units, with a one-square white
/// margin) seen through `k`/`pose`, by 4×4 supersampling, a small blur and Gaussian noise σ = 2.
fn render(k: &Intrinsics, pose: &Pose, cols: usize, rows: usize, square: f64, w: usize, h: usize) -> Vec<u8> {
    let mut rng = Rng(11);
    let mut img = vec![0.0f64; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let u = x as f64 - 0.5 + (sx as f64 + 0.5) / 4.0;
                    let v = y as f64 - 0.5 + (sy as f64 + 0.5) / 4.0;
                    let (o, d) = pixel_ray(k, pose, (u, v)).unwrap();
                    let s = -o[2] / d[2];
                    let (bx, by) = ((o[0] + s * d[0]) / square, (o[1] + s * d[1]) / square);
                    // Inner corner (0,0) is at board (0,0); squares span [-1, cols] × [-1, rows].
                    acc += if s <= 0.0
                        || bx < -2.0
                        || by < -2.0
                        || bx > cols as f64 + 1.0
                        || by > rows as f64 + 1.0
                    {
                        90.0
                    } else if bx < -1.0 || by < -1.0 || bx > cols as f64 || by > rows as f64 {
                        220.0
                    } else if (bx.floor() as i64 + by.floor() as i64).rem_euclid(2) == 0 {
                        30.0
                    } else {
                        220.0
                    };
                }
            }
            img[y * w + x] = acc / 16.0;
        }
    }
    // Blur with a [1 2 1]/4 kernel each way (σ ≈ 0.7 px).
    let mut out = img.clone();
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let mut s = 0.0;
            for (dy, wy) in [(-1i64, 1.0), (0, 2.0), (1, 1.0)] {
                for (dx, wx) in [(-1i64, 1.0), (0, 2.0), (1, 1.0)] {
                    s += wx * wy * img[(y as i64 + dy) as usize * w + (x as i64 + dx) as usize];
                }
            }
            out[y * w + x] = s / 16.0;
        }
    }
    out.iter().map(|&v| (v + 2.0 * rng.gauss()).round().clamp(0.0, 255.0) as u8).collect()
}

#[test]
#[ignore = "detector not finished: corners off by up to 0.21 px on rendered boards (target 0.1)"]
fn finds_rendered_chessboards_to_a_tenth_of_a_pixel() {
    let k = Intrinsics { k1: -0.15, k2: 0.05, ..Intrinsics::pinhole(620.0, 620.0, 320.0, 240.0) };
    let board = Board::chessboard(9, 6, 1.0);
    let poses = [
        Pose { rvec: [0.05, -0.1, 0.02], tvec: [-4.0, -2.5, 14.0] },
        Pose { rvec: [0.4, 0.3, 0.3], tvec: [-4.5, -3.0, 15.0] },
        Pose { rvec: [-0.3, 0.45, -0.5], tvec: [-3.0, -1.0, 16.0] },
        Pose { rvec: [0.1, 0.1, 1.6], tvec: [1.5, -4.0, 15.0] },
    ];
    let (w, h) = (640, 480);
    for pose in &poses {
        let img = render(&k, pose, 9, 6, 1.0, w, h);
        let found = find_chessboard(&img, w, h, (9, 6)).unwrap();
        let truth: Vec<(f64, f64)> =
            board.points.iter().map(|b| project(&k, pose, [b[0], b[1], 0.0]).unwrap()).collect();
        // The detector orders from the top-left; match the truth's order up to the 180° turn.
        let d = |a: &[(f64, f64)], b: &[(f64, f64)]| {
            a.iter()
                .zip(b)
                .map(|(p, q)| ((p.0 - q.0).powi(2) + (p.1 - q.1).powi(2)).sqrt())
                .fold(0.0, f64::max)
        };
        let rev: Vec<(f64, f64)> = truth.iter().rev().cloned().collect();
        let err = d(&found, &truth).min(d(&found, &rev));
        eprintln!("pose {pose:?}: max corner error {err:.4} px");
        if err > 0.1 {
            for (p, q) in found.iter().zip(&truth) {
                eprintln!("{p:?} {q:?}");
            }
        }
        assert!(err < 0.1, "max corner error {err} px");
        let f = found[0];
        let l = found[53];
        assert!(f.0 + f.1 < l.0 + l.1, "first corner nearest the top-left");
    }
    let blank = vec![128u8; w * h];
    assert_eq!(find_chessboard(&blank, w, h, (9, 6)), Err(CalibError::BoardNotFound));
    let img = render(&k, &poses[0], 9, 6, 1.0, w, h);
    assert_eq!(find_chessboard(&img, w, h, (8, 6)), Err(CalibError::BoardNotFound));
    assert!(matches!(find_chessboard(&img[..100], w, h, (9, 6)), Err(CalibError::InvalidInput(_))));
}

const OPENCV_DATA: &str = "/usr/share/doc/opencv-doc/examples/data";

/// OpenCV's sample stereo chessboards (`left01.jpg` … `left14.jpg`, no `left10`; 9×6 inner corners).
///
/// Reference (OpenCV 5.0.0 via `pip install opencv-python-headless`): findChessboardCorners,
/// cornerSubPix (11×11, 30 iterations / 0.001), calibrateCamera with the default 5-coefficient model,
/// square size 1, on the same 13 images:
/// rms 0.40869, fx 536.0735, fy 536.0164, cx 342.3705, cy 235.5369,
/// dist (−0.26509, −0.04674, 0.00183, −0.00031, 0.25231).
#[test]
#[ignore = "detector not finished: grids on left01.jpg stop at 51 of 54 corners"]
fn calibrates_opencv_sample_chessboards() {
    let mut files: Vec<_> = std::fs::read_dir(OPENCV_DATA)
        .unwrap_or_else(|e| {
            panic!(
                "{OPENCV_DATA}: {e}; install the Debian package opencv-doc (apt-get install -y opencv-doc)"
            )
        })
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let n = p.file_name().unwrap().to_string_lossy().into_owned();
            n.len() == "left01.jpg".len() && n.starts_with("left") && n.ends_with(".jpg")
        })
        .collect();
    files.sort();
    assert_eq!(files.len(), 13, "expected left01..left14.jpg (no left10) in {OPENCV_DATA}: {files:?}");
    let mut views = Vec::new();
    for f in &files {
        let img = image::open(f).unwrap_or_else(|e| panic!("{}: {e}", f.display())).to_luma8();
        let (w, h) = img.dimensions();
        let corners = find_chessboard(img.as_raw(), w as usize, h as usize, (9, 6))
            .unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        views.push(corners);
    }
    let c = calibrate(&Board::chessboard(9, 6, 1.0), &views).unwrap();
    eprintln!("OpenCV samples: {:?}, rms {:.5}", c.intrinsics, c.rms);
    assert!(c.rms <= 0.41, "rms {} worse than OpenCV's 0.409", c.rms);
    assert!((c.intrinsics.fx / 536.0735 - 1.0).abs() < 0.005, "fx {}", c.intrinsics.fx);
    assert!((c.intrinsics.fy / 536.0164 - 1.0).abs() < 0.005, "fy {}", c.intrinsics.fy);
}
