//! The virtual controller in real time on a pseudo-terminal (`lightrig sim --pty`) and
//! `lightrig` processes run against it, their stderr read as it comes: what the real-path
//! tests (`real_path.rs`, `live_api.rs`, `live_page.rs`) share.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use lightrig_host::client::{fresh_nonce, Client};
use lightrig_host::session::{journal_records, Record};
use lightrig_host::transport::SerialTransport;
use lightrig_protocol::event::{DeviceState, Event};
use lightrig_protocol::{Command as Cmd, Reply};

use crate::common::Scratch;

pub const BIN: &str = env!("CARGO_BIN_EXE_lightrig");
pub const WAIT: Duration = Duration::from_secs(60);

/// The shipped LLS gantry, small: one reflectance pass of `positions` positions, one exposure,
/// a 10 s heartbeat; homing as shipped (a 10 s seek) if `home`.
pub fn gantry(dir: &Path, positions: u32, home: bool) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/lls-gantry.toml");
    let half = (positions - 1) as f64;
    let mut edits = vec![
        ("heartbeat_timeout_ms", "heartbeat_timeout_ms = 10000".to_string()),
        ("pass_mm", format!("pass_mm = [-{half}, {half}]\nsettle_ms = 300")),
        ("step_mm", "step_mm = 2".into()),
        ("passes", "passes = [\"stripe\"]".into()),
        ("exposures_us", "exposures_us = [500]".into()),
    ];
    if !home {
        edits.push(("homing", "homing = { mode = \"none\" }".into()));
    }
    let mut lines: Vec<String> = std::fs::read_to_string(src).unwrap().lines().map(str::to_string).collect();
    for (start, with) in edits {
        let hits: Vec<usize> = (0..lines.len()).filter(|&i| lines[i].starts_with(start)).collect();
        assert_eq!(hits.len(), 1, "lls-gantry.toml: one line starting with {start:?}");
        lines[hits[0]] = with;
    }
    let path = dir.join("lls-gantry.toml");
    std::fs::write(&path, lines.join("\n")).unwrap();
    path
}

/// `lightrig sim --pty` on `rig`, its terminal linked at `dir/rig-tty`; killed when dropped.
pub struct Sim {
    pub child: Child,
    pub link: PathBuf,
}

impl Sim {
    pub fn start(rig: &Path, dir: &Path) -> Sim {
        let link = dir.join("rig-tty");
        let mut child = Command::new(BIN)
            .args(["sim", "--pty", "--seconds", "300", "--rig", rig.to_str().unwrap(), "--link"])
            .arg(&link)
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        assert!(line.starts_with("/dev/"), "the simulator printed its terminal: {line:?}");
        Sim { child, link }
    }

    pub fn connect(&self) -> String {
        format!("serial:{}", self.link.display())
    }

    /// The device's state, lasers armed and lasers on, asked over the port by a new host.
    pub fn status(&self) -> (DeviceState, u8, u8) {
        let port = SerialTransport::open(self.link.to_str().unwrap(), 115_200).unwrap();
        let mut c = Client::connect(port, fresh_nonce()).unwrap();
        let Reply::Status(s) = c.request(Cmd::GetStatus).unwrap() else { panic!("no status") };
        (s.state, s.armed, s.lasers_on)
    }
}

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `lightrig` process whose stderr is read as it comes, in pieces ended by a newline or by
/// the progress line's carriage return.
pub struct Run {
    pub child: Child,
    pub said: Receiver<String>,
    pub all: String,
}

/// `lightrig ARGS` with stdin from `stdin`; its control socket in `dir/run` (each test its own:
/// `lightrig stop` without a device stops every run it finds there).
pub fn spawn(dir: &Path, args: &[&str], stdin: Stdio) -> Run {
    let mut child = Command::new(BIN)
        .args(args)
        .env("XDG_RUNTIME_DIR", runtime(dir))
        .stdin(stdin)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = child.stderr.take().unwrap();
    let (tx, said) = channel();
    std::thread::spawn(move || {
        let mut piece = Vec::new();
        let mut byte = [0u8; 1];
        while let Ok(1) = err.read(&mut byte) {
            piece.push(byte[0]);
            if byte[0] == b'\n' || byte[0] == b'\r' {
                if tx.send(String::from_utf8_lossy(&piece).into_owned()).is_err() {
                    return;
                }
                piece.clear();
            }
        }
        let _ = tx.send(String::from_utf8_lossy(&piece).into_owned());
    });
    Run { child, said, all: String::new() }
}

pub fn runtime(dir: &Path) -> PathBuf {
    let d = dir.join("run");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `lightrig ARGS` run to its end: exit code, stdout, stderr.
pub fn lightrig(dir: &Path, args: &[&str]) -> (Option<i32>, String, String) {
    let out = Command::new(BIN)
        .args(args)
        .env("XDG_RUNTIME_DIR", runtime(dir))
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (out.status.code(), text(&out.stdout), text(&out.stderr))
}

impl Run {
    /// Reads stderr until a piece contains `what`.
    pub fn wait_for(&mut self, what: &str) {
        let deadline = Instant::now() + WAIT;
        while Instant::now() < deadline {
            match self.said.recv_timeout(deadline - Instant::now()) {
                Ok(piece) => {
                    self.all += &piece;
                    if piece.contains(what) {
                        return;
                    }
                }
                Err(_) => break,
            }
        }
        let _ = self.child.kill();
        panic!("no {what:?} on stderr within {WAIT:?}; it said:\n{}", self.all);
    }

    /// Sends SIGINT, as a terminal's Ctrl-C does.
    pub fn ctrl_c(&self) {
        let ok = Command::new("kill").args(["-INT", &self.child.id().to_string()]).status().unwrap();
        assert!(ok.success());
    }

    /// Waits for the process to end: its exit code and everything it said on stderr.
    pub fn end(mut self) -> (Option<i32>, String) {
        let deadline = Instant::now() + WAIT;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                // The reader thread ends at end of file.
                while let Ok(piece) = self.said.recv_timeout(Duration::from_secs(5)) {
                    self.all += &piece;
                }
                return (status.code(), self.all);
            }
            match self.said.recv_timeout(Duration::from_millis(100)) {
                Ok(piece) => self.all += &piece,
                Err(_) if Instant::now() > deadline => {
                    let _ = self.child.kill();
                    panic!("still running after {WAIT:?}:\n{}", self.all);
                }
                Err(_) => {}
            }
        }
    }
}

/// Waits until the session's journal holds a trigger with a laser on (the stripe pass's).
pub fn wait_for_a_lit_trigger(session: &Path, run: &mut Run) {
    let deadline = Instant::now() + WAIT;
    let lit = || {
        journal_records(session).is_ok_and(|rs| {
            let ready = rs.iter().any(|r| matches!(r, Record::Event { event: Event::LaserReady { .. }, .. }));
            ready && rs.iter().any(|r| matches!(r, Record::Event { event: Event::Trigger(_), .. }))
        })
    };
    while !lit() {
        if Instant::now() > deadline || run.child.try_wait().unwrap().is_some() {
            let _ = run.child.kill();
            panic!("no lit trigger journaled, or the run ended first");
        }
        // Stderr is drained meanwhile (a full pipe would stall the run).
        if let Ok(piece) = run.said.recv_timeout(Duration::from_millis(20)) {
            run.all += &piece;
        }
    }
}

/// A scratch directory, the gantry of `positions` positions on `lightrig sim --pty`, and
/// `lightrig acquire --yes` on it, once a lit trigger is journaled: (dir, sim, session, run).
pub fn lit_acquisition(name: &str, positions: u32) -> (Scratch, Sim, PathBuf, Run) {
    let dir = Scratch::new("real-path", name);
    let rig = gantry(&dir, positions, false);
    let sim = Sim::start(&rig, &dir);
    let session = dir.join("session");
    let (r, s, c) = (rig.to_str().unwrap(), session.to_str().unwrap(), sim.connect());
    let mut run = spawn(&dir, &["acquire", r, "--session", s, "--connect", &c, "--yes"], Stdio::null());
    wait_for_a_lit_trigger(&session, &mut run);
    (dir, sim, session, run)
}

/// A scratch directory, the gantry of `positions` positions on `lightrig sim --pty`, and
/// `lightrig acquire --yes` on it serving its live endpoint on a free port, once it said where:
/// (dir, sim, session, run, the endpoint's address).
pub fn served_acquisition(test: &str, name: &str, positions: u32) -> (Scratch, Sim, PathBuf, Run, String) {
    let dir = Scratch::new(test, name);
    let rig = gantry(&dir, positions, false);
    let sim = Sim::start(&rig, &dir);
    let session = dir.join("session");
    let (r, s, c) = (rig.to_str().unwrap(), session.to_str().unwrap(), sim.connect());
    let args = ["acquire", r, "--session", s, "--connect", &c, "--yes", "--serve", "127.0.0.1:0"];
    let mut run = spawn(&dir, &args, Stdio::null());
    let url = live_url(&mut run);
    (dir, sim, session, run, url)
}

/// Reads the run's stderr until it says where it serves its live endpoint: that address.
pub fn live_url(run: &mut Run) -> String {
    run.wait_for("live: http://");
    run.all.lines().find_map(|l| l.split_once("live: ").map(|(_, u)| u.trim().to_string())).unwrap()
}
