//! The live endpoint (docs/live-api.md) of real `lightrig acquire` processes: on the virtual
//! rig in-process and on `lightrig sim --pty`. What it serves is checked against the journal
//! the run wrote; a stop through it is checked by asking the device afterwards.
//!
//! Real time, real sockets: every wait is bounded and ends on what is awaited.
#![cfg(unix)]

use std::net::TcpStream;
use std::path::Path;
use std::process::Stdio;
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use lightrig_host::session::{decode_line, JOURNAL};
use lightrig_protocol::event::{DeviceState, FaultCause};
use lightrig_serve::client::Endpoint;
use serde_json::Value;

mod common;
mod rig_on_pty;
use common::Scratch;
use rig_on_pty::*;

/// The journal's records as JSON, line by line.
fn journal(session: &Path) -> Vec<Value> {
    let text = std::fs::read(session.join(JOURNAL)).unwrap();
    text.split_inclusive(|&b| b == b'\n')
        .map(|l| serde_json::from_slice(decode_line(l).expect("an intact line")).unwrap())
        .collect()
}

fn kind(record: &Value) -> &str {
    record["type"].as_str().unwrap_or("")
}

/// Reads stderr until the run says where it serves: its endpoint.
fn endpoint_of(run: &mut Run) -> Endpoint {
    Endpoint::parse(&live_url(run), None).unwrap()
}

/// The WebSocket feed from `since`, its messages on a channel (read on a thread of its own).
fn feed(e: &Endpoint, since: u64) -> Receiver<Value> {
    let s = TcpStream::connect(&e.authority).unwrap();
    let url = format!("ws://{}/api/v1/ws?since={since}", e.authority);
    let (mut ws, _) = tungstenite::client::client(url.as_str(), s).unwrap();
    let (tx, rx) = channel();
    std::thread::spawn(move || {
        while let Ok(m) = ws.read() {
            if let tungstenite::Message::Text(t) = m {
                if tx.send(serde_json::from_str::<Value>(&t).unwrap()).is_err() {
                    return;
                }
            }
        }
    });
    rx
}

/// Messages until one satisfies `done` (which is returned), all of them kept in `seen`.
fn until(rx: &Receiver<Value>, seen: &mut Vec<Value>, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let m = rx
            .recv_timeout(left)
            .unwrap_or_else(|_| panic!("no {what} from the feed; it sent {} messages", seen.len()));
        seen.push(m.clone());
        if done(&m) {
            return m;
        }
    }
}

/// The shipped gantry with `positions` reflectance positions, on the in-process virtual rig.
fn virtual_gantry(dir: &Path, positions: u32) -> std::path::PathBuf {
    let rig = gantry(dir, positions, false);
    let text = std::fs::read_to_string(&rig).unwrap();
    assert!(text.contains("connect = \"virtual\""), "the shipped gantry runs on the virtual rig");
    rig
}

#[test]
fn the_feed_is_the_journal_and_the_last_status_its_tally_on_the_virtual_rig() {
    let dir = Scratch::new("live-api", "virtual");
    let rig = virtual_gantry(&dir, 61);
    let session = dir.join("session");
    let (r, s) = (rig.to_str().unwrap(), session.to_str().unwrap());
    let mut run =
        spawn(&dir, &["acquire", r, "--session", s, "--yes", "--serve", "127.0.0.1:0"], Stdio::null());
    let e = endpoint_of(&mut run);
    let rx = feed(&e, 0);
    let mut seen = Vec::new();
    let hello = until(&rx, &mut seen, "hello", |m| m["type"] == "hello");
    assert_eq!(hello["api"], 1);
    assert_eq!(hello["status"]["run"]["command"], "acquire");
    assert_eq!(hello["status"]["run"]["session"], s);
    let frame = until(&rx, &mut seen, "a frame", |m| m["type"] == "frame");
    let end = until(&rx, &mut seen, "the end", |m| m["type"] == "end");
    assert_eq!(end["state"], "finished", "{end}");
    let (code, said) = run.end();
    assert_eq!(code, Some(0), "{said}");

    // Every record of the journal, in order, exactly once, as written.
    let written = journal(&session);
    let fed: Vec<(u64, Value)> = seen
        .iter()
        .filter(|m| m["type"] == "record")
        .map(|m| (m["seq"].as_u64().unwrap(), m["record"].clone()))
        .collect();
    assert_eq!(fed.iter().map(|f| f.0).collect::<Vec<_>>(), (0..written.len() as u64).collect::<Vec<_>>());
    assert!(fed.iter().map(|f| &f.1).eq(written.iter()), "the feed's records are the journal's");
    assert_eq!(kind(&written[0]), "SessionStarted");

    // The last status is the journal's tally.
    let last = seen.iter().rev().find(|m| m["type"] == "status").expect("a status before the end");
    let count = |k: &str| written.iter().filter(|r| kind(r) == k).count() as u64;
    let triggers =
        written.iter().filter(|r| kind(r) == "Event" && r["event"].get("Trigger").is_some()).count() as u64;
    let p = &last["progress"];
    assert_eq!(last["state"], "finished");
    assert_eq!(p["frames"].as_u64(), Some(count("Frame")));
    assert_eq!(p["missing"].as_u64(), Some(count("FrameMissing")));
    assert_eq!(p["steps_done"].as_u64(), Some(count("StepDone")));
    assert_eq!(p["steps"], p["steps_done"]);
    assert_eq!(p["triggered"].as_u64(), Some(triggers));
    assert_eq!(p["to_trigger"], p["triggered"]);
    assert_eq!(last["journal"]["next"].as_u64(), Some(written.len() as u64));
    assert_eq!(last["device"]["lasers_armed"], 0, "disarmed at the end");
    assert_eq!(last["run"]["method"], "linear-light-source");
    let started: Vec<&Value> = written.iter().filter(|r| kind(r) == "StepStarted").collect();
    let last_started = started.last().unwrap();
    assert_eq!(
        (&last["step"]["id"], &last["step"]["attempt"]),
        (&last_started["step"], &last_started["attempt"])
    );

    // A frame shown names the trigger the journal has for its camera and number.
    let t = &frame["trigger"];
    let journaled = written.iter().any(|r| {
        let j = &r["event"]["Trigger"];
        kind(r) == "Event"
            && j["sequence"] == t["sequence"]
            && j["camera"] == t["camera"]
            && j["frame"] == t["frame"]
            && j["tick"] == t["tick"]
    });
    assert!(journaled, "frame {frame} has a journaled trigger");
    assert_eq!(frame["frame"], t["frame"]);
}

#[test]
fn a_stop_through_the_endpoint_stops_the_device_on_a_real_port() {
    let (dir, sim, session, mut run, url) = served_acquisition("live-api", "stop", 41);
    let e = Endpoint::parse(&url, None).unwrap();
    wait_for_a_lit_trigger(&session, &mut run);
    // The journal first, then the status: the status has at least what the journal had.
    let written = journal(&session);
    let (code, st) = e.get_json("/api/v1/status").unwrap();
    assert_eq!(code, 200);
    assert_eq!(st["state"], "running", "{st}");
    let device = st["run"]["device"].as_str().unwrap();
    assert!(device.contains(sim.link.to_str().unwrap()), "the device is the port: {device}");
    // Fields the journal holds: the step running is the last one started (one step here).
    let last_started = written.iter().rev().find(|r| kind(r) == "StepStarted").unwrap();
    assert_eq!(st["step"]["id"], last_started["step"]);
    assert!(st["journal"]["next"].as_u64().unwrap() >= written.len() as u64);
    assert_ne!(st["device"]["lasers_armed"], 0, "a lit step runs armed: {st}");
    assert!(st["clock"]["samples"].as_u64().unwrap() > 0, "{st}");
    assert!(st["link"]["frames_received"].as_u64().unwrap() > 0, "{st}");
    let rx = feed(&e, 0);

    // `lightrig stop --url`, as from another machine.
    let url = format!("http://{}/", e.authority);
    let (code, out, err) = lightrig(&dir, &["stop", "--url", &url]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("stopped: the device answered the emergency stop"), "{out}");
    let mut seen = Vec::new();
    let end = until(&rx, &mut seen, "the end", |m| m["type"] == "end");
    assert_eq!(end["state"], "stopped", "{end}");
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    // Asked of the device over the port, by a new host.
    assert_eq!(sim.status(), (DeviceState::Faulted(FaultCause::EmergencyStop), 0, 0));
}

#[test]
fn a_pause_waits_at_a_step_boundary_disarmed_and_a_resume_finishes_the_run() {
    let (_dir, sim, session, run, url) = served_acquisition("live-api", "pause", 9);
    let e = Endpoint::parse(&url, None).unwrap();
    let (code, v) = e.post_json("/api/v1/pause").unwrap();
    assert_eq!(code, 200, "{v}");
    let rx = feed(&e, 0);
    let mut seen = Vec::new();
    let paused = until(&rx, &mut seen, "paused", |m| m["type"] == "status" && m["state"] == "paused");
    assert_eq!(paused["device"]["lasers_armed"], 0, "paused disarmed: {paused}");
    // At a boundary: every step started so far is done (or none started yet).
    let written = journal(&session);
    let started = written.iter().filter(|r| kind(r) == "StepStarted").count();
    let done = written.iter().filter(|r| kind(r) == "StepDone").count();
    assert_eq!(started, done, "paused between steps");
    let (code, v) = e.post_json("/api/v1/resume").unwrap();
    assert_eq!((code, v["state"].as_str()), (200, Some("running")), "{v}");
    let end = until(&rx, &mut seen, "the end", |m| m["type"] == "end");
    assert_eq!(end["state"], "finished", "{end}");
    let (code, said) = run.end();
    assert_eq!(code, Some(0), "{said}");
    let written = journal(&session);
    assert_eq!(written.iter().filter(|r| kind(r) == "FrameMissing").count(), 0);
    assert!(written.iter().any(|r| kind(r) == "SessionDone"));
    assert_eq!(sim.status(), (DeviceState::Ready, 0, 0), "left ready and disarmed");
}

#[test]
fn a_demo_serves_its_acquisition_pauses_in_process_and_stops_from_the_endpoint() {
    let dir = Scratch::new("live-api", "demo");
    let out = dir.join("demo");
    let o = out.to_str().unwrap();
    let mut run =
        spawn(&dir, &["demo", "lls", "--quick", "--out", o, "--serve", "127.0.0.1:0"], Stdio::null());
    let e = endpoint_of(&mut run);
    // Paused at the first step boundary it reaches (the virtual rig's time waits meanwhile).
    let (code, v) = e.post_json("/api/v1/pause").unwrap();
    assert_eq!(code, 200, "{v}");
    let rx = feed(&e, 0);
    let mut seen = Vec::new();
    let paused = until(&rx, &mut seen, "paused", |m| m["type"] == "status" && m["state"] == "paused");
    assert_eq!(paused["run"]["command"], "demo");
    assert_eq!(paused["run"]["method"], "linear-light-source");
    assert_eq!(paused["device"]["lasers_armed"], 0, "{paused}");
    let session = out.join("lls/session");
    let written = journal(&session);
    let started = written.iter().filter(|r| kind(r) == "StepStarted").count();
    assert_eq!(started, written.iter().filter(|r| kind(r) == "StepDone").count(), "paused between steps");
    // Stopped while paused: the run ends, stopped, the demo's exit says so.
    let (code, v) = e.post_json("/api/v1/stop").unwrap();
    assert_eq!(code, 200);
    assert_eq!(v["stop"]["answered"], true, "{v}");
    let end = until(&rx, &mut seen, "the end", |m| m["type"] == "end");
    assert_eq!(end["state"], "stopped", "{end}");
    let (code, said) = run.end();
    assert_eq!(code, Some(130), "{said}");
    let after = journal(&session);
    assert_eq!(
        after.iter().filter(|r| kind(r) == "StepStarted").count(),
        started,
        "no step began after the pause"
    );
}
