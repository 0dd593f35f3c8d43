//! Reading a session's frames: the session reader the Python package iterates
//! ([`SessionIndex::frames`]: each step's records, then each file read, checked against its
//! record and decoded). `python/benches/read_frames.py` runs this beside the same reading from
//! Python (docs/benchmarks.md).
//!
//!     cargo bench -p lightrig-host --bench read_frames -- SESSION [ROUNDS]
//!
//! Prints one line per round: frames, seconds, frames/s, decoded MB/s.

use std::sync::Arc;
use std::time::Instant;

use lightrig_host::session::SessionIndex;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| a != "--bench").collect();
    let Some(dir) = args.first() else {
        eprintln!("usage: cargo bench -p lightrig-host --bench read_frames -- SESSION [ROUNDS]");
        std::process::exit(2);
    };
    let rounds: usize = args.get(1).and_then(|r| r.parse().ok()).unwrap_or(3);
    for _ in 0..rounds {
        let t0 = Instant::now();
        let index = Arc::new(SessionIndex::read(dir).unwrap_or_else(|e| panic!("{dir}: {e}")));
        let (mut frames, mut bytes) = (0usize, 0usize);
        for f in index.frames(None, None).unwrap() {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            frames += 1;
            bytes += f.image.data.len() * 4;
            std::hint::black_box(&f.image.data);
        }
        let s = t0.elapsed().as_secs_f64();
        println!(
            "rust   {frames} frames  {s:.3} s  {:.0} frames/s  {:.1} MB/s",
            frames as f64 / s,
            bytes as f64 / s / 1e6
        );
    }
}
