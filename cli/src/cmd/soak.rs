//! `lightrig soak`: a long acquisition through the whole virtual rig over a damaged wire
//! ([`lightrig_sim::soak`]); fails unless every trigger's frame was stored once and paired
//! with it.

use std::path::PathBuf;
use std::process::ExitCode;

use lightrig_sim::soak;

use crate::error::{FAILURE, USAGE};

/// Arguments of `lightrig soak`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Camera triggers in all.
    #[arg(long, default_value_t = 1_000_000)]
    pub triggers: u64,
    /// Triggers per step (one device sequence each).
    #[arg(long, default_value_t = 1_000)]
    pub per_step: u32,
    /// Steps per session (each session is checked, then removed).
    #[arg(long, default_value_t = 20)]
    pub steps_per_session: u32,
    /// Fraction of bytes dropped, of bytes flipped and of bytes duplicated on the wire (each,
    /// each direction).
    #[arg(long, default_value_t = 1e-4)]
    pub damage: f64,
    /// Seed of the damage pattern.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Where the sessions go while they are checked (default: /dev/shm where there is one,
    /// else the temporary directory).
    #[arg(long)]
    pub dir: Option<PathBuf>,
}

/// Runs `lightrig soak`.
pub fn run(args: &Args) -> ExitCode {
    if !(0.0..0.01).contains(&args.damage) {
        eprintln!("error: --damage {}: must be a fraction in 0..0.01", args.damage);
        return ExitCode::from(USAGE);
    }
    let dir = args.dir.clone().unwrap_or_else(|| {
        let shm = PathBuf::from("/dev/shm");
        if shm.is_dir() {
            shm
        } else {
            std::env::temp_dir()
        }
    });
    let opts = soak::Options {
        triggers: args.triggers,
        per_step: args.per_step,
        steps_per_session: args.steps_per_session,
        damage_ppm: (args.damage * 1e6).round() as u32,
        seed: args.seed,
        dir,
    };
    println!(
        "lightrig soak: {} triggers through the virtual rig, {:.0e} of bytes dropped, {:.0e} flipped, \
         {:.0e} duplicated (seed {}), sessions in {}",
        opts.triggers,
        args.damage,
        args.damage,
        args.damage,
        opts.seed,
        opts.dir.display()
    );
    let tty = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let progress = |r: &soak::Report| {
        // A log (CI) gets the figures at the end only.
        if !tty {
            return;
        }
        eprint!(
            "\r  {:>8} / {} triggers  {:.0} triggers/s   ",
            r.triggers,
            opts.triggers,
            r.triggers as f64 / r.wall.as_secs_f64().max(1e-3)
        );
    };
    let r = match soak::run(&opts, progress) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("\nsoak FAILED: {e:#}");
            return ExitCode::from(FAILURE);
        }
    };
    eprintln!();
    let d = r.damage;
    let l = &r.host_link;
    println!("  triggers            {}", r.triggers);
    println!("  frames paired       {} (mispaired {})", r.frames, r.mispaired);
    println!("  missing, extra      {}, {}", r.missing, r.extra);
    println!("  trigger events      {} journaled, each once", r.trigger_events);
    println!("  steps, attempts     {}, {} (in {} sessions)", r.steps, r.attempts, r.sessions);
    println!(
        "  wire                {} bytes: {} dropped, {} flipped, {} duplicated",
        d.bytes, d.dropped, d.flipped, d.duplicated
    );
    println!(
        "  host link           {} frames sent, {} received, {} retransmitted, {} rejected (crc {}, cobs {})",
        l.frames_sent,
        l.frames_received,
        l.retransmits,
        l.rejected(),
        l.bad_crc,
        l.bad_cobs
    );
    println!(
        "  time                {:.0} s simulated in {:.0} s ({:.0} triggers/s)",
        r.simulated_us as f64 / 1e6,
        r.wall.as_secs_f64(),
        r.triggers as f64 / r.wall.as_secs_f64().max(1e-3)
    );
    if r.clean() {
        println!("ok: every trigger's frame stored once and paired with it; 0 lost, 0 duplicated");
        ExitCode::SUCCESS
    } else {
        eprintln!("soak FAILED: frames and triggers do not match one to one (see the counts above)");
        ExitCode::from(FAILURE)
    }
}
