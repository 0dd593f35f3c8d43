//! `lightrig sim --pty`: serve the virtual rig's controller on a pseudo-terminal.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// Arguments of `lightrig sim`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Serve the controller on a new pseudo-terminal and print its path; connect to it with
    /// `--connect serial:PATH` (or any serial client).
    #[arg(long)]
    pub pty: bool,
    /// A rig file: the simulated board is wired as it says (homing switches, interlocks,
    /// cameras' exposure outputs). Without one, a bare board.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Also make this path a symbolic link to the terminal (a name that stays the same from
    /// run to run, for scripts). An existing link there is replaced.
    #[arg(long)]
    pub link: Option<PathBuf>,
    /// Stop after this many seconds; by default it runs until interrupted.
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// Runs `lightrig sim`.
pub fn run(args: &Args) -> ExitCode {
    match serve(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err((code, message)) => {
            eprintln!("error: {message}");
            ExitCode::from(code)
        }
    }
}

#[cfg(unix)]
fn serve(args: &Args) -> Result<(), (u8, String)> {
    use std::io::Write;

    use lightrig_firmware::sim::virtual_device_info;
    use lightrig_host::rigfile::RigFile;
    use lightrig_sim::board::board_for;
    use lightrig_sim::pty::PtyRig;

    use crate::error::{DEVICE, FAILURE, INPUT};

    if !args.pty {
        return Err((
            FAILURE,
            "say how to reach the virtual rig: `lightrig sim --pty` (in this process, other \
             commands take `--connect virtual`)"
                .into(),
        ));
    }
    let board = match &args.rig {
        Some(path) => {
            let rig = RigFile::load(path).map_err(|e| (INPUT, e.to_string()))?;
            board_for(&rig)
        }
        None => lightrig_firmware::sim::SimBoard::default(),
    };
    let mut rig = PtyRig::open(virtual_device_info(), board)
        .map_err(|e| (DEVICE, format!("cannot open a pseudo-terminal: {e}")))?;
    let path = rig.path().to_path_buf();
    if let Some(link) = &args.link {
        if link.symlink_metadata().is_ok_and(|m| m.file_type().is_symlink()) {
            let _ = std::fs::remove_file(link);
        }
        std::os::unix::fs::symlink(&path, link)
            .map_err(|e| (INPUT, format!("cannot link {} to {}: {e}", link.display(), path.display())))?;
    }
    // The first line is the port alone, for scripts; then how to use it. A script that
    // stopped reading must not stop the rig: write errors are ignored.
    let mut out = std::io::stdout();
    let _ = writeln!(out, "{}", path.display());
    let _ = writeln!(
        out,
        "virtual rig on {} (real time); connect with `lightrig info --connect serial:{}`; Ctrl-C stops it",
        path.display(),
        args.link.as_deref().unwrap_or(&path).display()
    );
    let _ = out.flush();
    let until = args.seconds.map(|s| Instant::now() + Duration::from_secs_f64(s.max(0.0)));
    let result = rig.serve(|| until.is_some_and(|t| Instant::now() >= t));
    if let Some(link) = &args.link {
        let _ = std::fs::remove_file(link);
    }
    result.map_err(|e| (DEVICE, format!("{}: {e}", path.display())))?;
    let _ = writeln!(
        out,
        "stopped: {} bytes in, {} out, {} dropped while no client read",
        rig.bytes_in, rig.bytes_out, rig.dropped
    );
    Ok(())
}

#[cfg(not(unix))]
fn serve(_: &Args) -> Result<(), (u8, String)> {
    Err((crate::error::FAILURE, "`lightrig sim --pty` needs a Unix pseudo-terminal".into()))
}
