//! Figures from the emulated board: instruction counts from the firmware's benchmarks (run on
//! the Cortex-M4 model under `-icount`) and the protocol's throughput over the emulated UART.
//!
//! Under `-icount shift=N` an instruction advances virtual time 2^N ns; the board counts
//! 25 MHz cycles (40 ns), so one cycle is 40 / 2^N instructions. The firmware's `calibrate`
//! benchmark (a loop of exactly 3 instructions per turn) checks that factor.

use std::path::Path;
use std::time::{Duration, Instant};

use lightrig_host::client::Client;
use lightrig_host::transport::SerialTransport;
use lightrig_protocol::config::*;
use lightrig_protocol::sequence::{Action, Chunk, Item};
use lightrig_protocol::{Command, Reply};

use crate::debug::DebugPort;
use crate::qemu::{Options, Qemu};

/// One `BENCH name units cycles` line.
#[derive(Debug, Clone, PartialEq)]
pub struct Bench {
    /// Workload.
    pub name: String,
    /// Units of work done (samples, items, steps, instructions).
    pub units: u64,
    /// 25 MHz cycles taken.
    pub cycles: u64,
}

/// Parses the benchmark lines.
pub fn parse(text: &str) -> Vec<Bench> {
    text.lines()
        .filter_map(|l| {
            let mut w = l.split_whitespace();
            (w.next()? == "BENCH").then_some(())?;
            let name = w.next()?.to_string();
            let units = w.next()?.parse().ok()?;
            let cycles = w.next()?.parse().ok()?;
            Some(Bench { name, units, cycles })
        })
        .collect()
}

/// Instructions per unit, given instructions per cycle.
pub fn per_unit(b: &Bench, instructions_per_cycle: f64) -> f64 {
    b.cycles as f64 * instructions_per_cycle / b.units.max(1) as f64
}

fn bench(elf: &Path, shift: u8, logs: &Path) -> Result<Vec<Bench>, String> {
    let opts = Options { elf: elf.into(), shift, args: vec!["bench".into()], log_dir: logs.into() };
    let mut qemu = Qemu::start(&opts)?;
    let mut port = serialport::new(&qemu.uart0, 115_200)
        .timeout(Duration::from_millis(100))
        .open()
        .map_err(|e| format!("{}: {e}", qemu.uart0))?;
    let lines = crate::qemu::read_lines(port.as_mut(), "BENCH done 0 0", Duration::from_secs(120))?;
    // The firmware ends the emulation itself after its last line.
    if qemu.wait_exit(Duration::from_secs(10)).is_none_or(|s| !s.success()) {
        return Err("the benchmark firmware did not exit cleanly".into());
    }
    Ok(parse(&lines.join("\n")))
}

/// Runs the benchmarks and the throughput measurement and prints the figures.
pub fn run(elf: &Path, shift: u8, logs: &Path) -> Result<(), String> {
    let benches = bench(elf, shift, logs)?;
    let nominal = 40.0 / f64::from(1u32 << shift);
    let calib = benches.iter().find(|b| b.name == "calibrate_instructions").ok_or("no calibration line")?;
    let measured = calib.units as f64 / calib.cycles.max(1) as f64;
    println!("emulated board: QEMU mps2-an386 (Cortex-M4F), -icount shift={shift}: {nominal} instructions per 25 MHz cycle");
    println!(
        "calibration: {} instructions in {} cycles = {measured:.3} per cycle",
        calib.units, calib.cycles
    );
    if (measured - nominal).abs() > nominal * 0.01 {
        return Err(format!("calibration {measured:.3} instructions/cycle, expected {nominal}"));
    }
    println!();
    println!("{:<26} {:>10} {:>14}   at 170 MHz (1 instr/cycle)", "workload", "units", "instr/unit");
    for b in benches.iter().filter(|b| b.units > 0 && b.name != "calibrate_instructions") {
        let i = per_unit(b, nominal);
        let at170 = match b.name.as_str() {
            n if n.starts_with("synth") => format!("{:.1} % CPU at 48 kHz", i * 48_000.0 / 170e6 * 100.0),
            n if n.starts_with("sequencer") => format!("{:.0} kitems/s", 170e6 / i / 1e3),
            _ => format!("{:.0} k steps/s", 170e6 / i / 1e3),
        };
        println!("{:<26} {:>10} {:>14.1}   {}", b.name, b.units, i, at170);
    }
    println!();
    throughput(elf, shift, logs, nominal)
}

fn throughput(elf: &Path, shift: u8, logs: &Path, instructions_per_cycle: f64) -> Result<(), String> {
    let opts = Options { elf: elf.into(), shift, args: vec!["boot=0x7e57".into()], log_dir: logs.into() };
    let qemu = Qemu::start(&opts)?;
    let port = SerialTransport::open(&qemu.uart0, 115_200).map_err(|e| e.to_string())?;
    let mut debug = DebugPort::open(&qemu.uart1)?;
    let mut c = Client::connect(port, 0x5eed).map_err(|e| e.to_string())?;
    c.set_heartbeat_us(100_000);
    let axis = GalvoAxis { min_code: 0, max_code: 65535, zero_code: 32768, nanorad_per_code: 5000 };
    let g = GalvoConfig {
        galvo: 0,
        dac: DacKind::Xy2_100,
        x: axis,
        y: axis,
        park: Xy::default(),
        settle_ticks: 0,
    };
    c.request(Command::Configure(ConfigItem::Galvo(g))).map_err(|e| e.to_string())?;

    println!("protocol over the emulated UART (wall clock of this machine; QEMU does not pace the UART)");
    // Latency-bound: one request at a time.
    const ROUND_TRIPS: u32 = 500;
    let (d0, t0) = (debug.info()?, Instant::now());
    for _ in 0..ROUND_TRIPS {
        c.request(Command::GetClock).map_err(|e| e.to_string())?;
    }
    let (d1, wall) = (debug.info()?, t0.elapsed().as_secs_f64());
    report("GetClock round trips", ROUND_TRIPS, wall, &d0, &d1, instructions_per_cycle);

    // Bulk: 32-item chunks (a galvo point each), loaded and dropped.
    const CHUNKS: u32 = 200;
    let items: heapless::Vec<Item, 32> = (0..32)
        .map(|i| Item {
            delta: 10,
            action: Action::GalvoPoint { galvo: 0, to: Xy { x: 1000 + i * 997, y: 40_000 - i * 13 } },
        })
        .collect();
    let (d0, t0) = (debug.info()?, Instant::now());
    for k in 0..CHUNKS {
        let chunk = Chunk { sequence: 100 + k, chunk: 0, last: true, items: items.clone() };
        let r = c.request(Command::SequenceLoad(chunk)).map_err(|e| e.to_string())?;
        if !matches!(r, Reply::Buffer(_)) {
            return Err(format!("SequenceLoad answered {r:?}"));
        }
        c.request(Command::SequenceAbort { sequence: 100 + k }).map_err(|e| e.to_string())?;
    }
    let (d1, wall) = (debug.info()?, t0.elapsed().as_secs_f64());
    report("32-point chunk + abort", CHUNKS, wall, &d0, &d1, instructions_per_cycle);
    drop(c);
    drop(qemu);
    Ok(())
}

fn report(
    what: &str,
    n: u32,
    wall: f64,
    d0: &crate::debug::BoardInfo,
    d1: &crate::debug::BoardInfo,
    ipc: f64,
) {
    let (rx, tx) = (d1.rx_bytes - d0.rx_bytes, d1.tx_bytes - d0.tx_bytes);
    let busy = (d1.busy_cycles - d0.busy_cycles) as f64 * ipc;
    let virt = (d1.now - d0.now) as f64 / 1e6;
    let turns = d1.wakeups - d0.wakeups;
    println!("{what}: {n} in {wall:.2} s wall ({virt:.2} s virtual) = {:.0}/s", f64::from(n) / wall);
    println!(
        "    bytes: {rx} to the device ({:.0} B/s), {tx} back ({:.0} B/s)",
        rx as f64 / wall,
        tx as f64 / wall
    );
    println!(
        "    firmware: {:.0} instructions each, in {:.1} run-loop turns ({:.0} instructions per turn)",
        busy / f64::from(n),
        turns as f64 / f64::from(n),
        busy / turns.max(1) as f64
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_lines_parse_and_convert() {
        let b = parse("junk\nBENCH calibrate_instructions 3000000 75000\nBENCH rig_step 200000 5523452\nBENCH done 0 0\n");
        assert_eq!(b.len(), 3);
        assert_eq!(b[1], Bench { name: "rig_step".into(), units: 200_000, cycles: 5_523_452 });
        assert_eq!(per_unit(&b[0], 40.0), 1.0);
        assert_eq!(per_unit(&b[1], 40.0), 1104.6904);
    }
}
