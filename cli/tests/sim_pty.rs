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
    sim_with(&[])
}

/// The simulator with more arguments (`--rig FILE`).
fn sim_with(args: &[&str]) -> Sim {
    let mut child = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["sim", "--pty", "--seconds", "120"])
        .args(args)
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

/// A small LLS gantry whose second pass asks a person to turn the light's mount.
const PROMPTING_RIG: &str = include_str!("../../sim/tests/support/prompting-gantry.toml");

fn temp_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("lightrig-pty-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The reproduction: a real-time controller, `lightrig acquire` stops at the first step
/// that needs a person (no terminal), the device times the departed host out, and `lightrig
/// resume` at a terminal asks, is answered, clears the fault it finds and completes the session.
#[test]
fn acquire_stops_at_a_prompt_and_resume_at_a_terminal_completes_the_session() {
    use std::io::Write;
    use std::os::fd::{FromRawFd, IntoRawFd};
    let dir = temp_dir("prompt");
    let rig_path = dir.join("rig.toml");
    std::fs::write(&rig_path, PROMPTING_RIG).unwrap();
    let sim = sim_with(&["--rig", rig_path.to_str().unwrap()]);
    let connect = format!("serial:{}", sim.path);
    let session = dir.join("session");

    let first = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["acquire", rig_path.to_str().unwrap(), "--session", session.to_str().unwrap()])
        .args(["--connect", &connect])
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&first.stderr);
    assert_eq!(first.status.code(), Some(1), "{err}");
    assert!(err.contains("needs a person") && err.contains("`lightrig resume` in a terminal"), "{err}");

    // The person walks over to a terminal; meanwhile the device times the departed host out.
    std::thread::sleep(std::time::Duration::from_millis(600));
    // At a terminal: the answer waits in the pseudo-terminal before the question comes.
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    master.write_all(b"\n").unwrap();
    let terminal = unsafe { std::fs::File::from_raw_fd(slave.into_raw_fd()) };
    let resumed = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["resume", session.to_str().unwrap(), "--connect", &connect])
        .stdin(terminal)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&resumed.stderr);
    assert!(resumed.status.success(), "{err}");
    assert!(
        err.contains("latched a fault: the host went silent"),
        "the departed host's fault is named: {err}"
    );
    assert!(err.contains("turn the linear light's mount to +15°"), "the person is asked: {err}");
    assert!(err.contains("session complete"), "{err}");
    let (s, _) = lightrig_host::session::Session::read(&session).unwrap();
    assert!(s.is_done());
    assert_eq!(s.verify(), vec![], "every frame stored intact");
    drop(sim);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn lightrig_stop_stops_a_device_from_another_process() {
    let sim = sim();
    let out = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["stop", "--connect", &format!("serial:{}", sim.path)])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        text.contains("emergency stop sent and answered") && text.contains("Faulted(EmergencyStop)"),
        "{text}"
    );
}

#[test]
fn lightrig_flash_updates_the_controller_through_its_serial_port() {
    let sim = sim();
    let dir = std::env::temp_dir().join(format!("lightrig-pty-flash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let code: Vec<u8> = (0..40_000u32).map(|k| (k % 253) as u8).collect();
    std::fs::write(dir.join("fw.bin"), code).unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_lightrig")).current_dir(&dir).args(args).output().unwrap()
    };
    let o = run(&[
        "flash",
        "sign",
        "fw.bin",
        "--virtual-key",
        "--board",
        "virtual",
        "--version",
        "0.3.0",
        "-o",
        "fw.lrfw",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let spec = format!("serial:{}", sim.path);
    // The transfer, the controller's reset into the bootloader's swap, the reconnection through
    // the same port, the confirmation.
    let o = run(&["flash", "fw.lrfw", "--connect", &spec]);
    let said = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{said}");
    assert!(said.contains("running 0.3.0 (confirmed); fallback 0.1.0 for Virtual"), "{said}");
    let o = run(&["info", "--json", "--connect", &spec]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((v["firmware"].as_str(), v["reset_cause"].as_str()), (Some("0.3.0"), Some("Software")));
    assert_eq!(
        (v["update"]["running"].as_str(), v["update"]["fallback"].as_str()),
        (Some("0.3.0"), Some("0.1.0"))
    );
    std::fs::remove_dir_all(&dir).ok();
}
