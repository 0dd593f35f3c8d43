//! `lightrig selfcheck`: the host's link against the firmware controller in-process over a
//! lossy simulated wire ([`lightrig_sim::selfcheck`]), with both links' counters.

use std::process::ExitCode;

use lightrig_protocol::link::LinkStats;
use lightrig_sim::selfcheck;

use crate::error::{FAILURE, USAGE};

/// Arguments of `lightrig selfcheck`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Clock requests to exchange.
    #[arg(long, default_value_t = 1000)]
    pub requests: u32,
    /// Percentage of frames dropped in each direction.
    #[arg(long, default_value_t = 5.0)]
    pub drop: f64,
    /// Percentage of frames with a damaged byte.
    #[arg(long, default_value_t = 2.0)]
    pub corrupt: f64,
    /// Seed of the fault pattern.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
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

/// Runs `lightrig selfcheck`.
pub fn run(args: &Args) -> ExitCode {
    let Args { requests, drop, corrupt, seed } = *args;
    let opts = match (per_mille(drop, "drop"), per_mille(corrupt, "corrupt")) {
        (Ok(d), Ok(c)) => selfcheck::Options { requests, drop_per_mille: d, corrupt_per_mille: c, seed },
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("error: {e}");
            return ExitCode::from(USAGE);
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
            ExitCode::from(FAILURE)
        }
    }
}
