//! `lightrig sim --pty`: the virtual rig's controller in another process, reached through a
//! pseudo-terminal by the host's real serial transport, exactly as a board's USB serial port.
//! These run in real time (the two processes share no clock), so they wait for I/O, never for
//! a fixed time.
#![cfg(unix)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

use lightrig_host::client::Client;
use lightrig_host::transport::SerialTransport;
use lightrig_protocol::session::BoardId;
use lightrig_protocol::{Command as Cmd, Reply, SCHEMA_HASH};

#[path = "../../sim/tests/support/triggers.rs"]
mod triggers;

/// The simulator, killed when dropped.
struct Sim {
    child: Child,
    path: String,
    _stdout: BufReader<std::process::ChildStdout>,
}

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn sim() -> Sim {
    let mut child = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["sim", "--pty", "--seconds", "120"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    let path = line.trim().to_string();
    assert!(path.starts_with("/dev/"), "first line is the port: {line:?}");
    Sim { child, path, _stdout: stdout }
}

#[test]
fn the_host_client_runs_a_sequence_through_the_pseudo_terminal() {
    let sim = sim();
    let port = SerialTransport::open(&sim.path, 115_200).unwrap();
    let mut c = Client::connect(port, 0x1234_5678).unwrap();
    assert_eq!(c.info().board, BoardId::Virtual);
    assert_eq!(c.info().schema_hash, SCHEMA_HASH);
    assert_ne!(c.info().boot_id, 0, "a fresh boot id, as a real device's");
    triggers::configure_camera(&mut c);
    let Reply::Clock { tick: now } = c.request(Cmd::GetClock).unwrap() else { panic!("no clock") };
    // 300 triggers 1 ms apart, more than the device's buffer holds: streamed under credit.
    const N: u32 = 300;
    let start = now + 200_000;
    let (outcome, triggers) = triggers::run_triggers(&mut c, 1, N, 1_000, start);
    assert_eq!(outcome.items, N);
    assert_eq!(outcome.tick, start + 1_000 * u64::from(N));
    assert_eq!(triggers.len(), N as usize);
    for (k, (frame, tick, host)) in triggers.iter().enumerate() {
        // Exact device ticks however the two processes were scheduled.
        assert_eq!((*frame, *tick), (k as u32, start + 1_000 * (k as u64 + 1)));
        assert!(host.is_some(), "trigger {k} has a host time");
    }
    // The device's clock is paced by the wall clock, as the host's is.
    let ppm = (c.clock().rate().unwrap() - 1.0).abs() * 1e6;
    assert!(ppm < 20_000.0, "device and host clocks agree within 2 % ({ppm} ppm)");
}

#[test]
fn the_host_cli_in_another_process_connects_to_it() {
    let sim = sim();
    let out = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["info", "--json", "--connect", &format!("serial:{}", sim.path)])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(info["board"], "Virtual");
    assert_eq!(info["schema_hash"], format!("0x{SCHEMA_HASH:016x}"));
    // A second client after the first left: the device resynchronises its link.
    let again = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["info", "--json", "--connect", &format!("serial:{}", sim.path)])
        .output()
        .unwrap();
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
}
