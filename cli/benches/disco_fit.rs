//! The whole DISCO fit against reading its frames, and its peak memory at two numbers of frames.
//!
//! Acquires three sessions of the pebble on the virtual rig at the paper's 768 × 496 (2 562
//! vertices, 4 turntable views × 2 camera positions; 6 × 6, 12 × 12 and 24 × 24 spots; kept under
//! `target/bench-disco/` and reused), then for each, in a fresh process: every frame read and
//! decoded whole (in parallel, as the fit reads them, block by block with `read_exr_rows`: the
//! quickest whole-frame read here; `io::read`'s figure beside it), and `lightrig fit disco`'s
//! `fit_session` (which decodes only the rows of a frame that show the object).
//! Prints the wall time of each, their ratio, and each process's peak resident memory
//! (VmHWM). The targets: the fit no slower than 2× reading the frames; its memory `F` plus a
//! bounded number of frames, whatever the number of frames.
//!
//! `cargo bench -p lightrig-cli --bench disco_fit` (~50 min and ~25 GB the first time: the acquisition)

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use lightrig_cli::demo::disco::{acquire_disco, DiscoDemoOptions};
use lightrig_host::session::Session;
use lightrig_imaging::io::read_exr_rows;
use rayon::prelude::*;

/// This process's peak resident memory, MiB.
fn peak_mib() -> f64 {
    lightrig_host::fit::disco::peak_resident_mib().unwrap_or(f64::NAN)
}

/// Child: does one job on `dir`, prints `seconds peak_mib frames`.
fn child(job: &str, dir: &Path) {
    let session = dir.join("session");
    let t = Instant::now();
    let mut phases = Vec::new();
    let frames = match job {
        "read" | "read-image" => {
            let (s, _) = Session::read(&session).expect("session");
            let files: Vec<PathBuf> = s.frame_index().iter().map(|f| session.join(&f.file)).collect();
            // `read`: the quickest whole-frame read the project has (block by block, as the fit
            // reads its bands); `read-image`: `io::read`, through the `exr` crate's image API.
            let pixels: usize = files
                .par_iter()
                .map(|p| match job {
                    "read" => read_exr_rows(p, 0..u32::MAX).map(|(i, _)| i.data.len()).unwrap_or(0),
                    _ => lightrig_imaging::io::read(p).map(|i| i.data.len()).unwrap_or(0),
                })
                .sum();
            assert!(pixels > 0);
            files.len()
        }
        _ => {
            let f = lightrig_host::fit::disco::fit_session(&session, None, &|_, _| {}).expect("fit");
            phases = f.phases.clone();
            f.frames
        }
    };
    println!("{} {} {}", t.elapsed().as_secs_f64(), peak_mib(), frames);
    for p in phases {
        println!("{} {} {}", p.seconds, p.peak_mib.unwrap_or(f64::NAN), p.name);
    }
}

/// (seconds, peak MiB, frames, the fit's phases as (seconds, peak MiB at its end, name)).
fn run(job: &str, dir: &Path) -> (f64, f64, usize, Vec<(f64, f64, String)>) {
    let exe = std::env::current_exe().expect("the bench's own path");
    let out = Command::new(exe).args(["--child", job]).arg(dir).output().expect("child");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let mut lines = text.lines();
    let v: Vec<&str> = lines.next().unwrap_or("").split_whitespace().collect();
    let phases = lines
        .filter_map(|l| {
            let (s, rest) = l.split_once(' ')?;
            let (m, n) = rest.split_once(' ')?;
            Some((s.parse().unwrap_or(f64::NAN), m.parse().unwrap_or(f64::NAN), n.to_string()))
        })
        .collect();
    (
        v.first().and_then(|x| x.parse().ok()).unwrap_or(f64::NAN),
        v.get(1).and_then(|x| x.parse().ok()).unwrap_or(f64::NAN),
        v.get(2).and_then(|x| x.parse().ok()).unwrap_or(0),
        phases,
    )
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child") {
        child(&args[i + 1], Path::new(&args[i + 2]));
        return;
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/bench-disco");
    println!("DISCO fit against reading its frames (768 × 496, 2 562 vertices); each in a fresh process");
    println!(
        "| spots | frames | read s | (io::read s) | fit s | fit / read | of which frames s | frames / read | read peak MiB | fit peak MiB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut details = Vec::new();
    // 24 × 24: 13 824 frames, still a sliver of a real session (the shipped plan's 884 736),
    // where the fixed costs (registration, projector, interpolation) have stopped mattering.
    for grid in [6u32, 12, 24] {
        let dir = root.join(format!("grid{grid}"));
        let done = dir.join("acquired");
        if !done.is_file() {
            let _ = std::fs::remove_dir_all(&dir);
            let opts = DiscoDemoOptions {
                quick: false,
                out: dir.clone(),
                seed: 1,
                progress: false,
                real_time: false,
            };
            acquire_disco(&opts, &[format!("plan.spot_grid=[{grid}, {grid}]")]).expect("acquisition");
            std::fs::write(&done, "").expect("marker");
        }
        // The page cache warmed alike for both: read once first.
        let _ = run("read", &dir);
        let (rt, rm, n, _) = run("read", &dir);
        let (it, _, _, _) = run("read-image", &dir);
        let (ft, fm, _, phases) = run("fit", &dir);
        // The streaming phase (reading the frames and the per-frame work) against reading
        // alone; the rest (F on the mesh) does not grow with the frames.
        let streaming = phases.iter().find(|p| p.2.starts_with("frames")).map_or(f64::NAN, |p| p.0);
        println!(
            "| {grid} × {grid} | {n} | {rt:.1} | ({it:.1}) | {ft:.1} | {:.2} | {streaming:.1} | {:.2} | {rm:.0} | {fm:.0} |",
            ft / rt,
            streaming / rt
        );
        details.push((grid, phases));
    }
    println!();
    for (grid, phases) in details {
        let list: Vec<String> =
            phases.iter().map(|(s, m, n)| format!("{n} {s:.1} s (peak {m:.0} MiB)")).collect();
        println!("{grid} × {grid}: {}", list.join("; "));
    }
}
