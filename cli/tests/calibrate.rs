//! `lightrig calibrate` end to end: rendered chessboard images of a camera with known intrinsics
//! (imaging's analytic renderer, PNG files), the CLI run as a process, the calibration file read
//! back and compared with the truth; the reference-plane pose; and the errors a user meets.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use lightrig_imaging::calib::{Intrinsics, Pose};
use lightrig_imaging::calib_file::{self, CalibrationFile};
use lightrig_imaging::io::{self, BitDepth, Encoding, Image};
use lightrig_imaging::synth::{render_chessboard, ChessboardScene};

const W: u32 = 640;
const H: u32 = 480;

fn truth() -> Intrinsics {
    Intrinsics {
        fx: 700.0,
        fy: 695.0,
        cx: 322.0,
        cy: 236.0,
        k1: -0.12,
        k2: 0.05,
        p1: 0.0008,
        p2: -0.0005,
        k3: 0.0,
    }
}

/// A pose that puts the centre `c` of the board (board units) at camera point `at`.
fn centred(rvec: [f64; 3], c: [f64; 2], at: [f64; 3]) -> Pose {
    let r = Pose { rvec, tvec: [0.0; 3] }.rotation();
    let rc = [0, 1, 2].map(|i| r[i][0] * c[0] + r[i][1] * c[1]);
    Pose { rvec, tvec: [at[0] - rc[0], at[1] - rc[1], at[2] - rc[2]] }
}

/// The calibration board: 9×6 inner corners, 20 mm squares, centre at (80, 50) mm.
fn views() -> Vec<Pose> {
    let c = [80.0, 50.0];
    [
        ([0.05, -0.05, 0.02], [0.0, 0.0, 380.0]),
        ([0.45, 0.1, 0.05], [-20.0, 10.0, 400.0]),
        ([-0.4, 0.15, -0.1], [15.0, -10.0, 390.0]),
        ([0.1, 0.45, 0.2], [10.0, 5.0, 410.0]),
        ([0.15, -0.45, -0.25], [-10.0, 0.0, 400.0]),
        ([0.3, 0.3, 1.4], [0.0, 10.0, 420.0]),
        ([-0.3, -0.3, -0.5], [20.0, -15.0, 370.0]),
        ([0.2, -0.1, 3.0], [-5.0, 5.0, 390.0]),
    ]
    .iter()
    .map(|&(r, at)| centred(r, c, at))
    .collect()
}

/// The reference plane's board: 7×5 inner corners, 30 mm squares, centre (90, 60) mm.
fn reference_pose() -> Pose {
    centred([0.55, 0.1, 0.05], [90.0, 60.0], [0.0, 10.0, 450.0])
}

fn write_render(path: &Path, scene: &ChessboardScene, pose: &Pose) {
    let px = render_chessboard(scene, &truth(), pose, W as usize, H as usize);
    let img = Image::from_fn(W, H, 1, |x, y, _| f32::from(px[(y * W + x) as usize]) / 255.0)
        .with_encoding(Encoding::Srgb);
    io::write_png(path, &img, BitDepth::Eight).unwrap();
}

/// Rendered once per run for all tests (read-only): `board/view0.png` … `view7.png` and
/// `plane.png`, in cargo's temporary directory for integration tests (no teardown needed).
fn fixture() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir =
            Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("calibrate-fixture-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("board")).unwrap();
        let scene = ChessboardScene { noise: 1.5, ..ChessboardScene::new(9, 6, 20.0) };
        for (i, pose) in views().iter().enumerate() {
            write_render(
                &dir.join(format!("board/view{i}.png")),
                &ChessboardScene { seed: i as u64, ..scene.clone() },
                pose,
            );
        }
        let plane = ChessboardScene { noise: 1.5, ..ChessboardScene::new(7, 5, 30.0) };
        write_render(&dir.join("plane.png"), &plane, &reference_pose());
        dir
    })
}

/// A fresh scratch directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightrig-calibrate-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn lightrig(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig")).args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn assert_pose(got: &Pose, want: &Pose, what: &str) {
    for i in 0..3 {
        assert!((got.rvec[i] - want.rvec[i]).abs() < 0.003, "{what}: rvec {:?} vs {:?}", got.rvec, want.rvec);
        assert!((got.tvec[i] - want.tvec[i]).abs() < 1.5, "{what}: tvec {:?} vs {:?}", got.tvec, want.tvec);
    }
}

#[test]
fn calibrates_rendered_boards_and_registers_the_reference_plane() {
    let fx = fixture();
    let out = scratch("ok");
    let cal = out.join("camera.toml");
    let boards = fx.join("board");
    let args = ["calibrate", s(&boards), "--cols", "9", "--rows", "6", "--square", "20", "--out", s(&cal)];
    let o = lightrig(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("view3.png") && stdout.contains("overall rms"), "{stdout}");

    let c: CalibrationFile = calib_file::read(&cal).unwrap();
    let (k, t) = (c.intrinsics, truth());
    eprintln!("recovered {k:?}, rms {}", c.rms);
    // Corner noise is ~0.01 px here (RMS 0.009); 8 views pin the focal lengths to well under 0.3 %.
    assert!((k.fx / t.fx - 1.0).abs() < 0.003 && (k.fy / t.fy - 1.0).abs() < 0.003, "{k:?}");
    assert!((k.cx - t.cx).abs() < 1.5 && (k.cy - t.cy).abs() < 1.5, "{k:?}");
    assert!((k.k1 - t.k1).abs() < 0.01 && (k.k2 - t.k2).abs() < 0.03, "{k:?}");
    assert!((k.p1 - t.p1).abs() < 0.001 && (k.p2 - t.p2).abs() < 0.001, "{k:?}");
    assert!(c.rms < 0.03, "rms {}", c.rms);
    assert_eq!(c.image_size, (W, H));
    assert_eq!((c.board.cols, c.board.rows, c.board.square, c.board.unit.as_str()), (9, 6, 20.0, "mm"));
    assert!(c.tool.starts_with("lightrig "), "{}", c.tool);
    assert!(c.skipped.is_empty() && c.reference.is_none());
    assert_eq!(c.views.len(), 8);
    for (i, (v, want)) in c.views.iter().zip(views()).enumerate() {
        assert!(v.file.ends_with(&format!("view{i}.png")), "{}", v.file);
        assert!(v.rms < 0.03, "{}: rms {}", v.file, v.rms);
        assert_pose(&v.pose, &want, &v.file);
    }

    // Same images, same bytes: no dates, fixed order, exact floats.
    let again = out.join("again.toml");
    let mut args2 = args;
    args2[9] = s(&again);
    assert!(lightrig(&args2).status.success());
    assert_eq!(std::fs::read(&cal).unwrap(), std::fs::read(&again).unwrap());

    // The reference plane: another board (7×5, 30 mm) in one image.
    let reg = out.join("registered.toml");
    let o = lightrig(&[
        "calibrate",
        "--pose-only",
        s(&fx.join("plane.png")),
        "--calibration",
        s(&cal),
        "--cols",
        "7",
        "--rows",
        "5",
        "--square",
        "30",
        "--out",
        s(&reg),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r = calib_file::read(&reg).unwrap();
    let reference = r.reference.as_ref().unwrap();
    assert_eq!((reference.board.cols, reference.board.rows, reference.board.square), (7, 5, 30.0));
    assert!(reference.rms < 0.03, "rms {}", reference.rms);
    assert_pose(&reference.pose, &reference_pose(), "reference");
    // Everything else is the calibration, unchanged.
    assert_eq!(CalibrationFile { reference: None, ..r.clone() }, c);
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn errors_name_the_file_and_what_to_do() {
    let fx = fixture();
    let dir = scratch("errors");
    let good: Vec<PathBuf> = (0..3).map(|i| fx.join(format!("board/view{i}.png"))).collect();
    let out = dir.join("c.toml");
    let run = |images: &[&Path], extra: &[&str]| {
        let mut a: Vec<&str> = vec!["calibrate"];
        a.extend(images.iter().map(|p| s(p)));
        a.extend(["--cols", "9", "--rows", "6", "--square", "20", "--out", s(&out)]);
        a.extend(extra);
        lightrig(&a)
    };

    // An unreadable image.
    let broken = dir.join("broken.png");
    std::fs::write(&broken, b"not a png at all").unwrap();
    let o = run(&[&good[0], &broken, &good[1]], &[]);
    assert_eq!(o.status.code(), Some(4));
    let e = stderr(&o);
    assert!(e.contains(s(&broken)), "{e}");

    // A missing image.
    let o = run(&[&good[0], &dir.join("nope.png")], &[]);
    assert_eq!(o.status.code(), Some(4));
    assert!(stderr(&o).contains("nope.png"), "{}", stderr(&o));

    // An image without the board: named, with the fix; --skip-missing records it instead.
    let blank = dir.join("blank.png");
    io::write_png(
        &blank,
        &Image::from_fn(W, H, 1, |_, _, _| 0.5).with_encoding(Encoding::Srgb),
        BitDepth::Eight,
    )
    .unwrap();
    let o = run(&[&good[0], &blank, &good[1], &good[2]], &[]);
    assert_eq!(o.status.code(), Some(4));
    let e = stderr(&o);
    assert!(
        e.contains(&format!(
            "{}: no chessboard of 9×6 inner corners found: no corner of four squares",
            s(&blank)
        )),
        "{e}"
    );
    assert!(e.contains("--skip-missing"), "{e}");
    assert!(!out.exists());
    let o = run(&[&good[0], &blank, &good[1], &good[2]], &["--skip-missing"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The report says why, per image.
    let report = String::from_utf8_lossy(&o.stdout);
    assert!(
        report
            .lines()
            .any(|l| l.contains(s(&blank)) && l.contains("skipped: no corner of four squares anywhere")),
        "{report}"
    );
    let c = calib_file::read(&out).unwrap();
    assert_eq!(c.skipped, vec![s(&blank).to_string()]);
    assert_eq!(c.views.len(), 3);

    // The wrong pattern: every image fails, the first is named.
    let o = lightrig(&[
        "calibrate",
        s(&good[0]),
        "--cols",
        "8",
        "--rows",
        "6",
        "--square",
        "20",
        "--out",
        s(&out),
    ]);
    assert!(
        stderr(&o).contains(&format!(
            "{}: no chessboard of 8×6 inner corners found: a grid larger than the pattern",
            s(&good[0])
        )),
        "{}",
        stderr(&o)
    );

    // Too few views.
    let o = run(&[&good[0], &good[1]], &[]);
    assert_eq!(o.status.code(), Some(4));
    assert!(stderr(&o).contains("found in 2 image(s); calibration needs at least 3"), "{}", stderr(&o));

    // Images of another size.
    let small = dir.join("small.png");
    io::write_png(
        &small,
        &Image::from_fn(320, 240, 1, |_, _, _| 0.5).with_encoding(Encoding::Srgb),
        BitDepth::Eight,
    )
    .unwrap();
    let o = run(&[&good[0], &small], &[]);
    assert!(stderr(&o).contains(&format!("{}: image is 320×240, but", s(&small))), "{}", stderr(&o));

    // --pose-only with a calibration file that is missing, then one with a bad value.
    let plane = fx.join("plane.png");
    let pose = |cal: &Path| {
        lightrig(&[
            "calibrate",
            "--pose-only",
            s(&plane),
            "--calibration",
            s(cal),
            "--cols",
            "7",
            "--rows",
            "5",
            "--square",
            "30",
            "--out",
            s(&dir.join("r.toml")),
        ])
    };
    let o = pose(&dir.join("absent.toml"));
    assert_eq!(o.status.code(), Some(4));
    assert!(stderr(&o).contains(&format!("{}: cannot read", s(&dir.join("absent.toml")))), "{}", stderr(&o));
    let text = std::fs::read_to_string(&out).unwrap();
    let line = text.lines().position(|l| l.starts_with("fy = ")).unwrap() + 1;
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, text.replacen("fy = ", "fy = -", 1)).unwrap();
    let o = pose(&bad);
    assert!(
        stderr(&o).contains(&format!("{}:{line}: intrinsics.fy: -", s(&bad)))
            && stderr(&o).contains("not a positive focal length"),
        "{}",
        stderr(&o)
    );
    // Geometry is required when calibrating.
    let o = lightrig(&["calibrate", s(&good[0]), "--out", s(&out)]);
    assert!(stderr(&o).contains("--cols and --rows"), "{}", stderr(&o));
    std::fs::remove_dir_all(&dir).unwrap();
}
