//! `lightrig`: the command-line entry point. Each subcommand lives in its own module of the
//! `lightrig_cli` library ([`lightrig_cli::cmd`], [`lightrig_cli::demo`]).

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use lightrig_cli::cmd::{self, acquire, calibrate, device, display, fit, flash, hdr, selfcheck, sim, soak};
use lightrig_cli::demo;

#[derive(Parser)]
#[command(name = "lightrig", version, about = "Firmware and host toolkit for appearance-capture rigs")]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run a whole acquisition and fit on the virtual rig and compare the fit with the ground
    /// truth (the default method is the linear light source).
    Demo(demo::Args),
    /// Fit a session: `lightrig fit lls SESSION --out DIR [--calibration cam.toml]`,
    /// `lightrig fit firs-surface|firs-volume SESSION --out DIR`,
    /// `lightrig fit display SESSION --out DIR [--calibration display-calibration.json]`, or
    /// `lightrig fit brrdf SESSION --spectralon CAL_SESSION --out DIR`.
    Fit(fit::Args),
    /// Run the host link against the firmware controller in-process over a lossy simulated wire.
    Selfcheck(selfcheck::Args),
    /// A long acquisition (10^6 triggers) through the whole virtual rig over a wire that drops,
    /// flips and duplicates bytes: every frame must be paired with its trigger once.
    Soak(soak::Args),
    /// Print this build's protocol version, schema hash and frame limits.
    Schema,
    /// List serial ports and USB controllers; with --probe, ask each what it is.
    Devices(device::DevicesArgs),
    /// Run a rig file's acquisition plan into a new session directory.
    Acquire(acquire::AcquireArgs),
    /// Continue an interrupted session: re-acquire the steps not finished.
    Resume(acquire::ResumeArgs),
    /// High dynamic range from exposure series.
    #[command(subcommand)]
    Hdr(hdr::Cmd),
    /// Camera calibration from chessboard images; with --pose-only, a board's pose on the
    /// reference plane. Writes a calibration file (docs/calibration-format.md).
    Calibrate(calibrate::Args),
    /// Serve the virtual rig's controller to other processes: `lightrig sim --pty`.
    Sim(sim::Args),
    /// Connect to a device and print what it says about itself and how its clock maps.
    Info(device::InfoArgs),
    /// Show a Ward roughness on a BRDF display, live: `lightrig display RIG --alpha 0.08,0.04`;
    /// new values from standard input change it over the controller's ramps.
    Display(display::Args),
    /// Emergency stop: lasers off, motors stopped at once, galvos parked, the fault latched.
    Stop(device::StopArgs),
    /// Update a controller's firmware over its link (`lightrig flash IMAGE --connect SPEC`), or
    /// make the keys (`keygen`) and signed images (`sign`) it takes.
    Flash(flash::Args),
}

fn main() -> ExitCode {
    match Cli::parse().command {
        Cmd::Demo(args) => demo::run(&args),
        Cmd::Fit(args) => fit::run(&args),
        Cmd::Selfcheck(args) => selfcheck::run(&args),
        Cmd::Soak(args) => soak::run(&args),
        Cmd::Schema => device::schema(),
        Cmd::Devices(args) => device::devices(&args),
        Cmd::Acquire(a) => cmd::exit(acquire::acquire(&a)),
        Cmd::Resume(a) => cmd::exit(acquire::resume(&a)),
        Cmd::Hdr(c) => hdr::run(&c),
        Cmd::Calibrate(args) => calibrate::run(&args),
        Cmd::Sim(args) => sim::run(&args),
        Cmd::Info(args) => device::info(&args),
        Cmd::Stop(args) => device::stop(&args),
        Cmd::Display(args) => cmd::exit(display::run(&args)),
        Cmd::Flash(args) => flash::run(&args),
    }
}
