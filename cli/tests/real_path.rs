//! The operator's paths as a rig runs them: `lightrig acquire`, `resume`, `stop` and `info` as
//! separate processes against `lightrig sim --pty` (the virtual controller in real time on a
//! pseudo-terminal, reached through the host's real serial transport), with real signals sent
//! to the real binary. Each test ends by asking the device its state (lasers, armed, fault)
//! over the port, and reads the session's journal. The shipped LLS gantry runs here with a
//! 10 s heartbeat, so that the device's watchdog cannot hide a host that leaves lasers on.
//!
//! These run in real time: they wait for I/O (a line on stderr, a record in the journal, a
//! process's exit), each wait bounded, never for a fixed time.
#![cfg(unix)]

use std::io::Write;
use std::path::Path;
use std::process::Stdio;

use lightrig_host::session::{journal_records, Record, Session};
use lightrig_host::transport::SerialTransport;
use lightrig_protocol::event::{DeviceState, FaultCause};

mod common;
mod rig_on_pty;
use common::Scratch;
use rig_on_pty::*;

fn records(session: &Path) -> Vec<Record> {
    journal_records(session).unwrap()
}

fn attempts(session: &Path) -> Vec<(u32, u32)> {
    records(session)
        .iter()
        .filter_map(|r| match r {
            Record::StepStarted { step, attempt, .. } => Some((*step, *attempt)),
            _ => None,
        })
        .collect()
}

fn cleared(session: &Path) -> Vec<(FaultCause, String)> {
    records(session)
        .into_iter()
        .filter_map(|r| match r {
            Record::FaultCleared { cause, by, .. } => Some((cause, by)),
            _ => None,
        })
        .collect()
}

const STOPPED: (DeviceState, u8, u8) = (DeviceState::Faulted(FaultCause::EmergencyStop), 0, 0);

/// A terminal for stdin with `answer` already typed into it.
fn terminal_with(answer: &str) -> (serialport::TTYPort, Stdio) {
    use std::os::fd::{FromRawFd, IntoRawFd};
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    master.write_all(answer.as_bytes()).unwrap();
    let file = unsafe { std::fs::File::from_raw_fd(slave.into_raw_fd()) };
    (master, Stdio::from(file))
}

/// The reproduction: Ctrl-C two seconds into a lit step. The run stops the device and
/// ends with 130, never reconnecting or clearing the stop; `resume` without a person refuses
/// to clear it; `resume` at a terminal whose person says yes completes the session.
#[test]
fn ctrl_c_in_a_lit_step_stops_the_device_for_good_and_only_a_person_clears_it() {
    let (dir, sim, session, run) = lit_acquisition("ctrl-c", 8);
    let (s, c) = (session.to_str().unwrap(), sim.connect());
    run.ctrl_c();
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    assert!(said.contains("Ctrl-C: stopping the device (EmergencyStop)"), "{said}");
    assert!(said.contains("was sent EmergencyStop and answered"), "{said}");
    assert!(!said.contains("device lost") && !said.contains("cleared"), "no reconnection: {said}");
    assert_eq!(sim.status(), STOPPED, "lasers off, disarmed, the stop latched");
    assert_eq!(attempts(&session), [(0, 1)], "nothing ran after the stop");
    assert_eq!(cleared(&session), []);
    let abandoned = records(&session).iter().any(|r| matches!(r, Record::StepAbandoned { step: 0, .. }));
    assert!(abandoned, "the interrupted attempt is abandoned, to be acquired again");

    // A script resuming with --yes: the stop is not cleared, and says how it may be.
    let (code, _, said) = lightrig(&dir, &["resume", s, "--connect", &c, "--yes"]);
    assert_eq!(code, Some(3), "{said}");
    assert!(said.contains("is emergency-stopped") && said.contains("--clear-stop"), "{said}");
    assert_eq!(sim.status(), STOPPED);
    assert_eq!(attempts(&session), [(0, 1)]);

    // A person at a terminal says it is safe: cleared, journaled as confirmed, completed.
    let (_master, tty) = terminal_with("yes\n");
    let (code, said) = spawn(&dir, &["resume", s, "--connect", &c, "--yes"], tty).end();
    assert_eq!(code, Some(0), "{said}");
    assert!(said.contains("has a person seen to it"), "the person is asked: {said}");
    assert!(said.contains("session complete"), "{said}");
    assert_eq!(cleared(&session), [(FaultCause::EmergencyStop, "confirmed".to_string())]);
    let (done, _) = Session::read(&session).unwrap();
    assert!(done.is_done());
    assert_eq!(done.frame_index().len(), 8);
    assert_eq!(sim.status(), (DeviceState::Ready, 0, 0), "done: lasers off and disarmed");
}

/// Ctrl-C while the gantry homes (a 10 s seek): the stop reaches the device mid-move.
#[test]
fn ctrl_c_during_homing_stops_the_device() {
    let dir = Scratch::new("real-path", "homing");
    let rig = gantry(&dir, 3, true);
    let sim = Sim::start(&rig, &dir);
    let session = dir.join("session");
    let (r, s, c) = (rig.to_str().unwrap(), session.to_str().unwrap(), sim.connect());
    let mut run = spawn(&dir, &["acquire", r, "--session", s, "--connect", &c, "--yes"], Stdio::null());
    run.wait_for("homing gantry");
    run.ctrl_c();
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    assert!(!said.contains("homed gantry"), "stopped before homing ended: {said}");
    assert_eq!(sim.status(), STOPPED);
    assert!(!session.join("manifest.json").exists(), "no session was started");
}

/// Ctrl-C at a step's prompt (a person asked to turn the light's mount, lasers disarmed): the
/// process ends with 130 within seconds, though the prompt's read never returns.
#[test]
fn ctrl_c_at_a_prompt_stops_the_device_and_ends_the_run() {
    let dir = Scratch::new("real-path", "prompt");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, include_str!("../../sim/tests/support/prompting-gantry.toml")).unwrap();
    let sim = Sim::start(&rig, &dir);
    let session = dir.join("session");
    let (r, s, c) = (rig.to_str().unwrap(), session.to_str().unwrap(), sim.connect());
    // A terminal nobody types into.
    let (_master, tty) = terminal_with("");
    let mut run = spawn(&dir, &["acquire", r, "--session", s, "--connect", &c], tty);
    run.wait_for("turn the linear light's mount to +15°");
    run.ctrl_c();
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    assert_eq!(sim.status(), STOPPED);
    assert_eq!(cleared(&session), []);
}

/// `lightrig stop --connect` from a second terminal while `acquire` holds the port: it reaches
/// the run through the run's control socket; the run stops the device and ends with 130.
#[test]
fn lightrig_stop_from_another_terminal_reaches_the_running_acquisition() {
    let (dir, sim, session, run) = lit_acquisition("stop", 8);
    let c = sim.connect();
    let (code, out, err) = lightrig(&dir, &["stop", "--connect", &c]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("the device answered the emergency stop"), "{out}");
    assert!(out.contains(&format!("lightrig acquire (pid {})", run.child.id())), "{out}");
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    assert!(said.contains("was sent EmergencyStop and answered"), "{said}");
    assert_eq!(sim.status(), STOPPED);
    assert_eq!(attempts(&session), [(0, 1)]);
    assert_eq!(cleared(&session), []);
    // With no run left, `stop` without a device says so; with one, it goes to the port.
    let (code, _, err) = lightrig(&dir, &["stop"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("no running `lightrig acquire` or `resume`"), "{err}");
    let (code, out, err) = lightrig(&dir, &["stop", "--connect", &c]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("emergency stop sent and answered"), "{out}");
}

/// `lightrig stop` with no device named stops every running acquisition of this user.
#[test]
fn lightrig_stop_alone_stops_the_running_acquisition() {
    let (dir, sim, _session, run) = lit_acquisition("stop-alone", 8);
    let (code, out, err) = lightrig(&dir, &["stop"]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("the device answered the emergency stop"), "{out}");
    assert_eq!(run.end().0, Some(130));
    assert_eq!(sim.status(), STOPPED);
}

/// A port another program holds is named with that program, not as a missing device.
#[test]
fn a_port_held_by_another_program_names_that_program() {
    let dir = Scratch::new("real-path", "held");
    let rig = gantry(&dir, 3, false);
    let sim = Sim::start(&rig, &dir);
    let held = SerialTransport::open(sim.link.to_str().unwrap(), 115_200).unwrap();
    let (code, _, err) = lightrig(&dir, &["info", "--connect", &sim.connect()]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains(&format!("held by pid {}", std::process::id())), "{err}");
    drop(held);
}

/// `info`, then `acquire` on the same controller: the second host is taken as the first left
/// it, and the run ends with the device ready, lasers off and disarmed.
#[test]
fn info_then_acquire_completes_and_leaves_the_device_disarmed() {
    let dir = Scratch::new("real-path", "info");
    let rig = gantry(&dir, 3, false);
    let sim = Sim::start(&rig, &dir);
    let session = dir.join("session");
    let (code, out, err) = lightrig(&dir, &["info", "--json", "--connect", &sim.connect()]);
    assert_eq!(code, Some(0), "{err}");
    let info: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(info["board"], "Virtual", "{out}");
    let (r, s, c) = (rig.to_str().unwrap(), session.to_str().unwrap(), sim.connect());
    let (code, _, err) = lightrig(&dir, &["acquire", r, "--session", s, "--connect", &c, "--yes"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("3 frames paired with their triggers, 0 missing"), "{err}");
    assert_eq!(attempts(&session), [(0, 1)]);
    assert_eq!(sim.status(), (DeviceState::Ready, 0, 0));
}

/// Unplugged mid-step (the controller's terminal closes with it) and plugged back once the
/// host's first reconnection attempt has failed: the run rides it out, acquires the
/// interrupted step again, whole, and leaves the new controller ready and dark.
#[test]
fn acquire_rides_out_an_unplug_and_replug() {
    let (dir, mut sim, session, mut run) = lit_acquisition("unplug", 5);
    drop(sim);
    run.wait_for("reconnection 1/12 failed");
    sim = Sim::start(&dir.join("lls-gantry.toml"), &dir);
    let (code, said) = run.end();
    assert_eq!(code, Some(0), "{said}");
    assert!(said.contains("device lost"), "{said}");
    assert!(said.contains("device back; going on from the interrupted step"), "{said}");
    assert!(said.contains("5 frames paired with their triggers, 0 missing"), "{said}");
    assert_eq!(attempts(&session), [(0, 1), (0, 2)], "the interrupted step runs again, whole");
    let (done, _) = Session::read(&session).unwrap();
    assert!(done.is_done() && done.verify().is_empty());
    assert_eq!(sim.status(), (DeviceState::Ready, 0, 0));
}
