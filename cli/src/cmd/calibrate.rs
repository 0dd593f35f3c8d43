//! `lightrig calibrate`: camera intrinsics from chessboard images, written as a calibration file
//! (`docs/calibration-format.md`); with `--pose-only`, the pose of a board on the rig's reference
//! plane from one image and an existing calibration (the linear light source registration).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use lightrig_imaging::calib::{self, Board, CalibError};
use lightrig_imaging::calib_file::{self, BoardSpec, CalibrationFile, Reference, View};
use lightrig_imaging::io;

/// Exit status for bad input data (as `lightrig hdr`).
const DATA_ERROR: u8 = 4;

/// Image file extensions taken from a directory.
const EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "tif", "tiff"];

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Board images: files, or directories (their PNG, JPEG and TIFF files, in name order).
    /// With --pose-only: the one image of the board on the reference plane.
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    /// Inner corners per row of the chessboard (squares per row minus one).
    #[arg(long)]
    pub cols: Option<usize>,
    /// Inner corners per column (squares per column minus one).
    #[arg(long)]
    pub rows: Option<usize>,
    /// Side of a square; poses are in this unit.
    #[arg(long)]
    pub square: Option<f64>,
    /// Name of the square's unit, recorded in the file.
    #[arg(long, default_value = "mm")]
    pub unit: String,
    /// Calibration file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Skip (and record) images in which the board is not found instead of failing.
    #[arg(long)]
    pub skip_missing: bool,
    /// Only register the board pose on the reference plane, with the intrinsics of --calibration;
    /// board geometry defaults to the calibration's board.
    #[arg(long, requires = "calibration")]
    pub pose_only: bool,
    /// Existing calibration file (for --pose-only).
    #[arg(long)]
    pub calibration: Option<PathBuf>,
}

/// Runs the subcommand, printing a report; errors go to stderr with exit status 4.
pub fn run(args: &Args) -> ExitCode {
    let result = if args.pose_only { run_pose(args) } else { run_calibrate(args) };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(DATA_ERROR)
        }
    }
}

fn tool() -> String {
    format!("lightrig {}", env!("CARGO_PKG_VERSION"))
}

fn run_calibrate(args: &Args) -> Result<(), String> {
    let (Some(cols), Some(rows), Some(square)) = (args.cols, args.rows, args.square) else {
        return Err("give the board's geometry: --cols and --rows (inner corners) and --square (side)".into());
    };
    if args.calibration.is_some() {
        return Err("--calibration is only used with --pose-only".into());
    }
    let board = BoardSpec { cols, rows, square, unit: args.unit.clone() };
    let files = collect_images(&args.images)?;
    let (c, why) = calibrate_files_saying_why(&files, &board, args.skip_missing, &tool())?;
    println!(
        "calibration of {} view(s), {}×{} inner corners, square {} {}:",
        c.views.len(),
        cols,
        rows,
        square,
        board.unit
    );
    for v in &c.views {
        println!("  {:<40} rms {:.4} px", v.file, v.rms);
    }
    for (s, why) in c.skipped.iter().zip(&why) {
        println!("  {s:<40} skipped: {why}");
    }
    let k = &c.intrinsics;
    println!("overall rms {:.4} px", c.rms);
    println!("  fx {:.3}  fy {:.3}  cx {:.3}  cy {:.3} (pixels)", k.fx, k.fy, k.cx, k.cy);
    println!("  k1 {:.5}  k2 {:.5}  p1 {:.6}  p2 {:.6}  k3 {:.5}", k.k1, k.k2, k.p1, k.p2, k.k3);
    calib_file::write(&args.out, &c).map_err(|e| e.to_string())?;
    println!("-> {}", args.out.display());
    Ok(())
}

fn run_pose(args: &Args) -> Result<(), String> {
    let cal_path = args.calibration.as_deref().ok_or("--pose-only needs --calibration FILE")?;
    let [image] = args.images.as_slice() else {
        return Err(format!(
            "--pose-only takes one image of the board on the reference plane, got {}",
            args.images.len()
        ));
    };
    let mut c = calib_file::read(cal_path).map_err(|e| e.to_string())?;
    let board = BoardSpec {
        cols: args.cols.unwrap_or(c.board.cols),
        rows: args.rows.unwrap_or(c.board.rows),
        square: args.square.unwrap_or(c.board.square),
        unit: if args.square.is_some() { args.unit.clone() } else { c.board.unit.clone() },
    };
    let reference = register(&c, image, &board)?;
    let p = &reference.pose;
    let centre = p.camera_centre();
    println!("reference board {}: rms {:.4} px", reference.file, reference.rms);
    println!("  rvec [{:.6}, {:.6}, {:.6}] rad", p.rvec[0], p.rvec[1], p.rvec[2]);
    println!("  tvec [{:.4}, {:.4}, {:.4}] {}", p.tvec[0], p.tvec[1], p.tvec[2], board.unit);
    println!(
        "  camera centre in board coordinates [{:.4}, {:.4}, {:.4}] {}",
        centre[0], centre[1], centre[2], board.unit
    );
    c.reference = Some(reference);
    calib_file::write(&args.out, &c).map_err(|e| e.to_string())?;
    println!("-> {}", args.out.display());
    Ok(())
}

/// The image files named by `inputs`: files as given, directories expanded to their image files
/// in name order.
pub fn collect_images(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, String> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let entries = std::fs::read_dir(input).map_err(|e| format!("{}: {e}", input.display()))?;
            let mut found: Vec<PathBuf> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.is_file()
                        && p.extension()
                            .and_then(|x| x.to_str())
                            .is_some_and(|x| EXTENSIONS.contains(&x.to_ascii_lowercase().as_str()))
                })
                .collect();
            if found.is_empty() {
                return Err(format!(
                    "{}: no image files (.{}) in this directory",
                    input.display(),
                    EXTENSIONS.join(", .")
                ));
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    Ok(files)
}

/// An image's corners, or why the board was not found: the whole message (naming the file)
/// and the detector's reason alone.
type Corners = Result<Vec<(f64, f64)>, (String, String)>;

/// Reads an image and looks for the board: an unreadable image is an error, a missing board is
/// the second value's (the caller may skip it).
fn detect(path: &Path, board: &BoardSpec) -> Result<(io::Gray8, Corners), String> {
    let img = io::read_gray8(path).map_err(|e| e.to_string())?;
    let found =
        calib::find_chessboard(&img.data, img.width as usize, img.height as usize, (board.cols, board.rows));
    let found = found.map_err(|e| match e {
        CalibError::BoardNotFound(miss) => (
            format!(
                "{}: no chessboard of {}×{} inner corners found: {miss}",
                path.display(),
                board.cols,
                board.rows
            ),
            miss.to_string(),
        ),
        other => (format!("{}: {other}", path.display()), other.to_string()),
    });
    Ok((img, found))
}

/// Detects the board in every file and calibrates. A file without the board is an error unless
/// `skip_missing`, when it is recorded in `skipped`. All images must have the same size.
pub fn calibrate_files(
    files: &[PathBuf],
    spec: &BoardSpec,
    skip_missing: bool,
    tool: &str,
) -> Result<CalibrationFile, String> {
    calibrate_files_saying_why(files, spec, skip_missing, tool).map(|(c, _)| c)
}

/// [`calibrate_files`], with why the board was not found in each skipped image (in the order
/// of `skipped`; see [`calib::Miss`]).
pub fn calibrate_files_saying_why(
    files: &[PathBuf],
    spec: &BoardSpec,
    skip_missing: bool,
    tool: &str,
) -> Result<(CalibrationFile, Vec<String>), String> {
    if spec.cols < 2 || spec.rows < 2 || !(spec.square > 0.0 && spec.square.is_finite()) {
        return Err(format!(
            "board {}×{} with square {}: need at least 2×2 inner corners and a positive square size",
            spec.cols, spec.rows, spec.square
        ));
    }
    let mut size = None;
    let mut used: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    let mut skipped = Vec::new();
    let mut why = Vec::new();
    for f in files {
        let (img, found) = detect(f, spec)?;
        match size {
            None => size = Some((img.width, img.height, f.clone())),
            Some((w, h, ref first)) if (w, h) != (img.width, img.height) => {
                return Err(format!(
                    "{}: image is {}×{}, but {} is {w}×{h}; one calibration is for one image size",
                    f.display(),
                    img.width,
                    img.height,
                    first.display()
                ));
            }
            Some(_) => {}
        }
        match found {
            Ok(corners) => used.push((f.display().to_string(), corners)),
            Err((e, reason)) if skip_missing => {
                eprintln!("warning: {e}; skipped");
                skipped.push(f.display().to_string());
                why.push(reason);
            }
            Err((e, _)) => return Err(format!("{e} (or pass --skip-missing to leave such images out)")),
        }
    }
    let board = spec.board();
    let views: Vec<Vec<(f64, f64)>> = used.iter().map(|u| u.1.clone()).collect();
    let fit = calib::calibrate(&board, &views).map_err(|e| match e {
        CalibError::TooFewViews { got, need } => format!(
            "the board was found in {got} image(s); calibration needs at least {need}, seen from varied angles"
        ),
        CalibError::Degenerate(what) => {
            format!("calibration failed: {what}; use views of the board at varied tilts and positions")
        }
        other => format!("calibration failed: {other}"),
    })?;
    let views = used
        .iter()
        .zip(&fit.views)
        .map(|((file, corners), pose)| View {
            file: file.clone(),
            rms: calib::reprojection_rms(&fit.intrinsics, pose, &board, corners),
            pose: *pose,
        })
        .collect();
    let (w, h, _) = size.ok_or("no images given")?;
    let file = CalibrationFile {
        tool: tool.into(),
        image_size: (w, h),
        intrinsics: fit.intrinsics,
        board: spec.clone(),
        rms: fit.rms,
        views,
        skipped,
        reference: None,
    };
    Ok((file, why))
}

/// The board → camera pose of `spec`'s board in `image` with the calibration's intrinsics.
pub fn register(c: &CalibrationFile, image: &Path, spec: &BoardSpec) -> Result<Reference, String> {
    let (img, found) = detect(image, spec)?;
    if (img.width, img.height) != c.image_size {
        return Err(format!(
            "{}: image is {}×{}, the calibration is for {}×{}",
            image.display(),
            img.width,
            img.height,
            c.image_size.0,
            c.image_size.1
        ));
    }
    let corners = found.map_err(|(e, _)| e)?;
    let board: Board = spec.board();
    let (pose, rms) = calib::pose_from_board(&c.intrinsics, &corners, &board)
        .map_err(|e| format!("{}: pose not determined: {e}", image.display()))?;
    Ok(Reference { file: image.display().to_string(), board: spec.clone(), rms, pose })
}
