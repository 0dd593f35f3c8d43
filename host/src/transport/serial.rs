//! A serial port (CDC-ACM over USB, or a UART) as a [`Transport`], on the wall clock.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use super::Transport;

/// How long a write may wait for room in the port's buffer: a frame of 300 bytes takes 26 ms
/// at 115 200 baud, a window of them a fifth of a second.
const SEND_TIMEOUT: Duration = Duration::from_secs(2);

/// A serial port: CDC-ACM over USB, or a UART.
pub struct SerialTransport {
    port: Box<dyn serialport::SerialPort>,
    path: String,
    epoch: Instant,
}

impl SerialTransport {
    /// Opens `path` at `baud` (ignored by CDC-ACM).
    pub fn open(path: &str, baud: u32) -> Result<Self, serialport::Error> {
        let port = serialport::new(path, baud).timeout(Duration::from_millis(10)).open()?;
        Ok(Self { port, path: path.to_string(), epoch: Instant::now() })
    }
}

impl Transport for SerialTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        // The port's timeout is whatever the last `recv` waited (down to 1 µs): a write that
        // must wait for room (a window of frames into a full buffer) would fail at once.
        self.port.set_timeout(SEND_TIMEOUT).map_err(io::Error::other)?;
        self.port.write_all(bytes)
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        let now = self.now_us();
        let wait = Duration::from_micros(deadline.saturating_sub(now).max(1));
        self.port.set_timeout(wait).map_err(io::Error::other)?;
        match self.port.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            // A signal (Ctrl-C) cut the wait short: nothing arrived, the port is fine. The
            // client's next turn sees what the signal asked for.
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }

    fn describe(&self) -> String {
        format!("serial {}", self.path)
    }
}

/// The processes other than this one that have `path` open (pid and command line), as far as
/// the OS tells (`/proc` on Linux; empty elsewhere, or for another user's processes).
pub fn holders(path: &str) -> Vec<(u32, String)> {
    let Ok(target) = std::fs::canonicalize(path) else { return Vec::new() };
    let Ok(procs) = std::fs::read_dir("/proc") else { return Vec::new() };
    let me = std::process::id();
    let mut out = Vec::new();
    for p in procs.flatten() {
        let Some(pid) = p.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
        if pid == me {
            continue;
        }
        let Ok(fds) = std::fs::read_dir(p.path().join("fd")) else { continue };
        if fds.flatten().any(|fd| std::fs::read_link(fd.path()).is_ok_and(|l| l == target)) {
            let cmd = std::fs::read(p.path().join("cmdline")).unwrap_or_default();
            let words: Vec<String> = cmd
                .split(|&b| b == 0)
                .filter(|w| !w.is_empty())
                .map(|w| String::from_utf8_lossy(w).into_owned())
                .collect();
            out.push((pid, words.join(" ")));
        }
    }
    out.sort();
    out
}
