//! `lightrig`: the command-line entry point.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use lightrig_host::cli_calibrate;
use lightrig_host::cli_hdr;
use lightrig_host::cli_sim;
use lightrig_host::client::Client;
use lightrig_host::selfcheck;
use lightrig_host::transport::{candidates, Connect, Transport};
use lightrig_protocol::{link::LinkStats, MAX_FRAME, MAX_PACKET, PROTOCOL_VERSION, SCHEMA_HASH};

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
    Demo {
        /// Method: `lls` (linear light source) or `firs` (fluorescent immersion).
        #[arg(default_value = "lls")]
        method: String,
        /// A small scene for a quick check (about half a minute).
        #[arg(long)]
        quick: bool,
        /// Output directory.
        #[arg(long, default_value = "lightrig-demo")]
        out: std::path::PathBuf,
        /// Noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Exit with failure if a fit accuracy target is missed.
        #[arg(long)]
        check: bool,
        /// Run the virtual rig in real time, as long as the real rig would take (by default
        /// simulated time jumps ahead whenever the device waits).
        #[arg(long)]
        real_time: bool,
        /// The LLS gantry's step, mm (default 1, 2 with --quick): 0.6 gives the 400-frame
        /// passes of the fit's benchmark (docs/benchmarks.md).
        #[arg(long)]
        step_mm: Option<f64>,
    },
    /// Fit a session: `lightrig fit lls SESSION --out DIR [--calibration cam.toml]`, or
    /// `lightrig fit firs-surface|firs-volume SESSION --out DIR`.
    Fit {
        /// Pipeline: `lls`, `firs-surface` or `firs-volume`.
        pipeline: String,
        /// Session directory.
        session: std::path::PathBuf,
        /// Output directory for the maps.
        #[arg(long)]
        out: std::path::PathBuf,
        /// The camera's calibration file from `lightrig calibrate` (else the rig file's
        /// `[plan.fit].camera`).
        #[arg(long)]
        calibration: Option<std::path::PathBuf>,
    },
    /// Run the host link against the firmware controller in-process over a lossy simulated wire.
    Selfcheck {
        /// Clock requests to exchange.
        #[arg(long, default_value_t = 1000)]
        requests: u32,
        /// Percentage of frames dropped in each direction.
        #[arg(long, default_value_t = 5.0)]
        drop: f64,
        /// Percentage of frames with a damaged byte.
        #[arg(long, default_value_t = 2.0)]
        corrupt: f64,
        /// Seed of the fault pattern.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Print this build's protocol version, schema hash and frame limits.
    Schema,
    /// List serial ports and USB controllers; with --probe, ask each what it is.
    Devices {
        /// Say Hello to every port (a port that is not a lightrig controller costs a 3 s timeout).
        #[arg(long)]
        probe: bool,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Run a rig file's acquisition plan into a new session directory.
    Acquire {
        /// The rig file (see docs/rigs).
        rig: std::path::PathBuf,
        /// Session directory to create.
        #[arg(long)]
        session: std::path::PathBuf,
        /// Override the rig file's `[device] connect`.
        #[arg(long)]
        connect: Option<Connect>,
        /// Take what steps ask of a person or of host instruments (`meta.operator`,
        /// `meta.host`) as done, without asking: for scripts on a rig set up beforehand.
        #[arg(long)]
        yes: bool,
    },
    /// Continue an interrupted session: re-acquire the steps not finished.
    Resume {
        /// Session directory.
        session: std::path::PathBuf,
        /// The original rig file (for its relative paths; must be unchanged).
        #[arg(long)]
        rig: Option<std::path::PathBuf>,
        /// Override the rig file's `[device] connect`.
        #[arg(long)]
        connect: Option<Connect>,
        /// Take what steps ask of a person or of host instruments (`meta.operator`,
        /// `meta.host`) as done, without asking: for scripts on a rig set up beforehand.
        #[arg(long)]
        yes: bool,
    },
    /// High dynamic range from exposure series.
    #[command(subcommand)]
    Hdr(HdrCmd),
    /// Camera calibration from chessboard images; with --pose-only, a board's pose on the
    /// reference plane. Writes a calibration file (docs/calibration-format.md).
    Calibrate(cli_calibrate::Args),
    /// Serve the virtual rig's controller to other processes: `lightrig sim --pty`.
    Sim(cli_sim::Args),
    /// Connect to a device and print what it says about itself and how its clock maps.
    Info {
        /// `virtual`, `serial:PATH[@BAUD]`, `usb` or `usb:SERIAL`.
        #[arg(long, default_value = "virtual")]
        connect: Connect,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum HdrCmd {
    /// Recover the camera response from an exposure series; write it as JSON.
    Calibrate {
        /// Exposures as FILE:SECONDS.
        exposures: Vec<String>,
        /// A sidecar file of `FILE SECONDS` lines instead.
        #[arg(long)]
        times: Option<std::path::PathBuf>,
        /// `debevec` (Debevec–Malik, sampled pixels) or `robertson` (every pixel, iterated).
        #[arg(long, default_value = "debevec")]
        method: cli_hdr::Method,
        /// Response file to write.
        #[arg(long)]
        out: std::path::PathBuf,
    },
    /// Merge an exposure series into linear radiance (float EXR).
    Merge {
        /// Exposures as FILE:SECONDS.
        exposures: Vec<String>,
        /// A sidecar file of `FILE SECONDS` lines instead.
        #[arg(long)]
        times: Option<std::path::PathBuf>,
        /// Response from `hdr calibrate` (recovered from the series itself if absent).
        #[arg(long)]
        response: Option<std::path::PathBuf>,
        /// Largest level treated as black (weight zero), in the data's levels (0–4095 for
        /// 12-bit data). Set it near 3σ of the camera's read noise: levels below the noise
        /// floor cannot be inverted and only add error (docs/benchmarks.md, HDR accuracy).
        #[arg(long, default_value_t = 0)]
        black: u32,
        /// EXR file to write.
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

fn exposures(list: &[String], times: Option<&std::path::Path>) -> Result<Vec<cli_hdr::Exposure>, String> {
    match times {
        Some(p) if list.is_empty() => cli_hdr::read_sidecar(p),
        Some(_) => {
            Err("give the exposures either as FILE:SECONDS arguments or with --times, not both".into())
        }
        None => list.iter().map(|s| cli_hdr::parse_exposure(s)).collect(),
    }
}

/// Exit codes: scripts can tell a usage error from an unreachable device from a fault.
mod exit {
    pub const FAILURE: u8 = 1;
    pub const USAGE: u8 = 2;
    pub const DEVICE: u8 = 3;
}

fn connect(spec: &Connect) -> Result<Client<Box<dyn Transport>>, (u8, String)> {
    let transport = spec.open().map_err(|e| (exit::DEVICE, e.to_string()))?;
    let nonce = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos() ^ (d.as_secs() as u32))
        .unwrap_or(1);
    Client::connect(transport, nonce).map_err(|e| (exit::DEVICE, e.to_string()))
}

fn info_json(c: &Client<Box<dyn Transport>>) -> serde_json::Value {
    let i = c.info();
    serde_json::json!({
        "device": c.transport().describe(),
        "board": format!("{:?}", i.board),
        "firmware": format!("{}.{}.{}", i.firmware.major, i.firmware.minor, i.firmware.patch),
        "protocol_version": i.protocol_version,
        "schema_hash": format!("0x{:016x}", i.schema_hash),
        "serial": i.serial,
        "tick_hz": i.tick_hz,
        "reset_cause": format!("{:?}", i.reset_cause),
        "boot_id": i.boot_id,
        "capabilities": format!("{:?}", i.capabilities),
        "clock": {
            "rate_ppm": c.clock().rate().map(|r| (r * 1e6 / f64::from(i.tick_hz) - 1.0) * 1e6),
            "residual_ticks": c.clock().residual(),
            "min_rtt_us": c.clock().min_rtt_us(),
        },
    })
}

fn per_mille(percent: f64, flag: &str) -> Result<u32, String> {
    if (0.0..100.0).contains(&percent) {
        Ok((percent * 10.0).round() as u32)
    } else {
        Err(format!("--{flag} {percent}: must be a percentage in 0..100"))
    }
}

fn stats_line(name: &str, s: &LinkStats) -> String {
    format!(
        "  {name:<7} sent {:>6}  received {:>6}  retransmitted {:>5}  timeouts {:>4}  rejected {:>4} \
         (crc {}, cobs {}, short {}, long {}, type {}, payload {})  duplicates {}",
        s.frames_sent,
        s.frames_received,
        s.retransmits,
        s.timeouts,
        s.rejected(),
        s.bad_crc,
        s.bad_cobs,
        s.too_short,
        s.too_long,
        s.unknown_type,
        s.bad_payload,
        s.duplicates
    )
}

fn main() -> ExitCode {
    match Cli::parse().command {
        Cmd::Calibrate(args) => cli_calibrate::run(&args),
        Cmd::Sim(args) => cli_sim::run(&args),
        Cmd::Hdr(cmd) => {
            let result = match cmd {
                HdrCmd::Calibrate { exposures: list, times, method, out } => exposures(
                    &list,
                    times.as_deref(),
                )
                .and_then(|e| cli_hdr::calibrate(&e, method, &out))
                .map(|r| {
                    eprintln!("response: {} channel(s), {} levels -> {}", r.g.len(), r.levels, out.display())
                }),
                HdrCmd::Merge { exposures: list, times, response, black, out } => {
                    exposures(&list, times.as_deref())
                        .and_then(|e| cli_hdr::merge(&e, response.as_deref(), black, &out))
                        .map(|bad| {
                            eprintln!(
                                "merged -> {} ({bad} pixels clipped or black in every exposure)",
                                out.display()
                            )
                        })
                }
            };
            match result {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("error: {e}");
                    ExitCode::from(4)
                }
            }
        }
        Cmd::Demo { method, quick, out, seed, check, real_time, step_mm } => {
            if let Some(step) = step_mm.filter(|_| method == "firs" || method == "fluorescent-immersion") {
                eprintln!(
                    "error: --step-mm {step}: the firs demo has no gantry; it is for `lightrig demo lls`"
                );
                return ExitCode::from(exit::USAGE);
            }
            if let Some(step) = step_mm.filter(|s| !(0.1..=5.0).contains(s)) {
                eprintln!("error: --step-mm {step}: give a gantry step from 0.1 to 5 mm");
                return ExitCode::from(exit::USAGE);
            }
            if method == "firs" || method == "fluorescent-immersion" {
                return firs_demo(quick, &out, seed, check, real_time);
            }
            if method != "lls" && method != "linear-light-source" {
                eprintln!("error: `lightrig demo {method}`: the methods with a demo are: lls, firs");
                return ExitCode::from(exit::USAGE);
            }
            let opts = lightrig_host::demo::DemoOptions {
                quick,
                out: out.join("lls"),
                seed,
                progress: true,
                real_time,
                step_mm,
            };
            match lightrig_host::demo::run_lls(&opts) {
                Ok((acc, _)) => {
                    let missed: Vec<_> = acc.targets().into_iter().filter(|t| !t.3).map(|t| t.0).collect();
                    if check && !missed.is_empty() {
                        eprintln!("error: accuracy targets missed: {}", missed.join(", "));
                        return ExitCode::from(exit::FAILURE);
                    }
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("error: {}", e.message);
                    ExitCode::from(e.code)
                }
            }
        }
        Cmd::Fit { pipeline, session, out, calibration } => {
            if pipeline == "firs-surface" {
                return fit_firs_surface(&session, &out);
            }
            if pipeline == "firs-volume" {
                return fit_firs_volume(&session, &out);
            }
            if pipeline != "lls" {
                eprintln!(
                    "error: `lightrig fit {pipeline}`: the pipelines are: lls, firs-surface, firs-volume"
                );
                return ExitCode::from(exit::USAGE);
            }
            let bar = indicatif::ProgressBar::new(0);
            let b = bar.clone();
            let maps = lightrig_host::lls_fit::fit_session(
                &session,
                calibration.as_deref(),
                &out,
                &move |done, total| {
                    b.set_length(total);
                    b.set_position(done);
                },
            );
            bar.finish();
            report_files(maps.and_then(|m| {
                let t = m.timing;
                println!(
                    "{} frames read in {:.2} s (one thread), fitted in {:.2} s on {} threads",
                    t.frames, t.read_s, t.fit_s, t.threads
                );
                println!("{}", m.tables_note);
                lightrig_host::lls_fit::write_outputs(&m, &out)
            }))
        }
        Cmd::Acquire { rig, session, connect, yes } => {
            match lightrig_host::cli_acquire::acquire(&rig, &session, connect.as_ref(), yes) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("error: {}", e.message);
                    ExitCode::from(e.code)
                }
            }
        }
        Cmd::Resume { session, rig, connect, yes } => {
            match lightrig_host::cli_acquire::resume(&session, rig.as_deref(), connect.as_ref(), yes) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("error: {}", e.message);
                    ExitCode::from(e.code)
                }
            }
        }
        Cmd::Devices { probe, json } => {
            let mut rows = Vec::new();
            for c in candidates() {
                let answer = if probe {
                    match c.connect.parse::<Connect>().map_err(|e| (exit::USAGE, e)).and_then(|s| connect(&s))
                    {
                        Ok(client) => Some(info_json(&client)),
                        Err((_, e)) => Some(serde_json::json!({ "error": e })),
                    }
                } else {
                    None
                };
                rows.push(serde_json::json!({ "connect": c.connect, "description": c.description, "hello": answer }));
            }
            if json {
                println!("{}", serde_json::Value::Array(rows));
            } else if rows.is_empty() {
                println!("no serial ports or USB controllers found (the virtual rig is always there: --connect virtual)");
            } else {
                for r in &rows {
                    println!(
                        "{:<28} {}",
                        r["connect"].as_str().unwrap_or(""),
                        r["description"].as_str().unwrap_or("")
                    );
                    if !r["hello"].is_null() {
                        println!("    {}", r["hello"]);
                    }
                }
            }
            ExitCode::SUCCESS
        }
        Cmd::Info { connect: spec, json } => match connect(&spec) {
            Ok(client) => {
                let v = info_json(&client);
                if json {
                    println!("{v}");
                } else if let Some(map) = v.as_object() {
                    for (k, val) in map {
                        println!("{k:<16} {val}");
                    }
                }
                ExitCode::SUCCESS
            }
            Err((code, e)) => {
                eprintln!("error: {e}");
                ExitCode::from(code)
            }
        },
        Cmd::Schema => {
            println!("protocol version {PROTOCOL_VERSION}");
            println!("schema hash      0x{SCHEMA_HASH:016x}");
            println!("max packet       {MAX_PACKET} bytes, max frame {MAX_FRAME} bytes");
            ExitCode::SUCCESS
        }
        Cmd::Selfcheck { requests, drop, corrupt, seed } => {
            let opts = match (per_mille(drop, "drop"), per_mille(corrupt, "corrupt")) {
                (Ok(d), Ok(c)) => {
                    selfcheck::Options { requests, drop_per_mille: d, corrupt_per_mille: c, seed }
                }
                (Err(e), _) | (_, Err(e)) => {
                    eprintln!("error: {e}");
                    return ExitCode::from(exit::USAGE);
                }
            };
            println!(
                "lightrig selfcheck: host link <-> firmware controller, {requests} requests, {drop}% dropped, {corrupt}% damaged (seed {seed})"
            );
            match selfcheck::run(opts) {
                Ok(r) => {
                    println!(
                        "  device  {:?} firmware {}.{}.{}, protocol {}, schema 0x{:016x}, {} Hz",
                        r.device.board,
                        r.device.firmware.major,
                        r.device.firmware.minor,
                        r.device.firmware.patch,
                        r.device.protocol_version,
                        r.device.schema_hash,
                        r.device.tick_hz
                    );
                    println!("{}", stats_line("host", &r.host_link));
                    println!("{}", stats_line("device", &r.device_link));
                    println!(
                        "ok: handshake, schema check, {} requests answered in order in {} simulated ticks, typed config errors",
                        r.answered, r.ticks
                    );
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("selfcheck FAILED: {e:#}");
                    ExitCode::from(exit::FAILURE)
                }
            }
        }
    }
}

/// `lightrig demo firs`.
fn firs_demo(quick: bool, out: &std::path::Path, seed: u64, check: bool, real_time: bool) -> ExitCode {
    use lightrig_host::firs_demo::FirsDemoObject;
    let opts = lightrig_host::firs_demo::FirsDemoOptions {
        objects: vec![FirsDemoObject::Sphere, FirsDemoObject::Faceted],
        volume: true,
        quick,
        out: out.join("firs"),
        seed,
        progress: true,
        real_time,
    };
    match lightrig_host::firs_demo::run_firs(&opts) {
        Ok(result) => {
            let missed = result.missed();
            if check && !missed.is_empty() {
                eprintln!("error: accuracy targets missed: {}", missed.join(", "));
                return ExitCode::from(exit::FAILURE);
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", e.message);
            ExitCode::from(e.code)
        }
    }
}

/// `lightrig fit firs-surface SESSION --out DIR`.
fn fit_firs_surface(session: &std::path::Path, out: &std::path::Path) -> ExitCode {
    let fit = lightrig_host::firs_fit::fit_surface(session, &|done, total| eprintln!("sweep {done}/{total}"));
    report_files(fit.and_then(|s| {
        println!(
            "{} pixels with a ray; sheets: {} samples, {:.2} µm RMS; {} points merged from {} orientation(s)",
            s.ray_pixels,
            s.sheet_samples,
            s.sheet_rms * 1e3,
            s.merged.len(),
            s.scans.len()
        );
        lightrig_host::firs_fit::write_outputs(&s, out)
    }))
}

/// `lightrig fit firs-volume SESSION --out DIR`.
fn fit_firs_volume(session: &std::path::Path, out: &std::path::Path) -> ExitCode {
    let fit = lightrig_host::firs_fit::fit_volume(session, out, &|_, _| {});
    report_files(fit.and_then(|v| {
        println!(
            "grid {:?} of {:.3} mm; {} triangles; enclosed {:.1} mm³",
            v.grid.dims,
            v.grid.voxel[0],
            v.mesh.triangles.len(),
            v.enclosed_mm3
        );
        lightrig_host::firs_fit::write_volume_outputs(&v, out)
    }))
}

/// A fit's written files, one per line, or its error.
fn report_files<E: std::fmt::Display>(files: Result<Vec<std::path::PathBuf>, E>) -> ExitCode {
    match files {
        Ok(files) => {
            for f in files {
                println!("{}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(exit::FAILURE)
        }
    }
}
