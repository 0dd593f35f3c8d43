//! `lightrig`: the command-line entry point.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use lightrig_host::selfcheck;
use lightrig_protocol::{link::LinkStats, MAX_FRAME, MAX_PACKET, PROTOCOL_VERSION, SCHEMA_HASH};

#[derive(Parser)]
#[command(name = "lightrig", version, about = "Firmware and host toolkit for appearance-capture rigs")]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
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
                    return ExitCode::from(2);
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
                    ExitCode::FAILURE
                }
            }
        }
    }
}
