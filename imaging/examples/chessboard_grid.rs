//! The detector against rendered boards of known corners, over a grid of hard cases (blur
//! 1.5-3 px, 14-30 squares away, tilted 0-60° about either axis, even and uneven light): how
//! many it finds and how close. With a directory argument it also writes each board (PGM) and
//! its true corners for `imaging/benches/opencv_chessboards.py`, which runs OpenCV on the same
//! images. Figures in docs/calibration-format.md.
//!
//! With `photo` after the directory, the boards are instead
//! [`lightrig_imaging::synth::photograph_like_boards`] (clutter, in-plane turns, a wide lens,
//! JPEG).
//!
//!     cargo run --release -p lightrig-imaging --example chessboard_grid -- /tmp/boards
//!     python3 imaging/benches/opencv_chessboards.py /tmp/boards 5
//!     cargo run --release -p lightrig-imaging --example chessboard_grid -- /tmp/photo photo
//!     python3 imaging/benches/opencv_chessboards.py /tmp/photo 5

use std::io::Write;

use lightrig_imaging::calib::{find_chessboard, project, Board, Intrinsics};
use lightrig_imaging::synth::{render_chessboard, ChessboardScene};

const W: usize = 640;
const H: usize = 480;

fn main() -> std::io::Result<()> {
    let dir = std::env::args().nth(1).map(std::path::PathBuf::from);
    if let Some(d) = &dir {
        std::fs::create_dir_all(d)?;
    }
    if std::env::args().nth(2).as_deref() == Some("photo") {
        return photo(dir.as_deref());
    }
    let k = Intrinsics { k1: -0.15, k2: 0.05, ..Intrinsics::pinhole(620.0, 620.0, 320.0, 240.0) };
    let base = ChessboardScene { noise: 2.0, ..ChessboardScene::new(9, 6, 1.0) };
    let board = Board::chessboard(9, 6, 1.0);
    let mut csv = String::from("name,found,max_px,rms_px\n");
    let (mut n, mut found_n, mut close_n) = (0, 0, 0);
    for blur in [1.5, 2.0, 2.5, 3.0] {
        for dist in [14.0, 22.0, 30.0] {
            for tilt_deg in [0.0f64, 45.0, 60.0] {
                for axis in 0..2 {
                    let pose = base.tilted_pose(tilt_deg, axis, dist);
                    for shading in [0.0, 0.6] {
                        let name = format!("b{blur}_d{dist}_t{tilt_deg}_a{axis}_s{shading}");
                        let scene = ChessboardScene { blur, shading, ..base.clone() };
                        let truth: Vec<(f64, f64)> = board
                            .points
                            .iter()
                            .filter_map(|b| project(&k, &pose, [b[0], b[1], 0.0]))
                            .collect();
                        let img = render_chessboard(&scene, &k, &pose, W, H);
                        if let Some(d) = &dir {
                            let mut f = std::fs::File::create(d.join(format!("{name}.pgm")))?;
                            write!(f, "P5\n{W} {H}\n255\n")?;
                            f.write_all(&img)?;
                            let t: Vec<String> = truth.iter().map(|p| format!("{} {}", p.0, p.1)).collect();
                            std::fs::write(d.join(format!("{name}.truth")), t.join("\n"))?;
                        }
                        n += 1;
                        let line = match find_chessboard(&img, W, H, (9, 6)) {
                            Ok(found) => {
                                let d: Vec<f64> = found
                                    .iter()
                                    .zip(&truth)
                                    .map(|(p, q)| (p.0 - q.0).hypot(p.1 - q.1))
                                    .collect();
                                let max = d.iter().cloned().fold(0.0, f64::max);
                                let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
                                found_n += 1;
                                close_n += usize::from(max < 0.3);
                                format!("{name},1,{max:.3},{rms:.3}\n")
                            }
                            Err(_) => format!("{name},0,,\n"),
                        };
                        csv.push_str(&line);
                    }
                }
            }
        }
    }
    if let Some(d) = &dir {
        std::fs::write(d.join("lightrig.csv"), &csv)?;
    }
    println!("lightrig: found {found_n} of {n} boards, {close_n} with every corner within 0.3 px");
    Ok(())
}

/// The photograph-like set, scored and written as the grid's.
fn photo(dir: Option<&std::path::Path>) -> std::io::Result<()> {
    let mut csv = String::from("name,found,max_px,rms_px\n");
    let (mut found_n, mut close_n) = (0, 0);
    let boards = lightrig_imaging::synth::photograph_like_boards();
    for b in &boards {
        if let Some(d) = dir {
            let mut f = std::fs::File::create(d.join(format!("{}.pgm", b.name)))?;
            write!(f, "P5\n{W} {H}\n255\n")?;
            f.write_all(&b.image)?;
            let t: Vec<String> = b.truth.iter().map(|p| format!("{} {}", p.0, p.1)).collect();
            std::fs::write(d.join(format!("{}.truth", b.name)), t.join("\n"))?;
        }
        let line = match find_chessboard(&b.image, W, H, (9, 6)) {
            Ok(found) => {
                let d: Vec<f64> =
                    found.iter().zip(&b.truth).map(|(p, q)| (p.0 - q.0).hypot(p.1 - q.1)).collect();
                let max = d.iter().cloned().fold(0.0, f64::max);
                let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
                found_n += 1;
                close_n += usize::from(max < 0.3);
                format!("{},1,{max:.3},{rms:.3}\n", b.name)
            }
            Err(_) => format!("{},0,,\n", b.name),
        };
        csv.push_str(&line);
    }
    if let Some(d) = dir {
        std::fs::write(d.join("lightrig.csv"), &csv)?;
    }
    println!(
        "lightrig: found {found_n} of {} photograph-like boards, {close_n} with every corner within 0.3 px",
        boards.len()
    );
    Ok(())
}
