//! `lightrig fit PIPELINE SESSION --out DIR`: a session through its rig's pipeline
//! (`lightrig_host::fit`), the files written listed one per line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use lightrig_host::fit::{brrdf, disco, display, firs, lls};
use lightrig_host::overrides::Override;

use crate::error::{FAILURE, USAGE};

/// Arguments of `lightrig fit`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Pipeline: `lls`, `firs-surface`, `firs-volume`, `display`, `brrdf` or `disco`.
    pub pipeline: String,
    /// Session directory.
    pub session: PathBuf,
    /// Output directory for the maps.
    #[arg(long)]
    pub out: PathBuf,
    /// `lls`: the camera's calibration file from `lightrig calibrate` (else the rig file's
    /// `[plan.fit].camera`). `display`: the display calibration a display session's plan was
    /// solved with.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// `brrdf`: the Spectralon session that scales the pairs (else the rig file's
    /// `[plan.fit] spectralon`).
    #[arg(long)]
    pub spectralon: Option<PathBuf>,
    /// `disco`: the object's scanned mesh, PLY or OBJ, in mm (else `--set
    /// plan.fit.mesh_unit=m`; the mesh itself else the rig file's `[plan.fit] mesh`, relative
    /// to the session directory).
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// `lls`: the reflectance models, `both` (Ward, then GGX on the same traces; the Mitsuba
    /// export needs GGX) or `ward` (else the rig file's `[plan.fit] models`, else `both`).
    #[arg(long)]
    pub model: Option<lls::Models>,
    /// Change a value of the session's rig file for this fit, `KEY=VALUE` (repeatable): keys
    /// under `plan.fit` (`plan.fit.light.height_mm=51.2`) and `camera[N].response`. The
    /// session is not changed.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<Override>,
}

/// Runs `lightrig fit`.
pub fn run(args: &Args) -> ExitCode {
    if !args.overrides.is_empty() {
        let set: Vec<String> = args.overrides.iter().map(|o| format!("--set {o}")).collect();
        eprintln!("fitting with the session's rig file changed by {}", set.join(" "));
    }
    match lightrig_host::fit::with_overrides(&args.overrides, || fit(args)) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(USAGE)
        }
    }
}

fn fit(args: &Args) -> ExitCode {
    match args.pipeline.as_str() {
        "lls" => fit_lls(&args.session, args.calibration.as_deref(), &args.out, args.model),
        "firs-surface" => fit_firs_surface(&args.session, &args.out),
        "firs-volume" => fit_firs_volume(&args.session, &args.out),
        "display" | "brdf-display" => fit_display(&args.session, args.calibration.as_deref(), &args.out),
        "brrdf" | "bispectral" => fit_brrdf(&args.session, args.spectralon.as_deref(), &args.out),
        "disco" => fit_disco(&args.session, args.mesh.as_deref(), &args.out),
        other => {
            eprintln!(
                "error: `lightrig fit {other}`: the pipelines are: lls, firs-surface, firs-volume, display, brrdf, disco"
            );
            ExitCode::from(USAGE)
        }
    }
}

/// `lightrig fit lls SESSION --out DIR [--calibration FILE] [--model both|ward]`.
fn fit_lls(session: &Path, calibration: Option<&Path>, out: &Path, models: Option<lls::Models>) -> ExitCode {
    let bar = indicatif::ProgressBar::new(0);
    let b = bar.clone();
    let tables = lls::default_tables_file();
    let streaming = lls::Streaming { scratch: out, block_bytes: lls::BLOCK_BYTES, tables: tables.as_deref() };
    let maps = lls::fit_session_with(session, calibration, streaming, models, &move |done, total| {
        b.set_length(total);
        b.set_position(done);
    });
    bar.finish();
    report_files(maps.and_then(|m| {
        let t = m.timing;
        println!(
            "{} frames read in {:.2} s (one thread), fitted in {:.2} s on {} threads",
            t.frames, t.read_s, t.fit_s, t.threads
        );
        println!("{}", m.tables_note);
        // The fit's own checks; what was not measured and what failed on stderr as well, so
        // that a script's log keeps them beside the exit status.
        for line in lls::quality::lines(&lls::quality::assess(&m, &lls::quality::validity(&m))) {
            if line.starts_with("warning:") || line.starts_with("not measured:") {
                eprintln!("{line}");
            } else {
                println!("{line}");
            }
        }
        lls::write_outputs(&m, out)
    }))
}

/// `lightrig fit firs-surface SESSION --out DIR`.
fn fit_firs_surface(session: &Path, out: &Path) -> ExitCode {
    let fit = firs::fit_surface(session, &|done, total| eprintln!("sweep {done}/{total}"));
    report_files(fit.and_then(|s| {
        println!(
            "{} pixels with a ray; sheets: {} samples, {:.2} µm RMS; {} points merged from {} orientation(s)",
            s.ray_pixels,
            s.sheet_samples,
            s.sheet_rms * 1e3,
            s.merged.len(),
            s.scans.len()
        );
        firs::write_outputs(&s, out)
    }))
}

/// `lightrig fit firs-volume SESSION --out DIR`.
fn fit_firs_volume(session: &Path, out: &Path) -> ExitCode {
    let fit = firs::fit_volume(session, out, &|_, _| {});
    report_files(fit.and_then(|v| {
        println!(
            "grid {:?} of {:.3} mm; {} triangles; enclosed {:.1} mm³",
            v.grid.dims,
            v.grid.voxel[0],
            v.mesh.triangles.len(),
            v.enclosed_mm3
        );
        firs::write_volume_outputs(&v, out)
    }))
}

/// `lightrig fit display SESSION --out DIR [--calibration FILE]`.
fn fit_display(session: &Path, calibration: Option<&Path>, out: &Path) -> ExitCode {
    report_files(display::fit_session(session, calibration, out).map(|(fitted, files)| {
        match fitted {
            display::Fitted::Calibration(c) => {
                for (k, a) in c.axes.iter().enumerate() {
                    let peak = a.response_m.iter().copied().fold(0.0, f64::max);
                    println!(
                        "axis {} ({}): |H| measured at {} frequencies, {:.0}–{:.0} Hz, peak {:.3} mm per full scale",
                        ["x", "y"][k],
                        a.coil,
                        a.frequencies_hz.len(),
                        a.frequencies_hz.iter().copied().fold(f64::INFINITY, f64::min),
                        a.frequencies_hz.iter().copied().fold(0.0, f64::max),
                        peak * 1e3
                    );
                }
            }
            display::Fitted::Shown(shown, _) => {
                println!("step  target αx, αy    shown αx, αy    error             lobe-shape error");
                for s in &shown {
                    let e = s.error();
                    println!(
                        "{:>4}  {:.4}, {:.4}  {:.4}, {:.4}  {:+.1} %, {:+.1} %    {:.3}",
                        s.step,
                        s.target[0],
                        s.target[1],
                        s.shown[0],
                        s.shown[1],
                        100.0 * e[0],
                        100.0 * e[1],
                        s.shape_error
                    );
                }
            }
        }
        files
    }))
}

/// `lightrig fit brrdf SESSION --spectralon CAL --out DIR`.
fn fit_brrdf(session: &Path, spectralon: Option<&Path>, out: &Path) -> ExitCode {
    let bar = indicatif::ProgressBar::new(0);
    let b = bar.clone();
    let fit = brrdf::fit_session(session, spectralon, &move |done, total| {
        b.set_length(total);
        b.set_position(done);
    });
    bar.finish_and_clear();
    report_files(fit.and_then(|f| {
        for n in &f.notes {
            println!("note: {n}");
        }
        let angles: Vec<String> = f.pca_angles.iter().map(|a| format!("{a:.1}°")).collect();
        println!("{} wavelength pairs; PCA angles {}", f.pairs.len(), angles.join(", "));
        for s in &f.spheres {
            println!(
                "{} sphere: {} samples ({} reconstructed from the chosen pairs), {} of {} bins observed",
                s.name,
                s.samples.len(),
                s.reconstructed,
                s.binned.observed(),
                s.binned.n.pow(3),
            );
            for a in &s.same_angle {
                println!(
                    "  same angle {:.1}°: {} bins, {} components for 1 % residual energy, {} for 0.1 %",
                    a.light_deg, a.bins, a.components_1pc, a.components_01pc
                );
            }
            if let Some(t) = &s.transfer {
                println!(
                    "  {:.1}° held out, {} pairs: PSNR non-specular {:.1} dB standard / {:.1} dB saturated, specular {:.1} / {:.1} dB",
                    t.held_out_deg,
                    t.chosen.len(),
                    t.psnr[0],
                    t.psnr_saturated[0],
                    t.psnr[1],
                    t.psnr_saturated[1]
                );
            }
        }
        brrdf::write_outputs(&f, out)
    }))
}

/// `lightrig fit disco SESSION --out DIR [--mesh FILE.ply|FILE.obj]`.
fn fit_disco(session: &Path, mesh: Option<&Path>, out: &Path) -> ExitCode {
    let bar = crate::demo::bar(true, 0, "frames");
    let b = bar.clone();
    let fit = disco::fit_session(session, mesh, &move |done, total| {
        b.set_length(total);
        b.set_position(done);
    });
    bar.finish_and_clear();
    report_files(fit.and_then(|f| {
        let n = f.mesh.vertices.len();
        println!(
            "{} views, {} laser frames: {} resampled, {} beam off the object or grazing, {} held out",
            f.views, f.frames, f.used, f.missed, f.held_out_frames
        );
        println!(
            "F: {n} vertices, {} of {} columns lit, {} of {} entries measured, the rest interpolated",
            f.lit_columns,
            n,
            f.observed.iter().filter(|&&o| o).count(),
            n * n
        );
        if let Some(g) = &f.registration {
            println!(
                "registered the mesh by its silhouette in {} views{}: turned {:.2}°, moved {:.2} mm; the worst view agrees to {:.2} % (intersection over union)",
                g.views_used,
                if g.from_hull { ", searched from the views' visual hull (the scan's own frame was far off)" } else { "" },
                g.pose.angle_deg(),
                lightrig_pipelines::vec3::norm(g.pose.translation),
                100.0 * g.min_iou()
            );
        }
        let pr = &f.projector;
        println!(
            "projector placed by {} spots ({} dropped): pivot moved {:.2} mm, turned {:.2}°, entry points moved up to {:.2} mm; its beams miss the spots by {:.3} mm RMS",
            pr.used, pr.dropped, pr.moved_mm, pr.turned_deg, pr.shift_mm, pr.rms_mm
        );
        if f.spots_seen > 0 {
            println!(
                "spot seen in {} frames: its peak {:.2} mm (median) from the projector's entry point",
                f.spots_seen, f.peak_offset_mm
            );
        }
        if f.held_out.frames > 0 {
            println!(
                "held-out spots: {} of their {} frames predicted from F, relative RMS error {:.1} % (median; beyond {:.1} mm of the spot)",
                f.held_out.frames,
                f.held_out_frames,
                100.0 * f.held_out.median_rel_rms,
                f.held_out.near_mm
            );
        }
        disco::write_outputs(&f, out)
    }))
}

/// A fit's written files, one per line, or its error.
fn report_files<E: std::fmt::Display>(files: Result<Vec<PathBuf>, E>) -> ExitCode {
    match files {
        Ok(files) => {
            for f in files {
                println!("{}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(FAILURE)
        }
    }
}
